"""Where does the policy fail from rest, and where do GRPO's short rollouts carry a signal? (C engine, CPU)

GRPO on short rollouts branched from the policy's own states (4 decisions of 4 actions) learns what it is paid for,
yet barely lifts success from rest, while whole episodes from rest do. One explanation is where the two put their
signal: a group of 16-action rollouts can only have mixed outcomes where success is within 16 actions, that is,
late in the task, while the episodes from rest may fail earlier. This measures both on the MuJoCo C engine, for the
policy as GRPO's rollouts run it (T ``--temperature``, proprio masked, ``--actions-per-decision`` actions a decision
(4 by default, the recipe's), no ensembling):

1. ``--episodes`` episodes from training-split states at rest, to the episode limit. After every decision the
   target bowl, the plate and whether both finger pads touch the bowl are read
   (:meth:`sim.lockstep.LockstepEnvs.poses`). Each episode's furthest stage (:func:`episode_stages`): ``success``;
   ``never grasped`` (reach or grasp failed); ``grasped, never over the plate`` (the carry failed); ``over the
   plate, not placed`` (held within ``--over-m`` of the plate in xy; the place or release failed).
2. ``--starts`` states drawn uniformly from the decisions of those episodes still running, each rolled out
   ``--group-size`` times for ``--horizon`` decisions, as GRPO's branched short rollouts are. Each start has a
   stage (:func:`start_stages`: ``before the grasp``, ``grasped``, ``over the plate``, ``after a release``), and per
   stage the benchmark counts the starts whose group had mixed outcomes, the groups that carry GRPO's signal.
   ``--branch-from rest`` branches instead from the episodes' first states, at rest (``rl.env.starts=rest``: GRPO
   from rest cut at the horizon), one start per episode.

Both are also broken down by task (``per_task``): each task's stages from rest and decisions to success, and its
starts, mixed groups and paid success. A task whose groups rarely mix gets little of an update that moves the
policy's shared weights for every task.

If many failures from rest come before the grasp and the mixed groups almost all start after it, a short rollout's
signal is for a part of the task where the policy fails less::

    python -m benchmarks.bench_failure_phases --policy runs/p/policy_d50.npz \\
        --out benchmarks/results/policy/failure_phases_small_cpu [--record]

``--record`` writes ``policy_failure_stages_small`` to ``benchmarks/results/latest.json``: its value is the share
of failures from rest whose bowl was never grasped.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic

EPISODE_STAGES = ("success", "never grasped", "grasped, never over the plate", "over the plate, not placed")
START_STAGES = ("before the grasp", "grasped", "over the plate", "after a release")


def _over(bowl: np.ndarray, plate: np.ndarray, radius: float) -> np.ndarray:
    return np.linalg.norm(np.asarray(bowl, float)[..., :2] - np.asarray(plate, float)[..., :2], axis=-1) < radius


def episode_stages(held: np.ndarray, bowl: np.ndarray, plate: np.ndarray, success: np.ndarray, *,
                   over_m: float = 0.03) -> np.ndarray:
    """Each episode's furthest stage (an index into :data:`EPISODE_STAGES`) from whether both finger pads touched the
    target bowl ``held [n, t]``, the bowl's and the plate's origins ``bowl``/``plate [n, t, 3]`` at its decisions
    (``t = 0``: the start; a finished episode repeats its last read) and ``success [n]``. Over the plate: held with
    the bowl's centre within ``over_m`` of the plate's in xy."""
    held, success = np.asarray(held, bool), np.asarray(success, bool)
    if held.ndim != 2 or np.shape(bowl) != held.shape + (3,) or np.shape(plate) != np.shape(bowl) \
            or success.shape != held.shape[:1]:
        raise ValueError(f"episode_stages: need held [n, t], bowl and plate [n, t, 3] and success [n], got "
                         f"{held.shape}, {np.shape(bowl)}, {np.shape(plate)}, {success.shape}")
    over = held & _over(bowl, plate, over_m)
    return np.where(success, 0, np.where(~held.any(1), 1, np.where(~over.any(1), 2, 3)))


def start_stages(held: np.ndarray, bowl: np.ndarray, plate: np.ndarray, held_before: np.ndarray, *,
                 over_m: float = 0.03) -> np.ndarray:
    """The stage of mid-episode states (an index into :data:`START_STAGES`) from whether the bowl is held now
    ``held [n]``, where it and the plate are ``bowl``/``plate [n, 3]`` and whether it was held earlier in the
    episode ``held_before [n]``: held over the plate, held, let go after a grasp, or not yet grasped."""
    held = np.asarray(held, bool)
    return np.where(held, np.where(_over(bowl, plate, over_m), 2, 1), np.where(np.asarray(held_before, bool), 3, 0))


class Recording:
    """``envs`` (a :class:`sim.lockstep.LockstepEnvs`) as :func:`sword_jax.rl.env_rollout.run_policy` drives it,
    reading :meth:`~sim.lockstep.LockstepEnvs.poses` after the reset and after every decision (``poses``: one dict
    per read)."""

    def __init__(self, envs: Any):
        self.envs, self.poses = envs, []
        self.n, self.language = envs.n, envs.language

    def reset(self, *args):
        out = self.envs.reset(*args)
        self.language = self.envs.language
        self.poses = [self.envs.poses()]
        return out

    def step(self, actions):
        out = self.envs.step(actions)
        self.poses.append(self.envs.poses())
        return out

    def stacked(self, key: str, steps: int) -> np.ndarray:
        """``key`` of every read ``[n, steps + 1, ...]``, the last read repeated past the episodes' end."""
        reads = [p[key] for p in self.poses] + [self.poses[-1][key]] * (steps + 1 - len(self.poses))
        return np.stack(reads[: steps + 1], axis=1)


def rollouts(probe: Any, starts: list, *, max_steps: int, stream: int, workers: int, recording: type = Recording):
    """The policy from ``starts`` for ``max_steps`` actions; ``(Rollout, recording)`` (a :class:`Recording` or the
    subclass given)."""
    import jax

    from sim.lockstep import LockstepEnvs
    from sword_jax.rl.env_rollout import run_policy

    with LockstepEnvs(starts, resolution=probe.cfg.sim.resolution, max_steps=max_steps, renderer="jax",
                      workers=workers) as envs:
        rec = recording(envs)
        out = run_policy(probe.act, probe.params, rec, probe.rl, key=jax.random.fold_in(probe.key, stream),
                         greedy=False, max_steps=max_steps, episodes=starts, proprio="missing")
    return out, rec


def branch_points(done: np.ndarray, count: int, rng: np.random.Generator, *, at_rest: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` (episode, decision) pairs drawn uniformly without replacement from the decisions at which an
    episode was still running (``done [n, t]``: done before decision ``t``); ``at_rest``: only the episodes' first
    decisions (their start states), so at most one start per episode."""
    running = ~np.asarray(done, bool)
    if at_rest:
        running = running & (np.arange(running.shape[1]) == 0)
    ep, at = np.nonzero(running)
    if ep.size == 0:
        raise ValueError("branch_points: no episode was running at any decision")
    pick = rng.choice(ep.size, size=min(count, ep.size), replace=False)
    return ep[pick], at[pick]


def summarise(stages: np.ndarray, start_stage: np.ndarray, group_success: np.ndarray,
              success_decision: np.ndarray, grasp_decision: np.ndarray, tasks: np.ndarray | None = None,
              start_tasks: np.ndarray | None = None) -> dict:
    """Counts and shares of :func:`main`'s two measurements; with the episodes' ``tasks [n]`` and the starts'
    ``start_tasks [starts]`` also per task (``per_task``, keyed by the task id)."""
    failed = stages != 0
    episodes = {name: int(np.sum(stages == i)) for i, name in enumerate(EPISODE_STAGES)}
    failures = {name: (int(np.sum(stages == i)) / max(1, int(failed.sum()))) for i, name in enumerate(EPISODE_STAGES)
                if i}
    mixed = group_success.any(1) & ~group_success.all(1)
    per_start = {}
    for i, name in enumerate(START_STAGES):
        mine = start_stage == i
        per_start[name] = {"starts": int(mine.sum()), "mixed_groups": int(np.sum(mixed & mine)),
                           "paid_success": float(group_success[mine].mean()) if mine.any() else None}
    ok = success_decision >= 0
    grasped_ok = ok & (grasp_decision >= 0)
    return {"episodes": int(stages.size), "success": float(np.mean(stages == 0)), "episode_stages": episodes,
            "failure_shares": failures, "starts": per_start, "mixed_groups": int(mixed.sum()),
            "mixed_after_the_grasp": float(np.sum(mixed & (start_stage != 0)) / max(1, int(mixed.sum()))),
            "decisions_to_success": _quartiles(success_decision[ok]),
            "decisions_from_grasp_to_success": _quartiles(success_decision[grasped_ok] - grasp_decision[grasped_ok]),
            **({"per_task": per_task(stages, group_success, success_decision, tasks, start_tasks)}
               if tasks is not None else {})}


def per_task(stages: np.ndarray, group_success: np.ndarray, success_decision: np.ndarray, tasks: np.ndarray,
             start_tasks: np.ndarray) -> dict[str, dict]:
    """Per task id (in order): its episodes from rest, their success and furthest stages, the median decisions to a
    success, and its starts, their mixed groups and paid success."""
    tasks, start_tasks = np.asarray(tasks), np.asarray(start_tasks)
    if tasks.shape != stages.shape or start_tasks.shape != group_success.shape[:1]:
        raise ValueError(f"per_task: need a task per episode {stages.shape} and per start {group_success.shape[:1]}, "
                         f"got {tasks.shape} and {start_tasks.shape}")
    mixed = group_success.any(1) & ~group_success.all(1)
    out = {}
    for t in sorted(set(tasks.tolist()) | set(start_tasks.tolist())):
        mine, starts = tasks == t, start_tasks == t
        won = success_decision[mine & (success_decision >= 0)]
        out[str(t)] = {"episodes": int(mine.sum()), "success": float(np.mean(stages[mine] == 0)) if mine.any() else None,
                       "episode_stages": {name: int(np.sum(stages[mine] == i)) for i, name in enumerate(EPISODE_STAGES)},
                       "decisions_to_success": float(np.median(won)) if won.size else None,
                       "starts": int(starts.sum()), "mixed_groups": int(np.sum(mixed & starts)),
                       "paid_success": float(group_success[starts].mean()) if starts.any() else None}
    return out


def _quartiles(x: np.ndarray) -> list[float] | None:
    return [float(q) for q in np.percentile(x, [25, 50, 75])] if np.size(x) else None


def parse(argv: Sequence[str]) -> argparse.Namespace:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, help="the policy's parameters (.npz)")
    parser.add_argument("--out", required=True, help="folder for failure_phases.json")
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--episodes", type=int, default=200, help="episodes from rest (stratified over the tasks)")
    parser.add_argument("--starts", type=int, default=128, help="branch points for the short rollouts")
    parser.add_argument("--group-size", type=int, default=8)
    parser.add_argument("--horizon", type=int, default=4, help="decisions of a short rollout")
    parser.add_argument("--actions-per-decision", type=int, default=4,
                        help="actions executed per policy call, in the episodes and the short rollouts (4: GRPO's "
                             "recipe; 8: a whole chunk, as a world model that predicts 8 frames a call would run)")
    parser.add_argument("--branch-from", choices=("running", "rest"), default="running",
                        help="the short rollouts' starts: decisions of the running episodes, or their first states")
    parser.add_argument("--temperature", type=float, default=0.5)
    parser.add_argument("--over-m", type=float, default=0.03, help="bowl within this far of the plate in xy: over it")
    parser.add_argument("--max-steps", type=int, default=0, help="the episode limit in actions (0: the config's)")
    parser.add_argument("--workers", type=int, default=0, help="C-engine processes (0: this one)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--record", action="store_true", help="write policy_failure_stages_small to latest.json")
    args = parser.parse_args(argv)
    if min(args.episodes, args.starts, args.horizon) < 1 or args.group_size < 2 or args.max_steps < 0:
        raise cli.UsageError("--episodes, --starts and --horizon must be >= 1, --group-size >= 2 and --max-steps >= 0")
    check_policy_args(args)
    return args


def check_policy_args(args: argparse.Namespace) -> None:
    """Refuses (``cli.UsageError``) a ``--temperature`` or ``--over-m`` not above 0 and a ``--policy`` that is not a
    file: the arguments of the benches that run the policy's episodes as this one does."""
    if not 0 < args.temperature or args.over_m <= 0:
        raise cli.UsageError("--temperature and --over-m must be > 0")
    if not os.path.isfile(args.policy):
        raise cli.UsageError(f"--policy {args.policy}: no such file")


def main(argv: Sequence[str] | None = None) -> dict:
    import sys

    args = parse(sys.argv[1:] if argv is None else list(argv))
    from benchmarks.bench_value_signal import Probe
    from sword_jax.rl.env_rollout import max_decisions

    probe = Probe(argparse.Namespace(config=args.config, temperature=args.temperature, group_size=args.group_size,
                                     groups=args.starts, policy=args.policy, seed=args.seed, workers=args.workers),
                  "failure-phases", max_steps=args.max_steps, execute_steps=args.actions_per_decision)
    limit, k = probe.limit, probe.rl.env.execute_steps
    os.makedirs(args.out, exist_ok=True)
    seconds = {}

    t0 = time.perf_counter()
    rest = probe.rest_starts(args.episodes, "failure_phases/rest")
    real, rec = rollouts(probe, rest, max_steps=limit, stream=1, workers=args.workers)
    seconds["rest_s"] = round(time.perf_counter() - t0, 1)
    steps = max_decisions(probe.rl, limit)
    bowl, plate = rec.stacked("bowl", steps), rec.stacked("plate", steps)
    held = rec.stacked("held", steps)
    success = np.asarray(real.success, bool)
    stages = episode_stages(held, bowl, plate, success, over_m=args.over_m)
    valid = np.asarray(real.valid) > 0  # [n, steps]: running before each decision (0 past the last one taken)
    decided = valid.sum(1).astype(int)  # decisions taken; a success is at the last
    success_decision = np.where(success, decided, -1)
    grasp_decision = np.where(held.any(1), held.argmax(1), -1)
    print(f"[failure-phases] {len(rest)} episodes from rest: success {success.mean():.3f}; stages "
          + ", ".join(f"{n} {int(np.sum(stages == i))}" for i, n in enumerate(EPISODE_STAGES))
          + f" ({seconds['rest_s']:.0f} s)", flush=True)

    t0 = time.perf_counter()
    ep, at = branch_points(~valid, args.starts, np.random.default_rng(args.seed), at_rest=args.branch_from == "rest")
    state = rec.stacked("state", steps)
    start_stage = start_stages(held[ep, at], bowl[ep, at], plate[ep, at],
                               np.array([held[e, :a].any() for e, a in zip(ep, at)]), over_m=args.over_m)
    tasks = np.array([int(t) for t, _ in rest])  # each episode's task id
    branched = [(int(tasks[e]), state[e, a]) for e, a in zip(ep, at) for _ in range(args.group_size)]
    short, _ = rollouts(probe, branched, max_steps=args.horizon * k, stream=2, workers=args.workers)
    group_success = np.asarray(short.success, bool).reshape(-1, args.group_size)
    seconds["short_s"] = round(time.perf_counter() - t0, 1)
    result = {"config": probe.cfg.name, "policy": args.policy, "temperature": args.temperature, "proprio": "missing",
              "actions_per_decision": k, "episode_limit": limit, "horizon_decisions": args.horizon,
              "branch_from": args.branch_from,
              "group_size": args.group_size, "over_m": args.over_m, "seed": args.seed,
              "device": "CPU (MuJoCo C engine)", "seconds": seconds,
              **summarise(stages, start_stage, group_success, success_decision, grasp_decision,
                          tasks=tasks, start_tasks=tasks[ep])}
    for name, s in result["starts"].items():
        print(f"[failure-phases] starts {name}: {s['starts']}, mixed groups {s['mixed_groups']}"
              + (f", paid success {s['paid_success']:.3f}" if s["paid_success"] is not None else ""), flush=True)
    print("[failure-phases] failures from rest: " + ", ".join(f"{n} {v:.2f}" for n, v in result["failure_shares"]
                                                                 .items())
          + f"; mixed groups starting after the grasp {result['mixed_after_the_grasp']:.2f} of {result['mixed_groups']} "
          f"({seconds['short_s']:.0f} s)", flush=True)
    for t, s in result["per_task"].items():
        print(f"[failure-phases] task {t}: success {s['success']:.2f} of {s['episodes']}, never grasped "
              f"{s['episode_stages']['never grasped']}, decisions to success {s['decisions_to_success']}; starts "
              f"{s['starts']}, mixed {s['mixed_groups']}"
              + (f", paid {s['paid_success']:.3f}" if s["paid_success"] is not None else ""), flush=True)
    write_json_atomic(os.path.join(args.out, "failure_phases.json"), result)
    if args.record:
        from benchmarks import common

        common.merge_results({"policy_failure_stages_small": common.record(
            "policy_failure_stages_small", result["failure_shares"]["never grasped"], None,
            unit="share of the sampled policy's failures from rest whose bowl was never grasped (C engine)",
            **{k: result[k] for k in ("episodes", "success", "failure_shares", "starts", "mixed_groups",
                                      "mixed_after_the_grasp", "decisions_to_success",
                                      "decisions_from_grasp_to_success", "horizon_decisions", "temperature")})})
    return result


if __name__ == "__main__":
    cli.run(main)
