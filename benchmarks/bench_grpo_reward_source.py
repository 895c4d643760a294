"""Which half of the learned simulator GRPO cannot use: its frames or its reward.

GRPO in the learned simulator's setting (keyframe starts, 48 actions executed 4 per decision, proprio missing,
``--rollout-batch`` start states x 8, T 0.5, lr 1e-4) in arms that differ in one part each, every arm at each seed:

* ``gt``: ground-truth GRPO on MJX in that setting, the real frames and the real reward;
* ``exec``: GRPO in Sword's world model, the policy acting on its frames, each imagined trajectory paid by the
  real outcome of its actions executed on MJX from the keyframe's recorded state (``rl.imagined.reward=executed``,
  :mod:`sword_jax.rl.imagined_check`); every step also logs what the detector would have paid;
* ``det``: GRPO in Sword's world model paid by its success detector (``rl.imagined.reward=detector``);
* ``cal`` (not run by default): the first ``--calibrate-steps`` steps as ``exec``, then the detector's reward at the
  threshold those steps set on the policy's own closed loop (``rl.imagined.reward=calibrated``: just above the
  median real failure's score that leaves at most ``rl.refresh.max_false_success`` of the real failures paid).
* ``ref`` and ``rexec`` (not run by default): GRPO in Sword's world model paid by its detector (``ref``) or, as
  ``exec``, by its actions executed on MJX (``rexec``: whether a refresh makes the world model keep more of what
  reality pays, per start bin), the world model and detector refreshed on the current policy's real MJX episodes
  (``rl.refresh``: every ``--refresh-every`` steps and at step 0, ``--refresh-episodes`` each within
  ``--refresh-budget``; the world model fine-tuned on them, the detector on their replays labelled with their real
  outcome and its threshold set on held-out replays). Its refreshes mix the world model's training
  latents into each fine-tune: with ``--bundle``, which carries none, ``run`` encodes the pipeline's training
  episodes with the bundle's VAE first (``python -m train.encode_latents``).

If ``exec`` lifts real success as ``gt`` does and ``det`` does not, the reward is what fails GRPO in the learned
simulator; if ``exec`` falls with ``det``, the frames do. No refresh runs: the world model and the detector stay
as the pipeline trained them (from ``--policy``'s own episodes beside the demonstrations). Every run is
evaluated on MJX (500 episodes per point: greedy, sampled at T 0.5, sampled with proprio masked)::

    python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs --policy runs/p/policy_d50.npz \\
        --gpus 0,1,2,3 --seeds 0,1,2 --steps 40 [--deadline-s 1500]
    python -m benchmarks.bench_grpo_reward_source summary --workdir runs/rs \\
        --out benchmarks/results/policy/grpo_reward_source_small [--record]
    python -m benchmarks.bench_grpo_reward_source horizons --workdirs runs/hz/h1,runs/hz/h2,runs/hz/h4 \\
        --out benchmarks/results/policy/grpo_horizon_honesty_small_2xh200 [--title T]

``--horizon N`` rolls every arm out N decisions instead of 12, ``--keyframe-fraction F`` draws its keyframes from the
first F of each demonstration (1.0: every phase, which a horizon of a decision or two needs to reach success at all;
0: the first keyframe alone, frame 4, the world model's counterpart of starting at rest), ``--keyframe-from F``
draws them from fraction F of each demonstration on (up to the keyframe fraction: the later phases, where the world
model's closed loop keeps reality's payment), ``--scale-by-std false`` leaves every arm's advantages centred (the
recipe that lifts on MJX from rest)
and ``--vae-variant vae8x`` builds the pipeline with the 8x VAE, which the world-model arms then load. The arms draw
their keyframes alike (the same demonstrations and rule, their own draws), so their first steps, before any update,
compare what the real closed loop and the imagined one are paid from like starts.

``run`` builds Sword's ``small`` pipeline on the first GPU (on several with ``--pipeline-gpus``, its trainers
data-parallel over them); once its data stage is done the ground-truth runs start on the other GPUs, and once the
pipeline is built the world-model runs take every GPU, the two arms of a seed side by side (``--arms gt`` alone
builds the data stage only). With ``--pipeline DIR``
it builds none and starts each run once the stages it reads have finished in ``DIR`` (:data:`NEEDS`), so a second
command, e.g. at another ``--actions-per-decision``, shares the first's world model (``--gpu-share`` splits a GPU's
memory between the two commands' world-model runs; each command splits its own share). Each process runs in its own
session (a deadline stops the runs still going; each keeps its last evaluation; with ``--grace-s`` they are asked
first and evaluate their step in flight). ``summary`` gives each run's gains with 95% intervals, what its training
rollouts were paid, and for ``exec`` the detector's success, agreement, false success and precision (the share of
its verdicts of success that reality paid too) on the same rollouts, and per decision where their closed loop left
the real one (``closed_loop``: :func:`sword_jax.rl.imagined_check.closed_loop_fidelity`, means over the steps)
and, where the steps counted them, the same rollouts pooled by their start's step in its episode (``by_start``:
the real success, the detector's success and precision per bin, :func:`by_start`); ``--record`` writes
``policy_grpo_reward_source_small`` to ``benchmarks/results/latest.json``. Each run's
``real_episodes`` counts the real episodes its GRPO steps consumed (the ground-truth steps' sampled trajectories, the
world model's executed ones, 0 for ``det``; evaluations not counted), each arm gives them per seed and each
world-model arm the ratio of its mean to the ``gt`` arm's (``real_episodes_vs_gt``).

``horizons`` reads ``run``'s work dirs of one experiment at several horizons: each one's decisions and actions per
decision from its runs' own commands (``commands.json`` in the work dir, which ``run`` writes, or for a work dir made
before it, the launcher's lines in ``<workdir>.out``), and per horizon what reality paid the ``gt`` and ``exec``
arms' training rollouts over every recorded step (pooled, 95% Wilson intervals), the share of it the world model's
frames kept (exec over gt), the groups with mixed outcomes per step, and the detector on exec's rollouts; it writes
``horizons.json`` (rows by actions, which the report's ``grpo-horizon-honesty`` table reads) and ``horizons.png``
to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence

from benchmarks import common
from benchmarks.bench_grpo_refresh import (add_deadline_options, add_deterministic_option, gain_between, pipeline_command,
                                          refresh_records, stop_at_deadline)
from benchmarks.bench_grpo_transfer import errorbar_curve, read_history
from sword_jax import cli

ARMS = ("gt", "exec", "det", "cal", "ref", "rexec")
ARM_LABELS = {"gt": "real frames, real reward (ground-truth GRPO on MJX)",
              "exec": "the world model's frames, the real outcome of their actions",
              "det": "the world model's frames, the detector's reward",
              "cal": "the world model's frames, the real outcome, then the detector's reward at the threshold it set",
              "ref": "the world model's frames, the detector's reward, both refreshed on the policy's real episodes",
              "rexec": "the refreshed world model's frames, the real outcome of their actions"}
# the learned simulator's setting and the GRPO recipe every arm shares
RECIPE = ("--rl.env.backend=mjx", "--rl.grpo.group_size=8", "--rl.grpo.minibatches=4",
          "--rl.grpo.update_microbatch=8", "--rl.grpo.temperature=0.5", "--rl.grpo.learning_rate=1e-4",
          "--rl.imagined.execute_steps=4", "--rl.imagined.max_chunks=12")
GROUND_TRUTH = ("--rl.grpo.max_sample_rounds=1", "--rl.grpo.eval_sampled=true", "--rl.env.starts=keyframes",
                "--rl.env.proprio=missing")
WORLD_MODEL = ("--rl.imagined.shared_group_noise=true",
               "--rl.imagined.eval_replay_episodes=0")
REWARD = {"exec": ("--rl.imagined.reward=executed",), "det": (), "cal": ("--rl.imagined.reward=calibrated",),
          "ref": (), "rexec": ("--rl.imagined.reward=executed", "--rl.refresh.branch=false")}  # keyframe starts
WORLD_MODEL_ARMS = ("exec", "det", "cal", "ref", "rexec")  # the arms that run GRPO in the world model (train.grpo)
REFRESHED_ARMS = ("ref", "rexec")  # the arms whose world model (and detector) are refreshed while they run
# VAE variant -> the config overrides of its VAE, given to every command that trains or loads that VAE
VAE_VARIANTS: dict[str, tuple[str, ...]] = {
    "base": (),
    "vae8x": ("--vae.dim_mult=1,4,4", "--vae.temporal_downsample=true,true"),  # 8x spatial: 16x16 latents at 128 px
    "lpips": ("--vae.perceptual_weight=1.0",),
}
GT_DIR = "grpo_env_proprio_missing_starts_keyframes_mjx"  # bench_policy.grpo_dir of the ground-truth setting


def pipeline(args) -> argparse.Namespace:
    """What :func:`benchmarks.bench_grpo_refresh.pipeline_command` reads: Sword's pipeline with the policy's own
    episodes (``--policy-rollouts`` per task) in the world model's and detector's data."""
    return argparse.Namespace(config=args.config, pipeline_seed=0, workdir=args.workdir, policy=args.policy,
                              policy_rollouts=args.policy_rollouts, data_backend="cpu", vae_steps=args.vae_steps,
                              world_model_steps=args.world_model_steps)


def recipe(args) -> tuple[str, ...]:
    """:data:`RECIPE` at ``--horizon`` decisions (``rl.imagined.max_chunks``) of ``--actions-per-decision`` actions
    (``rl.imagined.execute_steps``), with keyframes from the first ``--keyframe-fraction`` of each demonstration
    where given (``rl.imagined.keyframe_fraction``), from its fraction ``--keyframe-from`` on where given
    (``rl.imagined.keyframe_from``) and advantages only centred with ``--scale-by-std false``
    (``rl.grpo.scale_by_std``): every arm's."""
    set_to = {"--rl.imagined.max_chunks": args.horizon,
              "--rl.imagined.execute_steps": getattr(args, "actions_per_decision", 4)}
    keys = [f.partition("=")[0] for f in RECIPE]
    flags = tuple(f"{key}={set_to[key]}" if key in set_to else f for key, f in zip(keys, RECIPE))
    window = {"keyframe_fraction": args.keyframe_fraction, "keyframe_from": args.keyframe_from}
    return (flags + tuple(f"--rl.imagined.{key}={value}" for key, value in window.items() if value is not None)
            + (() if args.scale_by_std else ("--rl.grpo.scale_by_std=false",)))


def world_model_overrides(args) -> tuple[str, ...]:
    """The config overrides of the world model every stage that trains or loads it gets: the VAE variant's
    (:data:`VAE_VARIANTS`) and ``--world-model-set``'s (e.g. ``trainer.ema_decay=0.999``: the simulator then
    samples from the EMA weights; ``model.scan_layers=false``: unrolled layers, the same weights)."""
    return (*VAE_VARIANTS[args.vae_variant], *(f"--{kv}" for kv in getattr(args, "world_model_set", ())))


# the pipeline's stages each kind of run reads: the ground-truth runs the demonstrations, the world-model runs the
# VAE, the world model and the detector (train.pipeline writes stages/<name>.json once a stage has finished)
NEEDS = {"gt": ("data",), "world_model": ("vae", "world_model", "reward_model")}


def pipeline_dir(args) -> str:
    """The pipeline every run reads: ``--pipeline`` (built elsewhere) or ``<workdir>/pipeline`` (built by ``run``)."""
    return getattr(args, "pipeline", "") or os.path.join(args.workdir, "pipeline")


def pipeline_gpus(args) -> list[str]:
    """The GPUs the pipeline is built on: ``--pipeline-gpus``, or the first of ``--gpus``."""
    return getattr(args, "pipeline_gpus", None) or args.gpus[:1]


def needs(args, name: str) -> tuple[str, ...]:
    """The pipeline's stages run ``name`` waits for (:data:`NEEDS`): with ``--bundle`` the world-model runs read
    the world model, VAE and detector from it, and need only the demonstrations."""
    if name.startswith("gt") or getattr(args, "bundle", ""):
        return NEEDS["gt"]
    return NEEDS["world_model"]


def closed_loop_note(loop: dict | None) -> str:
    """A refresh's closed loop (``rl.refresh.closed_loop_starts``) as the summary line says it: its trajectories and,
    where measured, the held-out sample error from the world model's own context before and after the fine-tune."""
    if not loop or "episodes" not in loop:
        return ""
    fit = (loop.get("fit") or {})
    before, after = ((fit.get(when) or {}).get("closed_loop") for when in ("before", "after"))
    return (f", its closed loop {loop['episodes']} trajectories"
            + (f" (held-out sample error from its own context {before['sample_error']:.4f} -> "
               f"{after['sample_error']:.4f})" if before and after else ""))


def check_bundle(args) -> None:
    """``--bundle`` holds what the world-model arms read (``train.bundle unpack``'s layout), or the run is refused
    by name before anything starts."""
    wanted = ["world_model/checkpoints", "vae_run/vae"] + (["rl/reward_model"] if {"det", "cal", "ref"} & set(args.arms)
                                                           else [])
    missing = [w for w in wanted if not os.path.isdir(os.path.join(args.bundle, w))]
    if missing:
        raise SystemExit(f"bench_grpo_reward_source: --bundle {args.bundle} lacks {', '.join(missing)} "
                         "(a folder made by python -m train.bundle unpack)")


def latents_path(args) -> str:
    """The world model's training latents a refreshed run (:data:`REFRESHED_ARMS`) mixes into each fine-tune:
    ``--latents``; else with ``--bundle`` those ``run`` encodes from the demonstrations with the bundle's VAE
    (``<workdir>/latents.npz``, :func:`latents_command`); else the pipeline's own (``<pipeline>/data/latents.npz``)."""
    if getattr(args, "latents", ""):
        return args.latents
    if getattr(args, "bundle", ""):
        return os.path.join(args.workdir, "latents.npz")
    return os.path.join(pipeline_dir(args), "data", "latents.npz")


def latents_command(args) -> list[str]:
    """``train.encode_latents`` of the pipeline's training episodes with the bundle's VAE into
    :func:`latents_path` (a bundle carries no latents): the expert episodes the world model was trained on, with the
    config's styled copies."""
    return [sys.executable, "-m", "train.encode_latents", "--config", args.config, *world_model_overrides(args),
            "--vae", os.path.join(args.bundle, "vae_run", "vae"), "--out", latents_path(args),
            os.path.join(pipeline_dir(args), "data", "train.hdf5")]


def refresh_settings(args) -> tuple[str, ...]:
    """A refreshed arm's refresh (``rl.refresh``): every ``--refresh-every`` steps (and at step 0)
    ``--refresh-episodes`` real episodes of the current policy on MJX, within ``--refresh-budget`` for the run, and
    ``--refresh-set``'s other settings."""
    return (f"--rl.refresh.every={args.refresh_every}", f"--rl.refresh.episodes={args.refresh_episodes}",
            f"--rl.refresh.budget={args.refresh_budget}", *(f"--{kv}" for kv in args.refresh_set))


def step_flags(args) -> tuple[str, ...]:
    """Every arm's steps: ``--rollout-batch`` starts a step, ``--steps`` of them, an evaluation every
    ``--eval-every``."""
    return (f"--rl.grpo.rollout_batch={args.rollout_batch}", f"--rl.grpo.steps={args.steps}",
            f"--rl.grpo.eval_every={args.eval_every}")


def run_commands(args) -> dict[str, list[str]]:
    """``{run name: command}``: ``gt_s<k>`` (``bench_policy grpo``) and ``exec_s<k>`` / ``det_s<k>``
    (``train.grpo`` in the pipeline's world model, or ``--bundle``'s), each with ``--rl.grpo.steps`` and
    evaluations every ``--eval-every`` steps."""
    pipe = pipeline_dir(args)
    weights = getattr(args, "bundle", "") or pipe
    demos = os.path.join(pipe, "data", "demos.hdf5")
    steps = step_flags(args)
    episodes, shared, vae = args.eval_episodes_per_task, recipe(args), world_model_overrides(args)
    out = {}
    for seed in args.seeds if "gt" in args.arms else ():
        out[f"gt_s{seed}"] = [sys.executable, "-m", "benchmarks.bench_policy", "grpo", "--config", args.config,
                              "--seed", str(seed), "--out", os.path.join(args.workdir, "gt", f"s{seed}"), "--policy",
                              args.policy, "--eval-episodes", str(episodes), f"--demos={demos}", *shared, *GROUND_TRUTH,
                              *steps]
    for seed in args.seeds:
        for arm in (a for a in WORLD_MODEL_ARMS if a in args.arms):
            name = f"{arm}_s{seed}"
            out[name] = [sys.executable, "-m", "train.grpo", "--config", args.config, *vae, "--simulator", "world_model",
                         "--world-model", os.path.join(weights, "world_model"),
                         "--vae", os.path.join(weights, "vae_run", "vae"),
                         "--reward", os.path.join(weights, "rl", "reward_model"), "--demos", demos,
                         "--policy", args.policy,
                         "--seed", str(seed), "--workdir", os.path.join(args.workdir, name), *shared, *WORLD_MODEL,
                         f"--rl.grpo.eval_episodes_per_task={episodes}", *REWARD[arm], *steps,
                         *((f"--rl.imagined.calibrate_steps={args.calibrate_steps}",) if arm == "cal" else ()),
                         *((*refresh_settings(args), "--latents", latents_path(args)) if arm in REFRESHED_ARMS
                           else ())]
    return out


def placement(args) -> dict[str, str]:
    """The GPU of each run: the ground-truth runs on the GPUs the pipeline leaves free (all of them with one),
    the world-model runs round-robin over every GPU, a seed's two arms next to each other."""
    gpus = args.gpus
    building = pipeline_gpus(args)
    free = [g for g in gpus if g not in building] or gpus
    out = {f"gt_s{seed}": free[i % len(free)] for i, seed in enumerate(args.seeds) if "gt" in args.arms}
    names = [f"{arm}_s{seed}" for seed in args.seeds for arm in WORLD_MODEL_ARMS if arm in args.arms]
    out.update({name: gpus[i % len(gpus)] for i, name in enumerate(names)})
    return out


def run(args, *, poll_s: float = 5.0) -> dict:
    """The pipeline, then the runs as their inputs are ready (module docstring); the summary at the end."""
    if getattr(args, "bundle", ""):
        check_bundle(args)
    os.makedirs(args.workdir, exist_ok=True)
    common.record_gpus(os.path.join(args.workdir, "gpu.txt"))
    env = common.launch_env(args.workdir, deterministic=args.deterministic)
    commands, gpu_of = run_commands(args), placement(args)
    record_commands(args.workdir, commands)
    sharing = {g: sum(1 for n in commands if gpu_of[n] == g and not n.startswith("gt")) for g in args.gpus}
    start = time.perf_counter()

    def launch(name: str, cmd: list[str], gpu: str) -> subprocess.Popen:
        print(f"[reward-source] {name} on GPU {gpu} ({time.perf_counter() - start:.0f} s): {' '.join(cmd[2:])}",
              flush=True)
        own = dict(env, CUDA_VISIBLE_DEVICES=gpu)
        share = getattr(args, "gpu_share", 1.0)
        if (sharing.get(gpu, 1) > 1 or share < 1.0) and not name.startswith(("gt", "pipeline")):
            own["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{0.9 * share / max(sharing.get(gpu, 1), 1):.2f}"
        with open(os.path.join(args.workdir, f"{name}.log"), "a") as log:
            return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=own, start_new_session=True)

    base, vae = pipeline(args), world_model_overrides(args)
    if getattr(args, "pipeline", ""):  # built elsewhere, maybe still being built: each run waits for its stages
        phases = []
        waiting = {n: needs(args, n) for n in commands}
        print(f"[reward-source] the runs start as {args.pipeline}'s stages finish: {waiting}", flush=True)
    elif getattr(args, "bundle", ""):  # the world model, VAE and detector from a bundle: only the data is built
        refreshed = [] if getattr(args, "latents", "") else [n for n in commands
                                                             if n.rpartition("_s")[0] in REFRESHED_ARMS]
        phases = [("pipeline_data", pipeline_command(base, vae, stop_after="data"),
                   [n for n in commands if n not in refreshed])]
        if refreshed:  # and the latents a refresh mixes in, which a bundle does not carry
            phases.append(("latents", latents_command(args), refreshed))
        waiting = {}
        print(f"[reward-source] the world-model runs read {args.bundle}; the pipeline builds its data only",
              flush=True)
    else:
        phases = [("pipeline_data", pipeline_command(base, vae, stop_after="data"),
                   [n for n in commands if n.startswith("gt")]),
                  ("pipeline", pipeline_command(base, vae, stop_after="reward_model"),
                   [n for n in commands if not n.startswith("gt")])]
        while phases and not phases[-1][2]:  # the ground-truth arm alone builds no world model, VAE or detector
            phases.pop()
        waiting = {}
    procs: dict[str, subprocess.Popen] = {}
    stopped: list[str] = []
    building = None
    while phases or building is not None or waiting or any(p.poll() is None for p in procs.values()):
        for run_name, stages in list(waiting.items()):
            if all(os.path.exists(os.path.join(pipeline_dir(args), "stages", f"{st}.json")) for st in stages):
                del waiting[run_name]
                procs[run_name] = launch(run_name, commands[run_name], gpu_of[run_name])
        if building is None and phases:
            name, cmd, _ = phases[0]
            building = (name, launch(name, cmd, ",".join(pipeline_gpus(args))))
        if building is not None and building[1].poll() is not None:
            name, proc = building
            _, _, ready = phases.pop(0)
            building = None
            if proc.returncode:
                print(f"[reward-source] {name} failed (log: {args.workdir}/{name}.log)", flush=True)
                phases = []
            else:
                for run_name in ready:
                    procs[run_name] = launch(run_name, commands[run_name], gpu_of[run_name])
        if args.deadline_s and time.perf_counter() - start > args.deadline_s:
            stopped = stop_at_deadline(dict(procs, **({building[0]: building[1]} if building else {})),
                                       args.deadline_s, tag="reward-source", grace_s=args.grace_s)
            break
        time.sleep(poll_s)
    summary = dict(summarize(args.workdir), exit_codes={n: p.returncode for n, p in procs.items()},
                   stopped_at_deadline=stopped, seconds=round(time.perf_counter() - start, 1))
    if getattr(args, "bundle", ""):  # where the world model came from (train.bundle's manifest, kept beside it)
        manifest = os.path.join(args.bundle, "bundle.json")
        if os.path.exists(manifest):
            with open(manifest) as f:
                made = json.load(f)
            summary["bundle"] = {"path": args.bundle, "source": made.get("source"), "sha256": made.get("sha256"),
                                 "world_model": made.get("world_model")}
    with open(os.path.join(args.workdir, "reward_source_summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    failed = sorted(n for n, p in procs.items() if p.returncode and n not in stopped)
    if failed or len(procs) < len(commands) and not stopped:
        raise SystemExit(f"bench_grpo_reward_source: runs failed or never started: "
                         f"{failed or sorted(set(commands) - set(procs))}")
    return summary


def figure_runs(workdir: str) -> dict[str, tuple[str, int, str]]:
    """:func:`run_dirs` of a work dir a figure draws, refused by name where it holds none."""
    runs = run_dirs(workdir) if os.path.isdir(workdir) else {}
    if not runs:
        raise SystemExit(f"bench_grpo_reward_source figure: no runs with a success curve under {workdir}")
    return runs


def run_dirs(workdir: str) -> dict[str, tuple[str, int, str]]:
    """``{run name: (arm, seed, GRPO work dir)}`` of the runs under ``workdir`` that left a success curve."""
    out = {}
    gt = os.path.join(workdir, "gt")
    for seed_dir in sorted(os.listdir(gt)) if os.path.isdir(gt) else []:
        if re.fullmatch(r"s\d+", seed_dir) and os.path.exists(os.path.join(gt, seed_dir, GT_DIR, "success_curve.json")):
            out[f"gt_{seed_dir}"] = ("gt", int(seed_dir[1:]), os.path.join(gt, seed_dir, GT_DIR))
    for name in sorted(os.listdir(workdir)):
        match = re.fullmatch(rf"({'|'.join(WORLD_MODEL_ARMS)})_s(\d+)", name)
        grpo = os.path.join(workdir, name, "rl", "grpo")
        if match and os.path.exists(os.path.join(grpo, "success_curve.json")):
            out[name] = (match.group(1), int(match.group(2)), grpo)
    return out


def _gain(points: list[dict], key: str | None) -> dict | None:
    """:func:`~benchmarks.bench_grpo_refresh.gain_between`, None where a point lacks ``key``'s evaluation."""
    return gain_between(points, key) if key is None or all(key in p for p in points) else None


def read_points(grpo: str) -> list[dict]:
    """The evaluation points of the GRPO run at ``grpo`` (its ``success_curve.json``)."""
    with open(os.path.join(grpo, "success_curve.json")) as f:
        return json.load(f)["points"]


# the sampled policies an evaluation point may hold beside the greedy success (sword_jax.rl.jax_env_grpo's extras)
SAMPLED_POLICIES = ("sampled", "sampled_proprio_masked", "sampled_as_trained")


def evaluation_curve(points: Sequence[dict]) -> list[dict]:
    """Per evaluation point, its step and real success: greedy, and sampled (with proprio masked, and executed as
    the training rollouts execute it, too) where evaluated."""
    return [{"step": p["step"], "greedy": p["mean"], **{k: p[k]["mean"] for k in SAMPLED_POLICIES if k in p}}
            for p in points]


def paid_per_step(history: Sequence[dict]) -> list[float]:
    """What reality paid each step's training rollouts: ``rollout_success`` (ground-truth runs) or ``success_rate``
    (runs in the world model; with a reward paid by execution, the imagined actions' real outcome)."""
    return [h.get("rollout_success", h.get("success_rate")) for h in history]


def real_episodes(history: Sequence[dict]) -> int | None:
    """The real episodes a run's GRPO steps consumed (its evaluations' not counted): on the real simulator the sum
    of its steps' ``trajectories_sampled``, in the world model the sum of its executed steps' ``real_rollouts`` (0
    where no step executed any, as with the detector's reward), for a refreshed run (``ref``) also the real episodes
    its refreshes had collected by its last step (``real_episodes_used``); None for a ground-truth run whose steps
    did not record how many trajectories they sampled."""
    if any("trajectories_sampled" in h for h in history):
        return int(sum(h.get("trajectories_sampled", 0) for h in history))
    if any("real_episodes_used" in h for h in history):  # a refreshed run: its refreshes' (cumulative), and any
        return int(max(h.get("real_episodes_used", 0) for h in history)  # executed rollouts' (per step)
                   + sum(h.get("real_rollouts", 0) for h in history))
    if any("rollout_success" in h for h in history):  # a ground-truth run that did not count its trajectories
        return None
    return int(sum(h.get("real_rollouts", 0) for h in history))


def summarize_run(grpo: str) -> dict:
    """One run: its gains from step 0 to its last evaluation (greedy, sampled, sampled with proprio masked, sampled
    as the training rollouts execute it; None where not evaluated), the success its training rollouts were paid
    (first and last 5 steps), its groups with mixed outcomes, the real episodes its steps consumed
    (:func:`real_episodes`), and with a reward paid by execution, the detector's verdict on the same rollouts
    (means over the steps)."""
    points = read_points(grpo)
    history = read_history(grpo)
    paid = paid_per_step(history)
    mixed = [h.get("mixed_fraction", h.get("kept_fraction")) for h in history]
    out = {"steps": points[-1]["step"], "greedy": _gain(points, None), "sampled": _gain(points, "sampled"),
           "sampled_proprio_masked": _gain(points, "sampled_proprio_masked"),
           "sampled_as_trained": _gain(points, "sampled_as_trained"),
           "paid_success": ({"first": statistics.mean(paid[:5]), "last": statistics.mean(paid[-5:])} if paid else None),
           "mixed_median": statistics.median(mixed) if mixed else None,
           "real_episodes": real_episodes(history), "curve": evaluation_curve(points)}
    executed = [h for h in history if "detector_success" in h]  # the steps paid by execution (cal: its first)
    if executed:
        out["detector"] = detector_figures(executed)
    if executed and closed_loop_decisions(executed[0]):  # per decision, the mean over the steps
        out["closed_loop"] = per_decision(executed)
    counted = [h for h in history if "start_a0_rollouts" in h]  # ground truth's steps, the world model's executed
    if counted:  # where their starts stood, pooled over the steps
        out["by_start"] = by_start(counted)
    if any("real_rollouts" in h for h in history):  # the real episodes (partial, the rollout's length) it executed
        out["real_rollouts"] = int(sum(h.get("real_rollouts", 0) for h in history))
    if os.path.exists(os.path.join(grpo, "refreshes.json")) or os.path.isdir(os.path.join(grpo, "refresh")):
        out["refreshes"] = refresh_records(grpo)  # ref: what each refresh's replay said and set
    judged = [h["detector_threshold"] for h in history if "detector_threshold" in h]
    if judged:  # cal: the threshold its executed steps set, at which the detector paid the later ones
        out["calibrated_threshold"] = judged[0]
        out["executed_steps"] = len(executed)
    return out


# imagined_check.closed_loop_fidelity's figures (the _vae ones where the simulator decoded through its VAE), and
# the key that names each decision it recorded
CLOSED_LOOP = ("frame_error", "action_gap", "frame_error_prev", "action_gap_prev", "motion", "frame_error_vae",
               "action_gap_vae")
DECISION_KEY = re.compile(r"closed_loop_frame_error_(\d+)")


def closed_loop_decisions(row: dict) -> list[int]:
    """The decisions a history row holds the closed-loop record of."""
    return sorted(int(m.group(1)) for m in map(DECISION_KEY.fullmatch, row) if m)


def per_decision(rows: Sequence[dict]) -> dict:
    """``{"decisions": [...], figure: [mean over the rows, per decision]}`` of the closed-loop figures the rows
    hold (runs from before a figure existed lack it)."""
    decisions = closed_loop_decisions(rows[0])
    return {"decisions": decisions, **{what: [statistics.mean(r[f"closed_loop_{what}_{k}"] for r in rows)
                                              for k in decisions]
                                       for what in CLOSED_LOOP if f"closed_loop_{what}_{decisions[0]}" in rows[0]}}


# what an executed step records of how the detector's scores separate the real outcomes whatever its threshold
# (sword_jax.rl.imagined_check.detector_separation), read without its ``detector_`` prefix
BOUNDED = ("auc", "threshold_bounded", "recall_bounded", "precision_bounded")


def by_start(rows: Sequence[dict]) -> list[dict]:
    """The trajectories of ``rows`` (a run's steps that counted them: ground truth's, the world model's paid by
    execution) pooled by where their starts stood in their episodes
    (:func:`sword_jax.rl.imagined_check.outcomes_by_start`'s counts, summed over the steps): per bin, from its
    lower edge ``from_step``, the trajectories and their real successes, and where a detector judged them (the
    world model's) its verdicts of success and those that reality paid too; with the real success, the
    detector's success and its precision (None where nothing was there to divide or no detector judged)."""
    lowers = sorted(int(m.group(1)) for k in rows[0] if (m := re.fullmatch(r"start_a(\d+)_rollouts", k)))
    judged = f"start_a{lowers[0]}_said" in rows[0]
    out = []
    for a in lowers:
        n, real, said, both = (sum(h.get(f"start_a{a}_{k}", 0.0) for h in rows)
                               for k in ("rollouts", "real", "said", "said_real"))
        out.append({"from_step": a, "rollouts": int(n), "real": int(real), "real_success": real / n if n else None,
                    **({"said": int(said), "said_real": int(both), "detector_success": said / n if n else None,
                        "precision": both / said if said else None} if judged else {})})
    return out


def detector_figures(history: Sequence[dict]) -> dict:
    """What the detector said of the rollouts that reality paid (history rows with ``detector_*``): its success and
    agreement, its false success (the steps where some trajectory failed in reality) and its precision (the share
    of its verdicts of success that reality paid too, :func:`_true_paid`), means over the rows; where the steps
    recorded them, also :data:`BOUNDED`: the AUC of its scores against the real outcomes, and at the threshold
    that pays at most ``rl.refresh.max_false_success`` of the real failures, that threshold, its recall and
    precision (means over the steps where both outcomes occurred)."""
    def known(key: str) -> float | None:  # the mean over the rows that hold a number (NaN: an outcome missing)
        values = [h[key] for h in history if h.get(key) is not None and h[key] == h[key]]
        return statistics.mean(values) if values else None

    said = sum(h["detector_success"] for h in history)
    out = {"success": statistics.mean(h["detector_success"] for h in history),
           "agreement": statistics.mean(h["detector_agreement"] for h in history),
           "false_success": known("detector_false_success"),
           "precision": sum(_true_paid(h) for h in history) / said if said else None}
    if "detector_auc" in history[0]:  # how its scores rank the real outcomes, and a threshold bounded on them
        out.update({name: known(f"detector_{name}") for name in BOUNDED})
    return out


def _true_paid(h: dict) -> float:
    """The share of a step's trajectories the detector would have paid that reality paid too: its verdicts
    ``detector_success`` less the real failures it paid (``detector_false_success`` x the real failures' share,
    NaN where every trajectory succeeded in reality)."""
    real = h.get("imagined_success_sampled", h.get("success_rate"))
    false = h["detector_false_success"]
    return h["detector_success"] - (0.0 if false != false else false * (1.0 - real))


def _mean_known(values) -> float | None:
    """The mean of the values that are not None; None where none is."""
    known = [v for v in values if v is not None]
    return statistics.mean(known) if known else None


def summarize(workdir: str) -> dict:
    """Every run (:func:`summarize_run`) and per arm its seeds' sampled gains, smallest and mean, and the real
    episodes each seed's GRPO steps consumed; per world-model arm also ``real_episodes_vs_gt``: its mean real
    episodes over the seeds divided by the ``gt`` arm's (None without a ``gt`` run in ``workdir`` or where its mean
    is 0 or unknown); per arm whose runs were evaluated as their GRPO executes the sampled policy, those gains
    (``as_trained_gain_per_seed``), smallest and mean."""
    runs = {name: dict(arm=arm, seed=seed, **summarize_run(grpo)) for name, (arm, seed, grpo) in run_dirs(workdir).items()}
    episodes = {arm: {r["seed"]: r["real_episodes"] for r in runs.values() if r["arm"] == arm} for arm in ARMS}
    gt_mean = _mean_known(episodes["gt"].values())
    arms = {}
    for arm in ARMS:
        gains = {r["seed"]: r["sampled"]["gain"] for r in runs.values() if r["arm"] == arm and r["sampled"]}
        if gains:
            arms[arm] = {"label": ARM_LABELS[arm], "sampled_gain_per_seed": gains, "smallest": min(gains.values()),
                         "mean": statistics.mean(gains.values()),
                         "steps": min(r["steps"] for r in runs.values() if r["arm"] == arm),
                         "real_episodes_per_seed": episodes[arm]}
            if arm in WORLD_MODEL_ARMS:
                mean = _mean_known(episodes[arm].values())
                arms[arm]["real_episodes_vs_gt"] = mean / gt_mean if gt_mean and mean is not None else None
            trained = {r["seed"]: r["sampled_as_trained"]["gain"] for r in runs.values()
                       if r["arm"] == arm and r.get("sampled_as_trained")}
            if trained:  # the sampled policy as the arm's GRPO executes it
                arms[arm].update(as_trained_gain_per_seed=trained, as_trained_smallest=min(trained.values()),
                                 as_trained_mean=statistics.mean(trained.values()))
    return {"runs": runs, "arms": arms, **common.workdir_xla_flags(workdir)}


# the runs' commands as ``run`` records them in its work dir, and as its launcher prints each run it starts
COMMANDS_FILE = "commands.json"
LAUNCH_LINE = re.compile(r"\[reward-source\] ((?:gt|exec)_s\d+) on GPU \S+ \([\d.]+ s\): (.+)")
# what a horizon's row reads of its runs' commands: {its name in the row: the flag that sets it}
SETTING_FLAGS = {"decisions": "--rl.imagined.max_chunks", "actions_per_decision": "--rl.imagined.execute_steps",
                 "group_size": "--rl.grpo.group_size", "groups_per_step": "--rl.grpo.rollout_batch"}
# a step's share of groups with mixed outcomes: the ground-truth runs', the sampled groups' in the world model, the
# updated groups' in runs from before the sampled share was logged
MIXED_KEYS = ("mixed_fraction", "sampled_mixed_fraction", "kept_fraction")


def record_commands(workdir: str, commands: dict[str, list[str]]) -> None:
    """``commands`` (``{run name: command}``) merged into ``<workdir>/commands.json``, so that a command started
    again with other arms keeps the earlier runs'; :func:`recorded_commands` reads it back."""
    path = os.path.join(workdir, COMMANDS_FILE)
    recorded = {}
    if os.path.exists(path):
        with open(path) as f:
            recorded = json.load(f)
    with open(path, "w") as f:
        json.dump({**recorded, **commands}, f, indent=1)


def recorded_commands(workdir: str) -> tuple[dict[str, list[str]], str]:
    """The commands of a work dir's ``gt`` and ``exec`` runs and the file they were read from: its
    ``commands.json`` (:func:`record_commands`), else for a work dir made before ``run`` wrote one, the launcher's
    lines ``[reward-source] exec_s0 on GPU 0 (95 s): <command>`` in its output beside the work dir
    (``<workdir>.out`` or ``.log``) or in it (``*.log``, ``*.out``); ``({}, "")`` where none holds them."""
    workdir = os.path.normpath(workdir)
    path = os.path.join(workdir, COMMANDS_FILE)
    if os.path.exists(path):
        with open(path) as f:
            return {n: list(c) for n, c in json.load(f).items() if re.fullmatch(r"(gt|exec)_s\d+", n)}, path
    inside = sorted(os.path.join(workdir, n) for n in os.listdir(workdir) if n.endswith((".log", ".out")))
    for log in (workdir + ".out", workdir + ".log", *inside):
        if os.path.isfile(log):
            with open(log, errors="replace") as f:
                found = {m.group(1): m.group(2).split() for m in map(LAUNCH_LINE.match, f) if m}
            if found:
                return found, log
    return {}, ""


def rollout_setting(workdir: str) -> dict:
    """A work dir's rollouts as its runs' own commands set them (:func:`recorded_commands`): ``decisions``
    (``rl.imagined.max_chunks``) of ``actions_per_decision`` (``rl.imagined.execute_steps``), ``actions``, their
    product, ``group_size`` and ``groups_per_step`` (``rl.grpo.rollout_batch``), and ``source``, the file read.
    Refused by the work dir's name where no ``exec`` run's command is recorded, a command lacks one of those
    flags, or the runs' commands set different rollouts."""
    commands, source = recorded_commands(workdir)
    if not any(name.startswith("exec") for name in commands):
        where = os.path.normpath(workdir)
        raise SystemExit(f"bench_grpo_reward_source horizons: {workdir} records no exec run's command, so its horizon "
                         f"is unknown (read: its {COMMANDS_FILE}, else the lines '[reward-source] exec_s<k> on GPU "
                         f"...' of {where}.out, {where}.log and its own *.log, *.out)")
    settings = {}
    for name, command in sorted(commands.items()):
        flags = dict(arg.partition("=")[::2] for arg in command if arg.startswith("--"))
        missing = [flag for flag in SETTING_FLAGS.values() if flag not in flags]
        if missing:
            raise SystemExit(f"bench_grpo_reward_source horizons: {workdir}: the command of {name} in {source} lacks "
                             f"{', '.join(missing)}")
        settings[name] = {key: int(flags[flag]) for key, flag in SETTING_FLAGS.items()}
    if len({tuple(s.values()) for s in settings.values()}) > 1:
        raise SystemExit(f"bench_grpo_reward_source horizons: {workdir}: its runs' commands in {source} set different "
                         f"rollouts: {settings}")
    setting = next(iter(settings.values()))
    return {**setting, "actions": setting["decisions"] * setting["actions_per_decision"], "source": source}


def rollouts_over_steps(grpos: Sequence[str], setting: dict) -> dict | None:
    """One arm's training rollouts over every step its runs (GRPO work dirs ``grpos``) recorded: ``steps``, what
    reality paid them pooled (``successes`` of ``of`` trajectories, the ``rate`` with its 95% Wilson interval; a
    step's trajectories are its ``trajectories_sampled`` where recorded, else ``setting``'s groups x group size),
    the median over the steps of the groups with mixed outcomes (``mixed_groups_median``, a count, and
    ``mixed_share_median``, of the step's groups: :data:`MIXED_KEYS`) and, where recorded, what the detector said
    of them (:func:`detector_figures`). None where the runs recorded no step."""
    from sword_jax.rl.sim_agreement import wilson_rate

    rows = [h for grpo in grpos for h in read_history(grpo)]
    if not rows:
        return None
    unmixed = [h.get("step") for h in rows if not any(k in h for k in MIXED_KEYS)]
    if unmixed:
        raise SystemExit(f"bench_grpo_reward_source horizons: steps {unmixed} of {', '.join(grpos)} record no share "
                         f"of mixed groups ({', '.join(MIXED_KEYS)})")
    per_step = setting["groups_per_step"] * setting["group_size"]
    trajectories = [int(h.get("trajectories_sampled", per_step)) for h in rows]
    successes = sum(round(paid * n) for paid, n in zip(paid_per_step(rows), trajectories))
    groups = [n // setting["group_size"] for n in trajectories]
    mixed = [round(next(h[k] for k in MIXED_KEYS if k in h) * g) for h, g in zip(rows, groups)]
    out = {"steps": len(rows), "paid_success": {"successes": successes, **wilson_rate(successes, sum(trajectories))},
           "mixed_groups_median": statistics.median(mixed),
           "mixed_share_median": statistics.median(m / g for m, g in zip(mixed, groups))}
    if "detector_success" in rows[0]:
        out["detector"] = detector_figures(rows)
    return out


def horizon_row(workdir: str) -> dict:
    """One work dir of ``run`` at one horizon: its rollouts (:func:`rollout_setting`), per arm (``gt``, ``exec``)
    its runs and their training rollouts over every recorded step (:func:`rollouts_over_steps`), and
    ``exec_over_gt``, the share of what reality paid on real frames that the world model's frames kept (exec's paid
    rate over gt's; None without both arms or where gt was paid nothing)."""
    workdir = os.path.normpath(workdir)
    if not os.path.isdir(workdir):
        raise SystemExit(f"bench_grpo_reward_source horizons: {workdir}: no such folder")
    setting = rollout_setting(workdir)
    runs = run_dirs(workdir)
    arms = {}
    for arm in ("gt", "exec"):
        names = sorted(name for name, (of, _, _) in runs.items() if of == arm)
        pooled = rollouts_over_steps([runs[name][2] for name in names], setting)
        if pooled is not None:
            arms[arm] = {"runs": names, **pooled}
    if not arms:
        raise SystemExit(f"bench_grpo_reward_source horizons: {workdir}: no gt or exec run recorded a step")
    gt, ex = (arms[arm]["paid_success"]["rate"] if arm in arms else None for arm in ("gt", "exec"))
    return {"workdir": workdir, **setting, "arms": arms, "exec_over_gt": ex / gt if gt and ex is not None else None}


def horizons_summary(workdirs: Sequence[str]) -> dict:
    """``{"rows": [...]}``: a :func:`horizon_row` per work dir, by the actions a rollout executes."""
    return {"rows": sorted((horizon_row(w) for w in workdirs), key=lambda r: (r["actions"], r["decisions"]))}


def print_horizons(rows: Sequence[dict]) -> None:
    for r in rows:
        cells = []
        for arm in ("gt", "exec"):
            if arm in r["arms"]:
                a = r["arms"][arm]
                paid = a["paid_success"]
                cells.append(f"{arm} paid {paid['rate']:.3f} [{paid['ci95'][0]:.3f}, {paid['ci95'][1]:.3f}] of "
                             f"{paid['of']}, mixed {a['mixed_groups_median']:g} of {r['groups_per_step']}")
        kept = r["exec_over_gt"]
        print(f"[horizons] {r['decisions']} x {r['actions_per_decision']} = {r['actions']} actions: "
              + "; ".join(cells) + (f"; exec / gt {kept:.2f}" if kept is not None else ""), flush=True)


# a step paid by execution with the closed-loop record, as sword_jax.pipeline.grpo.payment_note writes it
PROGRESS = re.compile(r"grpo step (\d+)/\d+ real success of the imagined actions ([\d.]+) \(the detector said ([\d.]+), "
                      r"agreeing on ([\d.]+)\); closed loop frame error ([\d.]+) -> ([\d.]+), greedy action gap "
                      r"([\d.]+) -> ([\d.]+)(?: \(the VAE alone at decision 1: frame error ([\d.]+), gap ([\d.]+)\))?")
PROGRESS_KEYS = ("paid", "detector_success", "detector_agreement", "frame_error_first", "frame_error_last",
                 "action_gap_first", "action_gap_last", "frame_error_vae_first", "action_gap_vae_first")


def progress_steps(log: str) -> list[dict]:
    """The steps of a run's log that carry the closed-loop record: paid success, the detector's success and
    agreement, the frame error and greedy action gap at the first and the last decision, and where the line has
    them the VAE round trip's at the first."""
    with open(log) as f:
        return [{"step": int(m.group(1)), **{k: float(v) for k, v in zip(PROGRESS_KEYS, m.groups()[1:])
                                             if v is not None}}
                for m in map(PROGRESS.search, f) if m]


def history_steps(rows: Sequence[dict]) -> list[dict]:
    """:func:`progress_steps`' figures from a run's ``train_history.jsonl`` rows (those with the record)."""
    out = []
    for r in rows:
        decisions = closed_loop_decisions(r)
        if decisions and "detector_success" in r:
            first, last = decisions[0], decisions[-1]
            out.append({"step": r["step"], "paid": r["success_rate"], "detector_success": r["detector_success"],
                        "detector_agreement": r["detector_agreement"],
                        "frame_error_first": r[f"closed_loop_frame_error_{first}"],
                        "frame_error_last": r[f"closed_loop_frame_error_{last}"],
                        "action_gap_first": r[f"closed_loop_action_gap_{first}"],
                        "action_gap_last": r[f"closed_loop_action_gap_{last}"],
                        **{f"{what}_first": r[f"closed_loop_{what}_{first}"] for what in ("frame_error_vae",
                                                                                        "action_gap_vae")
                           if f"closed_loop_{what}_{first}" in r}})
    return out


def world_model_loss(metrics: str, upto: int | None = None) -> dict | None:
    """``{"steps", "loss"[, "evaluation"]}`` of a world model's ``metrics.jsonl``: its last logged step (at or before
    ``upto`` where given: the checkpoint a run read), the mean loss of its last 10 logged steps to there and, where
    the trainer measured fixed segments (``trainer.eval_every``), its last such measurement (``eval_*`` and its
    ``step``); None where the file is missing or logs no such step."""
    if not os.path.exists(metrics):
        return None
    with open(metrics) as f:
        logged = [r for r in (json.loads(line) for line in f if line.strip()) if upto is None or r["step"] <= upto]
    if not logged:
        return None
    out = {"steps": logged[-1]["step"], "loss": statistics.mean(r["loss"] for r in logged[-10:])}
    measured = [r for r in logged if any(k.startswith("eval_") for k in r)]
    if measured:
        out["evaluation"] = {"step": measured[-1]["step"],
                             **{k: v for k, v in measured[-1].items() if k.startswith("eval_")}}
    return out


def closed_loop_summary(runs: Sequence[Sequence], trajectories: int, *, first_steps: int = 0,
                        decision_actions: Sequence[int] = ()) -> dict:
    """Per run ``(label, GRPO work dir, log, world-model metrics.jsonl[, the world model's step])``: the success its
    trajectories were paid (pooled over the steps, with a 95% Wilson interval over ``trajectories`` a step), the
    detector's verdicts, the closed loop's frame error and greedy action gap at the first and last decision (means
    over the steps; the VAE round trip's at the first where the run logged it) and per decision, and the world
    model's loss (the mean of its last 10 logged steps, to the step given where the run read an earlier checkpoint).

    The figures come from the run's ``train_history.jsonl``. A run whose history was not kept (its process
    ended before writing it, or it was not copied) is read from its progress lines, which hold every figure
    but the decisions between the first and the last (``source`` says which). With ``first_steps`` only the steps
    up to it count, so that runs of different lengths compare over the same steps; ``decision_actions`` (one per
    run, in order) records the actions each run executed a decision as ``actions_per_decision``."""
    from sword_jax.rl.sim_agreement import wilson_rate

    if decision_actions and len(decision_actions) != len(runs):
        raise SystemExit(f"bench_grpo_reward_source closed-loop: {len(decision_actions)} --decision-actions for "
                         f"{len(runs)} --run; give one per run, in order")
    out = {}
    kept = lambda step: not first_steps or step <= first_steps  # noqa: E731 - the steps that count
    for i, (label, grpo, log, metrics, *upto) in enumerate(runs):
        rows = [r for r in read_history(grpo) if kept(r["step"])]
        steps, source = ((history_steps(rows), "history") if rows
                         else ([s for s in progress_steps(log) if kept(s["step"])], "progress lines"))
        if not steps:
            where = os.path.join(grpo, "train_history.jsonl") if rows else log
            raise SystemExit(f"bench_grpo_reward_source: {where} holds no step with the closed-loop record")
        world_model = world_model_loss(metrics, *upto[:1])
        if world_model is None:
            raise SystemExit(f"bench_grpo_reward_source: {metrics} holds no logged world-model step"
                             + (f" at or before {upto[0]}" if upto else ""))
        paid = sum(round(s["paid"] * trajectories) for s in steps)
        run = {"steps": len(steps), "source": source, "world_model_steps": world_model["steps"],
               "world_model_loss": world_model["loss"],
               **({"world_model_evaluation": world_model["evaluation"]} if "evaluation" in world_model else {}),
               "paid_success": wilson_rate(paid, trajectories * len(steps)), "per_step": steps,
               **{k: statistics.mean(s[k] for s in steps) for k in steps[0]
                  if k not in ("step", "paid") and all(k in s for s in steps)}}
        if decision_actions:
            run["actions_per_decision"] = int(decision_actions[i])
        if rows:
            run["per_decision"] = per_decision([r for r in rows if closed_loop_decisions(r)])
        out[label] = run
    return out


def smallest_gain_entry(summary: dict, arm: str, workdir: str, *, bench: str, unit: str, data: str,
                        command: str = "", smallest: str = "smallest") -> dict:
    """A ``latest.json`` entry of a run-and-summary GRPO benchmark: value the smallest gain over the seeds of
    ``arm`` (its ``summary["arms"][arm][smallest]``: the sampled policy's, or e.g. ``as_trained_smallest``), beside
    every arm's gains and every run's summary, stamped with the device the runs' work dir was made on and the XLA
    flags they were started with."""
    if arm not in summary["arms"]:
        raise SystemExit(f"{bench}: no run of the {arm} arm left an evaluation to record")
    launched = {k: summary[k] for k in ("xla_flags", "deterministic") if k in summary}  # older work dirs lack them
    return common.record("", summary["arms"][arm][smallest], None, arms=summary["arms"], runs=summary["runs"],
                         device=common.workdir_device(workdir), data=data, unit=unit, **launched,
                         **({"command": command} if command else {}))


def results_entries(summary: dict, workdir: str, *, data: str, command: str = "") -> dict[str, dict]:
    """``policy_grpo_reward_source_small`` where the summary has an ``exec`` arm: value the smallest sampled gain
    over the seeds of GRPO in the world model paid by the real outcome of its actions, beside every arm's gains and
    every run's summary. ``policy_grpo_ground_truth_as_trained_small`` where its ``gt`` arm was evaluated as its
    GRPO executes the sampled policy: value the smallest of those gains over the seeds. Refused with neither."""
    entries = {}
    if "exec" in summary["arms"]:
        entries["policy_grpo_reward_source_small"] = smallest_gain_entry(
            summary, "exec", workdir, bench="bench_grpo_reward_source", data=data, command=command,
            unit="real success gain of the sampled policy (T 0.5) on MJX (episodes per point: each run's curve)")
    gt = summary["arms"].get("gt", {})
    if "as_trained_smallest" in gt:
        entries["policy_grpo_ground_truth_as_trained_small"] = smallest_gain_entry(
            summary, "gt", workdir, bench="bench_grpo_reward_source", data=data, command=command,
            smallest="as_trained_smallest",
            unit="real success gain on MJX of the sampled policy (T 0.5) executed as ground-truth GRPO executes it "
                 "(its actions per decision, its proprio), from rest for whole episodes")
    if not entries:
        raise SystemExit("bench_grpo_reward_source: no run of the exec arm, and no gt run evaluated as trained, "
                         "left an evaluation to record")
    return entries


def print_runs(summary: dict) -> None:
    """A line per run: its gains, the detector on its executed rollouts, its rollouts by the start's step (with the
    share of the same seed's ground-truth success kept where the work dir holds that run), its refreshes and its
    closed loop."""
    truth = {r["seed"]: {b["from_step"]: b for b in r["by_start"]}
             for r in summary["runs"].values() if r["arm"] == "gt" and r.get("by_start")}
    for name, r in summary["runs"].items():
        s = r["sampled"]
        line = (f"[reward-source] {name}: {r['steps']} steps; sampled {s['start']:.3f} -> {s['end']:.3f} "
                f"({s['gain']:+.3f} [{s['ci95'][0]:+.3f}, {s['ci95'][1]:+.3f}])" if s else
                f"[reward-source] {name}: {r['steps']} steps")
        if r.get("sampled_as_trained"):
            a = r["sampled_as_trained"]
            line += f"; sampled as trained {a['start']:.3f} -> {a['end']:.3f} ({a['gain']:+.3f})"
        if r.get("detector"):
            d = r["detector"]
            line += f"; the detector on its rollouts: success {d['success']:.2f}, agreement {d['agreement']:.2f}"
            if d.get("precision") is not None:
                line += f", precision {d['precision']:.2f}"
            if d.get("auc") is not None:
                line += f", AUC {d['auc']:.2f}"
                if d.get("recall_bounded") is not None:
                    line += f" (at its bounded threshold: recall {d['recall_bounded']:.2f}"
                    line += (f", precision {d['precision_bounded']:.2f})" if d.get("precision_bounded") is not None
                             else ")")
        if r.get("by_start"):
            same = truth.get(r["seed"], {}) if r["arm"] != "gt" else {}

            def kept(b: dict) -> str:  # the share of ground truth's real success from the same bin, same seed
                g = same.get(b["from_step"])
                return (f", kept {100 * b['real_success'] / g['real_success']:.0f}%"
                        if g and g.get("real_success") else "")

            line += "; by the start's step: " + ", ".join(
                f"{b['from_step']}+: {b['rollouts']} rollouts, real {b['real_success']:.2f}" + kept(b)
                + (f", said {b['detector_success']:.2f}" if "said" in b else "")
                for b in r["by_start"] if b["rollouts"])
        for f in r.get("refreshes", []):  # what each refresh met and set
            false = f.get("false_success_before") or {}
            line += (f"; refresh at step {f['step']}: {f['real_episodes']} real episodes"
                     + (f" (real success {f['real_success']:.2f})" if f.get("real_success") is not None else "")
                     + (f", its replay's false success before {false['rate']:.2f}"
                        + (f" of {false['of']} real failures" if false.get("of") is not None else "")
                        if false.get("rate") is not None else "")
                     + (f", threshold {f['threshold']:.3f}" if f.get("threshold") is not None else "")
                     + closed_loop_note(f.get("closed_loop")))
        if r.get("closed_loop"):
            loop = r["closed_loop"]
            line += (f"; closed loop at decisions {loop['decisions'][0]} / {loop['decisions'][-1]}: frame error "
                     f"{loop['frame_error'][0]:.3f} / {loop['frame_error'][-1]:.3f}, greedy action gap "
                     f"{loop['action_gap'][0]:.3f} / {loop['action_gap'][-1]:.3f}")
            if "action_gap_vae" in loop:
                line += (f" (the VAE alone: frame error {loop['frame_error_vae'][0]:.3f} / "
                         f"{loop['frame_error_vae'][-1]:.3f}, gap {loop['action_gap_vae'][0]:.3f} / "
                         f"{loop['action_gap_vae'][-1]:.3f})")
        print(line, flush=True)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line, refused by name where a value cannot be run."""
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("run", "summary", "closed-loop", "figure", "horizons"))
    parser.add_argument("--workdir", default="", help="run / summary: the experiment's folder")
    parser.add_argument("--run", nargs=4, action="append", default=[],
                        metavar=("LABEL", "GRPO_DIR", "LOG", "WM_METRICS"),
                        help="closed-loop: one run paid by execution, its log and its world model's metrics.jsonl")
    parser.add_argument("--trajectories", type=int, default=512, help="closed-loop: trajectories a step")
    parser.add_argument("--first-steps", type=int, default=0,
                        help="closed-loop: only each run's steps up to this one (0: all), so that runs of different "
                        "lengths compare over the same steps")
    parser.add_argument("--decision-actions", default="",
                        help="closed-loop: comma list, the actions each --run executed a decision, in order "
                        "(e.g. 4,4,8), which figure --closed-loop puts the decisions of each run on")
    parser.add_argument("--closed-loop", default="",
                        help="figure: draw closed-loop's JSON (its runs side by side) instead of --workdir's runs")
    parser.add_argument("--world-model", default="",
                        help="figure: draw a world model's metrics.jsonl (its loss, and its trainer's measurement of "
                        "fixed training and held-out segments) instead of --workdir's runs")
    parser.add_argument("--workdirs", default="",
                        help="horizons: comma list of run's work dirs, one per horizon (--out: the folder written); "
                        "figure --episodes / --by-start: the work dirs whose runs it draws")
    parser.add_argument("--episodes", action="store_true",
                        help="figure: each run of --workdirs, its real success against the real episodes consumed")
    parser.add_argument("--by-start", action="store_true",
                        help="figure: each run of --workdirs, its training rollouts' real success by the start's step "
                             "(and the detector's verdict on the world model's)")
    parser.add_argument("--min-rollouts", type=int, default=20,
                        help="figure --by-start: a run's bins of fewer rollouts are left out")
    parser.add_argument("--evaluated", default="sampled", choices=("greedy", *SAMPLED_POLICIES),
                        help="figure --episodes: the policy whose success it draws")
    parser.add_argument("--title", default="", help="figure --closed-loop / --world-model, horizons: a line above the "
                        "panels (the model, batch, device, seeds)")
    parser.add_argument("--policy", default="", help="run: the supervised policy every run starts from (.npz)")
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--gpus", default="0", help="run: comma list; the pipeline takes the first (or those of "
                        "--pipeline-gpus)")
    parser.add_argument("--pipeline-gpus", default="",
                        help="run: comma list, some of --gpus: the pipeline sees these GPUs and its trainers (the VAE, "
                        "the world model) split each batch over them, data-parallel with the same global batch; the "
                        "ground-truth runs take the GPUs it leaves (all of them where it takes every one); default: "
                        "the first of --gpus")
    parser.add_argument("--gpu-share", type=float, default=1.0,
                        help="run: the share of each GPU this command's world-model runs may take between them (their "
                        "XLA_PYTHON_CLIENT_MEM_FRACTION: 0.9 x this over the runs on the GPU); below 1 where another "
                        "command's runs share the GPU (e.g. 0.7 and 0.25 for two commands)")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--calibrate-steps", type=int, default=4,
                        help="run: the cal arm's steps paid by execution, which set the detector's threshold "
                        "(rl.imagined.calibrate_steps)")
    parser.add_argument("--arms", default="gt,exec,det", help=f"run: comma list of {', '.join(ARMS)} (e.g. the "
                        "world-model arms alone, for another world model beside a ground-truth arm already run)")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--eval-every", type=int, default=10)
    parser.add_argument("--eval-episodes-per-task", type=int, default=50,
                        help="run: real evaluation episodes per task at each evaluation (10 tasks)")
    parser.add_argument("--rollout-batch", type=int, default=32, help="start states per GRPO step, every arm (x 8)")
    parser.add_argument("--policy-rollouts", type=int, default=20,
                        help="run: the policy's own episodes per task in the world model's and detector's data")
    parser.add_argument("--vae-steps", type=int, default=1000)
    parser.add_argument("--world-model-steps", type=int, default=3000)
    parser.add_argument("--vae-variant", choices=tuple(VAE_VARIANTS), default="base",
                        help="run: the pipeline's VAE (vae8x: 8x spatial, 16x16 latents at 128 px), which the "
                             "world-model arms load too")
    parser.add_argument("--horizon", type=int, default=12,
                        help="run: decisions (of --actions-per-decision actions) of every arm's rollouts "
                             "(rl.imagined.max_chunks)")
    parser.add_argument("--bundle", default="",
                        help="run: the world-model arms read the world model, VAE and detector of this folder "
                        "(python -m train.bundle unpack's, from an earlier pipeline); the pipeline builds only "
                        "its data (the demonstrations)")
    parser.add_argument("--pipeline", default="",
                        help="run: a pipeline built elsewhere (e.g. another run's <workdir>/pipeline, with the same "
                             "--vae-variant and --world-model-set) instead of building <workdir>/pipeline: each run "
                             "starts once the stages it reads have finished there, so two commands can share one "
                             "world model")
    parser.add_argument("--actions-per-decision", type=int, choices=(4, 8), default=4,
                        help="run: actions executed per policy decision, every arm (rl.imagined.execute_steps): 4, "
                             "or 8, a whole chunk, so that the world model is called half as often over a horizon")
    parser.add_argument("--refresh-every", type=int, default=5,
                        help="run, the ref and rexec arms: GRPO steps between refreshes (rl.refresh.every; a "
                             "multiple of --eval-every; one also at step 0)")
    parser.add_argument("--refresh-episodes", type=int, default=64,
                        help="run, the ref and rexec arms: real episodes of the current policy each refresh "
                             "collects on MJX")
    parser.add_argument("--refresh-budget", type=int, default=256,
                        help="run, the ref and rexec arms: real episodes each refreshed run may collect in all "
                             "(rl.refresh.budget)")
    parser.add_argument("--refresh-set", action="append", default=[], metavar="rl.refresh.KEY=VALUE",
                        help="run, the ref and rexec arms: another refresh setting (repeatable; e.g. "
                             "rl.refresh.world_model_steps=1000, rl.refresh.branch=true)")
    parser.add_argument("--latents", default="",
                        help="run, the ref and rexec arms: the world model's training latents (.npz) its refreshes "
                             "mix in; "
                             "default: with --bundle, the pipeline's training episodes encoded by the bundle's VAE "
                             "(python -m train.encode_latents) into <workdir>/latents.npz, else the pipeline's")
    parser.add_argument("--keyframe-fraction", type=float, default=None,
                        help="run: every arm starts from keyframes in the first this-fraction of each demonstration "
                             "(rl.imagined.keyframe_fraction; default the config's); 1.0 = all phases, which short "
                             "horizons need to reach success at all")
    parser.add_argument("--keyframe-from", type=float, default=None,
                        help="run: every arm starts from keyframes from this fraction of each demonstration on, up "
                             "to the keyframe fraction (rl.imagined.keyframe_from; default the config's, 0)")
    parser.add_argument("--scale-by-std", choices=("true", "false"), default="true",
                        help="run: every arm's advantages divided by their group's std (GRPO) or only centred (false: "
                             "Dr. GRPO, rl.grpo.scale_by_std)")
    parser.add_argument("--world-model-set", action="append", default=[], metavar="KEY=VALUE",
                        help="run: a config override of the world model's training and loading, given to the "
                             "pipeline and the world-model arms (repeatable; e.g. trainer.ema_decay=0.999, "
                             "model.scan_layers=false); rl.* keys are the arms' recipe and are refused")
    add_deadline_options(parser, "run: ")
    add_deterministic_option(parser, "run: ")
    common.add_summary_options(parser)
    args = parser.parse_args(argv)
    for kv in args.world_model_set:
        if not re.fullmatch(r"[a-z_]+(\.[a-z_0-9]+)+=\S+", kv) or kv.startswith("rl."):
            raise SystemExit(f"bench_grpo_reward_source: --world-model-set takes KEY=VALUE with a dotted config key "
                             f"outside rl.* (e.g. trainer.ema_decay=0.999), got {kv!r}")
    if args.world_model_set:  # refused here, by name, rather than by every stage it would reach
        import configs
        from configs.cli import apply_overrides

        try:
            overrides = [*VAE_VARIANTS[args.vae_variant], *args.world_model_set]
            apply_overrides(configs.get(args.config), overrides).validate()
        except (ValueError, KeyError, TypeError) as error:
            raise SystemExit(f"bench_grpo_reward_source: --world-model-set: {error}") from None
    if args.bundle and not os.path.isdir(args.bundle):
        raise SystemExit(f"bench_grpo_reward_source: --bundle {args.bundle}: no such folder (python -m train.bundle "
                         "unpack makes it)")
    if args.pipeline and not os.path.isdir(args.pipeline):
        raise SystemExit(f"bench_grpo_reward_source: --pipeline {args.pipeline}: no such folder (start the command "
                         f"that builds it first; its runs then start as its stages finish)")
    if not 0.0 < args.gpu_share <= 1.0:
        raise SystemExit(f"bench_grpo_reward_source: --gpu-share must be in (0, 1], got {args.gpu_share}")
    args.scale_by_std = args.scale_by_std == "true"
    args.seeds = [int(s) for s in args.seeds.split(",") if s]
    args.gpus = [g for g in args.gpus.split(",") if g]
    args.pipeline_gpus = [g for g in args.pipeline_gpus.split(",") if g] or args.gpus[:1]
    if set(args.pipeline_gpus) - set(args.gpus) or len(set(args.pipeline_gpus)) < len(args.pipeline_gpus):
        raise SystemExit(f"bench_grpo_reward_source: --pipeline-gpus must name GPUs of --gpus, each once, got "
                         f"{','.join(args.pipeline_gpus)} for --gpus {','.join(args.gpus)}")
    if args.pipeline and len(args.pipeline_gpus) > 1:
        raise SystemExit("bench_grpo_reward_source: --pipeline-gpus places a pipeline this command builds; with "
                         "--pipeline it builds none")
    args.arms = [a for a in args.arms.split(",") if a]
    if not args.arms or set(args.arms) - set(ARMS):
        raise SystemExit(f"bench_grpo_reward_source: --arms must name some of {', '.join(ARMS)}, got {args.arms}")
    if (not args.seeds or not args.gpus or args.steps < 1 or args.eval_every < 1 or args.policy_rollouts < 0
            or args.rollout_batch < 1 or args.rollout_batch % 4 or args.eval_episodes_per_task < 1):
        raise SystemExit("bench_grpo_reward_source: --seeds and --gpus need one entry or more, --steps, --eval-every "
                         "and --eval-episodes-per-task >= 1, --policy-rollouts >= 0, --rollout-batch a multiple of 4 "
                         "(4 minibatches)")
    if set(REFRESHED_ARMS) & set(args.arms):
        check_refresh(args)
    if "cal" in args.arms and not 1 <= args.calibrate_steps < args.steps:
        raise SystemExit(f"bench_grpo_reward_source: the cal arm needs 1 <= --calibrate-steps < --steps (steps paid by "
                         f"execution before the detector pays), got {args.calibrate_steps} of {args.steps}")
    if args.horizon < 1 or (args.keyframe_fraction is not None and not 0 <= args.keyframe_fraction <= 1):
        raise SystemExit(f"bench_grpo_reward_source: --horizon must be >= 1 and --keyframe-fraction in [0, 1], got "
                         f"{args.horizon} and {args.keyframe_fraction}")
    if args.keyframe_from is not None:  # the upper bound it must stay under: the flag's or the config's
        import configs

        upper = (args.keyframe_fraction if args.keyframe_fraction is not None
                 else configs.get(args.config).rl.imagined.keyframe_fraction)
        if not 0 <= args.keyframe_from <= upper:
            raise SystemExit(f"bench_grpo_reward_source: --keyframe-from must be in [0, the keyframe fraction "
                             f"{upper}] (--keyframe-fraction, or the config's rl.imagined.keyframe_fraction), got "
                             f"{args.keyframe_from}")
    return args


def check_refresh(args) -> None:
    """The refreshed arms' (:data:`REFRESHED_ARMS`) refresh settings, refused by name before anything starts: a
    refresh every ``--refresh-every`` steps, a multiple of ``--eval-every`` (a refresh follows an evaluation);
    ``--refresh-set`` keys under ``rl.refresh``; the whole applied to the config and validated; and latents a run
    can read (a bundle with a pipeline built elsewhere makes none)."""
    bad = [kv for kv in args.refresh_set if not re.fullmatch(r"rl\.refresh\.[a-z_]+=\S+", kv)]
    if bad:
        raise SystemExit(f"bench_grpo_reward_source: --refresh-set takes rl.refresh.KEY=VALUE, got {bad}")
    if args.refresh_every < 1 or args.refresh_every % args.eval_every:
        raise SystemExit(f"bench_grpo_reward_source: --refresh-every must be a positive multiple of --eval-every "
                         f"({args.eval_every}: a refresh follows an evaluation), got {args.refresh_every}")
    if args.bundle and args.pipeline and not args.latents:
        raise SystemExit("bench_grpo_reward_source: a refreshed arm with --bundle and --pipeline needs --latents (only "
                         "a command that builds the data encodes them)")
    import configs
    from configs.cli import apply_overrides

    for arm in (a for a in REFRESHED_ARMS if a in args.arms):  # each as its command sets it
        try:
            apply_overrides(configs.get(args.config), [*recipe(args), *WORLD_MODEL, *REWARD[arm], *step_flags(args),
                                                       *refresh_settings(args)]).validate()
        except (ValueError, KeyError, TypeError) as error:
            raise SystemExit(f"bench_grpo_reward_source: the {arm} arm's refresh: {error}") from None


# the figure's names of each arm's rollouts and of each greedy action gap (its key's suffix in the closed-loop record)
FIGURE_ARMS = {"gt": "real frames", "exec": "the world model's frames, executed", "det": "the world model's frames",
               "cal": "the world model's frames, executed, then judged",
               "ref": "the world model's frames, refreshed",
               "rexec": "the refreshed world model's frames, executed"}
FIGURE_GAPS = {"": "the world model's frame", "_vae": "the real frame through the VAE alone",
               "_prev": "the real frame of the decision before"}


def figure(workdir: str, path: str) -> dict:
    """Three panels from the runs under ``workdir`` (PNG at ``path``): what reality paid each run's training
    rollouts at every step (``exec``: the imagined actions executed; dashed, what the detector said of them); each
    run's real success at its evaluations (sampled at the GRPO temperature, greedy, dotted, and where evaluated the
    sampled policy executed as its GRPO executes it, dashed); and for each ``exec`` run, per decision, the policy's
    greedy action gap on the world model's frame against the real frame, with what the VAE alone makes and what the
    real frame of the decision before makes (means over the steps). Returns the plotted series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = figure_runs(workdir)
    series: dict[str, dict] = {}
    fig, (paid_ax, eval_ax, gap_ax) = plt.subplots(1, 3, figsize=(16, 4.2))
    for name, (arm, _seed, grpo) in runs.items():
        history = read_history(grpo)
        steps, paid = [h["step"] for h in history], paid_per_step(history)
        curve = evaluation_curve(read_points(grpo))
        evaluated = {"steps": [c["step"] for c in curve], "greedy": [c["greedy"] for c in curve],
                     "sampled": [c.get("sampled", float("nan")) for c in curve]}
        if any("sampled_as_trained" in c for c in curve):
            evaluated["sampled_as_trained"] = [c.get("sampled_as_trained", float("nan")) for c in curve]
        series[name] = {"steps": steps, "paid": paid, "evaluated": evaluated}
        paid_ax.plot(steps, paid, marker="o", ms=3, label=f"{name}: {FIGURE_ARMS[arm]}")
        line, = eval_ax.plot(evaluated["steps"], evaluated["sampled"], marker="o", ms=3, label=f"{name}: sampled")
        eval_ax.plot(evaluated["steps"], evaluated["greedy"], marker="o", ms=3, ls=":", color=line.get_color(),
                     label=f"{name}: greedy")
        if "sampled_as_trained" in evaluated:
            eval_ax.plot(evaluated["steps"], evaluated["sampled_as_trained"], marker="s", ms=3, ls="--",
                         color=line.get_color(), label=f"{name}: sampled as trained")
        if arm == "exec" and "detector_success" in history[0]:
            said = [h["detector_success"] for h in history]
            series[name]["detector"] = said
            paid_ax.plot(steps, said, ls="--", label=f"{name}: what the detector said of them (not real)")
        if arm != "exec" or not closed_loop_decisions(history[0]):
            continue
        loop = per_decision(history)
        gaps = {suffix: loop[f"action_gap{suffix}"] for suffix in FIGURE_GAPS if f"action_gap{suffix}" in loop}
        series[name]["action_gap"] = {"decisions": loop["decisions"],
                                      **{suffix or "world_model": v for suffix, v in gaps.items()}}
        for suffix, values in gaps.items():
            gap_ax.plot(loop["decisions"], values, marker="o", ms=3, ls=":" if suffix else "-",
                        label=f"{name}: {FIGURE_GAPS[suffix]}")
    common.finish_figure(fig, paid_ax, path, xlabel="GRPO step", ylabel="success of the training rollouts",
                         title="what reality paid", save=False)
    common.finish_figure(fig, eval_ax, path, xlabel="GRPO step", ylabel="real success (MJX evaluation)",
                         title="the policy in the real environment", save=False)
    common.finish_figure(fig, gap_ax, path, xlabel="decision", ylabel="greedy action gap to the real frame",
                         title="where the closed loop leaves the real one")
    return series


def episodes_consumed(history: Sequence[dict]) -> dict[int, int]:
    """``{step: real episodes consumed up to and including it}`` of a run's GRPO steps (:func:`real_episodes`' count
    step by step: a ground-truth step's ``trajectories_sampled``, a world-model step's executed ``real_rollouts``);
    step 0 consumed none. Refused for a ground-truth run that did not count its trajectories."""
    if any("rollout_success" in h for h in history) and not all("trajectories_sampled" in h for h in history):
        raise SystemExit("bench_grpo_reward_source figure --episodes: a ground-truth run's steps did not record "
                         "trajectories_sampled, so the real episodes it consumed are unknown")
    out, total = {0: 0}, 0
    for i, h in enumerate(history, 1):
        total += int(h.get("trajectories_sampled", h.get("real_rollouts", 0)))
        # a refreshed run's refreshes count cumulatively (their episodes so far)
        out[int(h.get("step", i))] = total + int(h.get("real_episodes_used", 0))
    return out


def episodes_figure(workdirs: Sequence[str], path: str, policy: str = "sampled", title: str = "") -> dict:
    """Each run's real success at its evaluations (``policy``: ``greedy``, or one of :data:`SAMPLED_POLICIES`; 95%
    Wilson intervals) against the real episodes its GRPO steps had consumed by then (:func:`episodes_consumed`;
    evaluations not counted), for the runs of every work dir in ``workdirs`` (e.g. ground truth from one, the world
    model's arms from another), one colour per arm; PNG at ``path``, log x. Returns the plotted series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sword_jax.rl.env_rollout import wilson_interval

    if policy not in ("greedy", *SAMPLED_POLICIES):
        raise SystemExit(f"bench_grpo_reward_source figure --episodes: --evaluated must be greedy or one of "
                         f"{', '.join(SAMPLED_POLICIES)}, got {policy!r}")
    series: dict[str, dict] = {}
    colours = {arm: f"C{i}" for i, arm in enumerate(ARMS)}
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    for workdir in workdirs:
        for name, (arm, seed, grpo) in figure_runs(workdir).items():
            used = episodes_consumed(read_history(grpo))
            points = [(p["step"], p if policy == "greedy" else p.get(policy)) for p in read_points(grpo)]
            points = [(step, e) for step, e in points if e is not None and step in used]
            if not points:
                raise SystemExit(f"bench_grpo_reward_source figure --episodes: {grpo} has no evaluation of "
                                 f"{policy} at a step its history records")
            curve = [{"step": used[step], "success": e["mean"], "ci95": list(wilson_interval(e["successes"],
                                                                                            e["episodes"]))}
                     for step, e in points]
            series[name] = {"arm": arm, "seed": seed, "steps": [s for s, _ in points],
                            "real_episodes": [c["step"] for c in curve], "success": [c["success"] for c in curve],
                            "ci95": [c["ci95"] for c in curve]}
            errorbar_curve(ax, curve, marker="osd^v"[seed % 5], color=colours[arm],
                           label=f"{name}: {FIGURE_ARMS[arm]}")
    ax.set_xscale("symlog", linthresh=1000)  # linear up to 1,000 episodes (a world-model arm's few), log beyond
    top = max(max(entry["real_episodes"]) for entry in series.values())
    ax.set_xticks([0, *(10 ** k for k in range(3, len(str(max(int(top), 1000)))))])  # none inside the linear part
    common.finish_figure(fig, ax, path, xlabel="real episodes consumed by GRPO's steps (evaluations not counted)",
                         ylabel=f"real success, {policy} (95% interval)", title=title or None)
    return series


def by_start_figure(workdirs: Sequence[str], path: str, title: str = "", min_rollouts: int = 20) -> dict:
    """Where each run's training rollouts stood when reality paid them (:func:`by_start`, pooled over its steps):
    per bin of the start's step, the real success of the runs of every work dir in ``workdirs`` (95% Wilson
    intervals; ground truth's on real frames, the world model's on its frames, paid by executing their actions)
    and, dashed, what the detector said of the world model's rollouts; one colour per arm, a marker per seed; a
    run's bins of fewer than ``min_rollouts`` rollouts left out (an interval of a few says little); PNG at ``path``.
    Returns the plotted series (each run named by its work dir's folder where there are several)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sword_jax.rl.env_rollout import wilson_interval

    series: dict[str, dict] = {}
    colours = {arm: f"C{i}" for i, arm in enumerate(ARMS)}
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    edges: list[int] = []  # every bin's lower edge, and those of the bins drawn
    drawn: set[int] = set()
    for workdir in workdirs:
        for name, (arm, seed, grpo) in figure_runs(workdir).items():
            counted = [h for h in read_history(grpo) if "start_a0_rollouts" in h]
            if not counted:
                continue
            every = by_start(counted)
            edges = sorted({*edges, *(b["from_step"] for b in every)})
            bins = [b for b in every if b["rollouts"] >= max(min_rollouts, 1)]
            if not bins:
                continue
            label = name if len(workdirs) == 1 else f"{os.path.basename(os.path.normpath(workdir))}/{name}"
            drawn |= {b["from_step"] for b in bins}
            series[label] = entry = {
                "arm": arm, "seed": seed, "from_step": [b["from_step"] for b in bins],
                "rollouts": [b["rollouts"] for b in bins], "real_success": [b["real_success"] for b in bins],
                "ci95": [list(wilson_interval(b["real"], b["rollouts"])) for b in bins],
                **({"detector_success": [b["detector_success"] for b in bins]} if "said" in bins[0] else {})}
            errorbar_curve(ax, [{"step": a, "success": m, "ci95": ci} for a, m, ci in
                                zip(entry["from_step"], entry["real_success"], entry["ci95"])],
                           marker="osd^v"[seed % 5], ms=5, color=colours[arm], label=f"{label}: {FIGURE_ARMS[arm]}")
            if "detector_success" in entry:
                ax.plot(entry["from_step"], entry["detector_success"], ls="--", marker="osd^v"[seed % 5], ms=3,
                        color=colours[arm], alpha=0.6, label=f"{label}: the detector said")
    if not series:
        raise SystemExit(f"bench_grpo_reward_source figure --by-start: no run under {', '.join(workdirs)} counted "
                         f"{min_rollouts} or more of its rollouts in a bin of the start's step (start_a*_rollouts)")
    upper = dict(zip(edges, edges[1:]))
    ticks = sorted(drawn)
    ax.set_xticks(ticks, [f"{a}-{upper[a] - 1}" if a in upper else f"{a}+" for a in ticks])
    ax.set_ylim(-0.02, 1.02)
    common.finish_figure(fig, ax, path, xlabel="the start's step in its demonstration (actions)",
                         ylabel="real success of the training rollouts (95% interval)", title=title or None)
    return series


def closed_loop_figure(source: str, path: str, title: str = "") -> dict:
    """Three panels from ``closed-loop``'s JSON at ``source`` (PNG at ``path``), its runs side by side: what reality
    paid each step's rollouts, and against the actions executed (each run's decisions times its
    ``actions_per_decision``, 4 where not recorded) the frame error to the real frame and the greedy action gap
    (dotted: the VAE alone), means over the steps; ``title`` above them (the model, batch, device, seeds). Returns
    the plotted series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        with open(source) as f:
            runs = json.load(f)["runs"]
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"bench_grpo_reward_source figure: {source} is not closed-loop's JSON ({e})") from None
    missing = [label for label, r in runs.items() if "per_decision" not in r]
    if not runs or missing:
        raise SystemExit(f"bench_grpo_reward_source figure: {source} holds no runs with a per-decision record"
                         + (f" ({', '.join(missing)} read from progress lines)" if missing else ""))
    series: dict[str, dict] = {}
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for i, (label, r) in enumerate(runs.items()):
        colour = f"C{i}"
        loop = r["per_decision"]
        actions = [k * r.get("actions_per_decision", 4) for k in loop["decisions"]]
        steps = [s["step"] for s in r["per_step"]]
        series[label] = {"steps": steps, "paid": [s["paid"] for s in r["per_step"]], "actions": actions,
                         **{what: loop[what] for what in ("frame_error", "action_gap", "frame_error_vae",
                                                          "action_gap_vae") if what in loop}}
        axes[0].plot(steps, series[label]["paid"], marker="o", ms=3, color=colour, label=label)
        for ax, what in ((axes[1], "frame_error"), (axes[2], "action_gap")):
            ax.plot(actions, loop[what], marker="o", ms=3, color=colour, label=label)
            if f"{what}_vae" in loop:
                ax.plot(actions, loop[f"{what}_vae"], ls=":", color=colour,
                        label="dotted: the real frame through the VAE alone" if i == 0 else None)
    common.finish_figure(fig, axes[0], path, xlabel="GRPO step", ylabel="real success of the imagined actions",
                         title="what reality paid", save=False)
    common.finish_figure(fig, axes[1], path, xlabel="actions executed", ylabel="frame error to the real frame",
                         title="the world model's frames", save=False, legend_size=7)
    if title:
        fig.suptitle(title, fontsize=10)
    common.finish_figure(fig, axes[2], path, xlabel="actions executed", ylabel="greedy action gap to the real frame",
                         title="the policy's actions on them", legend_size=7)
    return series


def world_model_figure(metrics: str, path: str, title: str = "") -> dict:
    """Two panels from a world model's ``metrics.jsonl`` at ``metrics`` (PNG at ``path``) whose trainer measured
    fixed segments (``trainer.eval_every``, :mod:`sword_jax.world_model.heldout`): the flow loss (the logged
    training loss, and the fixed-noise loss on the training and the held-out segments) and the sampler's error
    from the true context per split and Euler step count, against the training step, both on a log scale;
    ``title`` above them. Returns the plotted series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sword_jax.world_model.heldout import SPLIT_LABELS as labels

    try:
        with open(metrics) as f:
            logged = [json.loads(line) for line in f if line.strip()]
    except (OSError, ValueError) as e:
        raise SystemExit(f"bench_grpo_reward_source figure: {metrics} is not a metrics.jsonl ({e})") from None
    measured = [r for r in logged if any(k.startswith("eval_") for k in r)]
    if not measured:
        raise SystemExit(f"bench_grpo_reward_source figure: {metrics} logs no measurement of fixed segments "
                         "(eval_*: the run had no trainer.eval_every)")
    names = sorted({k for r in measured for k in r if k.startswith("eval_")})
    series = {"steps": [r["step"] for r in logged if "loss" in r], "loss": [r["loss"] for r in logged if "loss" in r],
              "eval_steps": [r["step"] for r in measured],
              **{name: [r.get(name, float("nan")) for r in measured] for name in names}}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    axes[0].plot(series["steps"], series["loss"], lw=0.6, alpha=0.5, color="0.5", label="training batches (logged)")
    splits = sorted({name.split("_")[1] for name in names})
    for i, split in enumerate(splits):
        colour = f"C{i}"
        if f"eval_{split}_loss" in series:
            axes[0].plot(series["eval_steps"], series[f"eval_{split}_loss"], marker="o", ms=3, color=colour,
                         label=f"{labels.get(split, split)} segments, fixed noise")
        errors = sorted((int(n.rsplit("_", 1)[1]), n) for n in names if n.startswith(f"eval_{split}_sample_error_"))
        for j, (steps, name) in enumerate(errors):
            axes[1].plot(series["eval_steps"], series[name], marker="o", ms=3, color=colour,
                         ls=("-", "--", ":", "-.")[j % 4], label=f"{labels.get(split, split)} segments, {steps} Euler steps")
    for ax in axes:
        ax.set_yscale("log")
    common.finish_figure(fig, axes[0], path, xlabel="world-model training step", ylabel="flow loss",
                         title="the flow loss", save=False)
    if title:
        fig.suptitle(title, fontsize=10)
    common.finish_figure(fig, axes[1], path, xlabel="world-model training step",
                         ylabel="relative squared error of the future latents",
                         title="one call of the sampler from the true context")
    return series


def horizons_figure(rows: Sequence[dict], path: str, title: str = "") -> dict:
    """Three panels from :func:`horizons_summary`'s rows (PNG at ``path``) against the actions a rollout executes:
    what reality paid each arm's training rollouts (95% Wilson intervals), the share of its groups with mixed
    outcomes (median over the steps), and the share of the real-frame arm's paid success that the world model's
    frames kept; ``title`` above them. Returns the plotted series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: dict[str, dict] = {}
    fig, (paid_ax, mixed_ax, kept_ax) = plt.subplots(1, 3, figsize=(15, 4.2))
    for i, arm in enumerate(("gt", "exec")):
        measured = [r for r in rows if arm in r["arms"]]
        paid = [r["arms"][arm]["paid_success"] for r in measured]
        series[arm] = {"actions": [r["actions"] for r in measured], "paid": [p["rate"] for p in paid],
                       "ci95": [p["ci95"] for p in paid],
                       "mixed_share": [r["arms"][arm]["mixed_share_median"] for r in measured]}
        below = [p["rate"] - p["ci95"][0] for p in paid]
        above = [p["ci95"][1] - p["rate"] for p in paid]
        paid_ax.errorbar(series[arm]["actions"], series[arm]["paid"], yerr=[below, above], marker="o", ms=4,
                         capsize=3, color=f"C{i}", label=FIGURE_ARMS[arm])
        mixed_ax.plot(series[arm]["actions"], series[arm]["mixed_share"], marker="o", ms=4, color=f"C{i}",
                      label=FIGURE_ARMS[arm])
    kept = [r for r in rows if r["exec_over_gt"] is not None]
    series["exec_over_gt"] = {"actions": [r["actions"] for r in kept], "ratio": [r["exec_over_gt"] for r in kept]}
    kept_ax.plot(series["exec_over_gt"]["actions"], series["exec_over_gt"]["ratio"], marker="o", ms=4, color="C1",
                 label="paid on the world model's frames / on real frames")
    kept_ax.axhline(1.0, color="0.6", ls=":", label="as much as on real frames")
    for r in kept:
        kept_ax.annotate(f"{r['exec_over_gt']:.2f}", (r["actions"], r["exec_over_gt"]), textcoords="offset points",
                         xytext=(0, 6), ha="center", fontsize=8)
    for ax in (paid_ax, mixed_ax, kept_ax):
        ax.set_xticks(sorted({r["actions"] for r in rows}))
    common.finish_figure(fig, paid_ax, path, xlabel="actions a rollout executes",
                         ylabel="real success paid to the training rollouts", title="what reality paid", save=False)
    common.finish_figure(fig, mixed_ax, path, xlabel="actions a rollout executes",
                         ylabel="groups with mixed outcomes (median share)", title="the learning signal", save=False)
    if title:
        fig.suptitle(title, fontsize=10)
    common.finish_figure(fig, kept_ax, path, xlabel="actions a rollout executes",
                         ylabel="share of the real successes kept", title="what the world model's frames keep")
    return series


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse(argv)
    if args.mode == "closed-loop":
        if not args.run or not args.out or args.trajectories < 1 or args.first_steps < 0:
            raise SystemExit("bench_grpo_reward_source closed-loop needs --run (one or more), --out, "
                             "--trajectories >= 1 and --first-steps >= 0")
        listed = [a.strip() for a in args.decision_actions.split(",")] if args.decision_actions else []
        if not all(a.isdigit() and int(a) >= 1 for a in listed):
            raise SystemExit(f"bench_grpo_reward_source closed-loop: --decision-actions {args.decision_actions!r} "
                             "is not a comma list of positive integers")
        result = {"trajectories_per_step": args.trajectories,
                  **({"first_steps": args.first_steps} if args.first_steps else {}),
                  "runs": closed_loop_summary(args.run, args.trajectories, first_steps=args.first_steps,
                                              decision_actions=[int(a) for a in listed])}
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        for label, r in result["runs"].items():
            print(f"[closed-loop] {label}: paid {r['paid_success']['rate']:.3f} over {r['steps']} steps; frame error "
                  f"{r['frame_error_first']:.3f} -> {r['frame_error_last']:.3f}, greedy action gap "
                  f"{r['action_gap_first']:.3f} -> {r['action_gap_last']:.3f}" + (
                      f" (the VAE alone at the first: frame error {r['frame_error_vae_first']:.3f}, gap "
                      f"{r['action_gap_vae_first']:.3f})" if "action_gap_vae_first" in r else ""), flush=True)
        return result
    if args.mode == "horizons":
        workdirs = [w for w in args.workdirs.split(",") if w]
        if not workdirs or not args.out:
            raise SystemExit("bench_grpo_reward_source horizons needs --workdirs (a comma list of run's work dirs, "
                             "one per horizon) and --out (the folder of horizons.json and horizons.png)")
        result = {**({"title": args.title} if args.title else {}), **horizons_summary(workdirs)}
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "horizons.json"), "w") as f:
            json.dump(result, f, indent=1)
        series = horizons_figure(result["rows"], os.path.join(args.out, "horizons.png"), args.title)
        print_horizons(result["rows"])
        return dict(result, figure=series)
    if args.mode == "figure" and not args.out:
        raise SystemExit("bench_grpo_reward_source figure needs --out (the PNG's path)")
    if args.mode == "figure" and sum(map(bool, (args.closed_loop, args.world_model, args.episodes,
                                                args.by_start))) > 1:
        raise SystemExit("bench_grpo_reward_source figure: give one of --closed-loop, --world-model, --episodes and "
                         "--by-start, not more")
    if args.mode == "figure" and (args.episodes or args.by_start):
        workdirs = [w for w in args.workdirs.split(",") if w]
        which = "--episodes" if args.episodes else "--by-start"
        if not workdirs:
            raise SystemExit(f"bench_grpo_reward_source figure {which} needs --workdirs (a comma list of work dirs)")
        if args.by_start:
            return by_start_figure(workdirs, args.out, args.title, args.min_rollouts)
        return episodes_figure(workdirs, args.out, args.evaluated, args.title)
    if args.mode == "figure" and args.closed_loop:
        return closed_loop_figure(args.closed_loop, args.out, args.title)
    if args.mode == "figure" and args.world_model:
        return world_model_figure(args.world_model, args.out, args.title)
    if not args.workdir:
        raise SystemExit(f"bench_grpo_reward_source {args.mode} needs --workdir")
    if args.mode == "figure":
        return figure(args.workdir, args.out)
    if args.mode == "summary":
        summary = summarize(args.workdir)
        common.save_summary(summary, args.out, (lambda: results_entries(
            summary, args.workdir, data=common.summary_data(args.out, args.workdir), command=args.command)) if args.record else None)
        print_runs(summary)
        return summary
    if not args.policy:
        raise SystemExit("bench_grpo_reward_source run needs --policy (the supervised policy every run starts from)")
    summary = run(args)
    print_runs(summary)
    return summary


if __name__ == "__main__":
    cli.run(main)
