"""Crash and resume: a run SIGKILLed mid-training (or mid-checkpoint) and restarted from its work dir
ends bit-identical to an uninterrupted run; a half-written checkpoint is never picked up; a
non-finite loss stops the run naming the step, leaving the last good checkpoint intact."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np

from tests.conftest import FAST_COMPILE, REPO
from tests.support.checkpoints import assert_same_final_checkpoint, final_arrays

STEPS = 6


def _env(cache_dir: str) -> dict[str, str]:
    env = dict(os.environ)
    env["XLA_FLAGS"] = FAST_COMPILE  # one CPU device per process: fast start
    env.update(JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=cache_dir,
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", PYTHONUNBUFFERED="1")
    return env


def _cmd(workdir: str, *extra: str) -> list[str]:
    return [sys.executable, "-m", "train.train_world_model", "--config", "sword:tiny", "--workdir", workdir,
            "--synthetic", f"--trainer.steps={STEPS}", "--trainer.checkpoint_every=1", "--trainer.log_every=1",
            "--trainer.keep_checkpoints=3",
            # the held-out measurement off: its resume is test_world_model_heldout's (a compile less per process)
            "--trainer.eval_every=0", *extra]


def _run(workdir: str, env: dict[str, str], *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(_cmd(workdir, *extra), cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


def _metrics(workdir: str) -> dict[int, dict]:
    rows = {}
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        for line in f:
            row = json.loads(line)
            rows[int(row["step"])] = row  # a re-run step after resume replaces the killed run's row
    return {k: {m: v for m, v in row.items() if m not in ("elapsed_s", "eta_s")} for k, row in rows.items()}


KILL_STEPS = 4  # a checkpoint every step: a kill after step 2 or 3 still leaves steps to resume


def test_sigkill_resume_is_bit_identical(tmp_path):
    env = _env(str(tmp_path / "xla_cache"))
    short = f"--trainer.steps={KILL_STEPS}"
    reference = str(tmp_path / "reference")
    done = _run(reference, env, short)
    assert done.returncode == 0, done.stderr[-2000:]

    crashed = str(tmp_path / "crashed")
    kill_at = random.Random(os.environ.get("SWORD_TEST_SEED", "7")).randint(2, KILL_STEPS - 1)
    proc = subprocess.Popen(_cmd(crashed, short), cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    ckpt_dir = os.path.join(crashed, "checkpoints")
    deadline = time.time() + 600
    while time.time() < deadline and proc.poll() is None:
        steps = [int(d) for d in os.listdir(ckpt_dir) if d.isdigit()] if os.path.isdir(ckpt_dir) else []
        if steps and max(steps) >= kill_at:
            break
        time.sleep(0.01)
    assert proc.poll() is None, "run finished before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)  # lands inside a step or a checkpoint write
    proc.wait()

    # A half-written checkpoint (as left by a kill during a write) must never be picked up.
    partial = os.path.join(ckpt_dir, f"{KILL_STEPS + 5}.orbax-checkpoint-tmp-1234")
    os.makedirs(os.path.join(partial, "state"), exist_ok=True)
    with open(os.path.join(partial, "state", "garbage"), "wb") as f:
        f.write(b"\x00" * 100)

    resumed = _run(crashed, env, short)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resumed from step" in resumed.stdout

    want, want_meta, got_meta = assert_same_final_checkpoint(reference, crashed, KILL_STEPS)
    assert got_meta["rng_root"] == want_meta["rng_root"]
    assert _metrics(crashed) == _metrics(reference)
    cache_leaves = [k for k in want if "cache" in k]
    assert cache_leaves and any(np.any(want[k] != 0) for k in cache_leaves), "the latent cache must be in the checkpoint"


def test_nonfinite_loss_stops_and_keeps_last_good_checkpoint(tmp_path):
    env = _env(str(tmp_path / "xla_cache"))
    workdir = str(tmp_path / "run")
    # A learning rate this large drives the parameters to inf within a few steps.
    result = _run(workdir, env, "--trainer.learning_rate=1e30", "--trainer.warmup_steps=0",
                  "--trainer.grad_clip=0", "--trainer.weight_decay=0")
    assert result.returncode != 0
    message = result.stderr
    assert "non-finite" in message and "step" in message, message[-2000:]
    arrays, meta = final_arrays(workdir)
    assert meta["step"] < STEPS
    assert all(np.all(np.isfinite(a)) for a in arrays.values() if a.dtype.kind == "f"), "last checkpoint must be finite"
