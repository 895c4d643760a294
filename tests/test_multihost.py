"""Multi-host: two processes joined by ``jax.distributed`` over loopback (gloo CPU collectives) run
sharded DLB steps equal to one process with the same global device count; checkpoints restore onto
a different device count."""

from __future__ import annotations

import os
import socket
import subprocess
import sys

import numpy as np

from tests.conftest import FAST_COMPILE, REPO
from tests.support.checkpoints import final_arrays

STEPS = 4
ARGS = ["--config", "sword:tiny", "--synthetic", f"--trainer.steps={STEPS}", "--trainer.checkpoint_every=2",
        "--trainer.log_every=2", "--data.batch_size=4", "--data.num_episodes=8"]


def _env(devices: int, cache_dir: str, **extra: str) -> dict[str, str]:
    env = dict(os.environ)
    env.update(XLA_FLAGS=f"{FAST_COMPILE} --xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu",
               JAX_COMPILATION_CACHE_DIR=cache_dir, PYTHONUNBUFFERED="1", **extra)
    return env


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _train(workdir: str, env: dict[str, str], *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "train.train_world_model", "--workdir", workdir, *ARGS, *extra],
                            cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait(proc: subprocess.Popen) -> str:
    out, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-3000:]
    return out


def test_two_processes_equal_one_and_checkpoint_moves_between_device_counts(tmp_path):
    cache = str(tmp_path / "xla_cache")
    single = str(tmp_path / "single")
    _wait(_train(single, _env(4, cache), "--mesh.data=4"))

    multi = str(tmp_path / "multi")
    port = _free_port()
    procs = [
        _train(multi, _env(2, cache, JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}", JAX_NUM_PROCESSES="2",
                           JAX_PROCESS_ID=str(i)), "--mesh.data=4", "--mesh.distributed=true")
        for i in range(2)
    ]
    outputs = [_wait(p) for p in procs]
    assert "mesh {'data': 4" in outputs[0]
    assert "mesh" not in outputs[1], "only process 0 logs"

    want, want_meta = final_arrays(single)
    got, got_meta = final_arrays(multi)
    assert want.keys() == got.keys()
    assert got_meta["step"] == want_meta["step"] == STEPS
    for name in want:
        np.testing.assert_allclose(got[name], want[name], rtol=2e-5, atol=2e-6, err_msg=name)

    # The 4-device checkpoint restores onto one device and training continues.
    resumed = _wait(_train(multi, _env(1, cache), "--mesh.data=1", f"--trainer.steps={STEPS + 2}"))
    assert f"resumed from step {STEPS}" in resumed
    after, after_meta = final_arrays(multi)
    assert after_meta["step"] == STEPS + 2
    assert any(not np.array_equal(after[k], got[k]) for k in got if "params" in k)
