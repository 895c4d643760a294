"""Short GRPO rollouts branched from the policy's own real states, closed by a fitted value: does the value give
them back the learning signal a success-only reward leaves them without?

Rollouts short enough for a learned simulator to stay honest (one or two decisions of its closed loop) seldom
reach success, so a success-only return gives most GRPO groups no spread. MBPO branches short model rollouts from
real states and closes them with a learned value; ``rl.value`` does that for GRPO (:mod:`sword_jax.rl.value`).
This measures it against the ground truth first, so that only the recipe is on trial, not a world model. Two arms
at each seed, ground-truth GRPO on MJX in the learned simulator's setting (4 actions a decision, proprio missing,
T 0.5, lr 1e-4, ``--rollout-batch`` starts x 8):

* ``value``: the rollouts start at decisions of ``--value-episodes`` real episodes of the starting policy (every
  phase before their outcome, ``rl.env.starts=branch``), run ``--horizon`` decisions, and one cut at the horizon is
  paid ``2 x`` the value of its final frame (``rl.value.bootstrap=true``);
* ``success``: the same branches and episodes, paid success alone (``rl.value.bootstrap=false``).

Both fit the value to the same episodes (the same draws) and report its calibration on held-out episodes. Every
run is evaluated on MJX from rest (500 episodes per point: greedy, sampled at T 0.5, sampled with proprio
masked)::

    python -m benchmarks.bench_grpo_value run --workdir runs/gv --policy runs/p/policy_d50.npz --gpus 0 \\
        --seeds 0 --steps 60 [--deadline-s 1400]
    python -m benchmarks.bench_grpo_value summary --workdir runs/gv --out runs/gv/grpo_value [--record]

``--scale-by-std false`` centres every arm's advantages without dividing by the group's std (Dr. GRPO,
``rl.grpo.scale_by_std``); ``--branch-starts open`` draws every arm's starts where the value says the outcome is
still open (``rl.value.branch_starts``); ``--branch-starts rest`` starts them instead at training-split states at
rest, as whole-episode GRPO does, still cut at ``--horizon`` (``rl.env.starts=rest``: the starts' share of a short
rollout's effect, told from the cut's; ``--value-episodes 0`` then fits no value, without the ``value`` arm); ``--min-mixed-groups N`` skips the update of a step with fewer than N
groups of mixed outcomes (``rl.grpo.min_mixed_groups``); ``--kl-coef K`` anchors every arm to the starting policy by
a k3 KL term of weight K (``rl.grpo.kl_coef``); ``--learning-rate`` replaces the recipe's 1e-4. ``--arms shuffled``
adds the noise-only control: success alone, each group's returns shuffled among its trajectories
(``rl.grpo.shuffle_returns``); ``summary`` sets every other arm against it seed by seed (``contrasts``). ``run``
starts every run at once, spread over ``--gpus`` (runs sharing a GPU split its memory). At ``--deadline-s`` the runs
still going are stopped; with ``--grace-s`` they are asked first: each checkpoints its step in flight and evaluates
it (:func:`sword_jax.cli.request_stop`), and the same command resumes them. ``--deterministic`` starts the runs with
XLA's deterministic GPU ops (:func:`benchmarks.common.launch_env`). ``summary`` gives each run's gains with
95% intervals, what its rollouts were paid (success, and the value's mean where it paid), its groups with mixed
outcomes, the share of its advantages' mass in groups split by success, the real episodes it used beyond evaluation
and the value's held-out calibration; ``--record`` writes ``policy_grpo_branched_value_small`` (``--record-as
open``: ``policy_grpo_branched_open_small``; ``open_b256``: ``policy_grpo_branched_open_b256_small``, the
open-starts runs at ``--rollout-batch 256``; ``open_b1024``: ``policy_grpo_branched_open_b1024_small``, at 1,024;
``open_h12``: ``policy_grpo_branched_open_h12_small``, 256 starts with 12-decision rollouts (``--horizon 12``);
``rest_h12``: ``policy_grpo_rest_h12_small``, the same from rest (``--branch-starts rest``); ``rest_whole``:
``policy_grpo_rest_whole_small``, from rest to the episode limit (``--horizon 55``), the whole-episode reference in
this setting;
``open_kl``: ``policy_grpo_branched_open_kl_small``, those with
``--kl-coef``) to ``benchmarks/results/latest.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence

from benchmarks import common
from benchmarks.bench_grpo_refresh import add_deadline_options, add_deterministic_option, wait_until_deadline
from benchmarks.bench_grpo_reward_source import RECIPE, smallest_gain_entry, summarize_run
from benchmarks.bench_grpo_transfer import read_history
from sword_jax import cli

ARMS = ("value", "success", "shuffled")
ARM_LABELS = {"value": "branched, paid success or the value at the horizon",
              "success": "branched, paid success alone",
              "shuffled": "branched, success shuffled within each group (the noise-only control)"}
SETTING = ("--rl.grpo.max_sample_rounds=1", "--rl.grpo.eval_sampled=true", "--rl.env.proprio=missing")
# bench_policy.grpo_dir of this setting, by rl.env.starts (--branch-starts rest: rest, otherwise branch)
GRPO_DIRS = {"branch": "grpo_env_proprio_missing_starts_branch_mjx", "rest": "grpo_env_proprio_missing_starts_rest_mjx"}


def arm_label(arm: str, starts: str = "branch") -> str:
    """The arm's label (:data:`ARM_LABELS`), said of runs from rest where they start there."""
    return ARM_LABELS[arm] if starts == "branch" else ARM_LABELS[arm].replace("branched", "from rest, cut at the horizon")


def run_commands(args) -> dict[str, list[str]]:
    """``{run name: command}``: ``<arm>_s<seed>``, each ``bench_policy grpo`` under ``<workdir>/<arm>/s<seed>``."""
    replace = {"--rl.imagined.max_chunks=": f"--rl.imagined.max_chunks={args.horizon}",
               **({"--rl.grpo.learning_rate=": f"--rl.grpo.learning_rate={args.learning_rate:g}"}
                  if args.learning_rate else {})}
    shared = tuple(next((new for prefix, new in replace.items() if f.startswith(prefix)), f) for f in RECIPE) + SETTING
    out = {}
    for seed in args.seeds:
        for arm in args.arms:
            out[f"{arm}_s{seed}"] = [
                sys.executable, "-m", "benchmarks.bench_policy", "grpo", "--config", args.config, "--seed", str(seed),
                "--out", os.path.join(args.workdir, arm, f"s{seed}"), "--policy", args.policy,
                "--eval-episodes", str(args.eval_episodes_per_task), *shared,
                f"--rl.env.starts={'rest' if args.branch_starts == 'rest' else 'branch'}",
                f"--rl.value.episodes={args.value_episodes}", f"--rl.value.steps={args.value_steps}",
                f"--rl.value.bootstrap={'true' if arm == 'value' else 'false'}",
                *(("--rl.grpo.shuffle_returns=true",) if arm == "shuffled" else ()),
                f"--rl.grpo.rollout_batch={args.rollout_batch}", f"--rl.grpo.steps={args.steps}",
                f"--rl.grpo.eval_every={args.eval_every}",
                *(() if args.scale_by_std else ("--rl.grpo.scale_by_std=false",)),
                *((f"--rl.value.branch_starts={args.branch_starts}",) if args.branch_starts == "open" else ()),
                *((f"--rl.grpo.min_mixed_groups={args.min_mixed_groups}",) if args.min_mixed_groups else ()),
                *((f"--rl.grpo.kl_coef={args.kl_coef:g}",) if args.kl_coef else ())]
    return out


def placement(names: Sequence[str], gpus: Sequence[str]) -> dict[str, str]:
    """Round-robin over the GPUs, a seed's arms on different GPUs where there are several."""
    return {name: gpus[i % len(gpus)] for i, name in enumerate(names)}


def run(args, *, poll_s: float = 5.0) -> dict:
    """Every run at once (module docstring); the summary at the end."""
    os.makedirs(args.workdir, exist_ok=True)
    common.record_gpus(os.path.join(args.workdir, "gpu.txt"))
    env = common.launch_env(args.workdir, deterministic=args.deterministic)
    commands = run_commands(args)
    gpu_of = placement(list(commands), args.gpus)
    sharing = {g: sum(1 for n in commands if gpu_of[n] == g) for g in args.gpus}
    start = time.perf_counter()
    procs = {}
    for name, cmd in commands.items():
        own = dict(env, CUDA_VISIBLE_DEVICES=gpu_of[name])
        if sharing[gpu_of[name]] > 1:
            own["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{0.9 / sharing[gpu_of[name]]:.2f}"
        print(f"[grpo-value] {name} on GPU {gpu_of[name]}: {' '.join(cmd[2:])}", flush=True)
        with open(os.path.join(args.workdir, f"{name}.log"), "a") as log:
            procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=own, start_new_session=True)
    stopped = wait_until_deadline(procs, args.deadline_s, start, tag="grpo-value", poll_s=poll_s,
                                  grace_s=args.grace_s)
    summary = dict(summarize(args.workdir), exit_codes={n: p.returncode for n, p in procs.items()},
                   stopped_at_deadline=stopped, seconds=round(time.perf_counter() - start, 1))
    with open(os.path.join(args.workdir, "grpo_value_summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    failed = sorted(n for n, p in procs.items() if p.returncode and n not in stopped)
    if failed:
        raise SystemExit(f"bench_grpo_value: runs failed: {failed} (logs in {args.workdir})")
    return summary


def run_dirs(workdir: str) -> dict[str, tuple[str, int, str, str]]:
    """``{run name: (arm, seed, GRPO work dir, where its rollouts started)}`` of the runs under ``workdir`` that left
    a success curve (from branch starts or from rest: the keys of :data:`GRPO_DIRS`)."""
    out = {}
    for arm in ARMS:
        folder = os.path.join(workdir, arm)
        for seed_dir in sorted(os.listdir(folder)) if os.path.isdir(folder) else []:
            if seed_dir[:1] != "s" or not seed_dir[1:].isdigit():
                continue
            for starts, name in GRPO_DIRS.items():
                grpo = os.path.join(folder, seed_dir, name)
                if os.path.exists(os.path.join(grpo, "success_curve.json")):
                    out[f"{arm}_{seed_dir}"] = (arm, int(seed_dir[1:]), grpo, starts)
    return out


def value_summary(grpo: str) -> dict | None:
    """The value a run fitted (``value/value.json``): real episodes used, their success, held-out calibration."""
    path = os.path.join(grpo, "value", "value.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        record = json.load(f)
    held = record.get("held_out") or {}
    return {"real_episodes": record["real_episodes"], "episode_success": record["episode_success"],
            "decisions": record["decisions"], "held_out_brier": held.get("brier"),
            "held_out_brier_constant": held.get("brier_constant"), "held_out_auc": held.get("auc"),
            "held_out_bins": held.get("bins")}


def summarize(workdir: str) -> dict:
    """Every run (:func:`~benchmarks.bench_grpo_reward_source.summarize_run`, with what the value paid and the
    value's record) and per arm its seeds' sampled gains (proprio masked: the mode the rollouts train), smallest and
    mean."""
    runs = {}
    for name, (arm, seed, grpo, starts) in run_dirs(workdir).items():
        run = dict(arm=arm, seed=seed, starts=starts, **summarize_run(grpo), value=value_summary(grpo))
        history = read_history(grpo)
        shares = [h["success_advantage_share"] for h in history if "success_advantage_share" in h]
        if shares:  # how much of the update real outcomes carried (runs from before it was logged lack it)
            run["success_advantage_share"] = statistics.mean(shares)
        paid = [h["terminal_value"] for h in history if "terminal_value" in h]
        if paid:
            run["terminal_value"] = {"first": statistics.mean(paid[:5]), "last": statistics.mean(paid[-5:])}
            run["truncated_fraction"] = statistics.mean(h["truncated_fraction"] for h in history)
        runs[name] = run
    arms = {}
    for arm in ARMS:
        mine = [r for r in runs.values() if r["arm"] == arm]
        gains = {r["seed"]: r["sampled_proprio_masked"]["gain"] for r in mine if r["sampled_proprio_masked"]}
        if gains:
            starts = {r["starts"] for r in mine}
            arms[arm] = {"label": arm_label(arm, starts.pop() if len(starts) == 1 else "branch"),
                         "masked_gain_per_seed": gains, "smallest": min(gains.values()),
                         "mean": statistics.mean(gains.values()), "steps": min(r["steps"] for r in mine)}
    contrasts = {arm: c for arm in ARMS if arm != CONTROL for c in (contrast(runs, arm),) if c}
    return {"runs": runs, "arms": arms, **({"contrasts": contrasts} if contrasts else {}),
            **common.workdir_xla_flags(workdir)}


CONTROL = "shuffled"  # the noise-only control every other arm is set against, seed by seed
MODES = ("sampled_proprio_masked", "sampled", "greedy")  # the evaluation's policies (summarize_run's gains)


def contrast(runs: dict, arm: str, control: str = CONTROL) -> dict | None:
    """``arm``'s real-success gain minus ``control``'s, per evaluated policy (:data:`MODES`): at each seed both ran
    and their mean over those seeds, with a 95% interval (normal approximation: the runs' evaluations are
    independent, and each gain's standard error is read from its own 95% interval). None where no seed has both."""
    from sword_jax.rl.env_rollout import mean_interval

    seeds = sorted(r["seed"] for r in runs.values() if r["arm"] == arm and f"{control}_s{r['seed']}" in runs)
    if not seeds:
        return None
    out = {"control": control, "seeds": seeds,
           "steps": min(min(runs[f"{arm}_s{s}"]["steps"], runs[f"{control}_s{s}"]["steps"]) for s in seeds)}
    for mode in MODES:
        pairs = [(runs[f"{arm}_s{s}"][mode], runs[f"{control}_s{s}"][mode]) for s in seeds]
        if any(a is None or b is None for a, b in pairs):
            continue
        diffs = [a["gain"] - b["gain"] for a, b in pairs]
        mean, ci95 = mean_interval(diffs, [g["ci95"] for pair in pairs for g in pair])
        out[mode] = {"per_seed": dict(zip(seeds, diffs)), "mean": mean, "ci95": list(ci95)}
    return out


# --record-as: which latest.json entry a summary writes and whose arm's smallest gain is its value
ENTRIES = {"value": ("policy_grpo_branched_value_small", "value"),  # uniform starts, advantages scaled by the std
           "open": ("policy_grpo_branched_open_small", "success"),  # open starts, centred advantages
           "open_b256": ("policy_grpo_branched_open_b256_small", "success"),  # the same with 256 starts a step
           "open_b1024": ("policy_grpo_branched_open_b1024_small", "success"),  # 1,024 starts a step
           "open_h12": ("policy_grpo_branched_open_h12_small", "success"),  # 256 starts, 12-decision rollouts
           "rest_h12": ("policy_grpo_rest_h12_small", "success"),  # the same from rest (--branch-starts rest)
           "rest_whole": ("policy_grpo_rest_whole_small", "success"),  # from rest to the episode limit
           "open_kl": ("policy_grpo_branched_open_kl_small", "success")}  # 64 starts, anchored by --kl-coef


def results_entries(summary: dict, workdir: str, *, data: str, command: str = "", record_as: str = "value"
                    ) -> dict[str, dict]:
    """One entry (:data:`ENTRIES`): ``policy_grpo_branched_value_small`` (the runs with uniform starts), value the
    smallest gain over the seeds of the ``value`` arm's sampled policy reading proprio masked (the mode its rollouts
    train), or ``policy_grpo_branched_open_small`` (open starts, centred advantages; ``..._open_b256_small``: the
    same at 256 starts a step, ``..._open_b1024_small`` at 1,024, ``..._open_h12_small`` at 256 with 12-decision
    rollouts; ``..._open_kl_small``: anchored to the starting policy by a KL term), that of the
    ``success`` arm; beside every arm's gains and every run's summary."""
    key, arm = ENTRIES[record_as]
    entry = smallest_gain_entry(summary, arm, workdir, bench="bench_grpo_value", data=data, command=command,
                                unit="real success gain of the sampled policy (T 0.5, proprio masked) on MJX")
    if summary.get("contrasts"):
        entry["contrasts"] = summary["contrasts"]
    return {key: entry}


def print_runs(summary: dict) -> None:
    for name, r in summary["runs"].items():
        parts = [f"[grpo-value] {name}: {r['steps']} steps"]
        for key in MODES:
            g = r.get(key)
            if g:
                p = g.get("paired")
                moved = f", paired: {p['gained']} episodes gained, {p['lost']} lost" if p else ""
                parts.append(f"{key} {g['start']:.3f} -> {g['end']:.3f} ({g['gain']:+.3f} "
                             f"[{g['ci95'][0]:+.3f}, {g['ci95'][1]:+.3f}]{moved})")
        if r.get("paid_success"):
            parts.append(f"paid success {r['paid_success']['first']:.3f} -> {r['paid_success']['last']:.3f}")
        if r.get("mixed_median") is not None:
            parts.append(f"mixed groups (median) {r['mixed_median']:.2f}")
        if r.get("success_advantage_share") is not None:
            parts.append(f"advantage mass in groups split by success {r['success_advantage_share']:.2f}")
        if r.get("terminal_value"):
            parts.append(f"value paid {r['terminal_value']['first']:.3f} -> {r['terminal_value']['last']:.3f}")
        v = r.get("value")
        if v and v["held_out_brier"] is not None:
            parts.append(f"value held-out Brier {v['held_out_brier']:.4f} (constant {v['held_out_brier_constant']:.4f})"
                         f", AUC {v['held_out_auc']}")
        print("; ".join(parts), flush=True)

    for arm, c in summary.get("contrasts", {}).items():
        for mode in MODES:
            if mode in c:
                d = c[mode]
                print(f"[grpo-value] {arm} minus {c['control']}, {mode}, seeds {c['seeds']}: {d['mean']:+.3f} "
                      f"[{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}]", flush=True)


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line, refused by name where a value cannot be run."""
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("run", "summary"))
    parser.add_argument("--workdir", required=True, help="the experiment's folder")
    parser.add_argument("--policy", default="", help="run: the supervised policy every run starts from (.npz)")
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--gpus", default="0", help="run: comma list; the runs are spread over them")
    parser.add_argument("--seeds", default="0")
    parser.add_argument("--arms", default="value,success", help=f"run: comma list of {', '.join(ARMS)} (shuffled: the "
                        "noise-only control, rl.grpo.shuffle_returns)")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--eval-every", type=int, default=10)
    parser.add_argument("--eval-episodes-per-task", type=int, default=50,
                        help="run: real evaluation episodes per task at each evaluation (10 tasks)")
    parser.add_argument("--rollout-batch", type=int, default=64, help="run: start states per GRPO step (x 8)")
    parser.add_argument("--horizon", type=int, default=4, help="run: decisions (4 actions each) of every rollout")
    parser.add_argument("--value-episodes", type=int, default=512,
                        help="run: real episodes of the starting policy the value is fitted to and the rollouts "
                             "branch from")
    parser.add_argument("--value-steps", type=int, default=2000, help="run: steps of the value's fit")
    parser.add_argument("--scale-by-std", choices=("true", "false"), default="true",
                        help="run: every arm's advantages divided by their group's std (GRPO) or only centred (false: "
                             "Dr. GRPO, rl.grpo.scale_by_std)")
    parser.add_argument("--branch-starts", choices=("uniform", "open", "rest"), default="uniform",
                        help="run: every arm's starts uniform over the decisions, or where the value says the outcome "
                             "is still open (rl.value.branch_starts), or at training-split states at rest, still cut at "
                             "--horizon (rl.env.starts=rest)")
    parser.add_argument("--min-mixed-groups", type=int, default=0,
                        help="run: a step whose batch holds fewer groups with mixed outcomes applies no update "
                             "(rl.grpo.min_mixed_groups; 0 = every step updates)")
    parser.add_argument("--learning-rate", type=float, default=0.0,
                        help="run: every arm's GRPO learning rate (rl.grpo.learning_rate; 0 = the recipe's, 1e-4)")
    parser.add_argument("--kl-coef", type=float, default=0.0,
                        help="run: every arm's weight of the k3 KL to the starting policy (rl.grpo.kl_coef; 0 = off)")
    add_deadline_options(parser, "run: ")
    add_deterministic_option(parser, "run: ")
    parser.add_argument("--record-as", choices=tuple(ENTRIES), default="value",
                        help="summary --record: the latest.json entry, " + "; ".join(
                            f"{k}: {key} (the {arm} arm's smallest gain)" for k, (key, arm) in ENTRIES.items()))
    common.add_summary_options(parser)
    args = parser.parse_args(argv)
    args.scale_by_std = args.scale_by_std == "true"
    args.seeds = [int(s) for s in args.seeds.split(",") if s]
    args.gpus = [g for g in args.gpus.split(",") if g]
    args.arms = [a for a in args.arms.split(",") if a]
    if not args.arms or set(args.arms) - set(ARMS):
        raise SystemExit(f"bench_grpo_value: --arms must name some of {', '.join(ARMS)}, got {args.arms}")
    if args.mode == "run" and not args.policy:
        raise SystemExit("bench_grpo_value run needs --policy (the supervised policy, .npz)")
    if (not args.seeds or not args.gpus or args.steps < 1 or args.eval_every < 1 or args.eval_episodes_per_task < 1
            or args.rollout_batch < 1 or args.rollout_batch % 4 or args.horizon < 1
            or (args.value_episodes < 2 and not (args.value_episodes == 0 and args.branch_starts == "rest"
                                                 and "value" not in args.arms))
            or args.value_steps < 1 or not 0 <= args.min_mixed_groups <= args.rollout_batch
            or not (args.kl_coef >= 0 and math.isfinite(args.kl_coef))
            or not (args.learning_rate >= 0 and math.isfinite(args.learning_rate))):
        raise SystemExit("bench_grpo_value: --seeds and --gpus need one entry or more; --steps, --eval-every, "
                         "--eval-episodes-per-task, --horizon and --value-steps >= 1; --value-episodes >= 2 (or 0 with "
                         "--branch-starts rest and no value arm); "
                         "--rollout-batch a multiple of 4 (4 minibatches); --min-mixed-groups in [0, --rollout-batch]; "
                         "--kl-coef and --learning-rate finite numbers >= 0")
    return args


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse(argv)
    if args.mode == "run":
        summary = run(args)
    else:
        summary = summarize(args.workdir)
        common.save_summary(summary, args.out, (lambda: results_entries(
            summary, args.workdir, data=common.summary_data(args.out, args.workdir), command=args.command,
            record_as=args.record_as))
            if args.record else None)
    print_runs(summary)
    return summary


if __name__ == "__main__":
    cli.run(main)
