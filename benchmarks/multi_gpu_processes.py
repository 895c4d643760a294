"""One process per device: the rows of ``benchmarks.bench_multi_gpu --small-processes``.

Each row is one job of ``k`` processes of one device each, started by the project's launcher
(:func:`sword_jax.pipeline.launch.launch`) and joined by ``jax.distributed``; every rank runs
``python -m benchmarks.multi_gpu_processes --worker SPEC`` (:func:`worker`), which times the small config's DLB
step on a ``data`` mesh over all the processes' devices, each process putting only its rows of the batch.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import sys
import tempfile
import threading
import time
from typing import Any

import jax

from benchmarks import bench_multi_gpu as bench
from benchmarks import common
from sword_jax import cli
from sword_jax import sharding as shd
from sword_jax.atomic_write import write_json_atomic
from sword_jax.dit.config import DiTConfig
from sword_jax.dlb.config import CacheConfig
from sword_jax.pipeline import launch as launcher

PROCESS_GRACE_S = 5.0  # a process-per-device job: SIGTERM -> SIGKILL of its other ranks once one failed
LOG_TAIL_CHARS = 600  # of a failed rank's output, kept in its row's error


def process_row(model_cfg: DiTConfig, processes: int, per_device_batch: int, hw: tuple[int, int], *, iters: int,
                blocks: int, unrolled: bool, timeout_s: float, on_cpu: bool) -> dict:
    """The small config's DLB step (cache on, no per-compile options) timed by ``processes`` processes of one
    device each, launched by :func:`sword_jax.pipeline.launch.launch` and joined by ``jax.distributed`` (process
    ``i`` on GPU ``i``, or on one CPU device with gloo collectives when ``on_cpu``), on a ``data`` mesh over
    every process's device. Each rank runs :func:`worker`; rank 0's figures make the row. A job that fails or
    runs past ``timeout_s`` (each rank stops itself then) gives a row with status ``error`` and the failed
    rank's last output."""
    label = f"{per_device_batch}/dev k={processes} {processes}proc" + (" unrolled" if unrolled else "")
    row: dict[str, Any] = {"label": label, "devices": processes, "processes": processes,
                           "per_device_batch": per_device_batch, "cache": True, "overlap": False, "unrolled": unrolled,
                           "status": "ok"}
    with tempfile.TemporaryDirectory(prefix="bench_multi_gpu_") as tmp:
        spec = {"label": label, "model": dataclasses.asdict(model_cfg), "cache": dataclasses.asdict(bench.DLB_CACHE),
                "per_device_batch": per_device_batch, "hw": list(hw), "iters": iters, "blocks": blocks,
                "unrolled": unrolled, "timeout_s": timeout_s, "out": os.path.join(tmp, "row.json")}
        write_json_atomic(os.path.join(tmp, "spec.json"), spec)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (common.REPO, os.environ.get("PYTHONPATH")) if p))
        if not on_cpu:  # this process keeps GPU memory of its own rows; the ranks take theirs as they need it
            env["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
        start = time.perf_counter()
        result = launcher.launch(worker_command(os.path.join(tmp, "spec.json")), processes,
                                 cpu_devices=1 if on_cpu else None, log_dir=os.path.join(tmp, "logs"),
                                 grace_s=PROCESS_GRACE_S, environ=env)
        row["launch_s"] = time.perf_counter() - start
        if result.stop_signal is not None:  # the benchmark was told to stop: it stops, not only this row
            signal.raise_signal(result.stop_signal)
        if os.path.exists(spec["out"]):
            with open(spec["out"]) as f:
                row.update({k: v for k, v in json.load(f).items() if k != "label"})
        if not os.path.exists(spec["out"]) or (result.returncode and row["status"] == "ok"):
            rank = result.failed_rank or 0
            log = os.path.join(tmp, "logs", f"rank{rank}.log")
            tail = open(log, errors="replace").read()[-LOG_TAIL_CHARS:] if os.path.exists(log) else ""
            row.update(status="error", error=f"the job ended with status {result.returncode} (rank {rank} failed "
                                             f"first); its last output: {tail.strip()}")
    if row["status"] != "ok":
        print(f"  {label}: {row['status'].upper()} -- {row['error']}", flush=True)
    return row


def worker_command(spec_path: str) -> list[str]:
    return [sys.executable, "-m", "benchmarks.multi_gpu_processes", "--worker", spec_path]


def worker(spec_path: str) -> int:
    """One rank of a :func:`process_row` job: joins it, times the step
    (:func:`benchmarks.bench_multi_gpu.measure_small`) on a ``data`` mesh over every process's devices, each
    process putting only its rows of the batch, and (rank 0) writes the row's figures or its failure to the
    spec's ``out``. Exits 124 once the spec's ``timeout_s`` has passed (the
    launcher then stops the other ranks), 1 when the step failed."""
    with open(spec_path) as f:
        spec = json.load(f)
    watchdog = threading.Timer(spec["timeout_s"], _expire, args=(spec["label"], spec["timeout_s"]))
    watchdog.daemon = True
    watchdog.start()
    launcher.join()
    model_cfg = DiTConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec["model"].items()})
    mesh = shd.make_mesh(shd.MeshConfig(data=-1), devices=jax.devices())
    row: dict[str, Any] = {"label": spec["label"], "status": "ok"}
    try:
        row.update(bench.measure_small(model_cfg, CacheConfig(**spec["cache"]), mesh, spec["per_device_batch"],
                                       tuple(spec["hw"]), options=None, iters=spec["iters"], blocks=spec["blocks"],
                                       unrolled=spec["unrolled"]))
    except Exception as err:  # noqa: BLE001 - reported in the row, and by the exit status
        bench.failure_row(row, err)
    if jax.process_index() == 0:
        write_json_atomic(spec["out"], row)
    watchdog.cancel()
    return 0 if row["status"] == "ok" else 1


def _expire(label: str, timeout_s: float) -> None:
    print(f"{label}: not done after {timeout_s:g} s, stopping", flush=True)
    os._exit(124)


def main(argv: list[str] | None = None) -> int:
    parser = cli.ArgumentParser(description=__doc__)
    parser.add_argument("--worker", required=True, metavar="SPEC", help="the row's spec (JSON)")
    return worker(parser.parse_args(argv).worker)


if __name__ == "__main__":
    cli.run(main)
