"""One (run, seed) slice of the comparison: which stages it runs, where its shared stages live, its record,
the command that reruns it, the parsing of ``--runs`` / ``--seeds`` / ``--shared-seed``, and running
slices side by side as child processes (``python -m train.compare`` runs them)."""

from __future__ import annotations

import json
import os
import shlex
import time
from collections.abc import Callable, Sequence
from typing import Any

from sword_jax import cli
from sword_jax.cli import UsageError
from sword_jax.pipeline.compare import COMPARISONS, GROUND_TRUTH, runs_for
from sword_jax.pipeline.stages import without_flags


def needs_policy(run: str) -> bool:
    return run == GROUND_TRUTH or any(run in (ours, baseline) for _, ours, baseline, splits in COMPARISONS
                                      if not splits)


EVALUATION_ONLY = ("probe", "evaluate", "report")  # left out by --no-evaluate (the report needs the evaluation)


def shared_dir_of(out: str, run: str, shared_seed: int) -> str:
    """Where ``run``'s shared stages at ``shared_seed`` live: ``<out>/shared/<run>`` at seed 0 (the
    default), ``<out>/shared-seed<k>/<run>`` otherwise. Runs adopt each other's stages only within one
    such root, so stages built at different seeds never mix."""
    root = "shared" if shared_seed == 0 else f"shared-seed{shared_seed}"
    return os.path.join(out, root, run)


def _rounded(value):
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def slice_record(run: str, seed: int, stages: dict, workdir: str) -> dict:
    """The science of one finished slice: overall metrics, per-horizon curves, success curve, losses."""
    evaluate = stages.get("evaluate", {})
    metrics = {split: next(iter(per_model.values())) for split, per_model in evaluate.get("metrics", {}).items()}
    curves, floor = {}, {}
    eval_results = os.path.join(workdir, "eval", "results.json")
    if os.path.exists(eval_results):
        with open(eval_results) as f:
            saved = json.load(f)
        curves = {split: next(iter(per_model.values())).get("curves", {})
                  for split, per_model in saved.get("models", {}).items()}
        floor = {split: r.get("overall", {}) for split, r in saved.get("vae_floor", {}).items()}
    record = {"run": run, "seed": seed, "metrics": metrics, "curves": curves, "vae_floor": floor}
    world_model = stages.get("world_model", {})
    record["world_model"] = {"steps": world_model.get("final_step"), "first_loss": world_model.get("first_loss"),
                             "final_metrics": world_model.get("final_metrics", {})}
    policy = stages.get("policy", {})
    if policy:
        record["success"] = policy.get("success", {})
        curve_path = os.path.join(policy.get("grpo", {}).get("workdir", ""), "success_curve.json")
        if os.path.exists(curve_path):
            with open(curve_path) as f:
                record["success_curve"] = json.load(f)["points"]
        record["policy"] = {k: policy[k] for k in ("reward_model", "sft", "grpo") if k in policy}
    return _rounded(record)


SLICES_AT_ONCE_ENV = "SWORD_COMPARE_SLICES_AT_ONCE"  # set by the parent: each slice records how crowded its device was


def slice_command(run: str, seed: int, *, size: str, shared_seed: int, share: bool, overrides: Sequence[str],
                  policy: bool = True, evaluate: bool = True) -> str:
    """The command that reruns exactly this slice."""
    argv = ["--size", size, "--runs", run, "--seeds", str(seed), *([] if policy else ["--no-policy"]),
            *([] if evaluate else ["--no-evaluate"])]
    argv += [f"--shared-seed={shared_seed}"] if share and shared_seed else []
    return shlex.join(["python", "-m", "train.compare", *argv, *([] if share else ["--no-share"]), *overrides])


def parse_runs(text: str, size: str, *, policy: bool = True) -> list[str]:
    """``--runs``; empty: every run (without ``policy``, every run but ``ground_truth``, which is all policy)."""
    known = runs_for(size)
    if not text:
        return [run for run in known if policy or run != GROUND_TRUTH]
    names = text.split(",")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise UsageError(f"--runs: unknown run(s) {', '.join(map(repr, unknown))}; known: {', '.join(known)}")
    if len(set(names)) < len(names):
        raise UsageError(f"--runs: a run is listed twice in {text!r}")
    return names


def parse_shared_seed(text: str) -> int | str:
    """``--shared-seed``: a non-negative integer, or ``slice`` (each seed's shared stages at that seed)."""
    if text == "slice":
        return text
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        import argparse

        raise argparse.ArgumentTypeError(f"--shared-seed takes a non-negative integer or 'slice', got {text!r}")
    return value


def shared_seed_of(shared_seed: int | str, seed: int) -> int:
    """The seed of the shared stages a slice at ``seed`` uses (``--shared-seed``, parsed)."""
    return seed if shared_seed == "slice" else int(shared_seed)


def parse_seeds(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        raise UsageError(f"--seeds takes comma-separated integers, got {text!r}") from None
    if len(set(seeds)) < len(seeds) or min(seeds) < 0:
        raise UsageError(f"--seeds: non-negative integers, each once, got {text!r}")
    return seeds


def run_slices_side_by_side(argv: Sequence[str], runs: Sequence[str], seeds: Sequence[int], args, overrides, *,
                            build: Callable[..., Any], launch: Callable[[list[str], str, dict], Any],
                            poll_s: float = 2.0) -> None:
    """``--slices-at-once N``: the parent builds the shared stages (here, so no two slices build them at
    once), run by run, and starts each (run, seed) slice as ``python -m train.compare ... --runs RUN
    --seeds K`` in its own process as soon as that run's shared stages are built, N at a time, in
    seed-major order (a slice never starts before one listed ahead of it, so a run stopped early leaves
    whole seeds). While the parent builds the next run's stages (e.g. latents without augmentation)
    the earlier runs' slices already train. The children find the shared stages finished and only
    adopt them. A failed slice or shared build starts no new slices; the running ones finish; then
    ``RuntimeError`` names what failed and the logs (a rerun skips every finished stage).

    A stop request (:func:`sword_jax.cli.request_stop`, ``SIGUSR1`` under ``cli.run``) is passed on to every
    running slice (each checkpoints its step in flight and exits ``cli.STOPPED_EXIT``); no slice or build starts
    after it, and once the running slices have ended :class:`~sword_jax.cli.StopRequested` names the slices stopped
    and those not started (the same command resumes them). A shared build that itself stops on the request counts
    as stopped, not failed. Slices that failed still raise ``RuntimeError``, which names the stop as well.

    With ``args.gpus`` (``--gpus 0,1,2,3``) each slice runs on one GPU of the list
    (``CUDA_VISIBLE_DEVICES``), the one fewest running slices hold, so ``--slices-at-once`` equal to the
    number of GPUs puts one slice on each; the parent's shared stages see the GPUs it was started with.
    NVLink multicast stays off in every slice.

    ``build(run, size, *, out, shared_seed, overrides, policy, parallel, evaluate)`` builds a run's shared
    stages; ``launch(argv, log_path, env) -> Popen`` starts one slice.
    """

    from sword_jax.pipeline.launch import NO_MULTICAST

    base = without_flags(argv, {"--slices-at-once": True, "--runs": True, "--seeds": True, "--gpus": True})
    logs = os.path.join(args.out, "logs")
    os.makedirs(logs, exist_ok=True)
    env = {**os.environ, SLICES_AT_ONCE_ENV: str(args.slices_at_once), **NO_MULTICAST}
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # several JAX processes share one device
    gpus = list(getattr(args, "gpus", None) or [])
    # in order: a later run adopts the earlier runs' stages where the sections agree
    builds = [] if args.no_share else [(shared_seed, run) for shared_seed in
                                        sorted({shared_seed_of(args.shared_seed, seed) for seed in seeds})
                                        for run in runs]
    built: set[tuple[int, str]] = set()
    pending = [(run, seed) for seed in seeds for run in runs]
    running: dict[tuple[str, int], tuple] = {}
    failed: list[str] = []
    stopped: list[str] = []
    forwarded = False  # the stop request passed on to the running slices

    def ready(run: str, seed: int) -> bool:
        return args.no_share or (shared_seed_of(args.shared_seed, seed), run) in built

    def halted() -> bool:
        return bool(failed or stopped or cli.stop_requested())

    while pending or running or (builds and not halted()):
        if (cli.stop_requested() or stopped) and not forwarded:
            forwarded = True
            asked = cli.ask_to_stop(entry[0] for entry in running.values())
            print(f"[compare] stop requested: asked {asked} running slice(s) to stop; no more slices start", flush=True)
        while pending and not halted() and len(running) < args.slices_at_once and ready(*pending[0]):
            run, seed = pending.pop(0)
            log_path = os.path.join(logs, f"{run}_seed{seed}.log")
            gpu = None
            if gpus:  # the GPU fewest running slices hold, the earliest listed of those
                busy = [entry[3] for entry in running.values()]
                gpu = min(gpus, key=lambda g: (busy.count(g), gpus.index(g)))
            proc = launch([*base, "--runs", run, "--seeds", str(seed)], log_path,
                          env if gpu is None else {**env, "CUDA_VISIBLE_DEVICES": gpu})
            running[(run, seed)] = (proc, log_path, time.perf_counter(), gpu)
            print(f"[compare] slice {run} seed {seed}: started{'' if gpu is None else f' on GPU {gpu}'} "
                  f"(log {log_path})", flush=True)
        if builds and not halted():
            shared_seed, run = builds.pop(0)
            try:
                build(run, args.size, out=args.out, shared_seed=shared_seed, overrides=overrides,
                      policy=not args.no_policy, parallel=args.parallel, evaluate=not args.no_evaluate)
                built.add((shared_seed, run))
            except cli.StopRequested:  # checkpointed; passed on to the running slices at the loop's top
                stopped.append(f"shared stages of {run} at seed {shared_seed}")
            except Exception as error:  # the running slices still finish and are merged
                failed.append(f"shared stages of {run} at seed {shared_seed} ({type(error).__name__}: {error})")
            continue
        if not running:
            break
        time.sleep(poll_s)
        for key, (proc, log_path, start, _) in list(running.items()):
            code = proc.poll()
            if code is None:
                continue
            del running[key]
            status = {0: "done", cli.STOPPED_EXIT: "stopped on request (resumes)"}.get(
                code, f"FAILED (exit {code}, see {log_path})")
            print(f"[compare] slice {key[0]} seed {key[1]}: {status} after {time.perf_counter() - start:.0f} s",
                  flush=True)
            if code == cli.STOPPED_EXIT:
                stopped.append(f"{key[0]} seed {key[1]}")
            elif code != 0:
                failed.append(f"{key[0]} seed {key[1]} ({log_path})")
    not_started = ", ".join(f"{r} seed {k}" for r, k in pending) or "none"
    if failed:
        raise RuntimeError(f"train.compare: slices failed: {'; '.join(failed)}; "
                           + (f"stopped on request: {', '.join(stopped)}; " if stopped else "")
                           + f"not started: {not_started}")
    if stopped or (cli.stop_requested() and pending):
        raise cli.StopRequested(f"train.compare: stopped on request: {', '.join(stopped) or 'no slice running'}; "
                                f"not started: {not_started}; the same command resumes")
