"""benchmarks.bench_multiprocess: its comparisons tell a bit-identical run from one a single ulp away; its plain
processes keep NVLink multicast off; on CPU (2 gloo processes of 2 devices) the whole benchmark kills a rank,
sees the job end within the grace, resumes bit-identical and restores on 2 and 1 devices with the same loss."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import bench_multiprocess as bench
from sword_jax.checkpoint import Checkpointer
from tests.conftest import REPO


def _run_dir(path: str, weights: np.ndarray, losses: list[float]) -> str:
    """A work dir as the trainer leaves it: a checkpoint of the last step and one metrics row per step."""
    os.makedirs(path)
    state = {"params": {"w": jnp.asarray(weights)}, "step": jnp.asarray(len(losses), jnp.int32)}
    with Checkpointer(os.path.join(path, "checkpoints")) as ckpt:
        ckpt.save(len(losses), state, {"step": len(losses), "data_position": [len(losses), 0]})
    with open(os.path.join(path, "metrics.jsonl"), "w") as f:
        for step, loss in enumerate(losses, start=1):
            f.write(json.dumps({"step": step, "loss": loss, "elapsed_s": step * 0.5, "eta_s": 1.0}) + "\n")
    return path


def test_comparisons_tell_identical_runs_from_runs_one_ulp_apart(tmp_path):
    weights = np.linspace(-1, 1, 12, dtype=np.float32).reshape(3, 4)
    reference = _run_dir(str(tmp_path / "reference"), weights, [1.5, 1.25])
    same = _run_dir(str(tmp_path / "same"), weights.copy(), [1.5, 1.25])
    with open(os.path.join(same, "metrics.jsonl"), "a") as f:  # a resumed run's repeated step: the last row counts
        f.write(json.dumps({"step": 2, "loss": 1.25, "elapsed_s": 9.0, "eta_s": 0.0}) + "\n")
    found = bench.compare_runs(reference, same, steps=2)
    assert found["equal"] and found["checkpoint"]["arrays"] == 2 and found["metrics"]["steps"] == [1, 2]

    nudged = weights.copy()
    nudged[1, 2] = np.nextafter(nudged[1, 2], np.float32(2))
    apart = _run_dir(str(tmp_path / "apart"), nudged, [1.5, 1.25 * (1 + 1e-7)])
    found = bench.compare_runs(reference, apart, steps=2)
    assert not found["equal"]
    assert list(found["checkpoint"]["differing_arrays"]) == ["/params/w"]
    assert 0 < found["checkpoint"]["differing_arrays"]["/params/w"] < 1e-6
    assert found["metrics"]["differing_steps"] == [2] and 0 < found["metrics"]["max_rel_diff"] < 1e-6

    shutil.rmtree(os.path.join(apart, "checkpoints"))
    assert "error" in bench.compare_runs(reference, apart, steps=2)  # reported, not raised


def test_plain_processes_keep_multicast_off_and_leave_the_job_variables_out():
    base = {"JAX_PROCESS_ID": "1", "JAX_NUM_PROCESSES": "2", "JAX_COORDINATOR_ADDRESS": "127.0.0.1:1",
            "XLA_FLAGS": "--xla_cpu_max_isa=AVX --xla_force_host_platform_device_count=8"}
    gpu = bench.single_process_env(base, 2, ["2", "3"])
    cpu = bench.single_process_env(base, 1, None)
    for env in (gpu, cpu):
        assert {k: env[k] for k in bench.launcher.NO_MULTICAST} == bench.launcher.NO_MULTICAST
        assert not any(k in env for k in ("JAX_PROCESS_ID", "JAX_NUM_PROCESSES", "JAX_COORDINATOR_ADDRESS"))
    assert gpu["CUDA_VISIBLE_DEVICES"] == "2,3"
    assert cpu["JAX_PLATFORMS"] == "cpu"
    assert cpu["XLA_FLAGS"] == "--xla_cpu_max_isa=AVX --xla_force_host_platform_device_count=1"


# ~100 s on 2 cores: six launches of the tiny world model (warm-up, reference, crash, resume, two restores).
@pytest.mark.slow
def test_benchmark_on_cpu_resumes_bit_identical_and_restores_on_fewer_devices(tmp_path):
    out = tmp_path / "report.json"
    results = os.path.join(REPO, "benchmarks", "results", "latest.json")
    before = open(results).read() if os.path.exists(results) else None
    proc = subprocess.run([sys.executable, "-m", "benchmarks.bench_multiprocess", "--processes", "2", "--cpu-devices",
                           "2", "--config", "sword:tiny", "--grace", "3", "--workdir", str(tmp_path / "runs"),
                           "--out", str(out), "--no-record"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["ok"] and report["resume_exact"]
    assert report["processes"] == 2 and report["devices"] == 4 and report["steps"] == 6

    crash = report["crash"]
    assert crash["killed_rank"] == 1 and crash["kill_step"] >= bench.KILL_AFTER
    assert crash["returncode"] == 137 and crash["names_failed_rank"]
    assert crash["seconds_kill_to_end"] <= crash["limit_s"] == 3.0 + bench.launcher.STOP_MARGIN_S + 1.0

    resume = report["resume"]
    assert resume["resumed_from"] == crash["resumable_from"] >= crash["kill_step"]
    assert resume["checkpoint"]["arrays"] > 100 and resume["checkpoint"]["differing_count"] == 0
    assert resume["checkpoint"]["step"] == 6 and resume["metrics"]["steps"] == [1, 2, 3, 4, 5, 6]
    assert report["warmup"]["equal_to_reference"]["equal"]  # no autotuning on CPU

    restore = report["restore"]
    assert restore["from_step"] == 3 and restore["rtol"] == bench.RESTORE_RTOL["float32"]
    assert [run["devices"] for run in restore["runs"]] == [2, 1]
    for run in restore["runs"]:
        assert run["ok"] and run["resumed_from"] == 3 and run["rel_diff"] < 1e-5, run
        assert run["loss"] == pytest.approx(run["reference_loss"], rel=1e-5)
    assert (open(results).read() if os.path.exists(results) else None) == before  # --no-record
