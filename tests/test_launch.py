"""``train.launch``: one process per GPU (here CPU devices, gloo) joined by ``jax.distributed``; each rank's
output prefixed; a failed or killed rank ends the whole job within the stated grace, naming the rank,
with no rank left waiting on a collective; each rank's world-model, VAE and light-decoder loaders read only its
rows.

The launcher driving the real ``train.train_world_model`` is ``tests/test_multihost.py``'s."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import time

import pytest

from sword_jax.pipeline import launch as launcher
from tests.conftest import FAST_COMPILE, REPO
from train import launch as launch_entry


def test_each_rank_gets_its_gpu_or_cpu_devices_and_multicast_off():
    env = launcher.rank_env(1, 4, "127.0.0.1:1234", gpu="3", environ={"PATH": "/bin"})
    assert env["CUDA_VISIBLE_DEVICES"] == "3" and env["PATH"] == "/bin"
    assert [env[f"JAX_{name}"] for name in ("COORDINATOR_ADDRESS", "NUM_PROCESSES", "PROCESS_ID")] == [
        "127.0.0.1:1234", "4", "1"]
    assert env["NCCL_NVLS_ENABLE"] == "0" and env["NVSHMEM_DISABLE_NVLS"] == "1"
    cpu = launcher.rank_env(0, 2, "h:1", cpu_devices=3,
                            environ={"XLA_FLAGS": "--a=1 --xla_force_host_platform_device_count=8"})
    assert cpu["JAX_PLATFORMS"] == "cpu" and "CUDA_VISIBLE_DEVICES" not in cpu
    assert cpu["XLA_FLAGS"] == "--a=1 --xla_force_host_platform_device_count=3"
    assert launcher.default_gpus(2, {}) == ["0", "1"]
    assert launcher.default_gpus(2, {"CUDA_VISIBLE_DEVICES": "4,6,7"}) == ["4", "6"]
    with pytest.raises(ValueError, match="names 1 GPUs"):
        launcher.default_gpus(2, {"CUDA_VISIBLE_DEVICES": "5"})


def test_the_command_line_refuses_a_trainer_that_would_not_join_the_job():
    with pytest.raises(launch_entry.UsageError, match="mesh.distributed=true"):
        launch_entry.main(["--processes", "2", "--", "python", "-m", "train.train_world_model", "--workdir", "w"])
    with pytest.raises(launch_entry.UsageError, match="train.train_policy does not join"):
        launch_entry.main(["--processes", "2", "--", "python", "-m", "train.train_policy", "--mesh.distributed=true"])
    folder = os.path.join(REPO, "train")
    joining = sorted(f"train.{name[:-3]}" for name in os.listdir(folder) if name.endswith(".py") and
                     name != "distributed.py" and "distributed.initialize(" in open(os.path.join(folder, name)).read())
    assert list(launch_entry.JOINING) == joining
    with pytest.raises(launch_entry.UsageError, match="after --"):
        launch_entry.main(["--processes", "2", "python", "x.py"])
    with pytest.raises(launch_entry.UsageError, match="2 GPUs for 4"):
        launch_entry.main(["--processes", "4", "--gpus", "0,1", "--", "python", "x.py"])


def test_ranks_output_is_prefixed_and_kept_per_rank(tmp_path):
    code = ("import os; r = os.environ['JAX_PROCESS_ID']; "
            "print('hello', r, os.environ['JAX_NUM_PROCESSES'], os.environ['CUDA_VISIBLE_DEVICES'])")
    out = io.StringIO()
    result = launcher.launch([sys.executable, "-c", code], 2, gpus=["5", "7"], log_dir=str(tmp_path), out=out)
    assert result == launcher.LaunchResult(0, None, (0, 0), None)
    lines = out.getvalue().splitlines()
    assert "[rank 0] hello 0 2 5" in lines and "[rank 1] hello 1 2 7" in lines
    assert (tmp_path / "rank1.log").read_text() == "hello 1 2 7\n"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


def test_a_failed_rank_stops_the_others_within_the_grace(tmp_path):
    """Rank 1 exits 3; rank 0 ignores SIGTERM and has a child of its own: both are SIGKILLed after the grace."""
    code = ("import os, signal, subprocess, sys, time\n"
            "if os.environ['JAX_PROCESS_ID'] == '1':\n    time.sleep(0.5); sys.exit(3)\n"
            "signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
            f"child = subprocess.Popen(['sleep', '60']); open({str(tmp_path / 'child')!r}, 'w').write(str(child.pid))\n"
            "time.sleep(60)\n")
    out = io.StringIO()
    grace = 1.0
    start = time.monotonic()
    result = launcher.launch([sys.executable, "-c", code], 2, cpu_devices=1, grace_s=grace, out=out)
    elapsed = time.monotonic() - start
    assert (result.returncode, result.failed_rank, result.rank_returncodes) == (3, 1, (-9, 3)), out.getvalue()
    assert grace <= result.stop_seconds <= grace + launcher.STOP_MARGIN_S
    assert elapsed < 0.5 + grace + launcher.STOP_MARGIN_S + 10  # + two interpreters' start
    assert "rank 1 failed first (exit status 3)" in out.getvalue()
    child = int((tmp_path / "child").read_text())
    deadline = time.monotonic() + 2.0  # SIGKILL is delivered, not waited for
    while _alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(child)  # the rank's whole process group went


def test_a_killed_jax_rank_ends_the_job_and_each_rank_reads_only_its_rows(tmp_path):
    """Two ``jax.distributed`` ranks of 2 CPU devices each: each loader (world model, VAE clips, VAE squares,
    light-decoder clips) reads 4 of the 8 rows of a batch and the global batch equals a single process's; then
    rank 1 is SIGKILLed while rank 0 enters a collective (alone, it would wait for JAX's heartbeat timeout): the
    job ends within the grace, naming rank 1."""
    grace = 2.0
    env = dict(os.environ, XLA_FLAGS=FAST_COMPILE)
    proc = subprocess.run([sys.executable, "-m", "train.launch", "--processes", "2", "--cpu-devices", "2", "--grace",
                           str(grace), "--log-dir", str(tmp_path), "--", sys.executable, "-m",
                           "tests.support.loader_rank"], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    ended = time.time()
    out = proc.stdout
    assert proc.returncode == 128 + 9, out[-3000:] + proc.stderr[-2000:]
    assert "rank 1 failed first (killed by SIGKILL)" in out
    for rank, rows in ((0, [0, 1, 2, 3]), (1, [4, 5, 6, 7])):
        assert out.count(f"[rank {rank}] rank {rank} rows {rows} read 4 of 8") == 3, out[-3000:]
        assert out.count(f"[rank {rank}] rank {rank} vae rows {rows} cut 4 of 8") == 3, out[-3000:]
        assert f"[rank {rank}] rank {rank} squares rows {rows} drew 4 of 8" in out, out[-3000:]
        assert out.count(f"[rank {rank}] rank {rank} light rows {rows} cut 4 of 8") == 3, out[-3000:]
    assert "passed a collective" not in out
    died = float(re.search(r"rank 1 dies at ([\d.]+)", out).group(1))
    assert ended - died < grace + launcher.STOP_MARGIN_S + 1.0  # + the launcher's own exit
    assert "rank 1 dies at" in (tmp_path / "rank1.log").read_text()


def test_a_launcher_told_to_stop_says_by_which_signal_and_restores_its_handlers(tmp_path):
    """SIGTERM to the launcher stops the ranks; the result names the signal (a caller running several jobs
    re-raises it) and the caller's own handler is back in place."""
    import signal
    import threading

    seen = []
    previous = signal.signal(signal.SIGTERM, lambda s, _f: seen.append(s))
    try:
        timer = threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGTERM))
        timer.start()
        result = launcher.launch([sys.executable, "-c", "import time; time.sleep(60)"], 2, cpu_devices=1,
                                 grace_s=1.0, out=io.StringIO())
        timer.join()
        assert result.stop_signal == signal.SIGTERM and result.returncode == 128 + signal.SIGTERM
        assert result.failed_rank is None and seen == []  # the launcher's handler took it, not the caller's
        os.kill(os.getpid(), signal.SIGTERM)
        assert seen == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)
