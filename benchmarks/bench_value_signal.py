"""Does a fitted value rank a GRPO group's trajectories by their real outcome, or only different groups?

GRPO closes a short rollout with the value of its final frame (``rl.value``); within a group, only the differences
between its trajectories' values move the policy. A value can rank episodes well (different start states, different
phases) and still not rank the trajectories of one group, whose final frames differ by a few actions. This measures
both, on the MuJoCo C engine (no accelerator needed):

1. ``--value-episodes`` episodes of the policy from training-split states at rest (T, proprio masked, 4 actions a
   decision, up to the episode limit), every decision labelled with its episode's outcome; the value is fitted to
   most and its calibration reported on the rest (:mod:`sword_jax.rl.value`).
2. ``--groups`` keyframes of expert demonstrations, every phase, each rolled out ``--group-size`` times by the
   sampled policy to the episode limit. Decision ``c`` samples with ``fold_in(key, c)``, so each trajectory's first
   ``--horizon`` decisions are exactly the short rollout GRPO would have run, and its end says what that short rollout
   led to. The value is read at the frame after the horizon.

The figure that matters is the within-group AUC: over pairs of trajectories of the same group still running at the
horizon, one of which went on to succeed and one not, how often the value at the horizon put the successful one
higher (0.5: the value's differences inside a group are noise to GRPO). Beside it the AUC over every such pair
across groups, and how much of the value's spread lies within groups, for each fit of the value (``--value-steps``
x ``--fit-seeds``, all on the same episodes: how much of the ranking survives another fit)::

    python -m benchmarks.bench_value_signal --policy runs/p/policy_d50.npz --demos demos.hdf5 \\
        --out benchmarks/results/policy/value_signal_small_cpu
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Sequence

import jax
import numpy as np

from sword_jax import cli


def pair_auc(values: np.ndarray, success: np.ndarray, groups: np.ndarray | None) -> dict:
    """P(value of a later success > value of a later failure) over pairs (ties count a half), within the same group
    (``groups`` [n], group ids) or over all pairs (``groups`` None): ``{"auc", "pairs"}``; ``auc`` None without pairs."""
    values, success = np.asarray(values, np.float64), np.asarray(success, bool)
    wins = pairs = 0.0
    ids = [None] if groups is None else np.unique(groups)
    for g in ids:
        mask = np.ones(values.size, bool) if g is None else groups == g
        pos, neg = values[mask & success], values[mask & ~success]
        if pos.size and neg.size:
            diff = pos[:, None] - neg[None, :]
            wins += float(np.sum(diff > 0) + 0.5 * np.sum(diff == 0))
            pairs += float(diff.size)
    return {"auc": wins / pairs if pairs else None, "pairs": int(pairs)}


def _auc(auc: float | None) -> str:
    """An AUC to three decimals, ``n/a`` where there was no pair to judge (one class only)."""
    return "n/a" if auc is None else f"{auc:.3f}"


def within_share(values: np.ndarray, groups: np.ndarray) -> float:
    """The share of the values' variance that lies within groups (the mean within-group variance over the total)."""
    total = float(np.var(values))
    inner = float(np.mean([np.var(values[groups == g]) for g in np.unique(groups)]))
    return inner / total if total > 0 else 0.0


def add_probe_options(parser: argparse.ArgumentParser, *, groups: int) -> None:
    """The options every C-engine probe of GRPO's groups shares (this one, ``bench_grpo_gradient_signal``)."""
    parser.add_argument("--policy", required=True, help="the supervised policy (.npz)")
    parser.add_argument("--demos", required=True, help="expert demonstrations with recorded states (train.gen_data)")
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--out", required=True, help="the folder for the probe's JSON")
    parser.add_argument("--groups", type=int, default=groups)
    parser.add_argument("--group-size", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=4, help="decisions (4 actions each) of the short rollout")
    parser.add_argument("--temperature", type=float, default=0.5)
    parser.add_argument("--workers", type=int, default=2, help="C-engine processes")
    parser.add_argument("--seed", type=int, default=0)


class Probe:
    """The policy as GRPO's short rollouts run it on the C engine (T ``--temperature``, proprio masked,
    ``execute_steps`` actions a decision (4, the recipe's), no ensembling), its training-split starts at rest and
    its keyframe starts; :meth:`episodes` rolls start states out to ``max_steps`` (default: the config's episode
    limit), decision ``c`` sampling with ``fold_in(fold_in(key, stream), c)``. ``grpo``: further ``rl.grpo`` fields.

    Raises:
      sword_jax.cli.UsageError: ``execute_steps`` is not between 1 and the policy's chunk length."""

    def __init__(self, args: argparse.Namespace, tag: str, *, max_steps: int = 0, execute_steps: int = 4, **grpo):
        import dataclasses

        import configs
        from sim import tasks as sim_tasks
        from sword_jax.rl.env_rollout import make_act_fns
        from sword_jax.rl.params_io import load_params_npz
        from sword_jax.rl.policy import build_policy

        self.cfg, _ = configs.from_argv(["--config", args.config])
        base = self.cfg.rl
        if not 1 <= execute_steps <= base.chunk_len:
            raise cli.UsageError(f"{tag}: actions a decision must be in [1, {base.chunk_len}] (the policy's chunk), "
                                 f"got {execute_steps}")
        self.rl = dataclasses.replace(
            base, env=dataclasses.replace(base.env, execute_steps=execute_steps, action_ensemble=False),
            grpo=dataclasses.replace(base.grpo, temperature=args.temperature, group_size=args.group_size,
                                     rollout_batch=args.groups, **grpo),
            imagined=dataclasses.replace(base.imagined, keyframe_fraction=1.0))
        self.graphdef, params = build_policy(self.rl, seed=0)
        self.params = load_params_npz(args.policy, params)
        self.act = make_act_fns(self.graphdef, self.rl)
        self.limit = max_steps or self.cfg.sim.max_steps
        self.tasks = list(self.cfg.sim.tasks)
        self.pool = {t: sim_tasks.split_init_states(t, "train", sim_tasks.TRAIN_RESERVE, seed=self.cfg.sim.init_seed)
                     for t in self.tasks}
        self.args, self.tag, self.key = args, tag, jax.random.key(args.seed)
        self.seconds: dict[str, float] = {}

    def rest_starts(self, count: int, stream: str) -> list:
        """``count`` training-split states at rest, stratified over the tasks."""
        from sim.mjx_batch import stratified_train_starts
        from sword_jax.rng import stream_rng
        return stratified_train_starts(self.tasks, count, stream_rng(self.args.seed, stream), pool=self.pool)

    def keyframe_starts(self) -> list:
        """``--groups`` keyframes of every phase of the demonstrations (GRPO's sampler at step 0)."""
        from sim.dataset import read_dataset
        from sim.grpo_env import keyframe_picks
        from sword_jax.rl import data as rl_data
        demos = rl_data.load_episodes([self.args.demos], read=read_dataset)
        return [(t, np.asarray(flat, np.float64)) for t, flat in keyframe_picks(demos, self.rl, seed=self.args.seed,
                                                                                 step=0)]

    def episodes(self, starts: list, name: str, stream: int):
        from sim.lockstep import LockstepEnvs
        from sword_jax.rl.env_rollout import run_policy
        t0 = time.perf_counter()
        with LockstepEnvs(starts, resolution=self.cfg.sim.resolution, max_steps=self.limit, renderer="jax",
                          workers=self.args.workers) as envs:
            out = run_policy(self.act, self.params, envs, self.rl, key=jax.random.fold_in(self.key, stream),
                             greedy=False, max_steps=self.limit, episodes=starts, proprio="missing")
        self.seconds[f"{name}_rollouts_s"] = round(time.perf_counter() - t0, 1)
        print(f"[{self.tag}] {name}: {len(starts)} episodes, success {float(np.mean(out.success)):.3f} "
              f"({self.seconds[f'{name}_rollouts_s']:.0f} s)", flush=True)
        return out


def main(argv: Sequence[str] | None = None) -> dict:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_probe_options(parser, groups=32)
    parser.add_argument("--value-episodes", type=int, default=256)
    parser.add_argument("--value-steps", default="300", help="comma list: one fit of the value per entry and fit seed")
    parser.add_argument("--fit-seeds", default="0", help="comma list of the fits' seeds (initialisation and batches)")
    args = parser.parse_args(argv)
    try:
        fit_steps = [int(x) for x in args.value_steps.split(",") if x]
        fit_seeds = [int(x) for x in args.fit_seeds.split(",") if x]
    except ValueError:
        raise SystemExit(f"bench_value_signal: --value-steps and --fit-seeds are comma lists of integers, got "
                         f"{args.value_steps!r} and {args.fit_seeds!r}") from None
    if (min(args.value_episodes, args.groups, args.horizon) < 1 or args.group_size < 2 or not fit_steps
            or not fit_seeds or min(fit_steps) < 1):
        raise SystemExit("bench_value_signal: --value-episodes, --value-steps, --groups and --horizon must be >= 1, "
                         "--group-size >= 2")

    import dataclasses

    from sim.mjx_batch import episode_starts
    from sword_jax.rl.policy import tokenize_instructions
    from sword_jax.rl.value import (as_value, build_value, calibration, decision_samples, fit_value, predict,
                                    split_episodes)

    probe = Probe(args, "value-signal")
    rl = probe.rl
    os.makedirs(args.out, exist_ok=True)

    # 1. the value, fitted to the policy's own episodes from rest
    rest = probe.rest_starts(args.value_episodes, "value_signal/rest")
    real = probe.episodes(rest, "value episodes", 1)
    tokens = tokenize_instructions(episode_starts(rest)[1], rl.policy.max_instruction_bytes)
    data = decision_samples(np.asarray(real.obs_frames), np.asarray(real.valid), tokens, np.asarray(real.success))
    fit, held = split_episodes(data, rl.value.holdout, np.random.default_rng(args.seed))
    values = {}
    for steps in fit_steps:
        for fit_seed in fit_seeds:
            fit_rl = dataclasses.replace(rl, value=dataclasses.replace(rl.value, steps=steps))
            value_graphdef, value_params = build_value(fit_rl, seed=fit_seed)
            value_params, metrics = fit_value(value_graphdef, value_params, fit_rl, fit, seed=fit_seed,
                                              log=lambda _: None)
            values[f"steps{steps}_seed{fit_seed}"] = (as_value(value_graphdef, value_params), metrics["loss"])

    # 2. groups from keyframes of every phase, each trajectory to the episode limit
    starts = [start for start in probe.keyframe_starts() for _ in range(args.group_size)]
    grouped = probe.episodes(starts, "groups", 2)
    valid = np.asarray(grouped.valid) > 0
    decided = valid.sum(axis=1)  # decisions each trajectory made before it ended
    running = decided > args.horizon  # still going after the short rollout: its frame after the horizon exists
    g_tokens = tokenize_instructions(episode_starts(starts)[1], rl.policy.max_instruction_bytes)
    frames = np.asarray(grouped.obs_frames)[:, args.horizon]
    at_frames = decision_samples(frames[:, None], np.ones((len(starts), 1)), g_tokens, np.asarray(grouped.success))
    success = np.asarray(grouped.success).astype(bool)
    group_id = np.repeat(np.arange(args.groups), args.group_size)
    keep = running
    fits = {}
    for name, (value, loss) in values.items():
        at_horizon = predict(value, at_frames)[keep]
        held_report = calibration(predict(value, held), held.labels)
        fits[name] = {"fit_loss": loss, "held_out": held_report, "value_at_horizon_mean": float(np.mean(at_horizon)),
                      "within_group_auc": pair_auc(at_horizon, success[keep], group_id[keep]),
                      "across_all_auc": pair_auc(at_horizon, success[keep], None),
                      "within_group_variance_share": within_share(at_horizon, group_id[keep])}
        w, a = fits[name]["within_group_auc"], fits[name]["across_all_auc"]
        print(f"[value-signal] {name}: held-out AUC {_auc(held_report['auc'])}, Brier {held_report['brier']:.4f} "
              f"(constant {held_report['brier_constant']:.4f}); at the horizon: within-group AUC {_auc(w['auc'])} over "
              f"{w['pairs']} pairs, across all {_auc(a['auc'])} over {a['pairs']}; within-group share of the variance "
              f"{fits[name]['within_group_variance_share']:.3f}", flush=True)
    result = {
        "config": args.config, "policy": args.policy, "temperature": args.temperature, "horizon_decisions": args.horizon,
        "actions_per_decision": 4, "value_episodes": args.value_episodes,
        "value_episode_success": float(np.mean(real.success)), "value_fit_episodes": int(len(np.unique(fit.episode))),
        "groups": args.groups, "group_size": args.group_size,
        "succeeded_within_horizon": float(np.mean(success & ~running)), "running_at_horizon": int(keep.sum()),
        "later_success_of_running": float(np.mean(success[keep])) if keep.any() else None,
        "groups_split_by_later_outcome": int(sum(1 for g in range(args.groups)
                                                 if len(set(success[keep & (group_id == g)])) == 2)),
        "fits": fits, "seed": args.seed, "device": "CPU (MuJoCo C engine)",
    }
    with open(os.path.join(args.out, "value_signal.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    cli.run(main)
