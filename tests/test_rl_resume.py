"""Crash and resume of the SFT, reward-model and GRPO trainers (``sword_jax.train_loop``).

A run of ``train.train_policy`` / ``train.train_reward`` / ``train.grpo`` SIGKILLed partway and rerun
in the same work dir ends with parameters (and optimizer state, and logged history, and GRPO's success
curve) bit-identical to an uninterrupted run; a non-finite loss stops the run naming the step, the
checkpoint before it intact; a checkpoint of another run is refused, naming the keys that differ.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax import checkpoint
from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, RLConfig
from sword_jax.rl.grpo_loop import grpo_run_id, train_grpo
from sword_jax.rl.policy import build_policy
from sword_jax.rl.reward_model import build_detector, train_detector
from sword_jax.rl.sft import train_sft
from sword_jax.train_loop import AnotherRunsCheckpoint, NonFiniteLoss
from tests.conftest import REPO, example_env
from tests.support.rl import POLICY_CFG, TINY_RL, brightening_episodes, reward_batches, write_demos

STEPS, KILL_AT = 8, 3
ENTRY = {  # entry point, its checkpoint dir under <workdir>/rl, its knobs for a short run checkpointed every step
    "sft": ("train.train_policy", "sft_checkpoints",
            [f"--rl.sft.steps={STEPS}", "--rl.sft.batch_size=4", "--rl.sft.eval_every=2", "--rl.sft.warmup_steps=2",
             "--rl.sft.checkpoint_every=1", "--holdout=0.3"]),
    "reward": ("train.train_reward", "reward_checkpoints",
               [f"--rl.reward_model.steps={STEPS}", "--rl.reward_model.batch_size=4",
                "--rl.reward_model.checkpoint_every=1"]),
}


def _env(tmp_path) -> dict[str, str]:
    # one CPU device, the persistent compilation cache shared by the three runs of a test
    return dict(example_env(), JAX_COMPILATION_CACHE_DIR=str(tmp_path / "xla_cache"),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", PYTHONUNBUFFERED="1")


def _cmd(trainer: str, workdir: str, demos: str) -> list[str]:
    module, _, knobs = ENTRY[trainer]
    return [sys.executable, "-m", module, "--config", "sword:tiny", f"--workdir={workdir}", "--demos", demos,
            *TINY_RL, *knobs]


def _steps_saved(directory: str) -> list[int]:
    return sorted(int(d) for d in os.listdir(directory) if d.isdigit()) if os.path.isdir(directory) else []


def _final_state(directory: str, like=None) -> tuple[list[np.ndarray], dict]:
    """The leaves of the newest checkpoint's train state (params, optimizer state, step) and its meta,
    restored as saved (nested dicts) or into the structure of the train state ``like``."""
    ckpt = checkpoint.Checkpointer(directory)
    state, meta = ckpt.restore(None if like is None else checkpoint.abstract_like(like))
    ckpt.close()
    return [np.asarray(leaf) for leaf in jax.tree.leaves(state)], meta


# The step loop (sword_jax.train_loop) is every trainer's: its exact resume after a SIGKILL is checked in the default
# run for the world model (test_reliability); the SFT, reward-model and GRPO runs of it are slow-marked (70 s, 50 s).
@pytest.mark.slow
@pytest.mark.parametrize("trainer", ["sft", "reward"])
def test_sigkill_resume_is_bit_identical(tmp_path, trainer):
    env = _env(tmp_path)
    demos = write_demos(str(tmp_path / "demos.hdf5"))
    crashed = str(tmp_path / "crashed")  # first: it compiles, the two runs after it read the compilation cache
    ckpt_dir = os.path.join(crashed, "rl", ENTRY[trainer][1])
    proc = subprocess.Popen(_cmd(trainer, crashed, demos), cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None and not any(s >= KILL_AT for s in _steps_saved(ckpt_dir)):
        time.sleep(0.005)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)  # lands inside a step or a checkpoint write
    proc.wait()
    killed_at = max(_steps_saved(ckpt_dir))
    assert KILL_AT <= killed_at < STEPS, killed_at

    reference = str(tmp_path / "reference")
    done = subprocess.run(_cmd(trainer, reference, demos), cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]

    resumed = subprocess.run(_cmd(trainer, crashed, demos), cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    match = re.search(r"resumed from step (\d+)", resumed.stdout)
    assert match and KILL_AT <= int(match.group(1)) < STEPS, resumed.stdout[-2000:]

    want, want_meta = _final_state(os.path.join(reference, "rl", ENTRY[trainer][1]))
    got, got_meta = _final_state(ckpt_dir)
    assert got_meta["step"] == want_meta["step"] == STEPS
    assert len(got) == len(want) > 10
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert got_meta["history"] == want_meta["history"] and len(want_meta["history"]) >= 2
    if trainer == "sft":  # the saved policy and the result's history (held-out metrics included) match too
        results = [json.load(open(os.path.join(d, "rl", "sft_result.json"))) for d in (reference, crashed)]
        assert results[0]["history"] == results[1]["history"]
        assert "heldout_loss" in results[0]["history"][-1]


def test_sft_non_finite_loss_stops_naming_the_step_and_keeps_the_last_good_checkpoint(tmp_path):
    # a learning rate this large sends the parameters past float32's range within a few steps
    cfg = dataclasses.replace(POLICY_CFG, sft=dataclasses.replace(POLICY_CFG.sft, learning_rate=1e30, warmup_steps=0, eval_every=1,
                                                           checkpoint_every=1))
    graphdef, params = build_policy(cfg, seed=0)
    directory = str(tmp_path / "sft_checkpoints")
    with pytest.raises(NonFiniteLoss, match=r"SFT: non-finite loss or gradient at step \d+ \(0-based\)") as err:
        train_sft(graphdef, params, cfg, brightening_episodes(), seed=0, steps=20, log=lambda line: None,
                  checkpoint_dir=directory)
    bad_step = int(re.search(r"at step (\d+)", str(err.value)).group(1))
    assert 1 <= bad_step < 20 and f"last good checkpoint: step {bad_step}" in str(err.value)
    leaves, meta = _final_state(directory)  # every step before the bad one was saved, nothing after
    assert meta["step"] == bad_step and meta["history"][-1]["step"] == bad_step
    assert all(np.all(np.isfinite(a)) for a in leaves if a.dtype.kind == "f")


@pytest.mark.slow  # the stop itself is pinned in the default run by test_optim's reward-model test
def test_reward_model_non_finite_loss_stops_and_the_checkpoint_before_it_resumes(tmp_path):
    cfg = dataclasses.replace(POLICY_CFG, reward_model=dataclasses.replace(POLICY_CFG.reward_model, checkpoint_every=1))
    directory = str(tmp_path / "reward_checkpoints")
    graphdef, params = build_detector(cfg)
    with pytest.raises(NonFiniteLoss, match=r"reward model: non-finite loss or gradient at step 3 \(0-based\).*"
                                            r"last good checkpoint: step 3"):
        train_detector(graphdef, params, cfg, reward_batches(cfg, poison_at=3), key=jax.random.key(0), steps=6,
                       log=lambda line: None, checkpoint_dir=directory)
    # the kept checkpoint is exactly the state after the three good steps
    graphdef, params = build_detector(cfg)
    straight, _ = train_detector(graphdef, params, cfg, reward_batches(cfg), key=jax.random.key(0), steps=3,
                                 log=lambda line: None)
    leaves, meta = _final_state(directory, like=straight)
    assert meta["step"] == 3 and all(np.all(np.isfinite(a)) for a in leaves if a.dtype.kind == "f")
    for a, b in zip(leaves, jax.tree.leaves(straight), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))
    # the checkpoint belongs to its run: another batch size is refused, naming the key
    graphdef, params = build_detector(cfg)
    other = dataclasses.replace(cfg, reward_model=dataclasses.replace(cfg.reward_model, batch_size=7))
    with pytest.raises(ValueError, match=r"rl\.reward_model\.batch_size"):
        train_detector(graphdef, params, other,
                       reward_batches(cfg), key=jax.random.key(0), steps=6, log=lambda line: None,
                       checkpoint_dir=directory)


GRPO_STEPS, GRPO_KILL_AT = 4, 2
# the toy simulator, evaluated and checkpointed every other step; XLA's cheapest CPU compile (the same program
# in every run, so bit-identity still means what it says) keeps the one cold compile of the step short
GRPO_ARGS = ["--simulator", "toy", "--rl.imagined.max_chunks=2", "--rl.grpo.rollout_batch=2", "--rl.grpo.group_size=2",
             "--rl.grpo.eval_every=2", f"--rl.grpo.steps={GRPO_STEPS}"]


def _grpo_cmd(workdir: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "train.grpo", "--config", "sword:tiny", f"--workdir={workdir}", *GRPO_ARGS,
            *TINY_RL, *extra]


# -m slow (about 50 s of four child processes). The default run keeps its parts: the entry point's kill and exact
# resume through the same step loop (tests/test_reliability.py::test_sigkill_resume_is_bit_identical), GRPO's loop
# resumed to the uninterrupted run's history, curve and parameters (test_grpo_run_stopped_after_a_checkpoint_leaves_
# its_history, test_grpo_stopped_on_request_evaluates_its_step_in_flight_and_resumes_there below) and another run's
# checkpoint refused by the key that differs (test_grpo_non_finite_loss_stops_and_a_resume_drops_evaluations_after_
# the_checkpoint below).
@pytest.mark.slow
def test_grpo_sigkill_resume_is_bit_identical_and_another_runs_checkpoint_is_refused(tmp_path):
    env = _env(tmp_path)
    crashed = str(tmp_path / "crashed")  # first: it compiles, the runs after it read the compilation cache
    ckpt_dir = os.path.join(crashed, "rl", "grpo", "checkpoints")
    proc = subprocess.Popen(_grpo_cmd(crashed), cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while (time.time() < deadline and proc.poll() is None
           and not any(s >= GRPO_KILL_AT for s in _steps_saved(ckpt_dir))):
        time.sleep(0.005)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)  # lands inside a step, an evaluation or a checkpoint write
    proc.wait()
    killed_at = max(_steps_saved(ckpt_dir))
    assert GRPO_KILL_AT <= killed_at < GRPO_STEPS, killed_at

    reference = str(tmp_path / "reference")
    done = subprocess.run(_grpo_cmd(reference), cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    resumed = subprocess.run(_grpo_cmd(crashed), cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    match = re.search(r"GRPO: resumed from step (\d+)", resumed.stdout)
    assert match and GRPO_KILL_AT <= int(match.group(1)) < GRPO_STEPS, resumed.stdout[-2000:]

    want, want_meta = _final_state(os.path.join(reference, "rl", "grpo", "checkpoints"))
    got, got_meta = _final_state(ckpt_dir)
    assert got_meta["step"] == want_meta["step"] == GRPO_STEPS
    assert len(got) == len(want) > 10
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert got_meta["history"] == want_meta["history"] and len(want_meta["history"]) == GRPO_STEPS
    curves = [json.load(open(os.path.join(d, "rl", "grpo", "success_curve.json"))) for d in (reference, crashed)]
    assert curves[0] == curves[1] and [p["step"] for p in curves[0]["points"]] == [0, 2, 4]

    # the work dir belongs to its run: another learning rate is refused in one line, naming the key
    other = subprocess.run(_grpo_cmd(crashed, "--rl.grpo.learning_rate=1e-3"), cwd=REPO, env=env, capture_output=True,
                           text=True, timeout=300)
    assert other.returncode == 1 and "Traceback" not in other.stderr, other.stderr[-3000:]
    assert "another run (differs in ['rl.grpo.learning_rate'])" in other.stderr, other.stderr[-3000:]


def _toy_grpo(step, rl: RLConfig, workdir: str, run_id: dict):
    """GRPO of a one-vector policy from zeros (batch ``k + 1`` at step ``k``), evaluated as its first entry."""
    state = grpo.init_state({"w": jnp.zeros((2,), jnp.float32)}, rl)
    evaluate = lambda done, params: ({"mean": float(params["w"][0]), "per_task": {}}, {})  # noqa: E731
    return train_grpo(step, state, lambda i: jnp.float32(i + 1), key=jax.random.key(0), rl=rl, workdir=workdir,
                      evaluate=evaluate, run_id=run_id, progress=lambda point, eta: "", log=lambda line: None)


def _curve_on_disk(workdir: str) -> list[tuple[int, float]]:
    with open(os.path.join(workdir, "success_curve.json")) as f:
        return [(p["step"], p["mean"]) for p in json.load(f)["points"]]


def test_grpo_non_finite_loss_stops_and_a_resume_drops_evaluations_after_the_checkpoint(tmp_path):
    """The loop around GRPO's step (the update's own finite gate is pinned in test_grpo): a non-finite loss
    stops the run with the last evaluation's checkpoint and curve intact; an evaluation a killed run wrote
    after its checkpoint is dropped on resume and recomputed."""
    rl = RLConfig(grpo=GRPOConfig(steps=6, eval_every=2))
    workdir = str(tmp_path / "grpo")
    run_id = grpo_run_id(rl, seed=0, simulator="toy", **{"sim.tasks": (0, 1)})

    def make_step(bad_step: int):
        @jax.jit
        def step(state, batch, key):
            params = {"w": state.params["w"] + batch}
            loss = jnp.where(state.step == bad_step, jnp.nan, jnp.sum(params["w"]))
            return state.replace(params=params, step=state.step + 1), {"loss": loss}

        return step

    def run(step, rl, run_id=run_id):
        return _toy_grpo(step, rl, workdir, run_id)

    def curve_on_disk():
        return _curve_on_disk(workdir)

    with pytest.raises(NonFiniteLoss, match=r"GRPO: non-finite loss or gradient at step 4 \(0-based\).*"
                                            r"last good checkpoint: step 4"):
        run(make_step(bad_step=4), rl)
    leaves, meta = _final_state(os.path.join(workdir, "checkpoints"))
    assert meta["step"] == 4 and [p["step"] for p in meta["history"]] == [1, 2, 3, 4]
    assert curve_on_disk() == [(0, 0.0), (2, 3.0), (4, 10.0)]  # w after 1 + 2, after 1 + 2 + 3 + 4

    # a killed run's evaluation after its checkpoint (6) is dropped on resume, not kept beside the new one
    with open(os.path.join(workdir, "success_curve.json")) as f:
        stale = json.load(f)
    stale["points"].append({"step": 6, "mean": -1.0, "per_task": {}})
    with open(os.path.join(workdir, "success_curve.json"), "w") as f:
        json.dump(stale, f)
    shorter = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, steps=4))
    _, points = run(make_step(bad_step=-1), shorter)  # resumes at its end
    assert [p["step"] for p in points] == [0, 2, 4] and curve_on_disk() == [(0, 0.0), (2, 3.0), (4, 10.0)]
    result, _ = run(make_step(bad_step=-1), rl)
    assert result.first_step == 4 and curve_on_disk() == [(0, 0.0), (2, 3.0), (4, 10.0), (6, 21.0)]
    other = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, group_size=4))
    with pytest.raises(AnotherRunsCheckpoint, match=r"differs in \['rl.grpo.group_size'\]"):
        run(make_step(bad_step=-1), rl, run_id=grpo_run_id(other, seed=0, simulator="toy", **{"sim.tasks": (0, 1)}))


class _Killed(Exception):
    pass


def _killable_grpo(rl: RLConfig, workdir: str, *, eval_pause_s: float = 0.0, frames_per_chunk: int = 0):
    """``run(kill_at)``: a GRPO run of a one-vector policy (``w += batch`` per step, batch ``k`` at step ``k``,
    ``mean_chunks`` ``k + 1``) whose evaluation of step ``kill_at`` raises :class:`_Killed`, as a killed run would
    stop there; each evaluation first waits ``eval_pause_s``."""
    import time

    run_id = grpo_run_id(rl, seed=0, simulator="toy", **{"sim.tasks": (0, 1)})

    @jax.jit
    def step(state, batch, key):
        params = {"w": state.params["w"] + batch}
        return state.replace(params=params, step=state.step + 1), {"loss": jnp.sum(params["w"]),
                                                                   "mean_chunks": batch + 1.0}

    def run(kill_at: int):
        def evaluate(done, params):
            time.sleep(eval_pause_s)
            if done == kill_at:
                raise _Killed(done)
            return {"mean": float(params["w"][0]), "per_task": {}}, {}

        state = grpo.init_state({"w": jnp.zeros((2,), jnp.float32)}, rl)
        return train_grpo(step, state, lambda i: jnp.float32(i + 1), key=jax.random.key(0), rl=rl, workdir=workdir,
                          evaluate=evaluate, run_id=run_id, progress=lambda point, eta: "", log=lambda line: None,
                          frames_per_chunk=frames_per_chunk)

    return run


def _jsonl(path: str) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f]


def test_grpo_run_stopped_after_a_checkpoint_leaves_its_history(tmp_path):
    """``train_history.jsonl`` is written after every step, not only at checkpoints: a run killed during the
    evaluation of step 4 leaves steps 1-4 (its checkpoint holds 1-2), and a resumed run the whole history, each step
    once."""
    workdir = str(tmp_path / "grpo")
    run = _killable_grpo(RLConfig(grpo=GRPOConfig(steps=6, eval_every=2)), workdir)

    def history_on_disk():
        return _jsonl(os.path.join(workdir, "train_history.jsonl"))

    with pytest.raises(_Killed):
        run(kill_at=4)
    _, meta = _final_state(os.path.join(workdir, "checkpoints"))
    assert meta["step"] == 2 and history_on_disk()[:2] == meta["history"]
    # w = 1, then 1 + 2, ...: the steps after the checkpoint are on disk too
    assert [(p["step"], p["loss"]) for p in history_on_disk()] == [(1, 2.0), (2, 6.0), (3, 12.0), (4, 20.0)]
    result, _ = run(kill_at=-1)
    assert result.first_step == 2 and history_on_disk() == result.history
    assert [p["step"] for p in history_on_disk()] == [1, 2, 3, 4, 5, 6]
    # the resumed run's history on disk is an uninterrupted run's
    uninterrupted = str(tmp_path / "straight")
    straight, _ = _killable_grpo(RLConfig(grpo=GRPOConfig(steps=6, eval_every=2)), uninterrupted)(kill_at=-1)
    assert _jsonl(os.path.join(uninterrupted, "train_history.jsonl")) == history_on_disk() == straight.history


def test_grpo_step_times_leave_evaluations_out_and_survive_a_resume(tmp_path):
    """``step_times.jsonl``: each step once (a resumed run times again the steps after its checkpoint), its
    time without the evaluations around it, and the imagined frames of a step from its ``mean_chunks``."""
    workdir = str(tmp_path / "grpo")
    rl = RLConfig(grpo=GRPOConfig(steps=4, eval_every=2, rollout_batch=2, group_size=3))
    # each evaluation far longer than a step: a step's time must not include it
    run = _killable_grpo(rl, workdir, eval_pause_s=1.0, frames_per_chunk=4)

    def times_on_disk():
        return _jsonl(os.path.join(workdir, "step_times.jsonl"))

    with pytest.raises(_Killed):
        run(kill_at=4)
    assert [r["step"] for r in times_on_disk()] == [1, 2]
    run(kill_at=-1)
    rows = times_on_disk()
    assert [r["step"] for r in rows] == [1, 2, 3, 4]
    assert all(0.0 <= r["step_s"] < 0.9 for r in rows), rows
    # 2 starts x 3 members x 4 frames per chunk x mean_chunks (step k's batch is k, so k + 1 chunks)
    assert [r["imagined_frames"] for r in rows] == [24 * 2, 24 * 3, 24 * 4, 24 * 5]
    assert all(r["imagined_frames_per_s"] == pytest.approx(r["imagined_frames"] / r["step_s"]) for r in rows)


def test_grpo_stopped_on_request_evaluates_its_step_in_flight_and_resumes_there(tmp_path):
    """A stop asked for while step 3 runs (SIGUSR1 under cli.run sets the same request): GRPO evaluates step 3
    although evaluations fall every 4 steps, checkpoints it and raises StopRequested; the resumed run goes on from
    step 3 to the uninterrupted run's parameters, its curve holding the extra point."""
    from sword_jax import cli

    rl = RLConfig(grpo=GRPOConfig(steps=6, eval_every=4))
    workdir = str(tmp_path / "grpo")
    run_id = grpo_run_id(rl, seed=0, simulator="toy", **{"sim.tasks": (0, 1)})
    update = jax.jit(lambda state, batch: state.replace(params={"w": state.params["w"] + batch}, step=state.step + 1))

    def run(ask_at: int):
        def step(state, batch, key):
            if float(batch) == ask_at:
                cli.request_stop()
            state = update(state, batch)
            return state, {"loss": jnp.sum(state.params["w"])}

        return _toy_grpo(step, rl, workdir, run_id)

    try:
        with pytest.raises(cli.StopRequested, match="GRPO: stopped on request after step 3 of 6; checkpoint of step 3"):
            run(ask_at=3)
    finally:
        cli.clear_stop_request()
    assert _final_state(os.path.join(workdir, "checkpoints"))[1]["step"] == 3
    assert _curve_on_disk(workdir) == [(0, 0.0), (3, 6.0)]  # w after 1 + 2 + 3
    result, _ = run(ask_at=-1)
    assert result.first_step == 3 and float(result.state.params["w"][0]) == 21.0  # 1 + ... + 6, as uninterrupted
    assert _curve_on_disk(workdir) == [(0, 0.0), (3, 6.0), (4, 10.0), (6, 21.0)]
