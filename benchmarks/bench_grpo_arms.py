"""Ground-truth GRPO arms from one supervised policy, side by side: greedy and sampled success.

Each arm is ``train.grpo --simulator env`` (GRPO in the real MuJoCo environments, reward = true
success) from the same SFT policy with its own overrides (temperature, seed, learning rate, ...).
Every evaluation measures the greedy policy (the policy's success) and the sampled policy at the
arm's temperature (``rl.grpo.eval_sampled``: the policy the update trains) on the same fixed
evaluation episodes. ``<out>.json``/``.png`` hold each arm's two curves with 95% intervals, its
gains (Newcombe interval of a difference of two proportions) and its training rollouts' success and
behaviour NLL per 10 steps.

    # GPU (small, one H200: two arms of 100 steps side by side in about 10 minutes)
    python -m benchmarks.bench_grpo_arms --policy runs/p/rl/policy_sft --out runs/arms/arms \\
        --arm "t10:" --arm "t07: --rl.grpo.temperature=0.7" --steps 100 --eval-every 50
    # CPU smoke run (44 s here) from the tiny quick start's policy
    python -m benchmarks.bench_grpo_arms --config sword:tiny --policy runs/sword-tiny/rl/policy_sft \
        --out runs/arms_smoke/arms --arm "a:" --arm "b: --rl.grpo.temperature=0.7" --steps 1 --eval-every 1 \
        --eval-episodes 1 --arm-workers 0
    # summarise arms that already ran (e.g. copied back from a GPU machine)
    python -m benchmarks.bench_grpo_arms --out runs/arms/arms --summarize t10=runs/arms/t10 t07=runs/arms/t07

Any other ``--section.key=value`` is passed to every arm.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence

from benchmarks.bench_grpo_transfer import _blocks, errorbar_curve, gain_interval, name_dir_pairs
from sword_jax import cli
from sword_jax.cli import not_dotted_overrides

DEFAULT_CONFIG = "cache_ablation:small-linear-direct-all"


def parse_arm(spec: str) -> tuple[str, list[str]]:
    """``"name: --a.b=1 --seed 1"`` -> ``("name", ["--a.b=1", "--seed", "1"])``."""
    name, sep, rest = spec.partition(":")
    name = name.strip()
    if not sep or not name or not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"bench_grpo_arms: an arm is 'name: overrides' with a plain name, got {spec!r}")
    return name, shlex.split(rest)


def commands(args, arms: Sequence[tuple[str, list[str]]], overrides: Sequence[str]) -> dict[str, list[str]]:
    """Each arm's ``python -m train.grpo`` command line (its own workdir under ``dirname(out)``)."""
    root = os.path.dirname(args.out) or "."
    common = ["--config", args.config, "--seed", str(args.seed), "--simulator", "env", "--policy", args.policy,
              "--env-workers", str(args.arm_workers), "--rl.env.execute_steps=4", "--rl.env.action_ensemble=false",
              f"--rl.grpo.steps={args.steps}", f"--rl.grpo.eval_every={args.eval_every}",
              f"--rl.grpo.eval_episodes_per_task={args.eval_episodes}", "--rl.grpo.eval_sampled=true", *overrides]
    names = [name for name, _ in arms]
    if len(set(names)) != len(names):
        raise ValueError(f"bench_grpo_arms: arm names must differ, got {names}")
    return {name: [sys.executable, "-m", "train.grpo", *common, *extra, "--workdir", os.path.join(root, name)]
            for name, extra in arms}


def _curve(points: Sequence[dict], key: str | None) -> list[dict]:
    rows = [p if key is None else p[key] for p in points]
    return [{"step": p["step"], "success": r["mean"], "ci95": r["ci95"], "episodes": r["episodes"],
             "successes": r["successes"]} for p, r in zip(points, rows)]


def summarize(arm_dirs: dict[str, str]) -> dict:
    """Every arm's greedy and sampled curves, gains and training-rollout statistics (arms without a
    success curve are listed under ``missing``)."""
    out: dict = {"arms": {}, "missing": []}
    for name, workdir in arm_dirs.items():
        curve_path = os.path.join(workdir, "rl", "grpo", "success_curve.json")
        if not os.path.exists(curve_path):
            out["missing"].append(name)
            continue
        with open(curve_path) as f:
            points = json.load(f)["points"]
        entry: dict = {"greedy": _curve(points, None)}
        if all("sampled" in p for p in points):
            entry["sampled"] = _curve(points, "sampled")
            entry["temperature"] = points[0]["sampled"].get("temperature")
        for kind in ("greedy", "sampled"):
            if kind in entry and len(entry[kind]) > 1:
                first, last = entry[kind][0], entry[kind][-1]
                entry[f"{kind}_gain"] = round(last["success"] - first["success"], 4)
                ends = [p if kind == "greedy" else p["sampled"] for p in (points[0], points[-1])]
                entry[f"{kind}_gain_ci95"] = [round(x, 4) for x in gain_interval(*ends)]
        history = os.path.join(workdir, "rl", "grpo", "train_history.jsonl")
        if os.path.exists(history):
            with open(history) as f:
                steps = [json.loads(line) for line in f if line.strip()]
            entry["rollout_success_per_10_steps"] = _blocks([s["rollout_success"] for s in steps])
            if all("behaviour_nll" in s for s in steps):
                entry["behaviour_nll_per_10_steps"] = _blocks([s["behaviour_nll"] for s in steps])
        out["arms"][name] = entry
    return out


def plot(summary: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for ax, kind, title in ((axes[0], "greedy", "greedy policy (its success)"),
                            (axes[1], "sampled", "sampled policy (what GRPO trains)")):
        for i, (name, entry) in enumerate(summary["arms"].items()):
            if kind not in entry:
                continue
            # side by side, not on top of each other; one colour per arm in both panels
            errorbar_curve(ax, entry[kind], offset=0.6 * i, label=name, color=f"C{i % 10}")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("GRPO step (real MuJoCo envs, true success)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success on the fixed evaluation states (95% interval)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _rates(curve: Sequence[dict]) -> str:
    return " -> ".join(format(p["success"], ".3f") for p in curve)


def write(summary: dict, out: str) -> None:
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    with open(out + ".json", "w") as f:
        json.dump(summary, f, indent=1)
    if summary["arms"]:
        plot(summary, out + ".png")
    for name, entry in summary["arms"].items():
        g = entry["greedy"]
        line = f"[arms] {name}: greedy {_rates(g)}"
        if "greedy_gain" in entry:
            lo, hi = entry["greedy_gain_ci95"]
            line += f" (gain {entry['greedy_gain']:+.3f} [{lo:+.3f}, {hi:+.3f}])"
        if "sampled" in entry:
            line += f"; sampled at T={entry['temperature']}: {_rates(entry['sampled'])}"
        print(line, flush=True)


def run(args, arms, overrides: Sequence[str]) -> dict:
    cmds = commands(args, arms, overrides)
    root = os.path.dirname(args.out) or "."
    os.makedirs(root, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")  # the arms share one GPU
    start, procs = time.perf_counter(), {}
    for name, cmd in cmds.items():
        with open(os.path.join(root, f"{name}.log"), "w") as log:
            procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
        print(f"[arms] {name}: {' '.join(cmd[2:])}", flush=True)
    codes = {name: proc.wait() for name, proc in procs.items()}
    summary = {"config": args.config, "policy": args.policy, "seconds": round(time.perf_counter() - start, 1),
               "exit_codes": codes, "commands": {n: " ".join(["python", *c[1:]]) for n, c in cmds.items()},
               **summarize({name: os.path.join(root, name) for name in cmds})}
    write(summary, args.out)
    failed = sorted({n for n, c in codes.items() if c} | set(summary["missing"]))
    if failed:
        raise SystemExit(f"bench_grpo_arms: arms failed or missing: {failed} (logs in {root})")
    return summary


def main(argv: Sequence[str] | None = None) -> dict:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0],
                                     epilog="Any other --section.key=value is passed to every arm.")
    parser.add_argument("--out", required=True, help="<out>.json / <out>.png; arms run in dirname(out)/<name>")
    parser.add_argument("--policy", default="", help="the SFT policy every arm starts from")
    parser.add_argument("--arm", action="append", default=[], help="'name: overrides' (repeat)")
    parser.add_argument("--summarize", nargs="+", default=None, metavar="NAME=WORKDIR",
                        help="only summarise arms that already ran")
    parser.add_argument("--config", default=DEFAULT_CONFIG)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--eval-every", type=int, default=50)
    parser.add_argument("--eval-episodes", type=int, default=50, help="real evaluation episodes per task")
    parser.add_argument("--arm-workers", type=int, default=7, help="C-engine processes of each arm")
    args, overrides = parser.parse_known_args(argv)
    if args.summarize is not None:
        summary = summarize(name_dir_pairs(args.summarize, "bench_grpo_arms --summarize", "WORKDIR"))
        write(summary, args.out)
        return summary
    bad = not_dotted_overrides(overrides)
    if bad:
        raise SystemExit(f"bench_grpo_arms: not a dotted config override (--section.key=value): {' '.join(bad)}")
    if not args.policy or not args.arm:
        raise SystemExit("bench_grpo_arms: give --policy (the SFT policy) and at least one --arm 'name: overrides'")
    if args.steps < 1 or args.eval_every < 1 or args.eval_episodes < 1 or args.arm_workers < 0:
        raise SystemExit("bench_grpo_arms: --steps, --eval-every and --eval-episodes must be >= 1, --arm-workers >= 0")
    try:
        arms = [parse_arm(spec) for spec in args.arm]
    except ValueError as e:
        raise SystemExit(str(e)) from None
    return run(args, arms, overrides)


if __name__ == "__main__":
    cli.run(main)
