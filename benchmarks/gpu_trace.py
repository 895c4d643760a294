"""Per-step kernel time of a ``jax.profiler`` trace on each GPU: collectives, other kernels, and the span from the
first kernel to the last (``benchmarks.bench_multi_gpu --profile``)."""

from __future__ import annotations

import glob
import gzip
import json
import os
import re
from typing import Any

import jax

from benchmarks import common

PROFILE_STEPS = 5  # steps traced per profiled row
# device-trace event names of collectives (NCCL kernels, XLA's collective thunks)
COLLECTIVE = re.compile(r"nccl|all[-_]?reduce|all[-_]?gather|reduce[-_]?scatter|all[-_]?to[-_]?all|collective|sendrecv",
                        re.IGNORECASE)


def summarize_trace(directory: str, steps: int) -> dict[str, Any]:
    """Per step, on each GPU of a ``jax.profiler`` trace (its perfetto JSON): milliseconds of collective kernels,
    of the other kernels, and of the span from the first kernel to the last. A collective that overlaps
    compute counts in both, so ``collective_ms + compute_ms - span_ms`` is at least the overlap. ``devices``
    is empty where the trace has no GPU lanes (a CPU run)."""
    paths = sorted(glob.glob(os.path.join(directory, "**", "*perfetto_trace.json.gz"), recursive=True))
    if not paths:
        return {"trace": None, "devices": {}}
    with gzip.open(paths[-1], "rt") as f:
        events = json.load(f)
    events = events.get("traceEvents", []) if isinstance(events, dict) else events
    lanes = {e["pid"]: e.get("args", {}).get("name", "") for e in events
             if e.get("ph") == "M" and e.get("name") == "process_name"}
    gpu = {pid: name for pid, name in lanes.items() if "/device:GPU" in name}
    threads = {(e["pid"], e.get("tid")): str(e.get("args", {}).get("name", "")) for e in events
               if e.get("ph") == "M" and e.get("name") == "thread_name" and e.get("pid") in gpu}
    # kernels only: a GPU lane's "Stream" threads (its XLA-module, XLA-op and step threads repeat the same time)
    streams = {key for key, name in threads.items() if name.lower().startswith("stream")}
    spans: dict[int, list[float]] = {}
    sums: dict[int, dict[str, float]] = {}
    for e in events:
        if e.get("ph") != "X" or e.get("pid") not in gpu or (streams and (e["pid"], e.get("tid")) not in streams):
            continue
        start, dur = float(e.get("ts", 0.0)), float(e.get("dur", 0.0))
        kind = "collective_ms" if COLLECTIVE.search(str(e.get("name", ""))) else "compute_ms"
        sums.setdefault(e["pid"], {"collective_ms": 0.0, "compute_ms": 0.0})[kind] += dur / 1e3
        lo_hi = spans.setdefault(e["pid"], [start, start + dur])
        lo_hi[0], lo_hi[1] = min(lo_hi[0], start), max(lo_hi[1], start + dur)
    devices = {}
    for pid, name in sorted(gpu.items(), key=lambda item: item[1]):
        if pid in sums:
            per = {k: v / steps for k, v in sums[pid].items()}
            per["span_ms"] = (spans[pid][1] - spans[pid][0]) / 1e3 / steps
            devices[name] = per
    return {"trace": paths[-1], "devices": devices}


def profile_steps(one, directory: str, steps: int = PROFILE_STEPS) -> dict[str, Any]:
    """``steps`` calls of ``one`` (a step returning its loss) dispatched back to back under ``jax.profiler``,
    written to ``directory``; their per-step summary (:func:`summarize_trace`)."""
    os.makedirs(directory, exist_ok=True)
    with jax.profiler.trace(directory, create_perfetto_trace=True):
        for _ in range(steps):
            loss = one()
        common.block(loss)
    return {"steps": steps, **summarize_trace(directory, steps)}
