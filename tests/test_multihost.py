"""Multi-host: two processes started by ``train.launch`` and joined by ``jax.distributed`` over loopback
(gloo CPU collectives) run sharded DLB steps equal to one process with the same global device count;
checkpoints restore onto a different device count; a rank killed mid-run ends the job within the
launcher's grace and the rerun resumes bit-identical; the VAE, each rank making only its rows of a
batch, trains as one process does and resumes bit-identical; so does GRPO in the toy simulator and in the
world model (evaluated in MuJoCo), each rank making (and encoding) only its rows of the start states."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from sword_jax.pipeline.launch import STOP_MARGIN_S
from tests.conftest import FAST_COMPILE, REPO
from tests.support.checkpoints import assert_same_final_checkpoint, final_arrays
from tests.support.rl import TINY_RL

STEPS = 4
ARGS = ["--config", "sword:tiny", "--synthetic", f"--trainer.steps={STEPS}", "--trainer.checkpoint_every=2",
        "--trainer.log_every=2", "--data.batch_size=4", "--data.num_episodes=8"]


def _env(devices: int, cache_dir: str, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(XLA_FLAGS=f"{FAST_COMPILE} --xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu",
               JAX_COMPILATION_CACHE_DIR=cache_dir, PYTHONUNBUFFERED="1", **extra)
    return env


def _train(workdir: str, env: dict[str, str], *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "train.train_world_model", "--workdir", workdir, *ARGS, *extra],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _launch(workdir: str, cache_dir: str, *extra: str, grace: float = 5.0, trainer: str = "train.train_world_model",
            args: list[str] = ARGS) -> subprocess.Popen:
    """``train.launch``: two ranks of 2 CPU devices each run the trainer on a 4-device mesh."""
    return subprocess.Popen([sys.executable, "-m", "train.launch", "--processes", "2", "--cpu-devices", "2", "--grace",
                             str(grace), "--", sys.executable, "-m", trainer, "--workdir", workdir,
                             *args, "--mesh.data=4", "--mesh.distributed=true", *extra],
                            cwd=REPO, env=_env(2, cache_dir), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def _wait(proc: subprocess.Popen) -> str:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, (out or "")[-3000:] + (err or "")[-3000:]
    return out


def test_two_processes_equal_one_and_checkpoint_moves_between_device_counts(tmp_path):
    cache = str(tmp_path / "xla_cache")
    single = str(tmp_path / "single")
    # one checkpoint, at the end, for each run; the held-out evaluation reads the weights and changes nothing: only
    # the launched run compiles it
    once = f"--trainer.checkpoint_every={STEPS}"
    _wait(_train(single, _env(4, cache), "--mesh.data=4", once, "--trainer.eval_every=0"))

    multi = str(tmp_path / "multi")
    output = _wait(_launch(multi, cache, once, "--trainer.eval_segments=true"))
    assert "[rank 0] [train_world_model] sword-tiny: mesh {'data': 4" in output
    assert "[rank 1] [train_world_model]" not in output, "only process 0 logs"
    # every fixed segment measured alone, gathered from both ranks: a batch's figure is its segments'
    # energy-weighted mean, and the evaluation's (its last step) the mean of its batches'
    with open(os.path.join(multi, "heldout_segments.json")) as f:
        segments = json.load(f)
    last = _metrics(multi)[STEPS]
    assert segments["step"] == STEPS and sorted(segments["splits"]) == ["heldout", "train"]
    for split, each in segments["splits"].items():
        assert len(each["episodes"]) == len(each["energy"]) == 2 * 4  # trainer.eval_batches x data.batch_size
        error, energy = (np.asarray(each[k]).reshape(2, 4) for k in ("sample_error_5", "energy"))
        figure = ((error * energy).sum(1) / energy.sum(1)).mean()
        assert figure == pytest.approx(last[f"eval_{split}_sample_error_5"], rel=1e-4), split

    want, want_meta = final_arrays(single)
    got, got_meta = final_arrays(multi)
    assert want.keys() == got.keys()
    assert got_meta["step"] == want_meta["step"] == STEPS
    for name in want:
        np.testing.assert_allclose(got[name], want[name], rtol=2e-5, atol=2e-6, err_msg=name)

    # The 4-device checkpoint restores onto one device and training continues.
    resumed = _wait(_train(multi, _env(1, cache), "--mesh.data=1", f"--trainer.steps={STEPS + 2}", once,
                           "--trainer.eval_every=0"))
    assert f"resumed from step {STEPS}" in resumed
    after, after_meta = final_arrays(multi)
    assert after_meta["step"] == STEPS + 2
    assert any(not np.array_equal(after[k], got[k]) for k in got if "params" in k)


LONG_STEPS = 8


def _metrics(workdir: str) -> dict[int, dict]:
    rows = {}
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        for line in f:
            row = json.loads(line)
            rows[int(row["step"])] = row  # a step run again after the resume replaces the killed run's row
    return {k: {m: v for m, v in row.items() if m not in ("elapsed_s", "eta_s")} for k, row in rows.items()}


def _kill_rank1_after_checkpoint(proc: subprocess.Popen, ckpt_dir: str, at_least: int, grace: float) -> tuple[int, float]:
    """Waits for a checkpoint of step >= ``at_least`` in ``ckpt_dir``, SIGKILLs rank 1 of the launched job ``proc``
    and checks the job ends, naming that rank, within the grace; returns (the newest checkpoint step then, seconds
    from the kill to the job's end)."""
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")), daemon=True)
    reader.start()
    deadline = time.time() + 600
    saved: list[int] = []
    while time.time() < deadline and proc.poll() is None:
        saved = [int(d) for d in os.listdir(ckpt_dir) if d.isdigit()] if os.path.isdir(ckpt_dir) else []
        if saved and max(saved) >= at_least:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "the run finished before it could be killed"
    rank1 = int(next(re.search(r"rank 1: pid (\d+)", line).group(1) for line in lines if "rank 1: pid" in line))
    os.kill(rank1, signal.SIGKILL)  # lands inside a step or a checkpoint write
    killed = time.monotonic()
    proc.wait(timeout=grace + 60)
    stopped = time.monotonic() - killed
    reader.join(timeout=5)
    output = "".join(lines)
    assert proc.returncode == 128 + signal.SIGKILL, output[-3000:]
    assert "rank 1 failed first (killed by SIGKILL)" in output
    assert stopped < grace + STOP_MARGIN_S + 1.0, stopped  # + the launcher's own exit
    return max(saved), stopped


# The default run keeps this covered in parts: tests/test_launch.py::test_a_killed_jax_rank_ends_the_job_and_each_
# rank_reads_only_its_rows (a killed jax.distributed rank ends the job within the grace), tests/test_reliability.py::
# test_sigkill_resume_is_bit_identical (a killed run resumes bit-identical) and the launched trainer above.
@pytest.mark.slow
def test_launched_run_with_a_killed_rank_ends_within_the_grace_and_resumes_bit_identical(tmp_path):
    cache = str(tmp_path / "xla_cache")
    long_args = (f"--trainer.steps={LONG_STEPS}", "--trainer.checkpoint_every=1", "--trainer.log_every=1")
    reference = str(tmp_path / "reference")
    _wait(_launch(reference, cache, *long_args))

    crashed = str(tmp_path / "crashed")
    grace = 3.0
    proc = _launch(crashed, cache, *long_args, grace=grace)
    step, stopped = _kill_rank1_after_checkpoint(proc, os.path.join(crashed, "checkpoints"), 2, grace)
    print(f"killed rank 1 at checkpoint {step}; the job ended {stopped:.2f} s later (grace {grace} s)")

    resumed = _wait(_launch(crashed, cache, *long_args))
    assert "resumed from step" in resumed
    assert_same_final_checkpoint(reference, crashed, LONG_STEPS)
    assert _metrics(crashed) == _metrics(reference)


VAE_STEPS = 3
VAE_ARGS = ["--config", "sword:tiny", "--synthetic", "--clip-latents=1", "--vae.batch_size=4",
            "--trainer.log_every=1", "--trainer.checkpoint_every=1"]


# The default run checks each rank's VAE rows and their global batch (tests/test_launch.py::test_a_killed_jax_rank_
# ends_the_job_and_each_rank_reads_only_its_rows) and a resumed VAE run (tests/test_vae_entry.py, also -m slow).
@pytest.mark.slow
def test_launched_vae_trains_as_one_process_and_resumes_bit_identical(tmp_path):
    """``train.train_vae`` as two ranks of 2 CPU devices, each making 2 of the 4 rows of a batch, ends as one
    process on 4 devices does (params, logged metrics); stopped after 2 steps and rerun it ends bit-identical
    to an uninterrupted launched run."""
    cache = str(tmp_path / "xla_cache")
    single = str(tmp_path / "single")
    _wait(subprocess.Popen([sys.executable, "-m", "train.train_vae", "--workdir", single, *VAE_ARGS, "--mesh.data=4",
                            f"--vae.train_steps={VAE_STEPS}"], cwd=REPO, env=_env(4, cache), stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True))
    straight, split = str(tmp_path / "straight"), str(tmp_path / "split")
    _wait(_launch(straight, cache, f"--vae.train_steps={VAE_STEPS}", trainer="train.train_vae", args=VAE_ARGS))
    _wait(_launch(split, cache, "--vae.train_steps=2", trainer="train.train_vae", args=VAE_ARGS))
    resumed = _wait(_launch(split, cache, f"--vae.train_steps={VAE_STEPS}", trainer="train.train_vae", args=VAE_ARGS))
    assert "[rank 0] train_vae: resumed from step 2" in resumed, resumed[-3000:]

    want, want_meta = final_arrays(single)
    got, got_meta = final_arrays(straight)
    assert want.keys() == got.keys() and len(want) > 10
    assert got_meta["step"] == want_meta["step"] == VAE_STEPS
    for name in want:  # gloo's reduction order, through Adam's step on near-zero gradients: a few 1e-6 on weights ~0.05
        np.testing.assert_allclose(got[name], want[name], rtol=2e-5, atol=1e-5, err_msg=name)
    want_rows, got_rows = _metrics(single), _metrics(straight)
    assert sorted(got_rows) == sorted(want_rows) == list(range(1, VAE_STEPS + 1))
    for step in want_rows:
        for name, value in want_rows[step].items():
            np.testing.assert_allclose(got_rows[step][name], value, rtol=1e-4, atol=1e-6, err_msg=f"{step} {name}")

    again, again_meta = final_arrays(split)
    assert again.keys() == got.keys() and again_meta["step"] == VAE_STEPS
    for name in got:
        np.testing.assert_array_equal(again[name], got[name], err_msg=name)
    assert _metrics(split) == _metrics(straight)


GRPO_STEPS = 6
GRPO_ARGS = ["--config", "sword:tiny", "--simulator", "toy", "--rl.imagined.max_chunks=2", "--rl.grpo.rollout_batch=4",
             "--rl.grpo.eval_every=1", f"--rl.grpo.steps={GRPO_STEPS}", *TINY_RL]


def _grpo_history(workdir: str) -> list[dict]:
    with open(os.path.join(workdir, "rl", "grpo", "train_history.jsonl")) as f:
        return [json.loads(line) for line in f]


# The default run checks each rank's rows of the start states (tests/test_grpo.py::test_a_process_makes_only_its_
# rows_of_the_start_states) and a resumed single-process GRPO run (tests/test_rl_entrypoints.py, also -m slow).
@pytest.mark.slow
def test_launched_grpo_trains_as_one_process_and_a_killed_rank_resumes_bit_identical(tmp_path):
    """``train.grpo --simulator toy`` as two ranks of 2 CPU devices, each making 2 of the 4 start states of a
    step, ends as one process on 4 devices does (history, params); only rank 0 logs; rank 1 killed after a
    checkpoint ends the job within the grace, and the rerun ends bit-identical to an uninterrupted launched run."""
    _grpo_as_one_process_and_resumed(tmp_path, GRPO_ARGS, GRPO_STEPS, kill_after=2)


WM_GRPO_STEPS = 3


# ~5 min on 2 cores: four runs of the tiny world model, each evaluated in MuJoCo after every step.
@pytest.mark.slow
def test_launched_world_model_grpo_trains_as_one_process_and_a_killed_rank_resumes_bit_identical(tiny_run, tmp_path):
    """``train.grpo --simulator world_model`` (the tiny run's world model and VAE, keyframes of 32x32 demos, a
    random reward model whose threshold splits the groups) as two ranks of 2 CPU devices, each cutting and
    encoding 2 of the 4 start states of a step, with the world model and the VAE on the 4-device mesh of both
    ranks and a MuJoCo evaluation on each, ends as one process on 4 devices does; rank 1 killed after a
    checkpoint ends the job, and the rerun ends bit-identical."""
    import configs
    from sword_jax.rl.params_io import save_params
    from sword_jax.rl.reward_model import build_detector
    from tests.support.rl import write_demos

    demos = write_demos(str(tmp_path / "demos.hdf5"), steps=24, size=32)
    rl_flags = ["--config", "sword:tiny", "--model.num_layers=1", *TINY_RL]
    reward = str(tmp_path / "reward_model")
    rl = configs.from_argv(rl_flags)[0].rl
    save_params(reward, build_detector(rl, seed=0)[1], rl, kind="reward_model", step=0)
    args = [*rl_flags, "--simulator", "world_model", "--demos", demos,
            "--world-model", os.path.join(tiny_run, "world_model"), "--vae", os.path.join(tiny_run, "vae_run", "vae"),
            "--reward", reward, "--rl.success_threshold=0.5", "--rl.imagined.eval_replay_episodes=0",
            "--rl.imagined.eval_masked_proprio=false", "--rl.imagined.max_chunks=1", "--rl.grpo.rollout_batch=4",
            "--rl.grpo.eval_every=1", f"--rl.grpo.steps={WM_GRPO_STEPS}", "--eval-episodes=1", "--sim.max_steps=40"]
    history = _grpo_as_one_process_and_resumed(tmp_path, args, WM_GRPO_STEPS, kill_after=1)
    assert any(p["grad_norm"] > 0 for p in history), "every group's rewards were equal: the params never moved"


def _grpo_as_one_process_and_resumed(tmp_path, args: list[str], steps: int, kill_after: int) -> list[dict]:
    """``train.grpo`` with ``args`` as two launched ranks of 2 CPU devices equals one process on 4 devices
    (history within float tolerance, final params); only rank 0 logs; rank 1 killed once a checkpoint of step
    ``kill_after`` is written ends the job within the grace, and the rerun ends bit-identical to the
    uninterrupted launched run. Returns the single process's history."""
    cache = str(tmp_path / "xla_cache")
    single = str(tmp_path / "single")
    _wait(subprocess.Popen([sys.executable, "-m", "train.grpo", "--workdir", single, *args, "--mesh.data=4"],
                           cwd=REPO, env=_env(4, cache), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    straight = str(tmp_path / "straight")
    output = _wait(_launch(straight, cache, trainer="train.grpo", args=args))
    assert f"[rank 0] grpo step {steps}/{steps}" in output and "[rank 1] grpo step" not in output
    assert "[rank 1] eval step" not in output, "only process 0 logs"

    want, got = _grpo_history(single), _grpo_history(straight)
    assert [p["step"] for p in got] == [p["step"] for p in want] == list(range(1, steps + 1))
    for a, b in zip(want, got):
        assert a.keys() == b.keys()
        for name in a:  # gloo's reduction order: a few float32 ulps
            np.testing.assert_allclose(b[name], a[name], rtol=1e-4, atol=1e-6, err_msg=f"{a['step']} {name}")
    want_arrays, want_meta = final_arrays(os.path.join(single, "rl", "grpo"))
    got_arrays, got_meta = final_arrays(os.path.join(straight, "rl", "grpo"))
    assert want_arrays.keys() == got_arrays.keys() and len(want_arrays) > 10
    assert got_meta["step"] == want_meta["step"] == steps
    for name in want_arrays:
        np.testing.assert_allclose(got_arrays[name], want_arrays[name], rtol=2e-5, atol=1e-6, err_msg=name)
    with open(os.path.join(straight, "rl", "grpo", "success_curve.json")) as f:
        assert [p["step"] for p in json.load(f)["points"]] == list(range(steps + 1))

    crashed = str(tmp_path / "crashed")
    grace = 3.0
    proc = _launch(crashed, cache, trainer="train.grpo", args=args, grace=grace)
    _kill_rank1_after_checkpoint(proc, os.path.join(crashed, "rl", "grpo", "checkpoints"), kill_after, grace)

    resumed = _wait(_launch(crashed, cache, trainer="train.grpo", args=args))
    assert "[rank 0] GRPO: resumed from step" in resumed, resumed[-3000:]
    again, again_meta = final_arrays(os.path.join(crashed, "rl", "grpo"))
    assert again.keys() == got_arrays.keys() and again_meta["step"] == steps
    for name in got_arrays:
        np.testing.assert_array_equal(again[name], got_arrays[name], err_msg=name)
    assert _grpo_history(crashed) == _grpo_history(straight)
    return want
