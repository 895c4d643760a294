"""XLA's GPU options for the multi-GPU benchmark: the collective-overlap options, which of them this XLA knows (as
``XLA_FLAGS`` for a whole run or as per-compile options), and the backend's environment, set before it starts."""

from __future__ import annotations

import os
import subprocess
import sys
from typing import Any

import jax
import numpy as np

# XLA's GPU collective-overlap options (DebugOptions fields; on other backends they are accepted and unused).
OVERLAP_OPTIONS: dict[str, bool | int] = {
    "xla_gpu_enable_latency_hiding_scheduler": True,
    "xla_gpu_enable_highest_priority_async_stream": True,
    "xla_gpu_enable_pipelined_all_gather": True,
    "xla_gpu_enable_pipelined_reduce_scatter": True,
    "xla_gpu_enable_pipelined_all_reduce": True,
    "xla_gpu_enable_while_loop_double_buffering": True,
    "xla_gpu_all_reduce_combine_threshold_bytes": 128 << 20,
    "xla_gpu_all_gather_combine_threshold_bytes": 128 << 20,
    "xla_gpu_reduce_scatter_combine_threshold_bytes": 64 << 20,
}


def xla_flag_strings(options: dict[str, bool | int]) -> list[str]:
    return [f"--{name}={str(value).lower() if isinstance(value, bool) else value}" for name, value in options.items()]


def usable_xla_flags(flags: list[str], base: str = "") -> tuple[list[str], list[str]]:
    """``(kept, dropped)``: ``flags`` less those this XLA does not know (an unknown flag in ``XLA_FLAGS``
    aborts the process), found by starting JAX on the CPU in a subprocess with ``base`` + the flags."""
    kept, dropped = list(flags), []
    code = "import jax, jax.numpy as jnp; jax.jit(lambda x: x + 1)(jnp.float32(1)).block_until_ready()"
    for _ in range(len(flags) + 1):
        env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=" ".join([base, *kept]).strip())
        try:
            proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        except subprocess.TimeoutExpired:
            print("--xla-overlap: JAX did not start in 120 s with the overlap flags; none are set", flush=True)
            return [], flags
        if proc.returncode == 0:
            return kept, dropped
        unknown = [f for f in kept if any("nknown flag" in line and f in line.split()
                                          for line in proc.stderr.splitlines())]
        if not unknown:
            print(f"--xla-overlap: JAX does not start with the overlap flags ({proc.stderr.strip()[-300:]}); "
                  "none are set", flush=True)
            return [], flags
        kept = [f for f in kept if f not in unknown]
        dropped += unknown
    return kept, dropped


def backend_started() -> bool:
    """Whether a JAX backend is up already (XLA_FLAGS would no longer be read); False when this JAX cannot say
    (a command line's ``main`` runs before any device call)."""
    try:
        return bool(jax._src.xla_bridge.backends_are_initialized())
    except Exception:  # noqa: BLE001 - a private helper that may move
        return False


def configure_backend(xla_overlap: bool, mem_fraction: float, preallocate: bool = True) -> dict[str, Any]:
    """Environment for the backend, set before it starts: the memory fraction, without ``preallocate`` no
    preallocation (memory taken as needed, so processes started later find the rest of each GPU free) and, with
    ``xla_overlap``, the overlap flags in ``XLA_FLAGS``. Returns what was applied."""
    started = backend_started()
    os.environ.setdefault("XLA_PYTHON_CLIENT_MEM_FRACTION", str(mem_fraction))
    if not preallocate:
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    applied: dict[str, Any] = {"xla_overlap_flags": [], "dropped_flags": [],
                               "preallocate": os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE", "true")}
    if xla_overlap:
        base = os.environ.get("XLA_FLAGS", "")
        kept, applied["dropped_flags"] = usable_xla_flags(xla_flag_strings(OVERLAP_OPTIONS), base)
        os.environ["XLA_FLAGS"] = " ".join([base, *kept]).strip()
        applied["xla_overlap_flags"] = kept
        if applied["dropped_flags"]:
            print(f"--xla-overlap: this XLA does not know {applied['dropped_flags']}; left out", flush=True)
        if started:
            print("--xla-overlap: the backend had already started, XLA_FLAGS is not read again; only the "
                  "+overlap rows get the options", flush=True)
            applied["xla_overlap_flags"] = []
    return applied


def usable_compile_options(options: dict[str, bool | int]) -> dict[str, bool | int]:
    """The options this XLA accepts as per-compile options (each tried on a trivial program)."""
    usable = {}
    for name, value in options.items():
        try:
            jax.jit(lambda x: x + 1).lower(np.float32(1)).compile(compiler_options={name: value})
            usable[name] = value
        except Exception as err:  # noqa: BLE001 - an option this version of XLA does not have
            print(f"overlap option {name} not accepted ({str(err)[:100]}); left out", flush=True)
    return usable
