"""``train_loop.run_steps`` options the VAE and world-model trainers use, on a toy step: placed batches,
extra checkpoint facts, how many checkpoints stay, which metrics decide "finite", and ``skip``."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax import checkpoint
from sword_jax.train_loop import NonFiniteLoss, run_steps

STEPS = 5


@jax.jit
def _step(state, batch, key):
    """Adds the batch to ``w`` unless it is non-finite (a step that skips a bad update itself);
    ``probe`` is NaN by design on even steps, as the world model's off-log-step metrics are."""
    finite = jnp.isfinite(batch["x"])
    w = jnp.where(finite, state["w"] + batch["x"], state["w"])
    metrics = {"loss": batch["x"], "nonfinite": (~finite).astype(jnp.int32),
               "probe": jnp.where(state["step"] % 2 == 0, jnp.nan, 1.0)}
    return {"w": w, "step": state["step"] + 1}, metrics


def _run(directory, *, poison_at=-1, **options):
    placed, first = [], []

    def place(host):
        placed.append(host)
        return {"x": jnp.asarray(host)}

    state = {"w": jnp.zeros((), jnp.float32), "step": jnp.zeros((), jnp.int32)}
    result = run_steps(_step, state, lambda i: np.float32(np.nan if i == poison_at else i + 1), key=jax.random.key(0),
                       steps=STEPS, log_every=1, name="toy", report=lambda done, m, _o, _eta: {"step": done, **m},
                       checkpoint_dir=directory, place=place, checkpoint_meta=lambda done: {"position": 10 * done},
                       keep_checkpoints=3, metrics_finite=lambda m: m["nonfinite"] == 0,
                       on_first_step=lambda: first.append(len(placed)), log=lambda line: None, **options)
    return result, placed, first


def _meta(directory):
    ckpt = checkpoint.Checkpointer(directory)
    try:
        return ckpt.latest_step(), ckpt.restore(checkpoint.abstract_like(
            {"w": jnp.zeros(()), "step": jnp.zeros((), jnp.int32)}))[1]
    finally:
        ckpt.close()


def test_run_steps_places_batches_keeps_checkpoint_facts_and_uses_the_given_finite_test(tmp_path):
    directory = str(tmp_path / "ok")
    result, placed, first = _run(directory)
    assert float(result.state["w"]) == sum(range(1, STEPS + 1)) and len(placed) == STEPS
    assert first == [1]  # once, after the first step
    saved = sorted(int(d) for d in os.listdir(directory) if d.isdigit())
    assert saved == [STEPS - 2, STEPS - 1, STEPS]  # keep_checkpoints=3
    step, meta = _meta(directory)
    assert step == STEPS and meta["position"] == 10 * STEPS and meta["step"] == STEPS
    assert [p["step"] for p in meta["history"]] == list(range(1, STEPS + 1))  # the NaN probe stopped nothing


def test_run_steps_stop_or_skip_on_a_nonfinite_step(tmp_path):
    with pytest.raises(NonFiniteLoss, match=r"toy: non-finite loss or gradient at step 2 \(0-based\).*"
                                            r"last good checkpoint: step 2"):
        _run(str(tmp_path / "stop"), poison_at=2)
    assert _meta(str(tmp_path / "stop"))[0] == 2
    result, _, _ = _run(str(tmp_path / "skip"), poison_at=2, on_nonfinite="skip")
    assert float(result.state["w"]) == sum(range(1, STEPS + 1)) - 3  # step 2's update was skipped, the run went on
    assert _meta(str(tmp_path / "skip"))[0] == STEPS
    with pytest.raises(ValueError, match="on_nonfinite"):
        _run(str(tmp_path / "bad"), on_nonfinite="ignore")


def test_a_run_id_holding_tuples_resumes_and_another_is_refused(tmp_path):
    """The checkpoint stores ``run_id`` as JSON (tuples come back as lists); the loop compares in that form,
    so the same run resumes and a different value is still refused, naming its key."""
    from sword_jax.train_loop import AnotherRunsCheckpoint

    directory = str(tmp_path / "ids")
    _run(directory, run_id={"seed": 0, "sim.tasks": (0, 1)})
    resumed, placed, _ = _run(directory, run_id={"seed": 0, "sim.tasks": (0, 1)})
    assert resumed.first_step == STEPS and placed == []
    with pytest.raises(AnotherRunsCheckpoint, match=r"differs in \['sim.tasks'\]"):
        _run(directory, run_id={"seed": 0, "sim.tasks": (0, 2)})


def test_a_state_with_host_leaves_resumes(tmp_path):
    """A train state built from weights read off ``.npz`` holds NumPy leaves (no ``.sharding``); a resumed run
    restores them onto the device and carries on from the checkpoint's step (GRPO from a policy file)."""
    directory = str(tmp_path / "host")
    host_state = lambda: {"w": np.zeros((2,), np.float32), "step": np.zeros((), np.int32)}  # noqa: E731

    def go(steps):
        return run_steps(_step, host_state(), lambda i: np.float32(i + 1), key=jax.random.key(0), steps=steps,
                         log_every=1, name="host", report=lambda done, m, _o, _eta: {"step": done},
                         checkpoint_dir=directory, place=lambda b: {"x": jnp.asarray(b)},
                         metrics_finite=lambda m: m["nonfinite"] == 0, log=lambda line: None)

    go(2)
    result = go(STEPS)  # resumes at step 2: batches 3..STEPS are added to the restored w
    np.testing.assert_array_equal(np.asarray(result.state["w"]), np.full((2,), sum(range(1, STEPS + 1)), np.float32))
    abstract = checkpoint.abstract_like({"a": np.ones((3,), np.float16), "b": 1.5})
    assert abstract["a"].shape == (3,) and abstract["a"].dtype == np.float16 and abstract["a"].sharding is not None
    assert abstract["b"].shape == () and abstract["b"].dtype == np.float32


def test_a_stop_request_checkpoints_the_step_in_flight_and_the_run_resumes_exactly(tmp_path):
    """A stop requested after step 2 (e.g. SIGUSR1 under cli.run): that step is read, passed to at_checkpoint
    and checkpointed although it is no checkpoint step, StopRequested names it, and the same call resumes there
    to the uninterrupted run's result."""
    from sword_jax.cli import StopRequested

    directory, seen, seen_steps = str(tmp_path / "stop"), [], []
    asked = lambda: len(seen_steps) >= 2  # noqa: E731 - asked for once two steps were dispatched

    def step(state, batch, key):
        seen_steps.append(int(batch["x"]))
        return _step(state, batch, key)

    def go(stop):
        return run_steps(step, {"w": jnp.zeros((), jnp.float32), "step": jnp.zeros((), jnp.int32)},
                         lambda i: np.float32(i + 1), key=jax.random.key(0), steps=STEPS, log_every=2, name="toy",
                         report=lambda done, m, _o, _eta: {"step": done}, checkpoint_dir=directory, checkpoint_every=4,
                         place=lambda b: {"x": jnp.asarray(b)}, metrics_finite=lambda m: m["nonfinite"] == 0,
                         at_checkpoint=lambda done, state, history: seen.append((done, [p["step"] for p in history])),
                         log=lambda line: None, stop_requested=stop)

    with pytest.raises(StopRequested, match=rf"toy: stopped on request after step 2 of {STEPS}; checkpoint of step 2"):
        go(asked)
    assert seen == [(2, [2])]  # step 2 was read and handed over although log_every / checkpoint_every are 2 / 4
    step_saved, meta = _meta(directory)
    assert step_saved == 2 and float(meta["history"][-1]["step"]) == 2
    result = go(lambda: False)
    assert result.first_step == 2 and float(result.state["w"]) == sum(range(1, STEPS + 1))
    assert seen[1:] == [(4, [2, 4]), (STEPS, [2, 4, STEPS])]
    # a request at the last step changes nothing: the run is complete
    last = run_steps(_step, {"w": jnp.zeros((), jnp.float32), "step": jnp.zeros((), jnp.int32)},
                     lambda i: np.float32(i + 1), key=jax.random.key(0), steps=1, log_every=1, name="toy",
                     report=lambda done, m, _o, _eta: {"step": done}, place=lambda b: {"x": jnp.asarray(b)},
                     metrics_finite=lambda m: m["nonfinite"] == 0, log=lambda line: None, stop_requested=lambda: True)
    assert float(last.state["w"]) == 1.0


_SIGNALLED_RUN = """
import os, sys
import jax, jax.numpy as jnp, numpy as np
from sword_jax import cli
from sword_jax.train_loop import run_steps

def main(argv):
    directory, signal_at = argv[0], int(argv[1])

    def step(state, batch, key):  # the signal arrives while step `signal_at` (1-based) is dispatched
        if int(batch) == signal_at:
            os.kill(os.getpid(), cli.STOP_SIGNAL)
        return {"w": state["w"] + batch}, {"loss": jnp.float32(batch)}

    result = run_steps(step, {"w": jnp.zeros((), jnp.float32)}, lambda i: np.float32(i + 1), key=jax.random.key(0),
                       steps=5, log_every=1, name="toy", report=lambda done, m, _o, _eta: {"step": done},
                       checkpoint_dir=directory, checkpoint_every=5, log=lambda line: None)
    print(float(result.state["w"]))

cli.run(main)
"""


def test_the_stop_signal_under_cli_run_checkpoints_and_exits_75_and_the_command_resumes(tmp_path):
    import subprocess
    import sys

    from sword_jax import cli

    def command(signal_at):
        return subprocess.run([sys.executable, "-c", _SIGNALLED_RUN, str(tmp_path / "ckpt"), str(signal_at)],
                              capture_output=True, text=True, timeout=300)

    stopped = command(2)
    assert stopped.returncode == cli.STOPPED_EXIT, stopped.stderr
    assert stopped.stderr.strip().splitlines()[-1].endswith("toy: stopped on request after step 2 of 5; checkpoint "
                                                             f"of step 2 in {tmp_path / 'ckpt'}; the same command "
                                                             "resumes from it")
    resumed = command(0)  # no signal: resumes at step 2 and adds batches 3..5
    assert resumed.returncode == 0, resumed.stderr
    assert float(resumed.stdout.strip()) == 15.0


_HOLDER = """
import sys, time
from sword_jax import checkpoint
lock = checkpoint.WriterLock(sys.argv[1], "holder")
print("held", flush=True)
time.sleep(600)
"""


def test_a_second_writer_of_a_run_is_refused_and_a_killed_ones_claim_is_gone(tmp_path):
    """WriterLock in run_steps: while another live process writes the checkpoint directory, a run on it is refused
    by name, before it reads or writes anything; once that process is killed (SIGKILL: no clean-up of its own),
    the same run goes through. In one process, a claim held elsewhere refuses too, and a finished or failed run
    gives its claim back."""
    import subprocess
    import sys

    directory = str(tmp_path / "run")
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, directory], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(checkpoint.CheckpointInUse, match=f"toy: {directory} is being written by another live "
                                                             f"process \\(pid {holder.pid} on "):
            _run(directory)
        assert os.listdir(directory) == [checkpoint.WriterLock.FILE]  # nothing read, nothing written
    finally:
        holder.kill()
        holder.wait(timeout=60)
    result, _, _ = _run(directory)
    assert float(result.state["w"]) == sum(range(1, STEPS + 1))
    with checkpoint.WriterLock(directory, "elsewhere"):
        with pytest.raises(checkpoint.CheckpointInUse, match="another live process"):
            _run(directory)
    with pytest.raises(NonFiniteLoss):
        _run(str(tmp_path / "bad"), poison_at=2)
    with checkpoint.WriterLock(str(tmp_path / "bad"), "after the failure"):  # the failed run let go of it
        pass
    assert _run(directory)[0].first_step == STEPS  # resumed at the end: nothing left to run


def test_a_file_system_without_flock_runs_unclaimed_with_a_warning(tmp_path, monkeypatch):
    """Where flock is not supported (ENOLCK, as on some network mounts), the run goes on unclaimed and says so;
    only a claim another process holds (EWOULDBLOCK) refuses."""
    import errno
    import fcntl

    def unsupported(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", unsupported)
    with pytest.warns(UserWarning, match="cannot be claimed .*No locks available"):
        result, _, _ = _run(str(tmp_path / "run"))
    assert float(result.state["w"]) == sum(range(1, STEPS + 1))
