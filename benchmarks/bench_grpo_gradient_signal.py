"""Is a short rollout's GRPO gradient signal, and does it point where a full episode's does? (C engine, CPU)

Ground-truth GRPO lifts the policy with whole episodes from rest; with short rollouts from mid-episode states it
lowered real success, even paid the true outcome. This probe separates the two explanations at the starting policy,
without training: (1) the short rollouts' batch gradient is mostly noise, so an optimiser that normalises its step
(Adam) walks at random; (2) it is signal, but for an objective (success within the horizon, from those states) that
does not pull the policy where success from rest needs it.

It rolls out ``--groups`` groups of ``--group-size`` trajectories in each of two start distributions, every
trajectory to the episode limit (T, proprio masked, 4 actions a decision, as GRPO's short rollouts run):

- ``rest``: training-split starts at rest, whole episodes paid their success (the recipe that lifts; the reference);
- ``keyframes``: keyframes of every phase of expert demonstrations (``--demos``), scored three ways on the same
  trajectories: ``short`` (the first ``--horizon`` decisions, paid success within them: GRPO's short rollout),
  ``short_eventual`` (the same decisions paid the episode's eventual success: what a perfect value would pay) and
  ``full`` (every decision, the eventual success).

For each setting, :mod:`sword_jax.rl.gradient_signal` gives from the per-group gradients: the signal fraction of one
group, the expected cosine of two independent batches of ``--batch-groups`` groups, the alignment of its expected
gradient with the reference's, and the expected cosine of one batch with the reference's expected gradient
(``useful``), with bootstrap 95% intervals over groups. Raw gradients: Adam's preconditioning is not modelled.

    python -m benchmarks.bench_grpo_gradient_signal --policy runs/p/policy_d50.npz --demos /tmp/hz/demos.hdf5 \\
        --out benchmarks/results/policy/grpo_gradient_signal_small_cpu --groups 64
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Sequence

import numpy as np

from benchmarks.bench_value_signal import Probe, add_probe_options
from sword_jax import cli

SETTINGS = ("short", "short_eventual", "rest", "full")  # the cheap ones first


def main(argv: Sequence[str] | None = None) -> dict:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_probe_options(parser, groups=64)
    parser.add_argument("--batch-groups", type=int, default=64, help="the GRPO batch the cosines are predicted for")
    parser.add_argument("--scale-by-std", choices=("true", "false"), default="true")
    parser.add_argument("--max-steps", type=int, default=0, help="episode limit in actions (0: the config's)")
    parser.add_argument("--bootstrap", type=int, default=1000)
    parser.add_argument("--rest-groups", type=int, default=0, help="groups at rest (0: --groups)")
    parser.add_argument("--settings", default=",".join(SETTINGS),
                        help="comma list of the settings to measure (rest is always measured: the reference)")
    args = parser.parse_args(argv)
    asked = [n for n in args.settings.split(",") if n]
    if set(asked) - set(SETTINGS):
        raise SystemExit(f"bench_grpo_gradient_signal: --settings names some of {', '.join(SETTINGS)}, got {asked}")
    args.settings = [n for n in SETTINGS if n == "rest" or n in asked]
    args.rest_groups = args.rest_groups or args.groups
    if (min(args.horizon, args.batch_groups, args.bootstrap) < 1 or min(args.groups, args.rest_groups) < 2
            or args.group_size < 2):
        raise SystemExit("bench_grpo_gradient_signal: --groups, --rest-groups and --group-size must be >= 2, --horizon, "
                         "--batch-groups and --bootstrap >= 1")
    if not os.path.exists(args.demos):
        raise SystemExit(f"bench_grpo_gradient_signal: no demonstrations at {args.demos} (make them with "
                         "python -m train.gen_data ... --stop-at-success)")

    from sword_jax.rl import gradient_signal as gs

    probe = Probe(args, "gradient-signal", max_steps=args.max_steps, scale_by_std=args.scale_by_std == "true",
                  minibatches=1, update_microbatch=0)
    rl, graphdef, params = probe.rl, probe.graphdef, probe.params
    os.makedirs(args.out, exist_ok=True)
    rest = probe.episodes([s for s in probe.rest_starts(args.rest_groups, "gradient_signal/rest")
                           for _ in range(args.group_size)], "rest", 1)
    keyframes = probe.episodes([s for s in probe.keyframe_starts() for _ in range(args.group_size)], "keyframes", 2)
    short = gs.first_decisions(keyframes, args.horizon, rl)
    scored = {"rest": rest, "short": short,
              "short_eventual": short._replace(success=keyframes.success, returns=keyframes.returns),
              "full": keyframes}  # every decision, paid the eventual outcome
    timings = probe.seconds
    vectors, settings, outcomes, start = [], {}, {}, 0
    for name in args.settings:
        t0 = time.perf_counter()
        batch = scored[name]
        h = gs.group_gradients(graphdef, rl, params, batch)
        timings[f"{name}_gradients_s"] = round(time.perf_counter() - t0, 1)
        vectors.append(h)
        settings[name] = gs.Setting(np.arange(start, start + len(h)), "" if name == "rest" else "keyframes")
        start += len(h)
        returns = np.asarray(batch.returns, np.float32).reshape(-1, args.group_size)
        outcomes[name] = {"paid_success": float(np.mean(returns > 0)),
                          "mixed_groups": int(np.sum(returns.max(axis=1) > returns.min(axis=1))),
                          "decisions_scored": float(np.mean((np.asarray(batch.valid) > 0).sum(axis=1)))}
        print(f"[gradient-signal] {name}: paid success {outcomes[name]['paid_success']:.3f}, mixed groups "
              f"{outcomes[name]['mixed_groups']} of {len(returns)} ({timings[f'{name}_gradients_s']:.0f} s)", flush=True)
    gram = gs.gram_matrix(np.concatenate(vectors))
    del vectors
    stats = gs.statistics(gram, settings, reference="rest", batch_groups=args.batch_groups)
    intervals = gs.bootstrap(gram, settings, reference="rest", batch_groups=args.batch_groups, draws=args.bootstrap,
                             seed=args.seed)
    for name in args.settings:
        s, ci = stats[name], intervals[name]
        print(f"[gradient-signal] {name}: signal fraction {_fmt(s['signal_fraction'])} {_ci(ci['signal_fraction'])}, "
              f"cos of two {args.batch_groups}-group batches {_fmt(s['cos_at_batch'])} {_ci(ci['cos_at_batch'])}, "
              f"alignment with rest {_fmt(s['alignment'])} {_ci(ci['alignment'])}, one batch's cosine with rest's "
              f"gradient {_fmt(s['useful'])} {_ci(ci['useful'])}", flush=True)
    result = {
        "config": args.config, "policy": args.policy, "temperature": args.temperature, "proprio": "missing",
        "actions_per_decision": 4, "horizon_decisions": args.horizon, "groups": args.groups,
        "rest_groups": args.rest_groups,
        "group_size": args.group_size, "batch_groups": args.batch_groups, "scale_by_std": args.scale_by_std == "true",
        "loss_norm": rl.grpo.loss_norm, "seed": args.seed, "bootstrap_draws": args.bootstrap, "max_steps": probe.limit,
        "outcomes": outcomes, "statistics": stats, "intervals": intervals, "seconds": timings,
        "device": "CPU (MuJoCo C engine)",
        "gram": gram.tolist(), "rows": {n: s.rows.tolist() for n, s in settings.items()},
    }
    with open(os.path.join(args.out, "gradient_signal.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


def _fmt(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _ci(pair) -> str:
    return "[" + ", ".join("-inf" if not np.isfinite(x) else f"{x:.3f}" for x in pair) + "]"


if __name__ == "__main__":
    cli.run(main)
