"""Does GRPO in the learned simulator transfer? Three arms from one supervised policy, side by side.

1. ``world_model``: the pipeline up to GRPO inside the learned simulator (``train.pipeline --stop-after
   policy``, stages side by side with ``--parallel``), evaluated in the real environments, with the
   replay diagnostic (real episodes replayed in the simulator: false successes, resample
   disagreement) at every evaluation.
2. ``ground_truth``: GRPO with the same update in the real environments from rest (``train.grpo
   --simulator env``): the control that says whether this policy can be lifted at all.
3. ``ground_truth_keyframes``: GRPO in the real environments in the learned simulator's setting
   (its keyframe starts, horizon and execution, proprio missing): whether that setting can lift it.

Arms 2 and 3 start as soon as the pipeline's supervised policy exists and run beside it. At the end
``<workdir>/transfer.json`` and ``transfer.png`` hold every arm's real success curve with 95%
intervals, its gain (with the Newcombe interval of the difference of two proportions), its
training rollouts' success per 10 steps, and the world-model arm's replay agreement.

    python -m benchmarks.bench_grpo_transfer --workdir runs/transfer              # GPU: small, ~25 min on an H100
    python -m benchmarks.bench_grpo_transfer --workdir runs/t --config sword:tiny --steps 2 --eval-every 1 \\
        --eval-episodes 1 --arm-workers 0                                          # CPU smoke run

Any ``--section.key=value`` is passed to all three arms.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence

from benchmarks import common
from sword_jax import cli
from sword_jax.cli import not_dotted_overrides

ARMS = ("world_model", "ground_truth", "ground_truth_keyframes")


def commands(args, overrides: Sequence[str]) -> dict[str, list[str]]:
    """The three arms' command lines (``python -m ...``)."""
    py = [sys.executable, "-m"]
    common = ["--config", args.config, "--seed", str(args.seed), "--rl.env.execute_steps=4",
              "--rl.env.action_ensemble=false", f"--rl.grpo.steps={args.steps}", f"--rl.grpo.eval_every={args.eval_every}",
              f"--rl.grpo.eval_episodes_per_task={args.eval_episodes}", *overrides]
    pipe = os.path.join(args.workdir, "pipeline")
    env_arm = [*py, "train.grpo", *common, "--simulator", "env", "--policy", os.path.join(pipe, "rl", "policy_sft"),
               "--env-workers", str(args.arm_workers)]
    return {
        "world_model": [*py, "train.pipeline", *common, "--sim.backend=cpu", f"--workdir={pipe}",
                        "--skip", "probe,evaluate", "--stop-after", "policy", "--parallel", str(args.parallel)],
        "ground_truth": [*env_arm, "--workdir", os.path.join(args.workdir, "ground_truth")],
        "ground_truth_keyframes": [*env_arm, "--workdir", os.path.join(args.workdir, "ground_truth_keyframes"),
                                   "--demos", os.path.join(pipe, "data", "demos.hdf5"), "--rl.env.starts=keyframes",
                                   "--rl.env.proprio=missing"],
    }


def gain_interval(a: dict, b: dict) -> list[float]:
    """95% interval of ``rate(b) - rate(a)`` for two evaluation points of one run: paired episode by episode where
    both kept their outcomes, else Newcombe's (:func:`sword_jax.rl.env_rollout.gain_interval`)."""
    from sword_jax.rl.env_rollout import gain_interval as interval

    return list(interval(a, b))


def _blocks(values: Sequence[float], size: int = 10) -> list[float]:
    return [round(sum(values[i:i + size]) / len(values[i:i + size]), 4) for i in range(0, len(values), size)]


REPLAY_KEYS = ("imagined_success", "real_success", "false_success", "missed_success", "resample_disagreement",
               "settle_steps", "sustained_success_sweep")  # what a summary keeps of each evaluation's replay


def curve_and_gain(points: Sequence[dict]) -> dict:
    """A GRPO success curve's points, and its gain from the first to the last with the Newcombe interval."""
    return {"curve": [{"step": p["step"], "success": p["mean"], "ci95": p["ci95"], "episodes": p["episodes"]}
                      for p in points],
            "gain": points[-1]["mean"] - points[0]["mean"], "gain_ci95": gain_interval(points[0], points[-1])}


def name_dir_pairs(items: Sequence[str], flag: str, value: str = "DIR") -> dict[str, str]:
    """``["a=DIR", ...]`` -> ``{"a": "DIR"}``; ``SystemExit`` naming ``flag`` (and ``NAME=<value>``) on anything else."""
    pairs = [item.partition("=") for item in items]
    if any(not sep or not name or not path for name, sep, path in pairs):
        raise SystemExit(f"{flag} takes NAME={value} pairs, got {list(items)}")
    return {name: path for name, _, path in pairs}


def read_history(grpo_dir: str) -> list[dict]:
    """A GRPO run's per-step metrics (``train_history.jsonl``, written after every step); [] without one."""
    from sword_jax.rl.grpo_loop import read_history as read

    return read(grpo_dir)


def summarize(workdir: str) -> dict:
    """Every finished arm's curve, gain and per-step rollout success (arms that did not finish are
    listed under ``missing``)."""
    out: dict = {"arms": {}, "missing": []}
    curves = {"world_model": os.path.join(workdir, "pipeline", "rl", "grpo", "success_curve.json"),
              "ground_truth": os.path.join(workdir, "ground_truth", "rl", "grpo", "success_curve.json"),
              "ground_truth_keyframes": os.path.join(workdir, "ground_truth_keyframes", "rl", "grpo",
                                                     "success_curve.json")}
    for arm in ARMS:
        if not os.path.exists(curves[arm]):
            out["missing"].append(arm)
            continue
        with open(curves[arm]) as f:
            points = json.load(f)["points"]
        entry = curve_and_gain(points)
        mode_key = "proprio_masked" if arm == "world_model" else "train_mode"
        modes = [p[mode_key] for p in points if mode_key in p]
        if len(modes) == len(points) and modes:
            entry["trained_mode_curve"] = [{"step": p["step"], "success": m["mean"], "ci95": m["ci95"]}
                                           for p, m in zip(points, modes)]
            entry["trained_mode_gain"] = modes[-1]["mean"] - modes[0]["mean"]
            entry["trained_mode_gain_ci95"] = gain_interval(modes[0], modes[-1])
        if arm == "world_model":
            entry["replay"] = [{"step": p["step"], **{k: p["replay"].get(k) for k in REPLAY_KEYS}}
                               for p in points if "replay" in p]
        metric = "success_rate" if arm == "world_model" else "rollout_success"
        rates = [p[metric] for p in read_history(os.path.dirname(curves[arm])) if metric in p]
        if rates:
            entry["rollout_success_per_10_steps"] = _blocks(rates)
        out["arms"][arm] = entry
    return out


def errorbar_curve(ax, curve: Sequence[dict], *, offset: float = 0.0, **kwargs) -> None:
    """A success curve (points with ``step``, ``success``, ``ci95``) with its 95% intervals as error
    bars, shifted right by ``offset`` steps (arms side by side); ``kwargs`` go to ``errorbar`` (round markers and
    caps of 3 unless they say otherwise)."""
    y = [p["success"] for p in curve]
    ax.errorbar([p["step"] + offset for p in curve], y,
                yerr=[[v - p["ci95"][0] for v, p in zip(y, curve)], [p["ci95"][1] - v for v, p in zip(y, curve)]],
                **{"marker": "o", "capsize": 3, **kwargs})


def plot(summary: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = {"world_model": "GRPO in the learned simulator", "ground_truth": "GRPO in the real envs (from rest)",
              "ground_truth_keyframes": "GRPO in the real envs, simulator's setting"}
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for arm, entry in summary["arms"].items():
        errorbar_curve(ax, entry["curve"], label=labels[arm])
    common.finish_figure(fig, ax, path, xlabel="GRPO step", ylabel="real success (true proprio, 95% interval)")


def run(args, overrides: Sequence[str], *, poll_s: float = 5.0) -> dict:
    os.makedirs(args.workdir, exist_ok=True)
    cmds = commands(args, overrides)
    env = dict(os.environ)
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # three processes share one GPU
    procs: dict[str, subprocess.Popen] = {}
    start = time.perf_counter()

    def launch(arm: str) -> None:
        with open(os.path.join(args.workdir, f"{arm}.log"), "w") as log:
            procs[arm] = subprocess.Popen(cmds[arm], stdout=log, stderr=subprocess.STDOUT, env=env)
        print(f"[transfer] {arm}: started ({time.perf_counter() - start:.0f} s): {' '.join(cmds[arm][2:])}", flush=True)

    launch("world_model")
    marker = os.path.join(args.workdir, "pipeline", "stages", "sft_policy.json")
    while procs["world_model"].poll() is None and not os.path.exists(marker):
        time.sleep(poll_s)
    if os.path.exists(marker):
        for arm in ARMS[1:]:
            launch(arm)
    codes = {}
    for arm, proc in procs.items():
        codes[arm] = proc.wait()
        print(f"[transfer] {arm}: exit {codes[arm]} ({time.perf_counter() - start:.0f} s)", flush=True)
    summary = {"config": args.config, "seed": args.seed, "steps": args.steps, "exit_codes": codes,
               "seconds": round(time.perf_counter() - start, 1),
               "commands": {arm: " ".join(["python", *cmd[1:]]) for arm, cmd in cmds.items()}, **summarize(args.workdir)}
    with open(os.path.join(args.workdir, "transfer.json"), "w") as f:
        json.dump(summary, f, indent=1)
    if summary["arms"]:
        plot(summary, os.path.join(args.workdir, "transfer.png"))
    for arm, entry in summary["arms"].items():
        lo, hi = entry["gain_ci95"]
        print(f"[transfer] {arm}: real success {entry['curve'][0]['success']:.3f} -> {entry['curve'][-1]['success']:.3f} "
              f"(gain {entry['gain']:+.3f} [{lo:+.3f}, {hi:+.3f}]); rollouts per 10 steps "
              f"{entry.get('rollout_success_per_10_steps')}", flush=True)
    failed = [arm for arm, code in codes.items() if code]
    if failed or summary["missing"]:
        raise SystemExit(f"bench_grpo_transfer: arms failed or missing: {sorted(set(failed) | set(summary['missing']))} "
                         f"(logs in {args.workdir})")
    return summary


def compare_world_model_arms(arms: dict[str, str]) -> dict:
    """GRPO-in-the-learned-simulator runs side by side (e.g. two success rules from one pipeline):
    ``{name: folder holding success_curve.json}`` -> each run's real success curve, gain with its
    Newcombe interval, and per evaluation the replay's agreement, its k-frame sweep and imagined
    success by action h among real successes vs real failures (recomputed from the stored
    per-episode first successes, so runs logged before that key existed are covered too)."""
    import numpy as np

    from sword_jax.rl.sim_agreement import success_by_horizon

    out = {}
    for name, folder in arms.items():
        path = os.path.join(folder, "success_curve.json")
        if not os.path.exists(path):
            raise SystemExit(f"bench_grpo_transfer --compare: {name}: no success_curve.json in {folder}")
        with open(path) as f:
            points = json.load(f)["points"]
        replay = [{"step": p["step"], **{k: p["replay"].get(k) for k in REPLAY_KEYS},
                   "imagined_success_by_horizon": success_by_horizon(
                       np.asarray(p["replay"]["real_success_flags"], bool),
                       np.asarray(p["replay"]["imagined_first_success"]))}
                  for p in points if p.get("replay")]
        out[name] = {**curve_and_gain(points), "replay": replay}
    return out


def plot_world_model_arms(summary: dict, path: str) -> None:
    """Left: real success of each run; right: the replay's imagined success by action h at step 0 of
    the first run, real successes vs real failures (the simulator's discrimination by horizon)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, (name, entry) in enumerate(summary.items()):
        errorbar_curve(left, entry["curve"], offset=0.6 * i, label=name)
    left.set_xlabel("GRPO step")
    left.set_ylabel("real success (95% interval)")
    left.legend(fontsize=8)
    name, entry = next(iter(summary.items()))
    if entry["replay"]:
        by_h = entry["replay"][0]["imagined_success_by_horizon"]
        labels = list(by_h)
        x = list(range(len(labels)))
        for j, (group, colour, label) in enumerate((("real_success", "tab:green", "real successes"),
                                                    ("real_failure", "tab:red", "real failures"))):
            rates = [by_h[h][group]["rate"] or 0.0 for h in labels]
            lo = [r - by_h[h][group]["ci95"][0] for r, h in zip(rates, labels)]
            hi = [by_h[h][group]["ci95"][1] - r for r, h in zip(rates, labels)]
            right.bar([v + 0.38 * j for v in x], rates, width=0.38, color=colour, yerr=[lo, hi], capsize=3,
                      label=label)
        right.set_xticks([v + 0.19 for v in x], [f"by action {h}" if h != "all" else "whole replay" for h in labels])
        right.set_ylabel("imagined success (replay)")
        right.set_title(f"{name}, step {entry['replay'][0]['step']}: does the simulator tell them apart?", fontsize=9)
        right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> dict:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0],
                                     epilog="Any --section.key=value is passed to all three arms.")
    parser.add_argument("--workdir", default="runs/grpo_transfer")
    parser.add_argument("--config", default="cache_ablation:small-linear-direct-all")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=50, help="GRPO steps of every arm")
    parser.add_argument("--eval-every", type=int, default=25)
    parser.add_argument("--eval-episodes", type=int, default=20, help="real evaluation episodes per task")
    parser.add_argument("--arm-workers", type=int, default=4, help="C-engine processes of each ground-truth arm")
    parser.add_argument("--parallel", type=int, default=2, help="pipeline stages side by side (train.pipeline --parallel)")
    parser.add_argument("--compare", nargs="+", metavar="NAME=DIR", default=None,
                        help="only summarise finished GRPO-in-the-simulator runs (DIR holds success_curve.json) into "
                             "--out.json/.png; nothing is run")
    parser.add_argument("--out", default="", help="with --compare: output path without extension")
    args, overrides = parser.parse_known_args(argv)
    if args.compare is not None:
        if not args.out:
            raise SystemExit("bench_grpo_transfer --compare needs --out PATH")
        summary = compare_world_model_arms(name_dir_pairs(args.compare, "bench_grpo_transfer --compare"))
        with open(args.out + ".json", "w") as f:
            json.dump(summary, f, indent=1)
        plot_world_model_arms(summary, args.out + ".png")
        for name, entry in summary.items():
            lo, hi = entry["gain_ci95"]
            print(f"[transfer] {name}: " + " -> ".join(f"{p['success']:.3f}" for p in entry["curve"]) +
                  f" (gain {entry['gain']:+.3f} [{lo:+.3f}, {hi:+.3f}])")
        return summary
    bad = not_dotted_overrides(overrides)
    if bad:
        raise SystemExit(f"bench_grpo_transfer: not a dotted config override (--section.key=value): {' '.join(bad)}")
    if args.steps < 1 or args.eval_every < 1 or args.eval_episodes < 1 or args.arm_workers < 0 or args.parallel < 0:
        raise SystemExit("bench_grpo_transfer: --steps, --eval-every and --eval-episodes must be >= 1, "
                         "--arm-workers and --parallel >= 0")
    return run(args, overrides)


if __name__ == "__main__":
    cli.run(main)
