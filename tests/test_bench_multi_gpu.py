"""benchmarks.bench_multi_gpu on 2 and 4 of the fake CPU devices: the small config's scaling rows (k = 1, 2, 4, the
cache off, the overlap options, unrolled layers, one process per device), the 5B-part sweep (rows, an out-of-memory
setting reported and passed over, the time --time-budget-s), its JSON table and the results entries it would
record."""

import dataclasses
import gzip
import json
import math
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import bench_multi_gpu as bench
from benchmarks import gpu_trace, xla_options
from benchmarks import multi_gpu_processes as processes
from sword_jax.pipeline import launch as launcher
from sword_jax.cli import UsageError


@pytest.fixture(autouse=True)
def _isolated(tmp_path, monkeypatch):
    monkeypatch.setattr(bench.common, "RESULTS", str(tmp_path / "latest.json"))
    monkeypatch.setenv("XLA_PYTHON_CLIENT_MEM_FRACTION", "0.75")  # main sets it only where unset; restored after


def _no_fsdp(*args, **kwargs):
    return {"layers": 2, "dim": 64, "devices": 4, "rows": [], "skipped": []}


def _scaling_entry(summary: dict, n: int) -> dict:
    """Checks the small part's figures on ``n`` devices against its single-process rows; its results entry."""
    rows = [r for r in summary["small"]["rows"] if r["processes"] == 1]
    by_k = {r["devices"]: r for r in rows if r["cache"] and not r["overlap"] and not r["unrolled"]}
    off = {r["devices"]: r["pipelined_step_s"] for r in rows if not r["cache"]}
    unrolled = {r["devices"]: r["pipelined_step_s"] for r in rows if r["unrolled"]}
    [overlap] = [r for r in rows if r["overlap"]]
    scaling = summary["small"]["by_batch"]["2"]
    assert set(scaling["efficiency"]) == {str(k) for k in by_k} and scaling["efficiency"]["1"] == 1.0
    assert scaling["efficiency"][str(n)] == pytest.approx(by_k[1]["pipelined_step_s"] / by_k[n]["pipelined_step_s"])
    assert scaling["waiting_efficiency"][str(n)] == pytest.approx(by_k[1]["step_s"] / by_k[n]["step_s"])
    assert scaling["dp_overhead_s"] == pytest.approx(off[n] - off[1])
    assert scaling["cache_cross_device_s"] == pytest.approx(
        by_k[n]["pipelined_step_s"] - off[n] - (by_k[1]["pipelined_step_s"] - off[1]))
    assert scaling["overlap_efficiency"] == pytest.approx(by_k[1]["pipelined_step_s"] / overlap["pipelined_step_s"])
    assert scaling["unrolled_efficiency"] == pytest.approx(unrolled[1] / unrolled[n])
    entry = bench.results_entries(summary)[f"dp_scaling_efficiency_small_{n}gpu"]
    fastest = min(by_k[1]["pipelined_step_s"], unrolled[1])
    assert entry["efficiency_by_mode"]["single_process_scanned"] == pytest.approx(
        fastest / by_k[n]["pipelined_step_s"])
    assert entry["efficiency_by_mode"]["single_process_unrolled"] == pytest.approx(fastest / unrolled[n])
    assert entry["value"] == max(entry["efficiency_by_mode"].values())
    assert entry["efficiency_by_mode"][entry["mode"]] == entry["value"]
    assert entry["efficiency"] == scaling["efficiency"][str(n)] and entry["per_device_batch"] == 2
    return entry


# nine rows each compiled, two in gloo processes; the plan and profile tests keep the rows' code in the default run
@pytest.mark.slow
def test_small_rows_of_every_kind_compiled_on_two_devices_and_two_gloo_processes(tmp_path, monkeypatch):
    """One --tiny run of the small part on 2 devices: k = 1, 2, the cache off, the overlap options, unrolled layers
    and (--small-processes) 2 gloo processes of one device each, scanned and unrolled; every row's step compiled and
    timed. (The plan on 4 devices and --profile: the next test; a traced step: the one after.)"""
    monkeypatch.setattr(bench, "run_fsdp", _no_fsdp)
    # the sampled cache-vs-inference metric's branch compiles slowly on a CPU; the sweep test keeps it
    monkeypatch.setattr(bench, "DLB_CACHE", dataclasses.replace(bench.DLB_CACHE, log_inference_distance=False))
    out = tmp_path / "mg.json"
    summary = bench.main(["--tiny", "--devices", "2", "--small-unrolled", "--small-processes", "--small-blocks", "2",
                          "--out", str(out)])
    rows = summary["small"]["rows"]
    assert [(r["devices"], r["cache"], r["overlap"], r["unrolled"], r["processes"]) for r in rows] == [
        (1, True, False, False, 1), (2, True, False, False, 1), (1, False, False, False, 1),
        (2, False, False, False, 1), (2, True, True, False, 1), (1, True, False, True, 1), (2, True, False, True, 1),
        (2, True, False, False, 2), (2, True, False, True, 2)]
    for row in rows:
        assert row["status"] == "ok" and not row["through_jit"], row
        assert row["step_s"] > 0 and row["pipelined_step_s"] > 0 and row["compile_s"] > 0 and math.isfinite(row["loss"])
        assert len(row["pipelined_blocks_s"]) == 2  # --small-blocks
        assert row["pipelined_step_s"] == statistics.median(row["pipelined_blocks_s"])
    entry = _scaling_entry(summary, 2)
    # the options this XLA accepts, every one of them (jaxlib 0.11 no longer has the pipelined-collective ones)
    kept = summary["overlap_options"]
    assert kept and kept.items() <= bench.OVERLAP_OPTIONS.items()
    for name in set(bench.OVERLAP_OPTIONS) - set(kept):
        with pytest.raises(Exception, match=name):
            jax.jit(lambda x: x + 1).lower(np.float32(1)).compile(compiler_options={name: bench.OVERLAP_OPTIONS[name]})
    assert set(entry["efficiency_by_mode"]) == set(bench.MODES) and entry["target"] is None

    multi = {r["unrolled"]: r for r in rows if r["processes"] > 1}
    single = {(r["devices"], r["unrolled"]): r for r in rows
              if r["processes"] == 1 and r["cache"] and not r["overlap"]}
    assert [r["label"] for r in multi.values()] == ["2/dev k=2 2proc", "2/dev k=2 2proc unrolled"]
    for unrolled, row in multi.items():
        assert row["launch_s"] > row["compile_s"] > 0
        # each process put only its rows of the same global batch: the step one process runs on 2 devices
        assert row["loss"] == pytest.approx(single[(2, unrolled)]["loss"], rel=1e-5)
        assert row["loss"] != pytest.approx(single[(1, unrolled)]["loss"], rel=1e-5)  # half that batch
    scaling = summary["small"]["by_batch"]["2"]
    assert scaling["processes_pipelined_step_s"] == {"2": multi[False]["pipelined_step_s"]}
    assert scaling["processes_efficiency"] == {
        "2": pytest.approx(single[(1, False)]["pipelined_step_s"] / multi[False]["pipelined_step_s"])}
    assert scaling["unrolled_processes_efficiency"] == {
        "2": pytest.approx(single[(1, True)]["pipelined_step_s"] / multi[True]["pipelined_step_s"])}
    # single-process figures leave the per-process rows out
    assert scaling["pipelined_step_s"]["2"] == single[(2, False)]["pipelined_step_s"]
    fastest = min(single[(1, False)]["pipelined_step_s"], single[(1, True)]["pipelined_step_s"])
    assert entry["efficiency_by_mode"]["process_per_device_unrolled"] == pytest.approx(
        fastest / multi[True]["pipelined_step_s"])

    written = json.loads(out.read_text())
    assert written["done"] and written["small"]["by_batch"]["2"]["efficiency"] == scaling["efficiency"]
    assert not (tmp_path / "latest.json").exists()  # --tiny records nothing


def test_small_plan_on_four_devices_its_efficiencies_and_the_cache_split(tmp_path, monkeypatch):
    """The small part's rows on 4 devices (k = 1, 2, 4, the cache off, the overlap options, unrolled layers) and the
    figures and record made of them, each row's step time made up from what it was measured on (its mesh, cache,
    options and layers), so that every figure has distinct times to come from."""
    monkeypatch.setattr(bench, "run_fsdp", _no_fsdp)

    def measure(model_cfg, cache_cfg, mesh, per_device_batch, hw, *, options, iters, blocks, unrolled,
                profile_dir=None):
        assert (per_device_batch, iters, blocks) == (2, 2, 4)
        step_s = (1.0 + 0.1 * mesh.size) * (1.0 if cache_cfg.enabled else 0.8) * (0.9 if options else 1.0)
        step_s *= 0.7 if unrolled else 1.0
        timings = {"step_s": step_s, "pipelined_step_s": 0.6 * step_s, "pipelined_blocks_s": [0.6 * step_s] * blocks,
                   "compile_s": 1.0, "loss": 0.5, "through_jit": False}
        return timings | ({"profile": {"trace": profile_dir}} if profile_dir else {})

    monkeypatch.setattr(bench, "measure_small", measure)
    summary = bench.main(["--tiny", "--devices", "4", "--small-unrolled", "--small-blocks", "4", "--profile",
                          str(tmp_path / "prof")])
    rows = summary["small"]["rows"]
    assert [(r["devices"], r["cache"], r["overlap"], r["unrolled"], r["processes"]) for r in rows] == [
        (1, True, False, False, 1), (2, True, False, False, 1), (4, True, False, False, 1),
        (1, False, False, False, 1), (4, False, False, False, 1), (4, True, True, False, 1),
        (1, True, False, True, 1), (4, True, False, True, 1)]
    assert all(r["status"] == "ok" for r in rows), rows  # what measure asserts is caught into the row
    # --profile traces the plain step on 1 and 4 devices
    assert [(r["devices"], r["profile"]["trace"]) for r in rows if "profile" in r] == [
        (k, str(tmp_path / "prof" / f"small_2dev_k{k}")) for k in (1, 4)]
    assert list(bench.results_entries(summary)) == ["dp_scaling_efficiency_small_4gpu"]
    entry = _scaling_entry(summary, 4)
    assert set(entry["efficiency_by_mode"]) == {"single_process_scanned", "single_process_unrolled"}
    assert entry["target"] == 0.9


def test_a_profiled_step_is_traced_after_the_timed_ones(tmp_path):
    """--profile: time_step runs PROFILE_STEPS more steps under jax.profiler, their trace written where it was told
    (a CPU trace has no GPU lanes to summarise)."""
    step = jax.jit(lambda state, data, key: (state + 1, {"loss": jnp.float32(0.5)}))
    timings, state, loss = bench.time_step(step, jnp.int32(0), None, None, iters=2, pipelined=True, blocks=2,
                                           profile_dir=str(tmp_path / "prof"))
    assert timings["profile"]["steps"] == gpu_trace.PROFILE_STEPS and timings["profile"]["devices"] == {}
    assert timings["profile"]["trace"].startswith(str(tmp_path / "prof"))
    assert int(state) == 2 + 2 + 2 * 2 + gpu_trace.PROFILE_STEPS + 1 and loss == 0.5


def test_a_failing_or_stuck_rank_gives_an_error_row_quickly(monkeypatch):
    monkeypatch.setattr(bench, "DLB_CACHE", dataclasses.replace(bench.DLB_CACHE, log_inference_distance=False))
    start = time.monotonic()
    bad = dataclasses.replace(bench.TINY_CFG, num_heads=3)  # does not divide dim 64: no model is built
    row = processes.process_row(bad, 2, 2, bench.TINY_HW, iters=2, blocks=1, unrolled=False, timeout_s=120, on_cpu=True)
    assert (row["status"], row["processes"], row["label"]) == ("error", 2, "2/dev k=2 2proc"), row
    assert "ValueError" in row["error"] and "num_heads=3" in row["error"] and "step_s" not in row
    # ranks past their time (here before their first step) stop themselves, and the launcher the rest
    row = processes.process_row(bench.TINY_CFG, 2, 2, bench.TINY_HW, iters=2, blocks=1, unrolled=True, timeout_s=1,
                            on_cpu=True)
    assert row["status"] == "error" and row["unrolled"], row
    assert "status 124" in row["error"] and "not done after 1 s" in row["error"]
    assert time.monotonic() - start < 60


@pytest.mark.slow  # a sweep of compiled settings; the plan and profile tests keep the rows' code in the default run
def test_sweep_rows_and_an_out_of_memory_setting_passed_over(tmp_path, monkeypatch):
    monkeypatch.setattr(bench, "run_small", lambda *a, **kw: {"rows": [], "by_batch": {}})
    real_time_step = bench.time_step
    calls = []

    def out_of_memory_on_the_second(step, state, data, key, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # the step runs (its state is donated, so gone), then the device is out of memory
            step(state, data, key)
            raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 81.20GiB.")
        return real_time_step(step, state, data, key, **kwargs)

    monkeypatch.setattr(bench, "time_step", out_of_memory_on_the_second)
    out = tmp_path / "mg.json"
    summary = bench.main(["--tiny", "--devices", "4", "--sweep", "2xnone,2xdots,2xfull+overlap", "--out", str(out)])
    fsdp = summary["fsdp"]
    rows = fsdp["rows"]
    assert [(r["setting"], r["status"]) for r in rows] == [
        ("2xnone", "ok"), ("2xdots", "oom"), ("2xfull+overlap", "ok")]
    assert "RESOURCE_EXHAUSTED" in rows[1]["error"] and "step_s" not in rows[1]
    assert fsdp["skipped"] == [] and len(fsdp["state_s"]) == 2  # the donated state was made again
    for row in (rows[0], rows[2]):
        assert (row["per_device_batch"], row["batch"]) == (2, 8) and not row["through_jit"]
        assert row["step_s"] > 0 and row["compile_s"] > 0 and row["setting_s"] >= row["compile_s"]
        assert 0 < row["mfu"] < 1 and row["mfu_nominal_peak"] is None  # no datasheet peak for a CPU
        assert row["params"] > 0 and len(row["peak_gb_per_device"]) == 4 and math.isfinite(row["loss"])
        assert row["compiled_gb_per_device"] > 0
    assert rows[2]["overlap"] and rows[2]["remat"] == "full"
    assert json.loads(out.read_text())["fsdp"]["rows"][1]["status"] == "oom"

    entries = bench.results_entries(summary)
    assert list(entries) == ["dit_train_mfu_5b_2layers_4gpu"]  # not the full depth: its own key, no target
    entry = entries["dit_train_mfu_5b_2layers_4gpu"]
    best = max((rows[0], rows[2]), key=lambda r: r["mfu"])
    assert entry["value"] == best["mfu"] and entry["target"] is None and entry["remat"] == best["remat"]
    assert [r["status"] for r in entry["rows"]] == ["ok", "oom", "ok"]


class _Clock:
    """Seconds that pass only when a fake setting runs."""

    def __init__(self):
        self.now = 0.0

    def monotonic(self):
        return self.now

    def perf_counter(self):
        return self.now


@pytest.mark.parametrize("limit,ran", [(0, []), (250, ["8xdots", "8xnone"]), (None, ["8xdots", "8xnone", "4xfull"])])
def test_no_setting_starts_that_would_end_past_the_time_limit(monkeypatch, limit, ran):
    clock, order = _Clock(), []
    monkeypatch.setattr(bench, "time", clock)

    def small(*args, **kwargs):
        order.append("small")
        return {"rows": [], "by_batch": {}}

    def setting(ctx, setting, **kwargs):
        order.append(setting.name)
        clock.now += 100.0
        return {"setting": setting.name, "status": "ok", "step_s": 1.0, "mfu": 0.5, "mfu_nominal_peak": None,
                "compile_s": 90.0, "compiled_gb_per_device": 1.0, "peak_gb_per_device": [None]}

    monkeypatch.setattr(bench, "run_small", small)
    monkeypatch.setattr(bench, "ensure_state", lambda ctx, result: True)
    monkeypatch.setattr(bench, "fsdp_row", setting)
    argv = ["--tiny", "--devices", "4", "--sweep", "8xdots,8xnone,4xfull"]
    summary = bench.main(argv + ([] if limit is None else ["--time-budget-s", str(limit)]))
    assert order == ["small"] + ran  # the scaling part first, whatever the limit
    assert [r["setting"] for r in summary["fsdp"]["rows"]] == ran
    skipped = summary["fsdp"]["skipped"]
    assert [s["setting"] for s in skipped] == [s for s in ("8xdots", "8xnone", "4xfull") if s not in ran]
    assert all(s["reason"].startswith(f"--time-budget-s {limit}:") for s in skipped)


def test_records_of_a_full_depth_sweep_on_four_and_eight_devices():
    def row(setting, status, mfu=None):
        batch, remat = setting.split("x")
        return {"setting": setting, "status": status, "per_device_batch": int(batch), "remat": remat, "overlap": False,
                "mfu": mfu, "step_s": 0.5, "mfu_nominal_peak": mfu and mfu * 0.8, "peak_gb_per_device": [40.0] * 4,
                "compiled_gb_per_device": 38.0, "params": 5e9}

    for n, target in ((4, 0.55), (8, None)):
        summary = {"devices": n, "measured_peak_tflops": 800.0, "nominal_peak_tflops": 989.4, "xla_overlap_flags": [],
                   "small_batches": [32, 128], "small": {"by_batch": {
                       "32": {"per_device_batch": 32, "efficiency": {"1": 1.0, str(n): 0.7},
                              "pipelined_step_s": {"1": 0.7, str(n): 1.0},
                              "step_s": {}, "waiting_efficiency": {}, "cache_off_pipelined_step_s": {},
                              "cache_off_efficiency": 0.8, "overlap_efficiency": 0.75},
                       "128": {"per_device_batch": 128, "efficiency": {"1": 1.0, str(n): 0.9}}}},
                   "fsdp": {"layers": 30, "rows": [row("24xdots", "ok", 0.5), row("48xdots", "oom"),
                                                   row("32xdots", "ok", 0.52)], "skipped": []}}
        entries = bench.results_entries(summary)
        mfu, scaling = entries[f"dit_train_mfu_5b_full_{n}gpu"], entries[f"dp_scaling_efficiency_small_{n}gpu"]
        assert (mfu["value"], mfu["target"], mfu["per_device_batch"], mfu["devices"]) == (0.52, target, 32, n)
        assert scaling["value"] == 0.7 and scaling["per_device_batch"] == 32  # the first per-device batch listed
        assert scaling["target"] == (0.9 if n == 4 else None) and set(scaling["by_batch"]) == {"32", "128"}


def test_pipelined_time_is_the_median_block_so_one_slow_block_is_seen_but_not_counted(monkeypatch):
    """Steps that take 1 ms of a fake clock, except in the third of five blocks (a host hiccup: 10 ms each)."""
    clock, calls = _Clock(), []
    monkeypatch.setattr(bench, "time", clock)
    waiting = 2 + 3  # common.time_fn's warm-up and timed steps come first

    def step(state, data, key):
        calls.append(1)
        block = (len(calls) - waiting - 1) // 3
        clock.now += 0.010 if block == 2 else 0.001
        return state + 1, {"loss": np.float32(0.5)}

    timings, state, loss = bench.time_step(step, 0, None, None, iters=3, pipelined=True, blocks=5)
    assert len(calls) == waiting + 5 * 3 + 1 and state == len(calls) and loss == 0.5
    assert timings["pipelined_blocks_s"] == pytest.approx([0.001, 0.001, 0.010, 0.001, 0.001])
    assert timings["pipelined_step_s"] == pytest.approx(0.001)  # a mean over the blocks would say 0.0028
    timings, _, _ = bench.time_step(step, 0, None, None, iters=3, pipelined=False, blocks=5)
    assert "pipelined_step_s" not in timings and "pipelined_blocks_s" not in timings


def test_the_recorded_scaling_is_the_best_mode_against_the_fastest_one_device_time():
    """Each mode's n-device step time over the fastest one-device step time of the run (here unrolled layers): against their
    own one-device step times the scanned modes would look better than they are, and one process per device, scanned,
    would win (0.010 / 0.011)."""
    headline = {"per_device_batch": 32, "efficiency": {"1": 1.0, "4": 0.010 / 0.0136},
                "pipelined_step_s": {"1": 0.010, "2": 0.012, "4": 0.0136}, "step_s": {"1": 0.0095, "4": 0.012},
                "waiting_efficiency": {"4": 0.79}, "cache_off_pipelined_step_s": {}, "cache_off_efficiency": None,
                "overlap_efficiency": None, "unrolled_pipelined_step_s": {"1": 0.0064, "4": 0.0139},
                "processes_pipelined_step_s": {"2": 0.0105, "4": 0.011},
                "unrolled_processes_pipelined_step_s": {"4": 0.008}}
    summary = {"devices": 4, "xla_overlap_flags": [], "small_batches": [32],
               "small": {"by_batch": {"32": headline}}}
    entry = bench.results_entries(summary)["dp_scaling_efficiency_small_4gpu"]
    assert entry["efficiency_by_mode"] == pytest.approx({
        "single_process_scanned": 0.0064 / 0.0136, "single_process_unrolled": 0.0064 / 0.0139,
        "process_per_device_scanned": 0.0064 / 0.011, "process_per_device_unrolled": 0.0064 / 0.008})
    assert entry["mode"] == "process_per_device_unrolled" and entry["value"] == pytest.approx(0.8)
    assert (entry["reference_1dev_pipelined_step_s"], entry["reference_1dev_layers"]) == (0.0064, "unrolled")
    assert entry["efficiency"] == headline["efficiency"]["4"] and entry["target"] == 0.9  # the fields kept

    # scanned layers fastest on one device, no unrolled or per-process rows: the one mode against its own time
    for field in ("unrolled_pipelined_step_s", "processes_pipelined_step_s", "unrolled_processes_pipelined_step_s"):
        headline[field] = {}
    entry = bench.results_entries(summary)["dp_scaling_efficiency_small_4gpu"]
    assert entry["efficiency_by_mode"] == {"single_process_scanned": 0.010 / 0.0136}
    assert entry["mode"] == "single_process_scanned" and entry["reference_1dev_layers"] == "scanned"
    headline["pipelined_step_s"] = {"1": 0.010}  # nothing on 4 devices: nothing recorded
    assert bench.results_entries(summary) == {}


@pytest.mark.parametrize("sweep", ["24xbogus", "x", "0xnone", "24xdots+fast", "", "24"])
def test_a_bad_sweep_is_a_usage_error(sweep):
    with pytest.raises(UsageError, match="--sweep"):
        bench.parse_sweep(sweep)


def test_sweep_and_batch_lists_parse():
    assert bench.parse_sweep("32xdots, 24xnone+overlap") == [bench.Setting(32, "dots"), bench.Setting(24, "none", True)]
    assert bench.parse_batches("32,128") == [32, 128]
    with pytest.raises(UsageError):
        bench.parse_batches("32,many")
    assert bench.device_counts(4) == [1, 2, 4] and bench.device_counts(6) == [1, 2, 4, 6]


def test_overlap_flags_this_xla_does_not_know_are_dropped():
    flags = xla_options.xla_flag_strings(bench.OVERLAP_OPTIONS)
    assert "--xla_gpu_enable_latency_hiding_scheduler=true" in flags
    kept, dropped = xla_options.usable_xla_flags(flags[:2] + ["--xla_gpu_no_such_flag=true"])
    assert kept == flags[:2] and dropped == ["--xla_gpu_no_such_flag=true"]


def test_out_of_memory_is_told_from_other_failures():
    is_oom = bench.common.is_oom
    assert is_oom(jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate"))
    assert is_oom(RuntimeError("CUDA_ERROR_OUT_OF_MEMORY: out of memory"))
    assert not is_oom(ValueError("shapes do not match"))


def test_a_trace_is_summarized_per_gpu_and_step_from_its_kernel_streams(tmp_path):
    """Collective and other kernels per step on each GPU lane's stream threads; the lane's module and op threads
    (the same time again) and the host are left out."""
    def meta(pid, name, tid=None):
        return ({"ph": "M", "pid": pid, "name": "process_name", "args": {"name": name}} if tid is None else
                {"ph": "M", "pid": pid, "tid": tid, "name": "thread_name", "args": {"name": name}})

    def kernel(pid, tid, name, ts, dur):
        return {"ph": "X", "pid": pid, "tid": tid, "name": name, "ts": ts, "dur": dur}

    events = [meta(1, "/host:CPU"), meta(2, "/device:GPU:0"), meta(3, "/device:GPU:1"),
              meta(2, "Stream #13(Compute)", 7), meta(2, "XLA Modules", 8), meta(3, "Stream #13(Compute)", 7),
              kernel(1, 1, "python", 0, 10_000),
              kernel(2, 8, "jit_step", 0, 9_000),  # a module event: not a kernel
              kernel(2, 7, "fusion.12", 0, 3_000), kernel(2, 7, "ncclDevKernel_AllReduce_Sum_f32_RING_LL", 3_000, 1_000),
              kernel(2, 7, "all-reduce-start.3", 5_000, 1_000), kernel(2, 7, "gemm_fusion", 7_000, 1_000),
              kernel(3, 7, "fusion.12", 1_000, 2_000)]
    run = tmp_path / "plugins" / "profile" / "run"
    run.mkdir(parents=True)
    with gzip.open(run / "host.perfetto_trace.json.gz", "wt") as f:
        json.dump({"traceEvents": events}, f)
    summary = gpu_trace.summarize_trace(str(tmp_path), steps=2)
    assert summary["trace"].endswith("perfetto_trace.json.gz")
    assert summary["devices"] == {
        "/device:GPU:0": {"collective_ms": 1.0, "compute_ms": 2.0, "span_ms": 4.0},
        "/device:GPU:1": {"collective_ms": 0.0, "compute_ms": 1.0, "span_ms": 1.0}}
    assert gpu_trace.summarize_trace(str(tmp_path / "none"), steps=2) == {"trace": None, "devices": {}}


def test_a_benchmark_told_to_stop_stops_instead_of_timing_the_next_row(monkeypatch):
    """A stop signal the launcher received while a per-process row ran is raised again in the benchmark: the
    sweep ends there (its default action) instead of launching the next row."""
    import signal

    stopped = launcher.LaunchResult(128 + signal.SIGUSR1, None, (-15, -15), 1.0, signal.SIGUSR1)
    monkeypatch.setattr(processes.launcher, "launch", lambda *a, **kw: stopped)

    class Stopped(Exception):
        pass

    def handler(signum, _frame):
        raise Stopped(signum)

    previous = signal.signal(signal.SIGUSR1, handler)
    try:
        with pytest.raises(Stopped):
            processes.process_row(bench.TINY_CFG, 2, 2, bench.TINY_HW, iters=2, blocks=1, unrolled=False, timeout_s=60,
                                  on_cpu=True)
    finally:
        signal.signal(signal.SIGUSR1, previous)


def test_a_run_stopped_before_its_end_records_the_modes_it_reached(tmp_path, monkeypatch):
    """The small part's figures are re-made after every row: a run stopped before its last rows (here after the
    4-device unrolled row) has its scaling and entry in --out and latest.json, marked incomplete; --from-out
    records the same from such a file without measuring, with the run's device, command and date."""
    monkeypatch.setattr(bench, "run_fsdp", _no_fsdp)
    seen = []

    def measure(model_cfg, cache_cfg, mesh, per_device_batch, hw, *, options, iters, blocks, unrolled,
                profile_dir=None):
        seen.append((mesh.size, cache_cfg.enabled, bool(options), unrolled))
        if len(seen) == 8:  # the run is stopped while the last planned row runs
            raise KeyboardInterrupt
        step_s = (1.0 + 0.1 * mesh.size) * (0.5 if unrolled else 1.0)
        return {"step_s": step_s, "pipelined_step_s": step_s, "pipelined_blocks_s": [step_s] * blocks,
                "compile_s": 1.0, "loss": 0.5, "through_jit": False}

    monkeypatch.setattr(bench, "measure_small", measure)
    out = str(tmp_path / "mg.json")
    with pytest.raises(KeyboardInterrupt):
        bench.main(["--tiny", "--devices", "4", "--small-unrolled", "--out", out])
    with open(out) as f:
        partial = json.load(f)
    small = partial["small"]
    assert len(small["rows"]) == 7 and small["complete"] is False and "done" not in partial
    scaling = small["by_batch"]["2"]
    assert scaling["unrolled_pipelined_step_s"] == {"1": pytest.approx(0.55)}  # the 4-device row never came
    assert scaling["efficiency"]["4"] == pytest.approx(1.1 / 1.4)
    # the entry recorded from those rows: against the fastest one-device step (unrolled, 0.55 s)
    entry = bench.results_entries(partial)["dp_scaling_efficiency_small_4gpu"]
    assert entry["efficiency_by_mode"] == {"single_process_scanned": pytest.approx(0.55 / 1.4)}
    assert entry["complete"] is False and "stopped before all its rows" in entry["value_is"]
    # --tiny records nothing in latest.json; --from-out on the file does, stamped as the run
    monkeypatch.setattr(bench.common, "device_name", lambda: "elsewhere")
    partial.update(device="4 x GPU", command="python -m benchmarks.bench_multi_gpu --out mg.json", date="2026-01-02")
    del small["by_batch"], small["complete"]  # as a file written before the small part kept its figures
    with open(out, "w") as f:
        json.dump(partial, f)
    entries = bench.main(["--from-out", out])
    with open(bench.common.RESULTS) as f:
        recorded = json.load(f)["dp_scaling_efficiency_small_4gpu"]
    assert recorded == entries["dp_scaling_efficiency_small_4gpu"]
    assert recorded["value"] == pytest.approx(0.55 / 1.4) and recorded["complete"] is False
    assert (recorded["device"], recorded["command"], recorded["date"], recorded["summarised_from"]) == (
        "4 x GPU", "python -m benchmarks.bench_multi_gpu --out mg.json", "2026-01-02", out)
    # a file that is not an --out file, or whose rows give nothing on several devices, is refused by name
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(UsageError, match="not a bench_multi_gpu --out file"):
        bench.main(["--from-out", str(tmp_path / "bad.json")])
    small["rows"] = [r for r in small["rows"] if r["devices"] == 1]
    with open(out, "w") as f:
        json.dump(partial, f)
    with pytest.raises(SystemExit, match="no figure on several devices"):
        bench.main(["--from-out", out])
