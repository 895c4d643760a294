"""Multi-GPU: data-parallel scaling of the small config, then the DLB train step at full TI2V-5B size under FSDP.

    python -m benchmarks.bench_multi_gpu --time-budget-s 420 --out /tmp/mg.json    # 4 x H100 / H200, ~7 min
    python -m benchmarks.bench_multi_gpu --xla-overlap --time-budget-s 420 --out /tmp/mg_overlap.json
    python -m benchmarks.bench_multi_gpu --time-budget-s 1 --small-unrolled --small-processes --out /tmp/mg.json
    XLA_FLAGS=--xla_force_host_platform_device_count=4 python -m benchmarks.bench_multi_gpu --tiny   # CPU smoke run

Part 1 (always runs, first) times the small config's DLB step at a fixed per-device batch
(``--small-batch-per-device``, a comma list) on 1, 2, 4, ... devices (pure data parallel) and reports
the scaling efficiency ``t_1 / t_k`` (1.0 = linear). Each row has the step time with the host waiting
for every step (``step_s``, the median of ``--small-iters`` steps) and per step of steps dispatched back to
back (``pipelined_step_s``, how the train loop runs: it reads metrics one step late): ``--small-blocks``
blocks of ``--small-iters`` steps each, the median block's seconds per step, every block's in
``pipelined_blocks_s``. Efficiencies are of the pipelined figure. (``--time-budget-s 1``, as in the third
line above, runs part 1 alone: no 5B setting fits.) The same step with the DLB cache off on 1 and all devices
separates what the cache's cross-device reads and writes cost (``cache_cross_device_s``) from the gradient
all-reduce and the rest (``dp_overhead_s``); one more row on all devices compiles the step with the
collective-overlap options below.
``--profile DIR`` traces the plain step of the first per-device batch on 1 and on all devices (5 steps each,
perfetto JSON under ``DIR/small_<B>dev_k<k>``) and adds per GPU: kernel time in collectives, in other kernels and
the span from first kernel to last, per step (``row["profile"]``): whether the 1 -> N overhead is collectives
or gaps. ``--small-unrolled`` adds the step with unrolled layers (``model.scan_layers=false``) on 1 and all devices
(``unrolled_efficiency``): in the scan each layer's gradient all-reduce sits inside the loop's backward pass.
``--small-processes`` then times the same step (cache on; scanned and, with ``--small-unrolled``, unrolled layers)
run by k processes of one device each, for every device count k > 1 (rows ``processes: k``, labelled ``k=4 4proc``;
the single-process rows have ``processes: 1``): one ``jax.distributed`` job per row, started by
:func:`sword_jax.pipeline.launch.launch` (process i on GPU i, NVLink multicast off; on a CPU one device each with
gloo collectives), a ``data`` mesh over every process's device, each process putting only its rows of the batch.
``processes_efficiency`` (``unrolled_processes_efficiency``) is one process's time on one device over k processes'
time: whether one host thread driving every GPU is what costs. A job whose rank fails, or that is still running
after ``--small-processes-timeout-s``, gives a row with status ``error`` and the failed rank's last output. With
``--small-processes`` the GPUs are not preallocated (``XLA_PYTHON_CLIENT_PREALLOCATE=false`` unless the
environment sets it), so the ranks find the memory this process is not using.

The recorded ``dp_scaling_efficiency_small_<N>gpu`` is the best of the modes measured (one process driving every
device or one process per device, scanned or unrolled layers: ``mode``, all in ``efficiency_by_mode``), each
mode's time on N devices against the fastest one-device step time of the run, so no mode gains from a slow one-device
program of its own. Each batch's figures are re-made after every row (``small.by_batch``), so a run stopped before its
end still records the modes it reached, marked ``complete: false``; ``--from-out FILE`` measures nothing and records
the entries of an earlier run's ``--out`` file, re-summarised from its rows, with that run's device, command and date.

Part 2 builds the 30-layer, dim-3072 world model with AdamW state born sharded over an ``fsdp`` axis
spanning every device (the latent cache sharded over episodes) and times the DLB step for each
``--sweep`` setting ``BATCHxREMAT[+overlap]`` (per-device batch, remat policy, ``+overlap``: compiled
with the overlap options), in the order given: step time (median), MFU against the bf16 matmul peak of
one device measured in this run and against the datasheet peak, compile time, memory per device
(XLA's compiled estimate and the running peak of the allocator). A setting that runs out of device
memory is reported as ``oom`` and the sweep goes on; a non-finite loss marks its setting
``nonfinite`` and the command exits 1 after writing its figures.

``--time-budget-s S``: a 5B setting starts only while fewer than S seconds have passed since the start
and the last setting's duration still fits before S, so the run ends close to S (the skipped settings
are listed). ``--out PATH`` rewrites the whole table as JSON after every row, and the results entries are
merged after every row too, so what was measured survives a run stopped early.

On 4 x H200 (2026-11-28) the small part with ``--small-unrolled --small-processes`` took over 7 min: each unrolled
program compiles in about 60 s. On 4 x H200 (2026-11-27) the small part took about 2 min and two 5B settings 50 s after a 7 s train state:
``--time-budget-s 230 --sweep 32xdots+overlap,32xdots`` ended in 180 s. Estimates before that run, 4 x H100
(compile dominates): the bf16 peak and the option checks about 15 s; the
small part 1.5-3 min (six compiles of 10-40 s, the first the longest: later ones reuse its GEMM
autotuning); the 5B train state 0.5-1 min; each 5B setting 1-2.5 min, 60-120 s of it compiling (a
setting with the last one's per-device batch compiles faster). ``--time-budget-s 420`` thus measures
about two 5B settings and ends by about 7.5 min; every further 2 min of it adds about one.

``--xla-overlap`` puts XLA's GPU collective-overlap flags (latency-hiding scheduler, pipelined
all-gather / reduce-scatter / all-reduce inside the layer scan, while-loop double buffering, larger
combine thresholds; as in MaxText's and NVIDIA JAX-Toolbox's GPU recipes) into ``XLA_FLAGS``. XLA
reads ``XLA_FLAGS`` once, when the backend starts: the flag only works when this module's ``main`` runs
before anything in the process has touched a device (it warns otherwise). Flags this XLA does not know
(which would abort the process) are found with a short CPU-only subprocess and dropped. Without the flag
the same options reach the ``+overlap`` rows as per-compile options (``Lowered.compile(compiler_options)``).
``--mem-fraction`` sets ``XLA_PYTHON_CLIENT_MEM_FRACTION`` (default 0.9 instead of JAX's 0.75) unless the
environment already does.
"""

from __future__ import annotations

import dataclasses
import datetime
import gc
import json
import os
import statistics
import sys
import time
import traceback
from typing import Any

import jax
import numpy as np
from flax import nnx

from benchmarks import common
from benchmarks.bench_dit_train import forward_flops
from benchmarks.gpu_trace import profile_steps
from benchmarks.xla_options import OVERLAP_OPTIONS, configure_backend, usable_compile_options
from sword_jax import cli
from sword_jax import sharding as shd
from sword_jax.atomic_write import write_json_atomic
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dit.config import REMAT_POLICIES, DiTConfig
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import train_state, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig

DEFAULT_SWEEP = "32xdots,32xdots+overlap,24xdots,48xdots,16xnone,24xfull"
NUM_EPISODES, NUM_LATENTS, SEGMENT_LATENTS, ACTION_TOKENS = 64, 32, 4, 13
TRAINER = TrainerConfig(steps=1000, warmup_steps=10)
DLB_CACHE = CacheConfig(enabled=True, read_prob_start=0.5, read_prob_end=0.5)
# --tiny: both parts on this model at these latent sizes (CPU smoke runs)
TINY_CFG = DiTConfig(dim=64, ffn_dim=128, freq_dim=32, num_heads=4, num_layers=2, text_dim=16, text_len=8,
                     compute_dtype="float32")
TINY_HW = (4, 4)


@dataclasses.dataclass(frozen=True)
class Setting:
    per_device_batch: int
    remat: str
    overlap: bool = False

    @property
    def name(self) -> str:
        return f"{self.per_device_batch}x{self.remat}" + ("+overlap" if self.overlap else "")


def parse_sweep(text: str) -> list[Setting]:
    """``"32xdots,24xnone+overlap"`` -> settings (per-device batch x remat policy, optionally ``+overlap``)."""
    settings = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        base, _, extra = item.partition("+")
        batch, _, remat = base.partition("x")
        if not batch.isdigit() or int(batch) < 1 or remat not in REMAT_POLICIES or extra not in ("", "overlap"):
            raise cli.UsageError(f"--sweep: {item!r} is not BATCHxREMAT[+overlap] with a positive batch and a remat "
                                 f"of {'|'.join(REMAT_POLICIES)}")
        settings.append(Setting(int(batch), remat, extra == "overlap"))
    if not settings:
        raise cli.UsageError("--sweep: no settings")
    return settings


def parse_batches(text: str) -> list[int]:
    try:
        batches = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        batches = []
    if not batches or min(batches) < 1:
        raise cli.UsageError(f"--small-batch-per-device: {text!r} is not a comma list of positive integers")
    return batches


def free_device_memory() -> None:
    jax.clear_caches()
    gc.collect()


def make_batch(model_cfg: DiTConfig, batch: int, hw: tuple[int, int], mesh) -> tuple[dict, dict]:
    """A random batch of ``batch`` examples as global arrays split over ``mesh``'s batch axes, and their
    shardings. Each process makes only the rows its devices hold (:func:`sword_jax.sharding.rows_held`); row
    ``i`` is the same whichever process makes it."""
    shapes = {"latents": (SEGMENT_LATENTS, hw[0], hw[1], model_cfg.in_dim),
              "actions": (ACTION_TOKENS, model_cfg.action_dim), "episode": (), "start": ()}
    shardings = {k: shd.batch_sharding(mesh, 1 + len(shape)) for k, shape in shapes.items()}
    rows = shd.rows_held(shardings["episode"], batch)

    def example(row: int) -> dict[str, np.ndarray]:
        rng = np.random.default_rng([0, row])
        return {"latents": rng.standard_normal(shapes["latents"], dtype=np.float32),
                "actions": rng.uniform(-1, 1, shapes["actions"]).astype(np.float32),
                "episode": np.int32(rng.integers(0, NUM_EPISODES)), "start": np.int32(rng.integers(1, NUM_LATENTS - 2))}

    examples = [example(int(row)) for row in rows]
    host = {k: np.stack([e[k] for e in examples]) for k in shapes}  # (rows held, ...)
    return shd.to_global(host, shardings, rows, batch), shardings


def new_state(model_cfg: DiTConfig, cache_cfg: CacheConfig, hw: tuple[int, int], mesh):
    """``(graphdef, state, shardings)``, the state placed at its shardings (so the compiled step's input and
    output types agree)."""
    dataset_shape = (NUM_EPISODES, NUM_LATENTS, hw[0], hw[1], model_cfg.in_dim)
    graphdef, state, shardings = train_state.create_train_state(
        lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0)), TRAINER, cache_cfg,
        dataset_shape, mesh)
    return graphdef, shd.place(state, shardings, donate=True), shardings


def compile_dlb_step(graphdef, cache_cfg: CacheConfig, state, shardings, data, data_shardings, mesh, key,
                     options: dict | None):
    """The train step lowered on exactly the arrays it will be called with and compiled (with ``options`` as
    per-compile XLA options). Returns ``(compiled, compile_s, compiled_gb_per_device)``."""
    fn = train_step.make_train_step(graphdef, flow_cfg=FlowConfig(), trainer_cfg=TRAINER, cache_cfg=cache_cfg,
                                    num_context=1, num_episodes=NUM_EPISODES)
    step = train_step.compile_train_step(fn, shardings, data_shardings, mesh)
    start = time.perf_counter()
    compiled = step.lower(state, data, key).compile(compiler_options=options or None)
    compile_s = time.perf_counter() - start
    try:
        stats = compiled.memory_analysis()
        gb = (stats.argument_size_in_bytes + stats.output_size_in_bytes - stats.alias_size_in_bytes
              + stats.temp_size_in_bytes + stats.generated_code_size_in_bytes) / 1e9
    except Exception:  # noqa: BLE001 - not every backend reports it
        gb = None
    through_jit = []

    def run(state, data, key):
        if not through_jit:
            try:
                return compiled(state, data, key)
            except (TypeError, ValueError) as err:  # arguments refused before running (nothing donated)
                print(f"  the compiled step refused its arguments ({str(err)[:200]}); running it through jax.jit "
                      "instead (compiled again, without per-compile options)", flush=True)
                through_jit.append(True)
        return step(state, data, key)

    run.through_jit = through_jit  # type: ignore[attr-defined]
    return run, compile_s, gb


def time_step(step, state, data, key, *, iters: int, pipelined: bool, blocks: int = 1,
              profile_dir: str | None = None) -> tuple[dict, Any, float]:
    """Runs the compiled step on the donated state: the median seconds of a step the host waits for
    (``step_s``) and, with ``pipelined``, ``blocks`` blocks of ``iters`` steps dispatched back to back: each
    block's seconds per step (``pipelined_blocks_s``) and the median block's (``pipelined_step_s``), so one
    slow block (a hiccup of the host) neither hides nor counts. With ``profile_dir`` a few more steps are traced
    there (``timings["profile"]``, :func:`profile_steps`). Returns ``(timings, state, loss of the last step)``;
    raises on a non-finite loss."""
    holder = {"state": state}

    def one():
        holder["state"], metrics = step(holder["state"], data, key)
        return metrics["loss"]

    timings: dict[str, Any] = {"step_s": common.time_fn(one, warmup=2, iters=iters)["median_s"]}
    if pipelined:
        per_block = []
        for _ in range(blocks):
            start = time.perf_counter()
            for _ in range(iters):
                loss = one()
            common.block(loss)
            per_block.append((time.perf_counter() - start) / iters)
        timings.update(pipelined_step_s=statistics.median(per_block), pipelined_blocks_s=per_block)
    if profile_dir:
        timings["profile"] = profile_steps(one, profile_dir)
    loss = float(one())
    if not np.isfinite(loss):
        raise FloatingPointError(f"non-finite loss {loss}")
    return timings, holder.pop("state"), loss


def failure_row(row: dict, err: BaseException) -> dict:
    status = "oom" if common.is_oom(err) else "nonfinite" if isinstance(err, FloatingPointError) else "error"
    row.update(status=status, error=f"{type(err).__name__}: {str(err)[:300]}")
    if status == "error":
        traceback.print_exception(err)
    print(f"  {row.get('setting', row.get('label'))}: {status.upper()} -- {row['error']}", flush=True)
    return row


def peak_gb(devices) -> list[float | None]:
    return [common.peak_memory_gb(d) for d in devices]


def small_row(model_cfg: DiTConfig, devices, per_device_batch: int, hw: tuple[int, int], *, cache_on: bool,
              options: dict | None, iters: int, blocks: int = 1, unrolled: bool = False,
              profile_dir: str | None = None) -> dict:
    k = len(devices)
    label = (f"{per_device_batch}/dev k={k}" + ("" if cache_on else " cache-off") + (" overlap" if options else "")
             + (" unrolled" if unrolled else ""))
    row: dict[str, Any] = {"label": label, "devices": k, "processes": 1, "per_device_batch": per_device_batch,
                           "cache": cache_on, "overlap": bool(options), "unrolled": unrolled, "status": "ok"}
    mesh = shd.make_mesh(shd.MeshConfig(data=-1), devices=devices)
    cache_cfg = dataclasses.replace(DLB_CACHE, enabled=cache_on)
    try:
        row.update(measure_small(model_cfg, cache_cfg, mesh, per_device_batch, hw, options=options, iters=iters,
                                 blocks=blocks, unrolled=unrolled, profile_dir=profile_dir))
    except Exception as err:  # noqa: BLE001 - reported in the row
        failure_row(row, err)
    return row


def measure_small(model_cfg: DiTConfig, cache_cfg: CacheConfig, mesh, per_device_batch: int, hw: tuple[int, int], *,
                  options: dict | None, iters: int, blocks: int, unrolled: bool,
                  profile_dir: str | None = None) -> dict[str, Any]:
    """The small config's DLB step on ``mesh`` (pure data parallel, ``per_device_batch`` per device), compiled
    and timed (:func:`time_step`): its timings, compile seconds, compiled size per device and last loss."""
    if unrolled:  # the layers as separate ops, so each layer's gradient all-reduce can overlap the backward pass
        model_cfg = dataclasses.replace(model_cfg, scan_layers=False)
    graphdef, state, shardings = new_state(model_cfg, cache_cfg, hw, mesh)
    data, data_shardings = make_batch(model_cfg, per_device_batch * mesh.size, hw, mesh)
    key = shd.put(jax.random.key(0), shd.replicated(mesh))
    step, compile_s, compiled_gb = compile_dlb_step(graphdef, cache_cfg, state, shardings, data, data_shardings, mesh,
                                                    key, options)
    timings, _, loss = time_step(step, state, data, key, iters=iters, pipelined=True, blocks=blocks,
                                 profile_dir=profile_dir)
    return {**timings, "compile_s": compile_s, "compiled_gb_per_device": compiled_gb, "loss": loss,
            "through_jit": bool(step.through_jit)}


def scaling_summary(rows: list[dict], per_device_batch: int, n: int) -> dict:
    """Efficiencies ``t_1 / t_k`` (pipelined and host-waiting) and the cache / all-reduce split of one batch;
    ``processes_efficiency``: one process's time on one device over that of ``k`` processes of one device each
    (``unrolled_processes_efficiency`` the same with unrolled layers)."""
    def times(cache: bool, overlap: bool, field: str, unrolled: bool = False,
              processes: bool = False) -> dict[int, float]:
        return {r["devices"]: r[field] for r in rows if r["per_device_batch"] == per_device_batch
                and r["status"] == "ok" and r["cache"] == cache and r["overlap"] == overlap
                and r.get("unrolled", False) == unrolled and (r.get("processes", 1) > 1) == processes}

    on, on_wait = times(True, False, "pipelined_step_s"), times(True, False, "step_s")
    off = times(False, False, "pipelined_step_s")
    overlap = times(True, True, "pipelined_step_s")
    unrolled = times(True, False, "pipelined_step_s", unrolled=True)
    processes = times(True, False, "pipelined_step_s", processes=True)
    unrolled_processes = times(True, False, "pipelined_step_s", unrolled=True, processes=True)
    summary: dict[str, Any] = {
        "per_device_batch": per_device_batch,
        "pipelined_step_s": {str(k): t for k, t in on.items()}, "step_s": {str(k): t for k, t in on_wait.items()},
        "efficiency": {str(k): on[1] / t for k, t in on.items()} if 1 in on else {},
        "waiting_efficiency": {str(k): on_wait[1] / t for k, t in on_wait.items()} if 1 in on_wait else {},
        "cache_off_pipelined_step_s": {str(k): t for k, t in off.items()},
        "cache_off_efficiency": off[1] / off[n] if 1 in off and n in off else None,
        "overlap_pipelined_step_s": overlap.get(n),
        "overlap_efficiency": on[1] / overlap[n] if 1 in on and n in overlap else None,
        "unrolled_pipelined_step_s": {str(k): t for k, t in unrolled.items()},
        # unrolled on 1 device against unrolled on n: the scaling of that program, not a speed-up over the scan
        "unrolled_efficiency": unrolled[1] / unrolled[n] if 1 in unrolled and n in unrolled else None,
        "processes_pipelined_step_s": {str(k): t for k, t in processes.items()},
        "processes_efficiency": {str(k): on[1] / t for k, t in processes.items()} if 1 in on else {},
        "unrolled_processes_pipelined_step_s": {str(k): t for k, t in unrolled_processes.items()},
        "unrolled_processes_efficiency": ({str(k): unrolled[1] / t for k, t in unrolled_processes.items()}
                                          if 1 in unrolled else {}),
    }
    if all(k in d for d in (on, off) for k in (1, n)):
        summary["dp_overhead_s"] = off[n] - off[1]  # gradient all-reduce and the rest, without the cache
        summary["cache_cross_device_s"] = (on[n] - off[n]) - (on[1] - off[1])  # what the cache costs more on n devices
    return summary


def small_summary(rows: list[dict], batches: list[int], n: int, *, complete: bool) -> dict:
    """The small part's record: its rows, each batch's :func:`scaling_summary` of the rows so far, and whether
    every planned row was measured (``complete``; a run stopped before its end keeps what it measured)."""
    return {"rows": rows, "by_batch": {str(b): scaling_summary(rows, b, n) for b in batches}, "complete": complete}


def device_counts(n: int) -> list[int]:
    counts = [1 << i for i in range(n.bit_length()) if 1 << i <= n]
    return counts if counts[-1] == n else counts + [n]


def run_small(model_cfg: DiTConfig, devices, batches: list[int], hw: tuple[int, int], *, iters: int, blocks: int,
              overlap_options: dict, overlap_everywhere: bool, report, unrolled: bool = False,
              profile: str | None = None, processes: bool = False, process_timeout_s: float = 600.0) -> dict:
    """The rows of part 1 (one process; then, with ``processes``, ``k`` processes of one device each for every
    ``k > 1`` of :func:`device_counts`, scanned and with ``unrolled`` unrolled layers) and each batch's
    :func:`scaling_summary`."""
    from benchmarks import multi_gpu_processes  # it imports this module

    n = len(devices)
    rows: list[dict] = []
    print(f"\n== small config ({model_cfg.num_layers} layers, dim {model_cfg.dim}): data-parallel scaling over "
          f"{device_counts(n)} devices", flush=True)
    for batch in batches:
        plan = [(k, True, None, False) for k in device_counts(n)] + [(1, False, None, False), (n, False, None, False)]
        if n > 1 and not overlap_everywhere:
            plan.append((n, True, overlap_options, False))
        if n > 1 and unrolled:
            plan += [(1, True, None, True), (n, True, None, True)]
        for k, cache_on, options, unroll in plan:
            # the first batch's plain step on 1 and on all devices is traced with --profile
            traced = profile and batch == batches[0] and k in (1, n) and cache_on and not options and not unroll
            profile_dir = os.path.join(profile, f"small_{batch}dev_k{k}") if traced else None
            row = small_row(model_cfg, devices[:k], batch, hw, cache_on=cache_on, options=options, iters=iters,
                            blocks=blocks, unrolled=unroll, profile_dir=profile_dir)
            rows.append(row)
            _print_small_row(row)
            report(small_summary(rows, batches, n, complete=False))
            free_device_memory()
        for k in [k for k in device_counts(n) if k > 1] if processes else []:
            for unroll in (False, True) if unrolled else (False,):
                row = multi_gpu_processes.process_row(model_cfg, k, batch, hw, iters=iters, blocks=blocks,
                                                      unrolled=unroll, timeout_s=process_timeout_s,
                                                      on_cpu=devices[0].platform == "cpu")
                rows.append(row)
                _print_small_row(row)
                report(small_summary(rows, batches, n, complete=False))
    small = small_summary(rows, batches, n, complete=True)
    for batch, s in small["by_batch"].items():
        eff = ", ".join(f"k={k}: {e:.3f}" for k, e in s["efficiency"].items())
        print(f"  {batch}/dev efficiency t_1/t_k (pipelined): {eff}; cache off 1->{n}: "
              f"{_fmt(s['cache_off_efficiency'])}; overlap: {_fmt(s['overlap_efficiency'])}; unrolled 1->{n}: "
              f"{_fmt(s['unrolled_efficiency'])}; all-reduce+rest "
              f"{_ms(s.get('dp_overhead_s'))}, "
              f"cache cross-device {_ms(s.get('cache_cross_device_s'))}", flush=True)
        if processes:
            per_process = ", ".join(f"k={k}: {e:.3f}" for k, e in s["processes_efficiency"].items())
            per_process_unrolled = ", ".join(f"k={k}: {e:.3f}" for k, e in s["unrolled_processes_efficiency"].items())
            print(f"  {batch}/dev one process per device, t_1/t_k: {per_process or 'n/a'}"
                  + (f"; unrolled: {per_process_unrolled or 'n/a'}" if unrolled else ""), flush=True)
        reference, by_mode = mode_efficiencies(s, n)
        if by_mode:
            print(f"  {batch}/dev against the fastest 1-device step time ({reference[1]} layers, {_ms(reference[0])}): "
                  + ", ".join(f"{mode} {e:.3f}" for mode, e in by_mode.items()), flush=True)
    common.print_table(rows, ["label", "status", "step_s", "pipelined_step_s", "compile_s", "compiled_gb_per_device"])
    sys.stdout.flush()
    return small


def _print_small_row(row: dict) -> None:
    if row["status"] != "ok":
        return
    print(f"  {row['label']:<28} waiting {row['step_s'] * 1e3:8.2f} ms  pipelined {row['pipelined_step_s'] * 1e3:8.2f} "
          f"ms (blocks {', '.join(f'{t * 1e3:.2f}' for t in row['pipelined_blocks_s'])})  compile "
          f"{row['compile_s']:.1f} s", flush=True)
    for lane, per in (row.get("profile") or {}).get("devices", {}).items():
        print(f"    {lane}: per step {per['span_ms']:.2f} ms from first kernel to last, collectives "
              f"{per['collective_ms']:.2f} ms, other kernels {per['compute_ms']:.2f} ms", flush=True)


# How the small step can run on n devices, and the field of scaling_summary holding its pipelined times by k.
MODES = {"single_process_scanned": "pipelined_step_s", "single_process_unrolled": "unrolled_pipelined_step_s",
         "process_per_device_scanned": "processes_pipelined_step_s",
         "process_per_device_unrolled": "unrolled_processes_pipelined_step_s"}


def mode_efficiencies(scaling: dict, n: int) -> tuple[tuple[float, str] | None, dict[str, float]]:
    """``((t_1, layers), {mode: t_1 / t_n})``: ``t_1`` the fastest one-device pipelined time of the run (one
    process; ``layers`` says whether scanned or unrolled), over each measured mode's (:data:`MODES`) pipelined
    time on ``n`` devices, so no mode gains from a slow one-device program of its own."""
    one_device = {layers: (scaling.get(field) or {}).get("1") for layers, field in
                  (("scanned", "pipelined_step_s"), ("unrolled", "unrolled_pipelined_step_s"))}
    measured = [(t, layers) for layers, t in one_device.items() if t is not None]
    if not measured:
        return None, {}
    reference = min(measured)
    by_mode = {mode: reference[0] / (scaling.get(field) or {})[str(n)] for mode, field in MODES.items()
               if (scaling.get(field) or {}).get(str(n)) is not None}
    return reference, by_mode


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def _ms(value: float | None) -> str:
    return "n/a" if value is None else f"{value * 1e3:.2f} ms"


def fsdp_row(ctx: dict, setting: Setting, *, iters: int, overlap_options: dict) -> dict:
    """One 5B setting on the FSDP mesh; reuses (and hands back through ``ctx``) the one train state."""
    mesh, n, hw = ctx["mesh"], ctx["n"], ctx["hw"]
    model_cfg = dataclasses.replace(ctx["model_cfg"], remat=setting.remat)
    row: dict[str, Any] = {"setting": setting.name, "per_device_batch": setting.per_device_batch,
                           "batch": setting.per_device_batch * n, "remat": setting.remat, "overlap": setting.overlap,
                           "status": "ok", "params": ctx["params"]}
    try:
        graphdef = nnx.split(shd.abstract_module(lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0))), nnx.Param, ...)[0]
        data, data_shardings = make_batch(model_cfg, row["batch"], hw, mesh)
        step, row["compile_s"], row["compiled_gb_per_device"] = compile_dlb_step(
            graphdef, ctx["cache_cfg"], ctx["state"], ctx["shardings"], data, data_shardings, mesh, ctx["key"],
            overlap_options if setting.overlap else None)
        timings, ctx["state"], row["loss"] = time_step(step, ctx["state"], data, ctx["key"], iters=iters,
                                                       pipelined=False)
        row["through_jit"] = bool(step.through_jit)
    except Exception as err:  # noqa: BLE001 - reported in the row
        return failure_row(row, err)
    flops = 3 * forward_flops(model_cfg, row["batch"], SEGMENT_LATENTS, hw, ACTION_TOKENS)
    row.update(step_s=timings["step_s"], model_tflops_per_device=flops / timings["step_s"] / 1e12 / n,
               mfu=common.mfu(flops, 1.0 / timings["step_s"], ctx["peak"] * n),
               mfu_nominal_peak=common.mfu(flops, 1.0 / timings["step_s"], ctx["nominal"] and ctx["nominal"] * n),
               peak_gb_per_device=peak_gb(mesh.devices.flat))
    return row


def ensure_state(ctx: dict, result: dict) -> bool:
    """Creates the 5B train state on first use, and again after a failed step consumed it (its buffers were
    donated). False (and ``result["state_error"]``) when it cannot be made."""
    if ctx["state"] is not None and not any(x.is_deleted() for x in jax.tree.leaves(ctx["state"])):
        return True
    if "state_error" in result:
        return False
    ctx["state"] = None
    free_device_memory()
    start = time.perf_counter()
    try:
        _, ctx["state"], ctx["shardings"] = new_state(ctx["model_cfg"], ctx["cache_cfg"], ctx["hw"], ctx["mesh"])
    except Exception as err:  # noqa: BLE001 - reported; the small part's figures still count
        result["state_error"] = failure_row({"setting": "train state"}, err)["error"]
        return False
    ctx["params"] = sum(x.size for x in jax.tree.leaves(ctx["state"].params))
    ctx["key"] = shd.put(jax.random.key(0), shd.replicated(ctx["mesh"]))
    result.setdefault("state_s", []).append(time.perf_counter() - start)
    print(f"  train state over {ctx['n']} devices: {ctx['params'] / 1e9:.3f}B params, "
          f"{result['state_s'][-1]:.1f} s", flush=True)
    return True


FSDP_COLUMNS = ["setting", "status", "step_s", "mfu", "mfu_nominal_peak", "compile_s", "compiled_gb_per_device",
                "setting_s"]


def run_fsdp(model_cfg: DiTConfig, devices, settings: list[Setting], hw: tuple[int, int], *, iters: int, peak: float,
             overlap_options: dict, overlap_everywhere: bool, budget_s: float | None, started: float, report) -> dict:
    n = len(devices)
    mesh = shd.make_mesh(shd.MeshConfig(data=1, fsdp=-1), devices=devices)
    cache_cfg = DLB_CACHE
    print(f"\n== {model_cfg.num_layers}-layer dim-{model_cfg.dim} DLB step, FSDP over {n} devices: "
          f"{', '.join(s.name for s in settings)}", flush=True)
    rows: list[dict] = []
    skipped: list[dict] = []
    ctx: dict[str, Any] = {"mesh": mesh, "n": n, "hw": hw, "model_cfg": model_cfg, "cache_cfg": cache_cfg, "peak": peak,
                           "nominal": common.nominal_peak_tflops(), "state": None, "params": None}
    result = {"layers": model_cfg.num_layers, "dim": model_cfg.dim, "devices": n, "rows": rows, "skipped": skipped}
    last_s = 0.0  # the last setting's seconds: later ones reuse its autotuning, so it predicts them best
    for setting in settings:
        elapsed = time.monotonic() - started
        if setting.overlap and overlap_everywhere:
            skipped.append({"setting": setting.name, "reason": "--xla-overlap already sets the options everywhere"})
        elif budget_s is not None and elapsed + last_s >= budget_s:
            skipped.append({"setting": setting.name, "reason": f"--time-budget-s {budget_s:.0f}: {elapsed:.0f} s "
                            f"elapsed, the last setting took {last_s:.0f} s"})
        elif not ensure_state(ctx, result):
            skipped.append({"setting": setting.name, "reason": f"no train state ({result['state_error']})"})
        else:
            setting_start = time.perf_counter()
            row = fsdp_row(ctx, setting, iters=iters, overlap_options=overlap_options)
            row["setting_s"] = last_s = time.perf_counter() - setting_start
            rows.append(row)
            if row["status"] == "ok":
                print(f"  {row['setting']:<18} {row['step_s'] * 1e3:8.1f} ms  MFU {row['mfu']:.3f} (nominal "
                      f"{_fmt(row['mfu_nominal_peak'])})  compile {row['compile_s']:.0f} s  compiled "
                      f"{_fmt(row['compiled_gb_per_device'])} GB/device  running peak GB {_peak(row)}", flush=True)
            free_device_memory()
        if skipped and skipped[-1]["setting"] == setting.name:
            print(f"  {setting.name:<18} skipped ({skipped[-1]['reason']})", flush=True)
        report(fsdp=result)
    ctx.clear()
    common.print_table(rows, FSDP_COLUMNS)
    sys.stdout.flush()
    return result


def _peak(row: dict) -> str:
    values = [v for v in row.get("peak_gb_per_device") or [] if v is not None]
    return f"{max(values):.1f}" if values else "n/a"


def results_entries(summary: dict) -> dict[str, dict]:
    """The ``latest.json`` entries of a run: the best 5B MFU over the sweep and the small config's scaling."""
    n, entries = summary["devices"], {}
    fsdp = summary.get("fsdp") or {}
    ok = [r for r in fsdp.get("rows", []) if r["status"] == "ok"]
    if ok:
        best = max(ok, key=lambda r: r["mfu"])
        full = fsdp["layers"] == DiTConfig().num_layers
        key = f"dit_train_mfu_5b_full_{n}gpu" if full else f"dit_train_mfu_5b_{fsdp['layers']}layers_{n}gpu"
        entries[key] = common.record(
            key, best["mfu"], 0.55 if n == 4 and full else None, per_device_batch=best["per_device_batch"],
            remat=best["remat"], overlap=best["overlap"], step_s=best["step_s"],
            mfu_nominal_peak=best["mfu_nominal_peak"], peak_gb_per_device=best["peak_gb_per_device"],
            compiled_gb_per_device=best["compiled_gb_per_device"], layers=fsdp["layers"], devices=n,
            params=best["params"], measured_peak_tflops=summary["measured_peak_tflops"],
            nominal_peak_tflops=summary["nominal_peak_tflops"], xla_overlap_flags=summary["xla_overlap_flags"],
            rows=fsdp["rows"], skipped=fsdp["skipped"],
            value_is="best MFU over the sweep against the bf16 matmul peak of one device measured in the run; "
                     "peak_gb_per_device is the allocator's running peak of the whole run")
    small = summary.get("small") or {}
    headline = small.get("by_batch", {}).get(str(summary["small_batches"][0]), {})
    reference, by_mode = mode_efficiencies(headline, n)
    complete = small.get("complete", True)
    if by_mode and n > 1:
        key = f"dp_scaling_efficiency_small_{n}gpu"
        mode = max(by_mode, key=by_mode.get)
        entries[key] = common.record(
            key, by_mode[mode], 0.90 if n == 4 else None, mode=mode, efficiency_by_mode=by_mode,
            reference_1dev_pipelined_step_s=reference[0], reference_1dev_layers=reference[1],
            efficiency=headline.get("efficiency", {}).get(str(n)), devices=n,
            per_device_batch=headline["per_device_batch"],
            pipelined_step_s=headline["pipelined_step_s"], step_s=headline["step_s"],
            waiting_efficiency=headline["waiting_efficiency"],
            cache_off_pipelined_step_s=headline["cache_off_pipelined_step_s"],
            cache_off_efficiency=headline["cache_off_efficiency"], overlap_efficiency=headline["overlap_efficiency"],
            dp_overhead_s=headline.get("dp_overhead_s"), cache_cross_device_s=headline.get("cache_cross_device_s"),
            by_batch=small["by_batch"], xla_overlap_flags=summary["xla_overlap_flags"],
            complete=complete,
            value_is="t_1 / t_N of the small config's DLB step at a fixed per-device batch, steps dispatched back to "
                     "back, for the best of the measured modes (mode; efficiency_by_mode: one process driving the N "
                     "devices or one process per device, scanned or unrolled layers); t_1 is the fastest one-device "
                     "step time of the run, scanned or unrolled, whatever the mode (efficiency: one process, scanned "
                     "layers, against its own t_1; waiting_efficiency: the same with the host waiting for every "
                     "step)" + ("" if complete else "; from a run stopped before all its rows (complete: false): the "
                                "modes it did not reach on N devices are absent from efficiency_by_mode"))
    return entries


def from_out(path: str) -> dict[str, dict]:
    """The ``latest.json`` entries of a run's ``--out`` file, its small part re-summarised from its rows (a run
    stopped before its end, e.g. by a time limit, leaves its rows there), stamped with the run's device, command
    and date. Nothing is measured."""
    try:
        with open(path) as f:
            summary = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise cli.UsageError(f"--from-out {path}: not a readable bench_multi_gpu --out file ({err})") from err
    missing = [k for k in ("devices", "small_batches", "small", "device", "command") if k not in summary]
    if missing or "rows" not in summary.get("small", {}):
        raise cli.UsageError(f"--from-out {path}: not a bench_multi_gpu --out file (no {missing or ['small rows']})")
    small = summary["small"]
    complete = bool(small.get("complete", summary.get("done", False)))
    summary["small"] = small_summary(small["rows"], summary["small_batches"], summary["devices"], complete=complete)
    entries = results_entries(summary)
    for entry in entries.values():
        entry.update(device=summary["device"], command=summary["command"], date=summary.get("date", entry["date"]),
                     summarised_from=path)
    return entries


def main(argv: list[str] | None = None) -> dict:
    """Both parts; the summary."""
    started = time.monotonic()
    parser = cli.ArgumentParser(description=__doc__)
    parser.add_argument("--tiny", action="store_true", help="CPU smoke run on tiny shapes (records nothing)")
    parser.add_argument("--sweep", default=None, help=f"5B settings BATCHxREMAT[+overlap],... (per-device batch; remat "
                        f"of {'|'.join(REMAT_POLICIES)}), most promising first (default {DEFAULT_SWEEP}; --tiny: "
                        "2xnone,2xdots)")
    parser.add_argument("--time-budget-s", type=float, default=None,
                        help="start no 5B setting that would not end within this many seconds of the start")
    parser.add_argument("--small-batch-per-device", default=None, help="comma list (default 32; --tiny 2); the "
                        "first is the recorded one")
    parser.add_argument("--layers", type=int, default=30, help="layers of the 5B-width model")
    parser.add_argument("--iters", type=int, default=5, help="timed steps per 5B setting")
    parser.add_argument("--small-iters", type=int, default=20, help="timed steps per small-config row (and per "
                        "block of pipelined steps)")
    parser.add_argument("--small-blocks", type=int, default=None, help="blocks of --small-iters steps dispatched back "
                        "to back per small-config row, the median block's seconds per step reported (default 5; "
                        "--tiny 3)")
    parser.add_argument("--profile", default="", metavar="DIR",
                        help="trace the small config's step on 1 and on all devices (first per-device batch) with "
                             "jax.profiler into DIR; each row then reports collective and other kernel time per step")
    parser.add_argument("--small-unrolled", action="store_true",
                        help="also the small config with unrolled layers (model.scan_layers=false) on 1 and all "
                             "devices: whether its gradient all-reduces then overlap the backward pass")
    parser.add_argument("--small-processes", action="store_true",
                        help="also the small config's step run by k processes of one device each (k = each device "
                             "count > 1), joined by jax.distributed: whether one host thread driving every device "
                             "is what costs")
    parser.add_argument("--small-processes-timeout-s", type=float, default=600.0,
                        help="a process-per-device row still running after this many seconds is stopped and "
                             "reported as an error (default %(default)s)")
    parser.add_argument("--devices", type=int, default=None, help="use the first N devices (default: all)")
    parser.add_argument("--xla-overlap", action="store_true", help="XLA's GPU collective-overlap flags in XLA_FLAGS "
                        "for the whole run (set before the backend starts)")
    parser.add_argument("--mem-fraction", type=float, default=0.9,
                        help="XLA_PYTHON_CLIENT_MEM_FRACTION unless the environment sets it")
    parser.add_argument("--out", default=None, help="write every row as JSON here, rewritten after each row")
    parser.add_argument("--from-out", default=None, metavar="FILE",
                        help="measure nothing: record the entries of a run's --out file, its small part "
                             "re-summarised from its rows (for a run stopped before its end)")
    args = parser.parse_args(argv)
    if args.from_out:
        entries = from_out(args.from_out)
        if not entries:
            raise SystemExit(f"bench_multi_gpu --from-out {args.from_out}: its rows give no figure on "
                             "several devices to record")
        common.merge_results(entries)
        for key, entry in entries.items():
            print(f"recorded {key} = {entry['value']:.4f} ({entry.get('mode', '')}; complete: "
                  f"{entry.get('complete', True)}) in {common.RESULTS}", flush=True)
        return entries
    settings = parse_sweep(args.sweep or ("2xnone,2xdots" if args.tiny else DEFAULT_SWEEP))
    batches = parse_batches(args.small_batch_per_device or ("2" if args.tiny else "32"))
    blocks = args.small_blocks if args.small_blocks is not None else 3 if args.tiny else 5
    if blocks < 1:
        raise cli.UsageError(f"--small-blocks {blocks}: at least one block")
    if args.small_processes_timeout_s <= 0:
        raise cli.UsageError("--small-processes-timeout-s must be positive")
    applied = configure_backend(args.xla_overlap, args.mem_fraction, preallocate=not args.small_processes)

    devices = jax.devices()
    if args.devices is not None:
        if not 1 <= args.devices <= len(devices):
            raise cli.UsageError(f"--devices {args.devices}: {len(devices)} devices are available")
        devices = devices[:args.devices]
    n = len(devices)
    peak = common.measured_matmul_tflops()
    overlap_options = usable_compile_options(OVERLAP_OPTIONS)
    summary: dict[str, Any] = {
        "device": common.device_name(), "devices": n, "measured_peak_tflops": peak,
        "nominal_peak_tflops": common.nominal_peak_tflops(), "xla_overlap_flags": applied["xla_overlap_flags"],
        "dropped_xla_flags": applied["dropped_flags"], "preallocate": applied["preallocate"],
        "overlap_options": overlap_options, "small_batches": batches,
        "sweep": [s.name for s in settings], "time_budget_s": args.time_budget_s, "command": common.command_line(),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")}
    print(f"{n} x {common.device_name()}: measured bf16 matmul {peak:.1f} TFLOP/s per device; nominal "
          f"{summary['nominal_peak_tflops']}; XLA overlap flags {'on' if applied['xla_overlap_flags'] else 'off'}",
          flush=True)

    def report(**parts):
        """Keeps what was measured so far: the --out table and (not --tiny) the results entries."""
        summary.update(parts, elapsed_s=time.monotonic() - started)
        if args.out:
            write_json_atomic(args.out, summary)
        entries = {} if args.tiny else results_entries(summary)
        if entries:
            common.merge_results(entries)

    if args.tiny:
        small_cfg, full_cfg, hw, small_hw = TINY_CFG, TINY_CFG, TINY_HW, TINY_HW
    else:
        small_cfg = DiTConfig(dim=512, ffn_dim=2048, num_heads=8, num_layers=8, text_dim=64, text_len=16)
        full_cfg, hw, small_hw = DiTConfig(num_layers=args.layers), (16, 16), (8, 8)
    overlap_everywhere = bool(applied["xla_overlap_flags"])
    small = run_small(small_cfg, devices, batches, small_hw, iters=2 if args.tiny else args.small_iters, blocks=blocks,
                      overlap_options=overlap_options, overlap_everywhere=overlap_everywhere,
                      report=lambda small: report(small=small), unrolled=args.small_unrolled,
                      profile=args.profile or None, processes=args.small_processes,
                      process_timeout_s=args.small_processes_timeout_s)
    report(small=small)
    free_device_memory()
    fsdp = run_fsdp(full_cfg, devices, settings, hw, iters=2 if args.tiny else args.iters, peak=peak,
                    overlap_options=overlap_options, overlap_everywhere=overlap_everywhere,
                    budget_s=args.time_budget_s, started=started, report=report)
    report(fsdp=fsdp, done=True)
    print(f"\ndone in {summary['elapsed_s']:.0f} s" + (f"; table in {args.out}" if args.out else ""), flush=True)
    if not args.tiny:
        print(f"recorded {sorted(results_entries(summary))} in {common.RESULTS}", flush=True)
    nonfinite = [r.get("setting", r.get("label")) for r in small["rows"] + fsdp["rows"] if r["status"] == "nonfinite"]
    if nonfinite:
        raise SystemExit(f"non-finite loss in {nonfinite} (the other figures are written)")
    return summary


if __name__ == "__main__":
    cli.run(main)
