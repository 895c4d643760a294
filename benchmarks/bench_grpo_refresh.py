"""GRPO in the learned simulator refreshed on the policy's real episodes, against ground-truth GRPO, by real
episodes consumed (issue 41's experiment, one command on a machine of several GPUs).

``run``: one pipeline builds the world model, VAE and success detector (``train.pipeline --stop-after
reward_model`` on the first GPU), then GRPO runs in it from the same supervised policy, one process per GPU
(``CUDA_VISIBLE_DEVICES``), side by side: ``refreshed`` at every seed (``rl.refresh`` every
``--refresh-every`` steps within ``--budget`` real episodes) and ``once`` at the first seed (one refresh at
step 0, then the budget is spent: the simulator adapted to the supervised policy, never again); with
``--wovr-config cache_ablation:small-wovr`` a WoVR-config world model is built beside it and refreshed the same
way at every seed (``wovr_refreshed_seed<k>``; the summary pairs the gains seed by seed). Every run is
evaluated on MJX as ground-truth GRPO is (the greedy, ensembled policy and the sampled one, 500 episodes).
``--variant NAME=OVERRIDES`` adds pipelines of Sword's config with other settings (each on its own GPU, its runs
``NAME_refreshed_seed<k>``): the first refresh's replay measures, before any GRPO step, whether each world model
separates the policy's real successes from its real failures. Every pipeline after the first links the first
one's episodes (one data stage); each pipeline's runs start as soon as it is built; ``--deadline-s`` stops the
runs still going and summarises them at their last evaluation (with ``--grace-s`` they are asked first: each
checkpoints its step in flight, GRPO evaluates it, and the same command resumes them).

``summary``: each run's real success curves and gains (Newcombe intervals), the real episodes it used, every
refresh's replay (the share of the policy's new real failures the simulator called successes before it was
refreshed) and detector calibration, and the guards' verdicts at each evaluation (``guard``: the exploitation
guard's, and with ``rl.refresh.real_guard_margin`` the real-success guard's under ``real_success``, e.g. from
``--run-variant "realguard=--rl.refresh.real_guard_margin=0.15"``); the figure plots real success against real
episodes consumed for ground-truth GRPO (``--ground-truth``: a ``bench_policy grpo-seeds`` folder) and the
refreshed runs.

    python -m benchmarks.bench_grpo_refresh run --workdir runs/r41 --policy runs/p/policy_d50.npz --gpus 0,1,2,3
    python -m benchmarks.bench_grpo_refresh summary --workdir runs/r41 \\
        --ground-truth benchmarks/results/policy/grpo_mjx_seeds_small_4xh100 --out benchmarks/results/policy/grpo_refresh_small
    python -m benchmarks.bench_grpo_refresh run --workdir runs/r41v --policy runs/p/policy_d50.npz --gpus 0 --seeds 0 \\
        --arms refreshed --variant "lpips=--vae.perceptual_weight=1.0" --variant "long=--trainer.steps=15000" \\
        --variant-gpus 1,2 --data-backend cpu --deadline-s 1450
    python -m benchmarks.bench_grpo_refresh run --workdir runs/r41c --policy runs/p/policy_d50.npz --gpus 0 \
        --seeds 0 --arms refreshed --run-variant "separation=--rl.refresh.calibration=separation" \
        --run-variant "realdet=--rl.refresh.replay_share=0 --rl.refresh.calibration=separation" \
        --run-variant "light=--rl.imagined.decoder=light --rl.refresh.calibration=separation" \
        --run-variant-seeds 0 --run-variant-gpus 0 --policy-rollouts 20 --data-backend cpu \
        --rl.refresh.pause_untrusted=true --deadline-s 1450

``--policy-rollouts N`` starts every pipeline from ``--policy`` (``rl.sft.init``) and adds N of its episodes per
task, failures included, to each world model's and detector's training data. ``--run-variant NAME=--rl...`` adds
runs with other GRPO settings in Sword's world model (no pipeline of their own), ``NAME_refreshed_seed<k>`` on
``--run-variant-gpus``, e.g. ``--run-variant "realdet=--rl.refresh.replay_share=0"``; several runs may share a GPU
(``--gpus 0``: memory is not preallocated). A run variant with
``--rl.imagined.decoder=light`` makes its pipeline distil the light rollout decoder and its runs decode with it
(their replays then measure the simulator through it, their ``step_times.jsonl`` its speed inside GRPO).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shlex
import signal
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

from benchmarks import common
from benchmarks.bench_grpo_transfer import errorbar_curve, gain_interval
from sword_jax import cli
from sword_jax.cli import not_dotted_overrides

# what ground-truth GRPO's recipe (issue 40) and the refreshed runs share; --section.key=value overrides
GRPO_FLAGS = ("--rl.env.backend=mjx", "--rl.grpo.rollout_batch=32", "--rl.grpo.group_size=8",
              "--rl.grpo.minibatches=4", "--rl.grpo.update_microbatch=8", "--rl.grpo.temperature=0.5",
              "--rl.grpo.learning_rate=1e-4", "--rl.grpo.eval_episodes_per_task=50", "--rl.imagined.execute_steps=4",
              "--rl.imagined.max_chunks=12", "--rl.imagined.shared_group_noise=true", "--rl.imagined.guard_margin=0.1",
              "--rl.refresh.episodes=64", "--rl.refresh.world_model_steps=200", "--rl.refresh.detector_steps=200",
              "--rl.refresh.horizons=24,48")
# the pipeline up to the detector; no supervised policy or its rollouts (the policy is given; the first
# refresh collects its episodes), 20 demonstrations per task for the detector
PIPELINE_FLAGS = ("--stop-after", "reward_model", "--skip", "probe,evaluate,sft_policy,policy_data", "--parallel", "2",
                  "--data.policy_rollouts_per_task=0", "--rl.sft.episodes_per_task=20")


@dataclasses.dataclass(frozen=True)
class Pipe:
    """One pipeline and the GRPO runs in its world model.

    ``folder``: under the work dir; ``overrides``: its own dotted overrides (its pipeline and its runs);
    ``prefix``: of its runs' names; ``seeds`` / ``gpus``: its runs' seeds and the GPUs they take in turn (its
    pipeline the first); ``once``: also the adapted-once arm at its first seed; ``runs_only``: runs in the
    pipeline of that folder built by another entry (a ``--run-variant``: its overrides are GRPO's alone)."""

    folder: str
    config: str
    overrides: tuple[str, ...] = ()
    prefix: str = ""
    seeds: tuple[int, ...] = (0,)
    gpus: tuple[str, ...] = ()
    once: bool = False
    runs_only: bool = False


# how the world model samples, not how it was trained: a run variant may change them in Sword's pipeline
SAMPLING_FLAGS = ("--flow.guidance_scale", "--flow.sample_steps")


def parse_variant(text: str, flag: str = "--variant") -> tuple[str, tuple[str, ...]]:
    """``NAME=--section.key=value --section.key=value`` -> ``(NAME, overrides)``; for ``--run-variant`` every
    override must be GRPO's (``--rl.``) or the world model's sampling (:data:`SAMPLING_FLAGS`): the runs share
    Sword's pipeline."""
    name, sep, rest = text.partition("=")
    overrides = tuple(shlex.split(rest))
    if not sep or not name.isidentifier() or name in ("wovr", "once", "refreshed") or not overrides:
        raise SystemExit(f"bench_grpo_refresh: {flag} wants NAME=OVERRIDES (NAME a word other than wovr, once, "
                         f"refreshed; OVERRIDES dotted --section.key=value), got {text!r}")
    bad = not_dotted_overrides(list(overrides))
    if bad:
        raise SystemExit(f"bench_grpo_refresh: {flag} {name}: not a dotted config override: {' '.join(bad)}")
    if flag == "--run-variant" and not all(o.startswith("--rl.") or o.split("=", 1)[0] in SAMPLING_FLAGS
                                           for o in overrides):
        raise SystemExit(f"bench_grpo_refresh: --run-variant {name}: its runs share Sword's pipeline, so it takes "
                         f"GRPO's settings (--rl.*) and the world model's sampling ({', '.join(SAMPLING_FLAGS)}) only; "
                         f"use --variant for its own pipeline: {' '.join(overrides)}")
    return name, overrides


def pipes(args) -> list[Pipe]:
    """Sword's pipeline; with ``--wovr-config`` the WoVR-config world model's; one per ``--variant`` (Sword's
    config with the variant's overrides, e.g. a VAE trained with the perceptual loss); one per ``--run-variant``
    (more runs in Sword's pipeline with other GRPO settings, ``runs_only``)."""
    gpus = tuple(g for g in args.gpus.split(",") if g)
    out = [Pipe("pipeline", args.config, seeds=tuple(args.seeds), gpus=gpus, once="once" in args.arms)]
    if args.wovr_config:
        out.append(Pipe("pipeline_wovr", args.wovr_config, prefix="wovr_",
                        seeds=tuple(getattr(args, "wovr_seeds", None) or args.seeds),
                        gpus=tuple(g for g in (getattr(args, "wovr_gpus", "") or args.gpus).split(",") if g)))
    variant_gpus = tuple(g for g in (getattr(args, "variant_gpus", "") or args.gpus).split(",") if g)
    for i, text in enumerate(getattr(args, "variant", None) or []):
        name, overrides = parse_variant(text)
        out.append(Pipe(f"pipeline_{name}", args.config, overrides, prefix=f"{name}_",
                        seeds=tuple(getattr(args, "variant_seeds", None) or args.seeds[:1]),
                        gpus=variant_gpus[i % len(variant_gpus):] + variant_gpus[:i % len(variant_gpus)]))
    run_gpus = tuple(g for g in (getattr(args, "run_variant_gpus", "") or args.gpus).split(",") if g)
    seeds = tuple(getattr(args, "run_variant_seeds", None) or args.seeds)
    for i, text in enumerate(getattr(args, "run_variant", None) or []):
        name, overrides = parse_variant(text, "--run-variant")
        shift = i * len(seeds) % len(run_gpus) if run_gpus else 0  # each variant's runs on the next GPUs
        out.append(Pipe("pipeline", args.config, overrides, prefix=f"{name}_", runs_only=True, seeds=seeds,
                        gpus=run_gpus[shift:] + run_gpus[:shift]))
    return out


def pipelines(args) -> dict[str, str]:
    """``{pipeline folder: config}`` of the pipelines :func:`pipes` builds."""
    return {pipe.folder: pipe.config for pipe in pipes(args) if not pipe.runs_only}


LIGHT = "--rl.imagined.decoder=light"


def uses_light_decoder(overrides: Sequence[str], p: Pipe) -> bool:
    """Whether ``p``'s runs decode their imagined frames with the light decoder (the last setting wins)."""
    said = [o for o in [*overrides, *p.overrides] if o.startswith("--rl.imagined.decoder=")]
    return bool(said) and said[-1] == LIGHT


def pipeline_command(args, overrides: Sequence[str], *, config: str | None = None, name: str = "pipeline",
                     stop_after: str = "reward_model", own: Sequence[str] = (), light: bool = False) -> list[str]:
    """``train.pipeline`` up to ``stop_after`` for pipeline ``name``; with ``light`` it also distils the light
    rollout decoder (its ``light_decoder`` stage runs with ``rl.imagined.decoder=light``) for runs that use it."""
    flags = list(PIPELINE_FLAGS)
    flags[flags.index("--stop-after") + 1] = stop_after
    rollouts = getattr(args, "policy_rollouts", 0)
    if rollouts:  # the given policy's own episodes (its failures too) join the world model's and detector's data
        flags[flags.index("--skip") + 1] = "probe,evaluate"
        flags[flags.index("--data.policy_rollouts_per_task=0")] = f"--data.policy_rollouts_per_task={rollouts}"
        flags.append(f"--rl.sft.init={os.path.abspath(args.policy)}")
    backend = getattr(args, "data_backend", "")
    return [sys.executable, "-m", "train.pipeline", "--config", config or args.config, "--seed", str(args.pipeline_seed),
            "--workdir", os.path.join(args.workdir, name), *flags,
            f"--vae.train_steps={args.vae_steps}", f"--trainer.steps={args.world_model_steps}",
            *([f"--sim.backend={backend}"] if backend else []),
            *[o for o in [*overrides, *own] if not o.startswith("--rl.")], *([LIGHT] if light else [])]


def pipe_runs(args, overrides: Sequence[str], p: Pipe) -> dict[str, list[str]]:
    """``{run name: command}`` of the GRPO runs in pipeline ``p``'s world model: ``<prefix>refreshed_seed<k>``
    for each of its seeds, ``<prefix>once_seed<first>`` with ``p.once`` (same policy, recipe and budget
    everywhere)."""
    pipe = os.path.join(args.workdir, p.folder)
    base = [sys.executable, "-m", "train.grpo", "--config", p.config, "--simulator", "world_model",
            "--world-model", os.path.join(pipe, "world_model"), "--vae", os.path.join(pipe, "vae_run", "vae"),
            "--reward", os.path.join(pipe, "rl", "reward_model"),
            "--demos", os.path.join(pipe, "data", "demos.hdf5"), "--latents", os.path.join(pipe, "data", "latents.npz"),
            "--policy", args.policy, *GRPO_FLAGS, f"--rl.grpo.steps={args.steps}",
            f"--rl.grpo.eval_every={args.refresh_every}", f"--rl.refresh.every={args.refresh_every}"]
    runs = {f"{p.prefix}refreshed_seed{seed}": [*base, "--seed", str(seed), f"--rl.refresh.budget={args.budget}",
                                                *overrides, *p.overrides] for seed in p.seeds}
    if p.once:
        runs[f"{p.prefix}once_seed{p.seeds[0]}"] = [*base, "--seed", str(p.seeds[0]), "--rl.refresh.budget=64",
                                                    *overrides, *p.overrides]
    if uses_light_decoder(overrides, p):  # the decoder its pipeline distilled
        runs = {name: [*cmd, "--light-decoder", os.path.join(pipe, "light_decoder")] for name, cmd in runs.items()}
    return {name: [*cmd, "--workdir", os.path.join(args.workdir, name)] for name, cmd in runs.items()}


def grpo_commands(args, overrides: Sequence[str]) -> dict[str, list[str]]:
    """Every pipeline's runs (:func:`pipes`, :func:`pipe_runs`), ``{run name: command}``."""
    return {name: cmd for p in pipes(args) for name, cmd in pipe_runs(args, overrides, p).items()}


def share_data(args, overrides: Sequence[str], pipe: Pipe | None = None) -> None:
    """A second pipeline (default the WoVR-config one) reads the episodes Sword's pipeline generated instead of
    generating them again: its ``data`` stage is marked done with Sword's files (linked under its own ``data/``;
    its latents, VAE and detector stay its own). Refused unless both generate the same episodes (same ``data``,
    ``sim``, ``seed`` and demonstrations per task)."""
    import configs

    pipe = pipe or next(p for p in pipes(args) if p.folder == "pipeline_wovr")

    def data_facts(config, own=()):
        cfg, _ = configs.from_argv(["--config", config, "--seed", str(args.pipeline_seed),
                                    *[o for o in [*overrides, *own] if not o.startswith("--rl.")],
                                    "--rl.sft.episodes_per_task=20"])
        return repr((cfg.data, cfg.sim, cfg.seed, cfg.rl.sft.episodes_per_task))

    if data_facts(args.config) != data_facts(pipe.config, pipe.overrides):
        raise SystemExit(f"bench_grpo_refresh: {args.config} and {pipe.folder} ({pipe.config} "
                         f"{' '.join(pipe.overrides)}) generate different episodes; it cannot share Sword's data")
    src, dst = os.path.join(args.workdir, "pipeline"), os.path.join(args.workdir, pipe.folder)
    with open(os.path.join(src, "stages", "data.json")) as f:
        marker = json.load(f)
    os.makedirs(os.path.join(dst, "data"), exist_ok=True)
    os.makedirs(os.path.join(dst, "stages"), exist_ok=True)
    for entry in marker["results"].values():
        if isinstance(entry, dict) and "path" in entry:
            link = os.path.join(dst, "data", os.path.basename(entry["path"]))
            if not os.path.lexists(link):
                os.symlink(os.path.abspath(entry["path"]), link)
            entry["path"] = link
    with open(os.path.join(dst, "stages", "data.json"), "w") as f:
        json.dump(marker, f, indent=1)


def run(args, overrides: Sequence[str], *, poll_s: float = 5.0) -> dict:
    """The pipelines, then each pipeline's GRPO runs as soon as it is built; with ``--deadline-s`` the runs
    still going then are stopped and summarised at their last evaluation."""
    os.makedirs(args.workdir, exist_ok=True)
    env = common.launch_env(args.workdir, deterministic=args.deterministic)
    gpus = [g for g in args.gpus.split(",") if g]
    start = time.perf_counter()

    def launch(name: str, cmd: list[str], gpu: str) -> subprocess.Popen:
        print(f"[refresh] {name} on GPU {gpu} ({time.perf_counter() - start:.0f} s): {' '.join(cmd[2:])}", flush=True)
        with open(os.path.join(args.workdir, f"{name}.log"), "a") as log:
            return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                    env=dict(env, CUDA_VISIBLE_DEVICES=gpu) if gpu else env)

    every = [p for p in pipes(args) if not p.runs_only]
    runs_in = {p.folder: [q for q in pipes(args) if q.folder == p.folder] for p in every}
    if len(every) > 1:  # the episodes once, on Sword's pipeline; the others link them
        if launch("pipeline", pipeline_command(args, overrides, stop_after="data"), gpus[0] if gpus else "").wait():
            raise SystemExit(f"bench_grpo_refresh: the data stage failed (log: {args.workdir}/pipeline.log)")
        for p in every[1:]:
            share_data(args, overrides, p)
    building = {p.folder: launch(p.folder, pipeline_command(
        args, overrides, config=p.config, name=p.folder, own=p.overrides,
        light=any(uses_light_decoder(overrides, q) for q in runs_in[p.folder])), p.gpus[0] if p.gpus else "")
                for p in every}  # side by side
    commands = grpo_commands(args, overrides)
    procs: dict[str, subprocess.Popen] = {}
    stopped: list[str] = []
    while building or any(p.poll() is None for p in procs.values()):
        for folder, proc in list(building.items()):
            if proc.poll() is None:
                continue
            del building[folder]
            if proc.returncode:
                print(f"[refresh] pipeline {folder} failed (log: {args.workdir}/{folder}.log)", flush=True)
                continue
            for pipe in runs_in[folder]:
                for i, (name, cmd) in enumerate(pipe_runs(args, overrides, pipe).items()):
                    procs[name] = launch(name, cmd, pipe.gpus[i % len(pipe.gpus)] if pipe.gpus else "")
        if args.deadline_s and time.perf_counter() - start > args.deadline_s:
            stopped = stop_at_deadline({**building, **procs}, args.deadline_s, tag="refresh", grace_s=args.grace_s)
            break
        time.sleep(poll_s)
    codes = {name: p.returncode for name, p in procs.items()}
    summary = dict(summarize(args.workdir, args.ground_truth), exit_codes=codes, stopped_at_deadline=stopped,
                   seconds=round(time.perf_counter() - start, 1))
    with open(os.path.join(args.workdir, "refresh_summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    failed = sorted(n for n, c in codes.items() if c and n not in stopped)
    if failed or len(procs) < len(commands) and not stopped:
        raise SystemExit(f"bench_grpo_refresh: runs failed or never started: {failed or sorted(set(commands) - set(procs))}")
    return summary


def stop_all(procs: Sequence[subprocess.Popen], grace_s: float = 20.0) -> list[subprocess.Popen]:
    """SIGTERM to the processes still running, SIGKILL after ``grace_s``; returns the ones that were running.

    A process that leads its own process group (started with ``start_new_session``) is signalled with its whole
    group, and the group is killed once the leader has ended, so what it started goes too (``train.pipeline
    --parallel``'s stage processes)."""
    running = [p for p in procs if p.poll() is None]
    leaders = {p.pid for p in running if _leads_group(p)}

    def send(p: subprocess.Popen, sig: int) -> None:
        try:
            if p.pid in leaders:
                os.killpg(p.pid, sig)
            else:
                p.send_signal(sig)
        except ProcessLookupError:  # the group has ended
            pass

    for p in running:
        send(p, signal.SIGTERM)
    deadline = time.perf_counter() + grace_s
    for p in running:
        try:
            p.wait(timeout=max(deadline - time.perf_counter(), 0.1))
        except subprocess.TimeoutExpired:
            send(p, signal.SIGKILL)
            p.wait()
        else:
            if p.pid in leaders:  # what of its group outlived it
                send(p, signal.SIGKILL)
    return running


def _leads_group(p: subprocess.Popen) -> bool:
    try:
        return os.getpgid(p.pid) == p.pid
    except ProcessLookupError:
        return False


def seconds_at_least_zero(text: str) -> float:
    """An argparse type: a finite number of seconds >= 0."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds >= 0, got {text!r}")
    return value


def add_deadline_options(parser: Any, prefix: str = "") -> None:
    """``--deadline-s`` and ``--grace-s`` of a launcher that stops its runs at a deadline (:func:`stop_at_deadline`);
    ``prefix`` starts their help (e.g. ``"run: "``)."""
    parser.add_argument("--deadline-s", type=seconds_at_least_zero, default=0.0,
                        help=f"{prefix}stop the runs still going this many seconds after the start and summarise "
                             "them at their last evaluation (0: no deadline)")
    parser.add_argument("--grace-s", type=seconds_at_least_zero, default=0.0,
                        help=f"{prefix}ask the runs still going at --deadline-s to stop first (each checkpoints its "
                             "step in flight and GRPO evaluates it; the same command resumes them) and stop them "
                             "outright this many seconds later (0: at the deadline)")


def add_deterministic_option(parser: Any, prefix: str = "") -> None:
    """``--deterministic``: the runs get XLA's deterministic ops (:func:`benchmarks.common.launch_env`)."""
    parser.add_argument("--deterministic", action="store_true",
                        help=f"{prefix}start the runs with XLA's deterministic GPU ops, so that an evaluation of the "
                             "same policy gives the same outcomes every time (written to the work dir's "
                             "xla_flags.txt and the summary)")


def stop_at_deadline(procs: dict[str, subprocess.Popen], deadline_s: float, *, tag: str, grace_s: float = 0.0,
                     poll_s: float = 1.0) -> list[str]:
    """The named processes still running at a deadline of ``deadline_s`` s, stopped; their names, sorted. With
    ``grace_s`` they are first asked to stop (``sword_jax.cli.STOP_SIGNAL``: a command under ``cli.run``
    checkpoints its step in flight, GRPO evaluates it, and exits ``cli.STOPPED_EXIT``), and those still running
    ``grace_s`` later are stopped (:func:`stop_all`); without it they are stopped at once."""
    running = {n: p for n, p in procs.items() if p.poll() is None}
    if grace_s > 0 and running:
        cli.ask_to_stop(running.values())
        print(f"[{tag}] deadline of {deadline_s:.0f} s: asked {sorted(running)} to stop, {grace_s:.0f} s to do so",
              flush=True)
        end = time.perf_counter() + grace_s
        while time.perf_counter() < end and any(p.poll() is None for p in running.values()):
            time.sleep(poll_s)
    killed = stop_all(list(running.values()))
    if grace_s <= 0:
        print(f"[{tag}] deadline of {deadline_s:.0f} s: stopped {sorted(running)}", flush=True)
    elif killed:
        print(f"[{tag}] still running after {grace_s:.0f} s: stopped "
              f"{sorted(n for n, p in running.items() if any(p is k for k in killed))}", flush=True)
    return sorted(running)


def wait_until_deadline(procs: dict[str, subprocess.Popen], deadline_s: float, start: float, *, tag: str,
                        poll_s: float = 5.0, grace_s: float = 0.0) -> list[str]:
    """Waits for the named processes to end; past ``deadline_s`` seconds after ``start`` (``time.perf_counter``;
    0 = no deadline) stops the ones still running (:func:`stop_at_deadline`, asking first with ``grace_s``) and
    returns their names, sorted."""
    while any(p.poll() is None for p in procs.values()):
        if deadline_s and time.perf_counter() - start > deadline_s:
            return stop_at_deadline(procs, deadline_s, tag=tag, grace_s=grace_s, poll_s=min(poll_s, 1.0))
        time.sleep(poll_s)
    return []


def gain_between(points: list[dict], key: str | None) -> dict:
    """Gain of the greedy (``key`` None) or sampled success from the first evaluation to the last; where both kept
    their episodes' outcomes, ``paired`` says how many episodes gained and lost success between them (the
    interval is then paired, :func:`sword_jax.rl.env_rollout.gain_interval`)."""
    from sword_jax.rl.env_rollout import outcome_changes

    a, b = points[0], points[-1]
    if key is not None:
        a, b = a[key], b[key]
    out = {"start": a["mean"], "end": b["mean"], "gain": b["mean"] - a["mean"], "ci95": gain_interval(a, b)}
    changes = outcome_changes(a, b)
    if changes is not None:
        out["paired"] = changes
    return out


def pending_evaluation(grpo: str, last_step: int) -> dict | None:
    """The evaluation a run made after its curve's last point and before the refresh it was stopped inside
    (``<grpo>/evaluations/step_*.json``, written before each refresh), marked ``refresh_incomplete``; None
    when there is none."""
    folder = os.path.join(grpo, "evaluations")
    later = sorted(f for f in (os.listdir(folder) if os.path.isdir(folder) else [])
                   if f.startswith("step_") and f.endswith(".json") and int(f[5:-5]) > last_step)
    if not later:
        return None
    with open(os.path.join(folder, later[-1])) as f:
        return dict(json.load(f), refresh_incomplete=True)


def summarize_run(folder: str) -> dict:
    """One refreshed run's curves, gains, real episodes used and refreshes (``folder``: its work dir); with its
    ``step_times.jsonl``, the median GRPO step time and imagined frames per second inside its steps."""
    grpo = os.path.join(folder, "rl", "grpo")
    with open(os.path.join(grpo, "success_curve.json")) as f:
        points = json.load(f)["points"]
    pending = pending_evaluation(grpo, points[-1]["step"])
    if pending is not None:  # stopped inside the refresh after its last evaluation: that evaluation still counts
        points = [*points, pending]
    out = {"steps": points[-1]["step"], "episodes": points[-1]["episodes"],
           **({"last_refresh_incomplete": True} if pending is not None else {}),
           "greedy": gain_between(points, None), "sampled": gain_between(points, "sampled"),
           **({"sampled_proprio_masked": gain_between(points, "sampled_proprio_masked")}
              if all("sampled_proprio_masked" in p for p in points) else {}),
           "curve": [{"step": p["step"], "greedy": p["mean"], "sampled": p["sampled"]["mean"],
                      "sampled_ci95": p["sampled"]["ci95"], "real_episodes_used": p.get("real_episodes_used"),
                      "sampled_proprio_masked": (p.get("sampled_proprio_masked") or {}).get("mean")}
                     for p in points],
           "real_episodes_used": points[-1].get("real_episodes_used"),
           "guard": [dict(step=p["step"], **p["guard"]) for p in points if "guard" in p]}
    times = os.path.join(grpo, "step_times.jsonl")
    if os.path.exists(times):  # medians: robust to the compiling first step after a start or resume
        with open(times) as f:
            rows = [json.loads(line) for line in f if line.strip()]
        out["step_s"] = statistics.median(r["step_s"] for r in rows) if rows else None
        fps = [r["imagined_frames_per_s"] for r in rows if "imagined_frames_per_s" in r]
        out["imagined_frames_per_s"] = statistics.median(fps) if fps else None
    out["refreshes"] = refresh_records(grpo)
    return out


def refresh_records(grpo: str) -> list[dict]:
    """The refreshes of the GRPO run at ``grpo`` (``refreshes.json``, or for a run stopped early each
    ``refresh/*/record.json`` written so far), each as the summary reads it: its step, real episodes and their real
    success, what its replay said before the refresh (false and missed success, separation by horizon, within
    groups), the detector's threshold and calibration after it, its trust, its verification and its closed loop
    (``rl.refresh.closed_loop_starts``: the trajectories, their drift and the fine-tune's held-out fit)."""
    refreshes = os.path.join(grpo, "refreshes.json")
    records = []
    if os.path.exists(refreshes):
        with open(refreshes) as f:
            records = json.load(f)
    else:  # a run stopped early: the records written so far
        ref = os.path.join(grpo, "refresh")
        for name in sorted(os.listdir(ref)) if os.path.isdir(ref) else []:
            path = os.path.join(ref, name, "record.json")
            if os.path.exists(path):
                with open(path) as f:
                    records.append(json.load(f))
    return [{"step": r["step"], "real_episodes": r["real_episodes"], "real_success": r.get("real_success"),
            "false_success_before": (r.get("replay") or {}).get("false_success"),
            "missed_success_before": (r.get("replay") or {}).get("missed_success"),
            "threshold": (r.get("detector") or {}).get("threshold"),
            "calibration": (r.get("detector") or {}).get("calibration"),
            "separation_before": separations((r.get("replay") or {}).get("imagined_success_by_horizon")),
            "within_group_before": (r.get("replay") or {}).get("within_group"),
            "separation_after": separations((r.get("detector") or {}).get("imagined_success_by_horizon")),
            "detector_real_frames": (r.get("detector") or {}).get("real_frames"),
            "detector_real_frames_run_threshold": (r.get("detector") or {}).get("real_frames_run_threshold"),
            "trust": r.get("trust"), "skipped": r.get("skipped"), "verify": r.get("verify"),
             "closed_loop": r.get("closed_loop")}
            for r in records]


def separations(by_horizon: dict | None) -> dict[str, float | None]:
    """``{horizon: imagined success among real successes minus among real failures}`` of a replay's
    ``imagined_success_by_horizon`` (None where a group is empty)."""
    from sword_jax.rl.refresh import separation

    return {h: separation(entry) for h, entry in (by_horizon or {}).items()}


def ground_truth_curves(folder: str) -> dict:
    """Ground-truth GRPO's sampled success against real episodes consumed, from a ``bench_policy grpo-seeds``
    folder: exact from a run's ``train_history.jsonl`` (episodes sampled per step), else approximate from the
    summary's mean rollouts per step (``costs_from_logs``, runs that predate the history) times the step."""
    from benchmarks.bench_grpo_transfer import read_history

    with open(os.path.join(folder, "grpo_ground_truth_seeds.json")) as f:
        seeds = json.load(f)
    out = {}
    for run_dir in seeds["per_seed"]:
        name = os.path.relpath(run_dir, folder).split(os.sep)[0]
        history = read_history(os.path.join(folder, os.path.relpath(run_dir, folder)))
        if history:
            used, total = {0: 0}, 0
            for point in history:
                total += int(point["trajectories_sampled"])
                used[int(point["step"])] = total
            exact = True
        else:
            per_step = (seeds.get("costs_from_logs") or {}).get(name, {}).get("rollouts_per_step")
            used, exact = ({} if per_step is None else None), False
        curve = seeds["curves"][run_dir]["sampled"]
        out[name] = [{"step": s, "sampled": m, "sampled_ci95": ci,
                      "real_episodes_used": (used.get(s) if used is not None else round(s * per_step)),
                      "episodes_exact": exact} for s, m, ci in curve]
    return out


def paired_gain(sword: dict, wovr: dict) -> dict:
    """Sword's sampled gain minus WoVR's from step 0 to the last evaluated step both runs reached (runs stopped
    by a deadline may have reached different steps)."""
    common = sorted({p["step"] for p in sword["curve"]} & {p["step"] for p in wovr["curve"]})
    at = common[-1]

    def gain(run):
        by_step = {p["step"]: p["sampled"] for p in run["curve"]}
        return by_step[at] - by_step[common[0]]

    return {"step": at, "sword": gain(sword), "wovr": gain(wovr), "difference": gain(sword) - gain(wovr)}


def summarize(workdir: str, ground_truth: str = "") -> dict:
    runs = {}
    for name in sorted(os.listdir(workdir)):
        if os.path.exists(os.path.join(workdir, name, "rl", "grpo", "success_curve.json")):
            runs[name] = summarize_run(os.path.join(workdir, name))
    refreshed = {n: r for n, r in runs.items() if n.startswith("refreshed")}
    out = {"runs": runs}
    wovr = {n[len("wovr_"):]: r for n, r in runs.items() if n.startswith("wovr_refreshed")}
    paired = {n: paired_gain(refreshed[n], wovr[n]) for n in sorted(refreshed) if n in wovr}
    if paired:  # Sword's gain minus WoVR's, seed by seed (same policy, recipe and budget), at the last step both reached
        out["sword_minus_wovr_sampled_gain"] = {n: p["difference"] for n, p in paired.items()}
        out["sword_vs_wovr"] = paired
    if refreshed:
        gains = [r["sampled"]["gain"] for r in refreshed.values()]
        out.update(sampled_min_gain=min(gains), sampled_mean_gain=sum(gains) / len(gains),
                   greedy_min_gain=min(r["greedy"]["gain"] for r in refreshed.values()),
                   real_episodes_used=max(r["real_episodes_used"] or 0 for r in refreshed.values()))
    if ground_truth:
        out["ground_truth"] = ground_truth_curves(ground_truth)
    out.update(common.workdir_xla_flags(workdir))
    return out


def results_entries(summary: dict, workdir: str, *, data: str, note: str = "", command: str = "") -> dict[str, dict]:
    """``latest.json`` entries of a summary: ``policy_grpo_world_model_gain_small`` (Sword's refreshed runs),
    ``policy_grpo_wovr_world_model_refreshed_gain_small`` (the WoVR-config world model's) and, with both,
    ``policy_grpo_sword_vs_wovr_small``; each gain the sampled policy's (T 0.5), value the smallest over seeds,
    with every run's curve, real episodes used and every refresh's replay and trust."""
    device = common.workdir_device(workdir)
    launched = {k: summary[k] for k in ("xla_flags", "deterministic") if k in summary}  # older work dirs lack them
    target = ">= +0.10 at 3 of 3 seeds within 100 steps, <= 10% of ground-truth GRPO's real episodes"

    def entry(prefix: str) -> dict | None:
        runs = {n: r for n, r in summary["runs"].items() if n.startswith(prefix)}
        if not runs:
            return None
        per_seed = {n: {"steps": r["steps"], "sampled": r["sampled"], "greedy": r["greedy"],
                        "sampled_proprio_masked": r.get("sampled_proprio_masked"),
                        "real_episodes_used": r["real_episodes_used"],
                        "refreshes": [compact_refresh(x) for x in r["refreshes"]]} for n, r in runs.items()}
        return common.record("", min(r["sampled"]["gain"] for r in runs.values()), target, per_seed=per_seed,
                             real_episodes_used=max(r["real_episodes_used"] or 0 for r in runs.values()),
                             steps=min(r["steps"] for r in runs.values()), device=device, data=data, **launched,
                             unit="real success gain of the sampled policy (T 0.5), 500 MJX episodes per point",
                             **({"note": note} if note else {}), **({"command": command} if command else {}))

    out = {}
    for key, prefix in (("policy_grpo_world_model_gain_small", "refreshed"),
                        ("policy_grpo_wovr_world_model_refreshed_gain_small", "wovr_refreshed")):
        made = entry(prefix)
        if made is not None:
            out[key] = made
    if summary.get("sword_vs_wovr"):
        pairs = summary["sword_vs_wovr"]
        out["policy_grpo_sword_vs_wovr_small"] = common.record(
            "", sum(p["difference"] > 0 for p in pairs.values()), ">= 2 of 3 seeds with Sword's gain >= WoVR's",
            per_seed=pairs, device=device, data=data, unit="seeds where Sword's sampled gain beats WoVR's",
            **({"command": command} if command else {}))
    return out


def compact_refresh(entry: dict) -> dict:
    """A summary's refresh entry as ``latest.json`` keeps it: the real success, the replay's false successes and
    separation by 48 actions before the refresh (inside the groups too, with grouped episodes), the threshold and
    the separation after (the full entry, with the calibration's trade-off, stays in the summary JSON)."""
    if entry.get("skipped"):
        return {"step": entry["step"], "skipped": entry["skipped"]}
    fs = entry.get("false_success_before") or {}
    return {"step": entry["step"], "real_success": entry.get("real_success"), "false_success_before": fs.get("rate"),
            "separation_before_48": (entry.get("separation_before") or {}).get("48"),
            "threshold": entry.get("threshold"), "separation_after_48": (entry.get("separation_after") or {}).get("48"),
            "trusted": (entry.get("trust") or {}).get("trusted"),
            **within_group_48(entry.get("within_group_before")), **verified(entry.get("verify"))}


def verified(check: dict | None) -> dict:
    """With ``rl.refresh.verify_starts``: the policy's imagined groups before the refresh, their actions executed
    for real: the share of imagined successes that were real, of real failures imagined as successes, and the
    separation inside the groups over the whole imagined rollout."""
    if not check or check.get("skipped"):
        return {"verify_skipped": check["skipped"]} if check else {}
    return {"verify_imagined_success": check["imagined_success"], "verify_real_success": check["real_success"],
            "verify_precision": check["precision"]["rate"], "verify_false_success": check["false_success"]["rate"],
            "verify_within_group_separation": ((check.get("within_group") or {}).get("all") or {}).get("separation")}


def within_group_48(within: dict | None) -> dict:
    """With grouped refresh episodes (``rl.refresh.group_size``): the separation of real outcomes inside the
    groups by 48 actions, the detector scores' ranking of them (AUC, threshold-free) and the share of groups the
    simulator's verdicts leave mixed, before the refresh."""
    if not within or "48" not in within:
        return {}
    return {"within_group_separation_before_48": within["48"]["separation"],
            "within_group_auc_before_48": within["48"].get("auc"),
            "imagined_mixed_groups_before_48": within["48"]["imagined_mixed"],
            "real_mixed_groups": f"{within['mixed_real_groups']} of {within['groups']}"}


def run_label(name: str) -> str:
    """``wovr_refreshed_seed1`` -> "GRPO in the refreshed WoVR-config world model, seed 1"."""
    head, _, seed = name.rpartition("_seed")
    variant, _, arm = head.rpartition("_")
    model = {"": "Sword", "wovr": "WoVR-config"}.get(variant, f"Sword ({variant})")
    if arm == "refreshed":
        return f"GRPO in the refreshed {model} world model, seed {seed}"
    return f"GRPO in the {model} world model adapted once, seed {seed}"


def plot(summary: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.4))
    for name, curve in summary.get("ground_truth", {}).items():
        pts = [{"step": p["real_episodes_used"], "success": p["sampled"], "ci95": p["sampled_ci95"]} for p in curve]
        errorbar_curve(ax, pts, label=f"ground-truth GRPO {name}", color="0.6", alpha=0.7)
    for name, entry in summary["runs"].items():
        pts = [{"step": p["real_episodes_used"] or 0, "success": p["sampled"], "ci95": p["sampled_ci95"]}
               for p in entry["curve"]]
        errorbar_curve(ax, pts, label=run_label(name))
    ax.set_xscale("symlog", linthresh=100)
    common.finish_figure(fig, ax, path, xlabel="real episodes consumed (evaluation episodes not counted)",
                         ylabel="real success, sampled T 0.5 (95% interval)")


def main(argv: Sequence[str] | None = None) -> dict:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0],
                                epilog="Any --section.key=value is passed to every run (rl.* to the GRPO runs only).")
    parser.add_argument("mode", choices=("run", "summary"))
    parser.add_argument("--workdir", default="runs/grpo_refresh")
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--policy", default="", help="the supervised policy (train_policy checkpoint or .npz)")
    parser.add_argument("--gpus", default="0", help="GPUs the runs take in turn (CUDA_VISIBLE_DEVICES values)")
    parser.add_argument("--wovr-gpus", default="", help="GPUs the WoVR pipeline and its runs take in turn "
                                                        "(default: --gpus)")
    parser.add_argument("--wovr-seeds", default="", help="seeds of the WoVR runs (default: --seeds)")
    parser.add_argument("--variant", action="append", default=[],
                        help="NAME=OVERRIDES: also a pipeline of --config with these dotted overrides (quoted, space "
                             "separated; e.g. lpips='--vae.perceptual_weight=1.0'), its runs named NAME_refreshed_seed<k>; "
                             "repeatable")
    parser.add_argument("--run-variant", action="append", default=[],
                        help="NAME=OVERRIDES: more GRPO runs in Sword's world model with other GRPO settings "
                             "(--rl.*) or sampling (--flow.guidance_scale, --flow.sample_steps), named "
                             "NAME_refreshed_seed<k>; repeatable")
    parser.add_argument("--run-variant-seeds", default="", help="seeds of each run variant (default: --seeds)")
    parser.add_argument("--run-variant-gpus", default="", help="GPUs the run variants' runs take in turn "
                                                               "(default: --gpus)")
    parser.add_argument("--variant-seeds", default="", help="seeds of each variant's runs (default: the first seed)")
    parser.add_argument("--variant-gpus", default="", help="GPUs the variants take in turn (default: --gpus)")
    parser.add_argument("--data-backend", default="", help="the data stage's simulator backend (--sim.backend of "
                                                           "the pipelines only; e.g. cpu: the C engine's workers)")
    parser.add_argument("--policy-rollouts", type=int, default=0,
                        help="episodes per task of --policy itself, successes and failures, added to each world "
                             "model's and detector's training data (data.policy_rollouts_per_task; 0: expert "
                             "demonstrations only, the policy's episodes arrive with the first refresh)")
    add_deadline_options(parser)
    add_deterministic_option(parser)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--arms", default="refreshed,once", help="refreshed (every seed) and once (the first seed)")
    parser.add_argument("--pipeline-seed", type=int, default=0)
    parser.add_argument("--wovr-config", default="", help="also refresh GRPO in this WoVR-config world model, e.g. "
                                                          "cache_ablation:small-wovr (its own pipeline, side by side)")
    parser.add_argument("--steps", type=int, default=100,
                        help="GRPO steps of each run; 0: step 0's evaluation and refresh only, a probe of each "
                             "simulator's signal (with --rl.refresh.group_size: its within-group separation)")
    parser.add_argument("--refresh-every", type=int, default=5)
    parser.add_argument("--budget", type=int, default=3000, help="real episodes each refreshed run may use")
    parser.add_argument("--vae-steps", type=int, default=1000)
    parser.add_argument("--world-model-steps", type=int, default=3000)
    parser.add_argument("--ground-truth", default="", help="a bench_policy grpo-seeds folder to plot against")
    parser.add_argument("--out", default="", help="summary: output path without extension (.json, .png)")
    parser.add_argument("--record", action="store_true",
                        help="summary: write the gains to benchmarks/results/latest.json (the runs' device from the "
                             "work dir's gpu.txt)")
    parser.add_argument("--note", default="", help="summary --record: a note stored with the entries")
    parser.add_argument("--command", default="", help="summary --record: the run's command, stored with the entries")
    args, overrides = parser.parse_known_args(argv)
    bad = not_dotted_overrides(overrides)
    if bad:
        raise SystemExit(f"bench_grpo_refresh: not a dotted config override (--section.key=value): {' '.join(bad)}")
    args.seeds = [int(s) for s in args.seeds.split(",") if s]
    args.wovr_seeds = [int(s) for s in args.wovr_seeds.split(",") if s]
    args.variant_seeds = [int(s) for s in args.variant_seeds.split(",") if s]
    args.run_variant_seeds = [int(s) for s in args.run_variant_seeds.split(",") if s]
    for text in args.variant:
        parse_variant(text)  # refuses a malformed one before anything runs
    for text in args.run_variant:
        parse_variant(text, "--run-variant")
    args.arms = {a for a in args.arms.split(",") if a}
    if not args.seeds or args.arms - {"refreshed", "once"} or args.steps < 0 or args.refresh_every < 1 or args.budget < 64:
        raise SystemExit("bench_grpo_refresh: --seeds needs one seed or more, --arms refreshed and/or once, --steps "
                         ">= 0, --refresh-every >= 1, --budget >= 64 (one refresh)")
    if args.mode == "summary":
        summary = summarize(args.workdir, args.ground_truth)
        common.save_summary(summary, args.out, (lambda: results_entries(
            summary, args.workdir, data=common.summary_data(args.out, args.workdir), note=args.note, command=args.command))
            if args.record else None)
        if args.out:
            plot(summary, args.out + ".png")
        print_runs(summary)
        return summary
    if not args.policy:
        raise SystemExit("bench_grpo_refresh run needs --policy (the supervised policy every run starts from)")
    summary = run(args, overrides)
    print_runs(summary)
    print(f"[refresh] summary: {os.path.join(args.workdir, 'refresh_summary.json')}", flush=True)
    return summary


def print_runs(summary: dict) -> None:
    """One line per run: its steps, real episodes, and greedy and sampled success from start to end."""
    for name, entry in summary["runs"].items():
        g, s = entry["greedy"], entry["sampled"]
        print(f"[refresh] {name}: steps {entry['steps']}, real episodes {entry['real_episodes_used']}; greedy "
              f"{g['start']:.3f} -> {g['end']:.3f}; sampled {s['start']:.3f} -> {s['end']:.3f} ({s['gain']:+.3f} "
              f"[{s['ci95'][0]:+.3f}, {s['ci95'][1]:+.3f}])"
              + (f"; {entry['imagined_frames_per_s']:.0f} imagined frames/s in its steps"
                 if entry.get("imagined_frames_per_s") else ""), flush=True)


if __name__ == "__main__":
    cli.run(main)
