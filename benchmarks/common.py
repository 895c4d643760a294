"""Shared benchmark plumbing: timing, the GPU's measured ceilings, and the results file.

Every benchmark prints a table and merges its figures into ``benchmarks/results/latest.json``,
each as ``{"value", "target", "device", "date", "command", ...}``. Ceilings (bf16 matmul
TFLOP/s, device copy bandwidth) are measured in the same process, so ratios are side by side.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from sword_jax.atomic_write import write_json_atomic
from sword_jax.pipeline.launch import DETERMINISTIC_OPS, NO_MULTICAST, with_flag

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the checkout the benchmarks run from
RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "latest.json")


def device_name() -> str:
    device = jax.devices()[0]
    return f"{getattr(device, 'device_kind', device.platform)} x{jax.device_count()} ({device.platform})"


def command_line() -> str:
    return "python -m benchmarks." + os.path.splitext(os.path.basename(sys.argv[0]))[0] + (
        (" " + " ".join(sys.argv[1:])) if len(sys.argv) > 1 else ""
    )


def block(tree: Any) -> Any:
    return jax.tree.map(lambda x: x.block_until_ready() if hasattr(x, "block_until_ready") else x, tree)


def time_fn(fn: Callable[[], Any], *, warmup: int = 2, iters: int = 10) -> dict[str, float]:
    """Median / min wall seconds of ``fn()`` (which must return device arrays), after warmup."""
    for _ in range(warmup):
        block(fn())
    samples = []
    for _ in range(iters):
        start = time.perf_counter()
        block(fn())
        samples.append(time.perf_counter() - start)
    return {"median_s": statistics.median(samples), "min_s": min(samples), "iters": iters}


# Dense bf16 tensor-core peak (no sparsity) by device kind, from the vendors' datasheets, TFLOP/s.
NOMINAL_BF16_TFLOPS = (("H100 PCIe", 756.0), ("H100", 989.4), ("H200", 989.4), ("A100", 312.0))


def nominal_peak_tflops(device_kind: str | None = None) -> float | None:
    """The datasheet bf16 dense peak of ``device_kind`` (default device 0's), None for a kind not listed
    (CPUs included)."""
    kind = device_kind if device_kind is not None else getattr(jax.devices()[0], "device_kind", "")
    return next((tflops for name, tflops in NOMINAL_BF16_TFLOPS if name in kind), None)


def mfu(flops_per_item: float, items_per_s: float, peak_tflops: float | None) -> float | None:
    """Model FLOP utilisation: ``flops_per_item * items_per_s`` over ``peak_tflops`` (None without a peak)."""
    return flops_per_item * items_per_s / (peak_tflops * 1e12) if peak_tflops else None


def measured_matmul_tflops(n: int = 8192, dtype=jnp.bfloat16, iters: int = 10) -> float:
    """Peak dense matmul throughput of device 0, measured now (TFLOP/s)."""
    if jax.devices()[0].platform == "cpu":
        n = min(n, 1024)
    a = jax.random.normal(jax.random.key(0), (n, n), dtype)
    b = jax.random.normal(jax.random.key(1), (n, n), dtype)
    # Several products per call so launch overhead does not count.
    chain = jax.jit(lambda a, b: (a @ b) @ b + a @ (b @ b))
    timing = time_fn(lambda: chain(a, b), warmup=2, iters=iters)
    return 4 * 2 * n**3 / timing["min_s"] / 1e12


def measured_copy_gbps(num_bytes: int = 2 << 30, iters: int = 10) -> float:
    """Device-memory copy bandwidth, counting bytes read and written (GB/s)."""
    if jax.devices()[0].platform == "cpu":
        num_bytes = 64 << 20
    x = jnp.ones((num_bytes // 4,), jnp.float32)
    copy = jax.jit(lambda x: x * jnp.float32(1.0001))
    timing = time_fn(lambda: copy(x), warmup=2, iters=iters)
    return 2 * num_bytes / timing["min_s"] / 1e9


def peak_memory_gb(device: Any = None) -> float | None:
    """The allocator's peak of ``device`` (default device 0) so far, GB; None where it keeps no statistics."""
    device = jax.devices()[0] if device is None else device
    stats = device.memory_stats() if hasattr(device, "memory_stats") else None
    if not stats:
        return None
    return stats.get("peak_bytes_in_use", 0) / 1e9


def is_oom(err: BaseException) -> bool:
    """Whether ``err`` is the device running out of memory (XLA's RESOURCE_EXHAUSTED, CUDA's out of memory)."""
    text = str(err)
    return "RESOURCE_EXHAUSTED" in text or "out of memory" in text.lower()


def record(key: str, value: float, target: Any, **extra: Any) -> dict[str, Any]:
    """One results entry, stamped with device, date and command."""
    return {
        "value": value,
        "target": target,
        "device": device_name(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
        "command": command_line(),
        **extra,
    }


def merge_results(entries: dict[str, dict[str, Any]], path: str | None = None) -> str:
    """Read-modify-write of ``path`` (:data:`RESULTS` as it is at the call): replaces only the given keys; atomic
    rename."""
    path = path or RESULTS
    os.makedirs(os.path.dirname(path), exist_ok=True)
    current: dict[str, Any] = {}
    if os.path.exists(path):
        with open(path) as f:
            current = json.load(f)
    current.update(entries)
    return write_json_atomic(path, current, sort_keys=True)


def add_summary_options(parser: Any) -> None:
    """A run-and-summary benchmark's ``summary`` options, which :func:`save_summary` serves: ``--out``,
    ``--record`` and ``--command``."""
    parser.add_argument("--out", default="", help="summary: output path without extension (.json)")
    parser.add_argument("--record", action="store_true", help="summary: write the entry to benchmarks/results/latest.json")
    parser.add_argument("--command", default="", help="summary --record: the run's command, stored with the entry")


def interval_text(figure: dict[str, Any]) -> str:
    """A success figure (``mean``, ``ci95``) as ``mean [low, high]``, three decimals."""
    return f"{figure['mean']:.3f} [{figure['ci95'][0]:.3f}, {figure['ci95'][1]:.3f}]"


def summary_data(out: str, workdir: str) -> str:
    """What a recorded entry's ``data`` names: the summary file :func:`save_summary` writes (``out + ".json"``),
    else the run's workdir."""
    return out + ".json" if out else workdir


def save_summary(summary: dict[str, Any], out: str, entries: Callable[[], dict[str, dict[str, Any]]] | None = None
                 ) -> None:
    """A benchmark's ``summary`` mode: the summary to ``out + ".json"`` when ``out`` is given, and with
    ``entries`` (``--record``) the entries it makes merged into ``latest.json`` (:func:`merge_results`)."""
    if out:
        with open(out + ".json", "w") as f:
            json.dump(summary, f, indent=1)
    if entries is not None:
        merge_results(entries())


def print_table(rows: list[dict[str, Any]], columns: list[str]) -> None:
    widths = {c: max([len(c)] + [len(_fmt(r.get(c))) for r in rows]) for c in columns}
    print("  ".join(c.ljust(widths[c]) for c in columns))
    for row in rows:
        print("  ".join(_fmt(row.get(c)).ljust(widths[c]) for c in columns))


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "" if value is None else str(value)


def jaxpr_flops(fn: Callable[..., Any], *args: Any) -> float:
    """Matmul, convolution and fused-attention FLOPs (multiply-add = 2) of ``fn(*args)``, counted on its jaxpr.

    Backend-independent (XLA's GPU cost analysis leaves out convolutions run as library calls). cuDNN's fused
    attention (``jax.nn.dot_product_attention(implementation="cudnn")``, one primitive) counts as the two
    matmuls it runs, ``Q K^T`` and ``P V`` (its backward as five), as the XLA implementation's are counted.
    Scans count ``length`` times their body, conds their costliest branch; while loops, whose trip
    count is unknown, once. Elementwise work is not counted.
    """
    return _jaxpr_flops(jax.make_jaxpr(fn)(*args).jaxpr)


def _jaxpr_flops(jaxpr) -> float:
    total = 0.0
    for eqn in jaxpr.eqns:
        name, params = eqn.primitive.name, eqn.params
        if name == "dot_general":
            (lhs_contract, _), (lhs_batch, _) = params["dimension_numbers"]
            lhs, out = eqn.invars[0].aval.shape, eqn.outvars[0].aval.shape
            total += 2.0 * math.prod(out) * math.prod(lhs[d] for d in lhs_contract)
        elif name == "conv_general_dilated":
            lhs_spec, rhs_spec, _ = params["dimension_numbers"]
            rhs = eqn.invars[1].aval.shape
            out = eqn.outvars[0].aval.shape
            window = math.prod(rhs[d] for d in rhs_spec[2:])
            in_per_group = rhs[rhs_spec[1]]
            total += 2.0 * math.prod(out) * window * in_per_group
        elif name.startswith("dot_product_attention") and ("fwd" in name or "bwd" in name):
            batch, q_len, heads, dim = eqn.invars[0].aval.shape  # query [B, T, N, H], key [B, S, K, H]
            k_len = eqn.invars[1].aval.shape[1]
            total += (2 if "fwd" in name else 5) * 2.0 * batch * heads * q_len * k_len * dim
        elif name == "scan":
            total += params["length"] * _jaxpr_flops(params["jaxpr"].jaxpr)
        elif name == "cond":
            total += max(_jaxpr_flops(branch.jaxpr) for branch in params["branches"])
        else:
            for value in params.values():
                for sub in value if isinstance(value, (tuple, list)) else (value,):
                    inner = getattr(sub, "jaxpr", None)
                    if inner is not None and hasattr(inner, "eqns"):
                        total += _jaxpr_flops(inner)
                    elif hasattr(sub, "eqns"):
                        total += _jaxpr_flops(sub)
    return total


def finish_figure(fig: Any, ax: Any, path: str, *, xlabel: str, ylabel: str, title: str | None = None,
                  legend_size: int = 8, save: bool = True) -> None:
    """Labels ``ax``, draws its legend and, with ``save``, writes ``fig`` to ``path`` (PNG, 120 dpi) and closes
    it (a figure of several panels finishes each and saves with the last)."""
    import matplotlib.pyplot as plt

    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.legend(fontsize=legend_size)
    if not save:
        return
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def record_gpus(path: str) -> None:
    """The machine's GPUs (``nvidia-smi``'s name and memory per GPU) in ``path``, which :func:`workdir_device`
    reads back; nothing where there is no ``nvidia-smi``."""
    try:
        listed = subprocess.run(["nvidia-smi", "--query-gpu=name,memory.total", "--format=csv"], capture_output=True,
                                text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return
    if listed.returncode == 0:
        with open(path, "w") as f:
            f.write(listed.stdout)


XLA_FLAGS_FILE = "xla_flags.txt"


def launch_env(workdir: str, *, deterministic: bool = False) -> dict[str, str]:
    """The environment a launcher starts its GPU runs in: this process's, with XLA taking GPU memory as needed,
    unbuffered output, NVLink multicast off and, with ``deterministic``, XLA's deterministic ops
    (:data:`~sword_jax.pipeline.launch.DETERMINISTIC_OPS`) added to ``XLA_FLAGS``. The runs' ``XLA_FLAGS`` is
    written to ``workdir/xla_flags.txt``, which :func:`workdir_xla_flags` reads back for the summary."""
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONUNBUFFERED="1", **NO_MULTICAST)
    if deterministic:
        env["XLA_FLAGS"] = with_flag(env.get("XLA_FLAGS", ""), DETERMINISTIC_OPS)
    os.makedirs(workdir, exist_ok=True)
    with open(os.path.join(workdir, XLA_FLAGS_FILE), "w") as f:
        f.write(env.get("XLA_FLAGS", "") + "\n")
    return env


def workdir_xla_flags(workdir: str) -> dict[str, Any]:
    """What :func:`launch_env` wrote for a work dir's runs: ``{"xla_flags": ..., "deterministic": bool}``, or
    ``{}`` for a work dir launched before it was written."""
    path = os.path.join(workdir, XLA_FLAGS_FILE)
    if not os.path.exists(path):
        return {}
    with open(path) as f:
        flags = f.read().strip()
    return {"xla_flags": flags, "deterministic": DETERMINISTIC_OPS in flags.split()}


def workdir_device(workdir: str) -> str:
    """The device a run's work dir was made on, from its ``gpu.txt`` (``NAME xN``); this machine's without one."""
    gpu = os.path.join(workdir, "gpu.txt")
    if os.path.exists(gpu):
        with open(gpu) as f:
            names = [line.split(",")[0].strip() for line in f.read().splitlines()[1:] if line.strip()]
        if names:
            return f"{names[0]} x{len(names)}"
    return device_name()
