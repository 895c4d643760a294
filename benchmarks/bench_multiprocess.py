"""One process per GPU: a killed rank ends the launched job within the grace, the rerun resumes bit-identical,
and a checkpoint of the job continues on fewer devices with the same loss.

    python -m benchmarks.bench_multiprocess --processes 4 --out /tmp/mp.json    # 4 GPUs: about 4 min
    python -m benchmarks.bench_multiprocess --processes 2 --cpu-devices 2 --no-record   # CPU (gloo): about 1.5 min

What ``tests/test_multihost.py`` checks with gloo processes on CPU, on GPUs (NCCL), with the world model
trained by ``train.launch --processes P -- python -m train.train_world_model --synthetic --mesh.distributed=true
--mesh.data=<devices of all ranks>`` (a checkpoint and a metrics row at every step):

1. warm-up and reference: the command, ``--steps`` steps, twice. The first fills the compilation cache, so every
   later run of the job loads the executables rank 0 compiled (a GPU rank that compiles for itself autotunes
   for itself); whether the two ended bit-identical is reported, not checked;
2. crash: the same command in another work dir; once a checkpoint of step >= 2 is written, rank P-1 gets
   SIGKILL, and the launcher must exit within ``--grace`` + 3 s of the kill, non-zero, naming that rank. The
   same command run again must say it resumed from the newest checkpoint and end with the reference's final
   checkpoint (every array bit for bit, the step, the data position) and logged metrics (every value of every
   step);
3. restore: the reference's checkpoint of step S = ``steps // 2``, copied, continues one step as one process
   (no ``jax.distributed``) on half the devices and on 1 device; its loss of step S + 1 must equal the
   reference's within ``--restore-rtol`` (the reduction order differs; see :data:`RESTORE_RTOL`).

On GPUs rank ``i`` runs on the ``i``-th visible GPU, and the two restored runs side by side on GPUs of their own
when there are enough. ``--cpu-devices K`` runs every rank on K CPU devices instead (gloo), the restored runs
on half of all devices and on one; the default config is then ``sword:tiny``. Any ``--section.key=value`` goes
to every run, and so do the environment's ``XLA_FLAGS``. Children share ``JAX_COMPILATION_CACHE_DIR`` (default
``<workdir>/xla_cache``, kept between calls); NVLink multicast stays off in every child. The full report goes
to ``--out`` (default ``<workdir>/report.json``) after each stage, and ``multiprocess_resume_exact`` into
``benchmarks/results/latest.json`` (unless ``--no-record``). The exit status is 1 when a check failed; a
difference is reported with its size (arrays, metrics).

Wall time on 4 H100s (sword:small at batch 8, 6 steps, a 440 MB checkpoint per step), estimated: about 4 min
with a cold compilation cache (the warm-up and the restored runs' new device counts compile, about a minute
each), about 2.5 min with a warm one. On 2 CPU cores with ``--processes 2 --cpu-devices 2``: 1.5 min.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

import configs
from benchmarks import common
from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic
from sword_jax.checkpoint import read_arrays
from sword_jax.pipeline import launch as launcher

# A batch and dataset small enough that a step is quick; both divisible by 4 devices (and by 2 and 1).
OVERRIDES = {
    "sword:small": ("--data.batch_size=8", "--data.num_episodes=16"),
    "sword:tiny": ("--data.batch_size=4", "--data.num_episodes=8"),
}
KILL_AFTER = 2  # the crashed run's rank is killed once a checkpoint of this step or later is written
# The restored run's loss of its one step against the reference's, relative. Both compute the same examples
# with the same keys (partitionable threefry); only the reduction order over devices differs. float32 on CPU
# measured 0 to 1.7e-7 on 2 devices and 6.8e-7 on 1 (from 2 processes x 2 devices, sword:tiny): the bound leaves
# 100x. bfloat16 activations may round one ulp (7.8e-3) apart where a kernel's tiling follows the per-device
# batch; averaged into the loss such flips stay far below one ulp, which is the bound.
RESTORE_RTOL = {"float32": 1e-4, "bfloat16": 1e-2}
STOP_SLACK_S = 1.0  # beyond the launcher's grace + STOP_MARGIN_S: its own exit
_DISTRIBUTED_VARS = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")


class Child:
    """A command running from the repository root; its output lines are kept, echoed with a prefix and
    written to ``log_path``."""

    def __init__(self, name: str, argv: Sequence[str], env: dict[str, str], log_path: str):
        self.name, self.lines = name, []
        self.start = time.monotonic()
        os.makedirs(os.path.dirname(log_path), exist_ok=True)
        self.proc = subprocess.Popen(list(argv), cwd=common.REPO, env=env, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, errors="replace")
        self.reader = threading.Thread(target=self._read, args=(log_path,), daemon=True)
        self.reader.start()

    def _read(self, log_path: str) -> None:
        with open(log_path, "w") as log:
            for line in iter(self.proc.stdout.readline, ""):
                self.lines.append(line)
                log.write(line)
                log.flush()
                print(f"[{self.name}] {line}", end="", flush=True)

    def wait(self, timeout_s: float, grace_s: float) -> int:
        """Waits for the exit status; past ``timeout_s`` SIGTERM (a launcher stops its ranks), then SIGKILL."""
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            print(f"[bench] {self.name}: still running after {timeout_s:.0f} s, stopping it", flush=True)
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=grace_s + launcher.STOP_MARGIN_S + 5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.reader.join(timeout=5)
        return self.proc.returncode

    @property
    def seconds(self) -> float:
        return time.monotonic() - self.start

    @property
    def output(self) -> str:
        return "".join(self.lines)


def saved_steps(checkpoint_dir: str) -> list[int]:
    """The complete checkpoints' steps (orbax renames a step's folder to its number once it is complete)."""
    if not os.path.isdir(checkpoint_dir):
        return []
    return sorted(int(d) for d in os.listdir(checkpoint_dir) if d.isdigit())


def metric_rows(workdir: str) -> dict[int, dict[str, float]]:
    """``metrics.jsonl`` by step, the timing columns left out; a step run again after a resume replaces the
    killed run's row."""
    rows = {}
    with open(os.path.join(workdir, "metrics.jsonl")) as f:
        for line in f:
            row = json.loads(line)
            rows[int(row["step"])] = {k: v for k, v in row.items() if k not in ("elapsed_s", "eta_s")}
    return rows


def rel_diff(value: float, reference: float) -> float:
    return abs(value - reference) / max(abs(reference), 1e-30)


def compare_checkpoints(reference: str, other: str) -> dict[str, Any]:
    """The newest checkpoints of two work dirs: arrays compared bit for bit (the largest difference of those that
    differ), and their steps and data positions."""
    want, want_meta = read_arrays(os.path.join(reference, "checkpoints"))
    got, got_meta = read_arrays(os.path.join(other, "checkpoints"))
    differing = {}
    for name in sorted(want.keys() & got.keys()):
        a, b = want[name], got[name]
        if a.dtype != b.dtype or a.shape != b.shape:
            differing[name] = None
        elif a.tobytes() != b.tobytes():
            differing[name] = float(np.max(np.abs(a.astype(np.float64) - b.astype(np.float64))))
    missing = sorted(want.keys() ^ got.keys())
    same_position = got_meta.get("data_position") == want_meta.get("data_position")
    return {"arrays": len(want), "differing_count": len(differing),
            "differing_arrays": dict(list(differing.items())[:20]),  # name -> largest |difference|
            "missing_arrays": missing[:20], "step": got_meta["step"], "reference_step": want_meta["step"],
            "same_data_position": same_position,
            "equal": bool(want) and not differing and not missing and got_meta["step"] == want_meta["step"]
            and same_position}


def compare_metrics(reference: str, other: str, steps: int) -> dict[str, Any]:
    """Two runs' logged metrics: every value of every step compared exactly (the largest relative difference)."""
    want, got = metric_rows(reference), metric_rows(other)
    differing = sorted(s for s in want.keys() | got.keys() if want.get(s) != got.get(s))
    diffs = [rel_diff(got[s][k], v) for s in differing if s in want and s in got
             for k, v in want[s].items() if k in got[s] and got[s][k] != v]
    return {"steps": sorted(got), "differing_steps": differing, "max_rel_diff": max(diffs, default=0.0),
            "equal": not differing and sorted(got) == sorted(want) == list(range(1, steps + 1))}


def compare_runs(reference: str, other: str, steps: int) -> dict[str, Any]:
    """:func:`compare_checkpoints` and :func:`compare_metrics`; ``equal`` when both are (an error is reported)."""
    try:
        found = {"checkpoint": compare_checkpoints(reference, other), "metrics": compare_metrics(reference, other, steps)}
    except Exception as err:  # noqa: BLE001 - the report says why, and the later stages still run
        return {"equal": False, "error": f"{type(err).__name__}: {err}"}
    return {**found, "equal": found["checkpoint"]["equal"] and found["metrics"]["equal"]}


def _parse(argv: Sequence[str]):
    parser = cli.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, default=4, help="ranks, one per GPU (default %(default)s)")
    parser.add_argument("--workdir", default=os.path.join("runs", "bench_multiprocess"),
                        help="where the runs go (their folders are replaced; xla_cache/ is kept)")
    parser.add_argument("--config", default=None, help="default sword:small, with --cpu-devices sword:tiny")
    parser.add_argument("--steps", type=int, default=6, help="steps of the reference run (default %(default)s)")
    parser.add_argument("--grace", type=float, default=5.0, help="the launcher's --grace (default %(default)s)")
    parser.add_argument("--cpu-devices", type=int, default=None, help="run each rank on K CPU devices (gloo)")
    parser.add_argument("--out", default=None, help="the report (JSON); default <workdir>/report.json")
    parser.add_argument("--no-record", action="store_true", help="leave benchmarks/results/latest.json alone")
    parser.add_argument("--restore-rtol", type=float, default=None,
                        help="relative tolerance of the restored runs' loss (default by compute dtype)")
    parser.add_argument("--timeout", type=float, default=600, help="seconds each run may take (default %(default)s)")
    args, rest = parser.parse_known_args(argv)
    if unknown := cli.not_dotted_overrides(rest):
        raise cli.UsageError(f"unrecognized arguments: {' '.join(unknown)}")
    if args.processes < 2:
        raise cli.UsageError("--processes must be >= 2 (a rank other than 0 is killed)")
    if args.steps < KILL_AFTER + 2:
        raise cli.UsageError(f"--steps must be >= {KILL_AFTER + 2}: the kill comes after the checkpoint of step "
                             f"{KILL_AFTER} and before the run ends")
    if (args.cpu_devices is not None and args.cpu_devices < 1) or args.grace < 0:
        raise cli.UsageError("--cpu-devices must be >= 1 and --grace >= 0")
    args.config = args.config or ("sword:tiny" if args.cpu_devices else "sword:small")
    return args, rest


def _probe_gpus(env: dict[str, str], processes: int) -> tuple[str, list[str]]:
    """The GPUs' kind and the ranks' GPUs (``CUDA_VISIBLE_DEVICES`` values), read by a short child so this
    process never holds a GPU."""
    code = "import jax, json; d = jax.devices(); print(json.dumps([d[0].platform, getattr(d[0], 'device_kind', ''), len(d)]))"
    probe = subprocess.run([sys.executable, "-c", code], env=dict(env, XLA_PYTHON_CLIENT_PREALLOCATE="false"),
                           capture_output=True, text=True, timeout=300)
    try:
        platform, kind, count = json.loads(probe.stdout.strip().splitlines()[-1])
    except (IndexError, ValueError):
        raise SystemExit(f"bench_multiprocess: could not list the devices: {probe.stderr.strip()[-2000:]}") from None
    if platform != "gpu" or count < processes:
        raise SystemExit(f"bench_multiprocess: {processes} processes need {processes} GPUs, JAX sees {count} "
                         f"{platform} device(s); pass --cpu-devices K to run on CPU")
    return kind, launcher.default_gpus(processes, env)


def single_process_env(env: dict[str, str], devices: int, gpus: Sequence[str] | None) -> dict[str, str]:
    """A plain (not distributed) process on ``devices`` CPU devices, or on ``gpus``."""
    env = {k: v for k, v in env.items() if k not in _DISTRIBUTED_VARS}
    env.update(PYTHONUNBUFFERED="1", **launcher.NO_MULTICAST)
    if gpus is None:
        return launcher.with_devices(env, cpu_devices=devices)
    return launcher.with_devices(env, gpus=",".join(gpus))


def crash_and_measure(child: Child, checkpoint_dir: str, rank: int, grace_s: float, timeout_s: float) -> dict[str, Any]:
    """Waits for a checkpoint of step >= :data:`KILL_AFTER`, SIGKILLs ``rank`` of the launched job ``child`` and
    times the job's end."""
    deadline = time.monotonic() + timeout_s
    pid, saved = None, []
    while time.monotonic() < deadline and child.proc.poll() is None:
        if pid is None:
            found = [re.search(rf"\[launch\] rank {rank}: pid (\d+)", line) for line in list(child.lines)]
            pid = next((int(m.group(1)) for m in found if m), None)
        saved = saved_steps(checkpoint_dir)
        if pid is not None and saved and saved[-1] >= KILL_AFTER:
            break
        time.sleep(0.01)
    if child.proc.poll() is not None or pid is None or not saved or saved[-1] < KILL_AFTER:
        code = child.wait(timeout_s, grace_s)
        return {"killed": False, "returncode": code,
                "error": f"the run ended (status {code}) or timed out before a checkpoint of step {KILL_AFTER}"}
    os.kill(pid, signal.SIGKILL)  # lands inside a step or a checkpoint write
    killed = time.monotonic()
    code = child.wait(grace_s + 120, grace_s)
    stop_s = time.monotonic() - killed
    limit_s = grace_s + launcher.STOP_MARGIN_S + STOP_SLACK_S
    named = f"rank {rank} failed first (killed by SIGKILL)" in child.output
    return {"killed": True, "killed_rank": rank, "kill_step": saved[-1], "seconds_kill_to_end": stop_s,
            "limit_s": limit_s, "returncode": code, "names_failed_rank": named,
            "ok": stop_s <= limit_s and code not in (0, None) and named,
            "resumable_from": (saved_steps(checkpoint_dir) or [None])[-1]}


def main(argv: Sequence[str] | None = None) -> int:
    args, overrides = _parse(sys.argv[1:] if argv is None else argv)
    jax.config.update("jax_platforms", "cpu")  # this process only reads checkpoints; the accelerators are the ranks'
    began = time.monotonic()
    processes, per_rank = args.processes, args.cpu_devices or 1
    devices = processes * per_rank
    cfg_flags = ["--config", args.config, *OVERRIDES.get(args.config, ()), *overrides]
    cfg = configs.from_argv(cfg_flags)[0]
    if cfg.data.batch_size % devices or cfg.data.num_episodes % devices:
        raise cli.UsageError(f"data.batch_size ({cfg.data.batch_size}) and data.num_episodes "
                             f"({cfg.data.num_episodes}) must be multiples of the {devices} devices")
    rtol = args.restore_rtol if args.restore_rtol is not None else RESTORE_RTOL.get(cfg.model.compute_dtype, 1e-2)
    root = os.path.abspath(args.workdir)
    out = args.out or os.path.join(root, "report.json")
    env = dict(os.environ, PYTHONUNBUFFERED="1", **launcher.NO_MULTICAST)
    env.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(root, "xla_cache"))
    env.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")  # every program of the job, not only slow ones
    if args.cpu_devices:
        gpus, device = None, f"cpu x{devices} (cpu, {processes} processes x {per_rank} devices, gloo)"
    else:
        env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # a rank's memory is back as soon as it ends
        kind, gpus = _probe_gpus(env, processes)
        device = f"{kind} x{processes} (gpu, {processes} processes)"
    for name in os.listdir(root) if os.path.isdir(root) else []:
        if name in ("warmup", "reference", "crash", "logs") or name.startswith("restore_"):
            shutil.rmtree(os.path.join(root, name))
    os.makedirs(root, exist_ok=True)

    steps = args.steps
    trainer_args = [*cfg_flags, "--synthetic", f"--trainer.steps={steps}", "--trainer.checkpoint_every=1",
                    "--trainer.log_every=1", f"--trainer.keep_checkpoints={steps}"]
    report: dict[str, Any] = {"processes": processes, "devices": devices, "device": device, "config": args.config,
                              "xla_flags": os.environ.get("XLA_FLAGS", ""),
                              "overrides": [*OVERRIDES.get(args.config, ()), *overrides], "steps": steps,
                              "grace_s": args.grace, "compilation_cache": env["JAX_COMPILATION_CACHE_DIR"]}

    def save() -> None:
        report["wall_s"] = time.monotonic() - began
        write_json_atomic(out, report, sort_keys=True)

    def launched(name: str, workdir: str) -> Child:
        own = [sys.executable, "-m", "train.launch", "--processes", str(processes), "--grace", str(args.grace),
               *(["--cpu-devices", str(per_rank)] if args.cpu_devices else ["--gpus", ",".join(gpus)])]
        trainer = [sys.executable, "-m", "train.train_world_model", "--workdir", workdir, *trainer_args,
                   f"--mesh.data={devices}", "--mesh.distributed=true"]
        return Child(name, [*own, "--", *trainer], env, os.path.join(root, "logs", f"{name}.log"))

    warmup, reference, crashed = (os.path.join(root, name) for name in ("warmup", "reference", "crash"))
    for name, workdir in (("warmup", warmup), ("reference", reference)):
        run = launched(name, workdir)
        report[name] = {"returncode": run.wait(args.timeout, args.grace), "seconds": run.seconds}
        save()
        if report[name]["returncode"] != 0:
            return _finish(report, save, args, f"the {name} run failed")
    # Told apart from the check: ranks that compiled for themselves (autotuned) against ranks that loaded rank 0's
    # cached executables, as every later run of the job does.
    report["warmup"]["equal_to_reference"] = compare_runs(reference, warmup, steps)

    crash = launched("crash", crashed)
    report["crash"] = crash_and_measure(crash, os.path.join(crashed, "checkpoints"), processes - 1, args.grace,
                                        args.timeout)
    report["crash"]["seconds"] = crash.seconds
    save()
    if not report["crash"]["killed"]:
        return _finish(report, save, args, report["crash"]["error"])

    rerun = launched("resume", crashed)
    code = rerun.wait(args.timeout, args.grace)
    said = re.search(r"\[rank 0\] train_world_model: resumed from step (\d+)", rerun.output)
    report["resume"] = {"returncode": code, "seconds": rerun.seconds,
                        "resumed_from": int(said.group(1)) if said else None}
    if code == 0:
        report["resume"].update(compare_runs(reference, crashed, steps))
    resume = report["resume"]
    report["resume_exact"] = bool(code == 0 and resume["resumed_from"] is not None
                                  and resume["resumed_from"] == report["crash"]["resumable_from"] and resume.get("equal"))
    save()

    try:
        report["restore"] = restore_runs(reference, root, steps // 2, trainer_args, env, devices, gpus, rtol, args)
    except Exception as err:  # noqa: BLE001 - the report keeps what the other stages found
        report["restore"] = {"ok": False, "error": f"{type(err).__name__}: {err}"}
    save()
    return _finish(report, save, args, None)


def restore_runs(reference: str, root: str, from_step: int, trainer_args: list[str], env: dict[str, str],
                 devices: int, gpus: list[str] | None, rtol: float, args) -> dict[str, Any]:
    """The reference's checkpoint of ``from_step`` continued one step as one process on half the devices and on
    one; each run's logged metrics of that step against the reference's."""
    counts = sorted({max(devices // 2, 1), 1}, reverse=True)
    # Side by side on GPUs of their own when there are enough; one after the other on CPU or too few GPUs.
    side_by_side = gpus is not None and sum(counts) <= len(gpus)
    want = metric_rows(reference)[from_step + 1]
    children, runs = [], []
    first_gpu = 0
    for count in counts:
        workdir = os.path.join(root, f"restore_{count}")
        os.makedirs(os.path.join(workdir, "checkpoints"))
        shutil.copy(os.path.join(reference, "config.json"), workdir)
        shutil.copytree(os.path.join(reference, "checkpoints", str(from_step)),
                        os.path.join(workdir, "checkpoints", str(from_step)))
        these = None
        if gpus is not None:
            these = gpus[first_gpu:first_gpu + count] if side_by_side else gpus[:count]
            first_gpu += count if side_by_side else 0
        argv = [sys.executable, "-m", "train.train_world_model", "--workdir", workdir, *trainer_args,
                f"--mesh.data={count}", f"--trainer.steps={from_step + 1}"]
        child = Child(f"restore_{count}", argv, single_process_env(env, count, these),
                      os.path.join(root, "logs", f"restore_{count}.log"))
        runs.append({"devices": count, "processes": 1, "gpus": these})
        children.append(child)
        if not side_by_side:
            child.wait(args.timeout, args.grace)
    for run, child in zip(runs, children):
        run["returncode"] = child.wait(args.timeout, args.grace)
        run["seconds"] = child.seconds
        said = re.search(r"train_world_model: resumed from step (\d+)", child.output)
        run["resumed_from"] = int(said.group(1)) if said else None
        got = metric_rows(os.path.join(root, f"restore_{run['devices']}")).get(from_step + 1, {}) \
            if run["returncode"] == 0 else {}
        run["loss"], run["reference_loss"] = got.get("loss"), want["loss"]
        run["rel_diff"] = rel_diff(got["loss"], want["loss"]) if "loss" in got else None
        run["metrics_rel_diff"] = {k: rel_diff(got[k], v) for k, v in want.items() if k != "step" and k in got}
        run["ok"] = bool(run["returncode"] == 0 and run["resumed_from"] == from_step and run["rel_diff"] is not None
                         and run["rel_diff"] <= rtol)
    return {"from_step": from_step, "step": from_step + 1, "reference_devices": devices, "rtol": rtol, "runs": runs,
            "ok": all(run["ok"] for run in runs)}


def _finish(report: dict[str, Any], save, args, error: str | None) -> int:
    """Writes the report (and the record), prints the summary; the exit status."""
    crash, restore = report.get("crash", {}), report.get("restore", {})
    report["ok"] = bool(error is None and report.get("resume_exact") and crash.get("ok") and restore.get("ok"))
    if error:
        report["error"] = error
    save()
    rows = [{"check": "kill -> job end (s)", "value": crash.get("seconds_kill_to_end"), "bound": crash.get("limit_s"),
             "ok": crash.get("ok")},
            {"check": "resume bit-identical", "value": report.get("resume_exact"), "bound": True,
             "ok": report.get("resume_exact")}]
    rows += [{"check": f"restore on {run['devices']} device(s): loss rel diff", "value": run["rel_diff"],
              "bound": restore["rtol"], "ok": run["ok"]} for run in restore.get("runs", [])]
    common.print_table(rows, ["check", "value", "bound", "ok"])
    print(f"report: {os.path.abspath(args.out or os.path.join(args.workdir, 'report.json'))}"
          + (f"; FAILED: {error}" if error else "" if report["ok"] else "; a check FAILED"), flush=True)
    if not args.no_record and "resume" in report:
        resume = report["resume"]
        common.merge_results({"multiprocess_resume_exact": common.record(
            "multiprocess_resume_exact", bool(report["resume_exact"]), True, device=report["device"],
            processes=report["processes"], devices=report["devices"], config=report["config"],
            xla_flags=report["xla_flags"], overrides=report["overrides"], steps=report["steps"],
            kill_step=crash.get("kill_step"),
            seconds_kill_to_end=crash.get("seconds_kill_to_end"), grace_s=report["grace_s"],
            stop_limit_s=crash.get("limit_s"), stopped_within_limit=crash.get("ok"),
            launcher_returncode=crash.get("returncode"), resumed_from=resume.get("resumed_from"),
            arrays_differing=resume.get("checkpoint", {}).get("differing_count"),
            metrics_max_rel_diff=resume.get("metrics", {}).get("max_rel_diff"),
            cold_compile_equal=report.get("warmup", {}).get("equal_to_reference", {}).get("equal"),
            restore=[{k: run[k] for k in ("devices", "loss", "reference_loss", "rel_diff", "ok")}
                     for run in restore.get("runs", [])],
            restore_from_step=restore.get("from_step"), restore_rtol=restore.get("rtol"),
            all_checks_ok=report["ok"], wall_s=report["wall_s"])})
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    cli.run(main)
