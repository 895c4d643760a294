"""Do the frames determine what the policy's actions lead to? (C engine, CPU)

GRPO in the world model fails where the policy reaches for and grasps the bowl: there, acting on the world model's
frames, its actions keep 13-17% of what reality pays them on real frames, against 57-63% once the bowl is held
(RESULTS, table ``grpo-by-start``), and a larger world model predicts the policy's unseen rollouts little better
(table ``world-model-size``). A world model conditioned on frames and actions can only be as right as the frames
determine the outcome. This measures how far they do, with no world model at all: the same recorded actions are
replayed from the same state with one object moved by a fraction of a pixel, a change a frame of
``sim.resolution`` pixels cannot show (or barely: an edge pixel may change), and the outcome is compared.

1. ``--episodes`` episodes of the policy from training-split states at rest, as GRPO's rollouts run it (T
   ``--temperature``, proprio masked, ``--actions-per-decision`` actions a decision, no ensembling), recording the
   state before every decision and the actions executed.
2. ``--starts`` (episode, decision) pairs drawn uniformly from the decisions of episodes still running (within
   their first ``--starts-before`` decisions, where given). From each,
   the actions that episode executed next (up to ``--horizon`` decisions, GRPO's imagined horizon) are replayed
   open loop on the C engine: once from the recorded state (the reference outcome: success within those actions),
   then ``--draws`` times per scale of ``--scales-px`` with an object moved in the table plane by that many pixels
   of the agent-view camera at the object's depth (:func:`metres_per_pixel`), in a random direction: the target
   bowl (``bowl``) where the finger pads do not touch it, and the plate (``plate``) everywhere. ``--tiny-m`` adds a
   displacement far below a pixel (the dynamics' own sensitivity).
3. Per start stage (``bench_failure_phases``: before the grasp, grasped, over the plate, after a release) and per
   bin of the start's action step in its episode (0-23, 24-47, 48+, the bins table ``grpo-by-start`` puts
   keyframes in): the reference success, the share of perturbed replays whose outcome differs from it
   (``flipped``), the share of the reference successes' perturbed replays that still succeed (``kept``) and of the
   reference failures' that succeed (``false_success``); and each start's own counts (``per_start``).

A start whose outcome flips when the bowl moves by half a pixel is one whose future the frames do not fix: any
world model conditioned on them, however large, predicts it only as a distribution::

    python -m benchmarks.bench_outcome_determinacy --policy runs/p/policy_d50.npz \\
        --out benchmarks/results/policy/outcome_determinacy_small_cpu

Not recorded to ``latest.json``.
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

OBJECTS = ("bowl", "plate")
STEP_BINS = ((0, 24), (24, 48), (48, None))  # the start's action step, as table grpo-by-start bins its starts


def metres_per_pixel(model: Any, data: Any, point: np.ndarray, resolution: int, camera: str = "agentview") -> float:
    """The width in metres of one pixel of ``camera`` (``resolution`` pixels high, a pinhole of the model's
    ``fovy``) at the depth of the world ``point`` in ``data``'s pose; raises ``ValueError`` for a point behind the
    camera."""
    cam = model.camera(camera).id
    axis = np.asarray(data.cam_xmat[cam]).reshape(3, 3)[:, 2]  # a MuJoCo camera looks along its -z
    depth = float(-(np.asarray(point, np.float64) - np.asarray(data.cam_xpos[cam])) @ axis)
    if depth <= 0:
        raise ValueError(f"metres_per_pixel: the point lies behind camera {camera!r} (depth {depth:.3f} m)")
    return 2.0 * depth * float(np.tan(np.deg2rad(model.cam_fovy[cam]) / 2)) / resolution


def free_joint_qpos(model: Any, body: int) -> int:
    """The qpos address of ``body``'s free joint (its x; y and z follow); ``ValueError`` if it has none."""
    import mujoco

    adr = int(model.body_jntadr[body])
    if model.body_jntnum[body] < 1 or model.jnt_type[adr] != mujoco.mjtJoint.mjJNT_FREE:
        raise ValueError(f"free_joint_qpos: body {model.body(body).name!r} has no free joint")
    return int(model.jnt_qposadr[adr])


def displaced(flat: np.ndarray, qpos_adr: int, offset_xy: np.ndarray) -> np.ndarray:
    """A flat state ``[time, qpos, qvel]`` with the free joint at ``qpos_adr`` moved by ``offset_xy`` (metres)."""
    out = np.array(flat, np.float64)
    out[1 + qpos_adr: 3 + qpos_adr] += np.asarray(offset_xy, np.float64)
    return out


def replay(env: Any, flat: np.ndarray, actions: np.ndarray) -> bool:
    """``actions [m, 7]`` executed open loop from the flat state ``flat`` on ``env`` (a
    :class:`sim.env.CpuEnv`); whether the task was solved on the way (it stops there)."""
    state = env.restore(flat)
    if state.done:
        return True
    for a in actions:
        state = env.step_inplace(state, np.clip(a, -1.0, 1.0))
        if state.done:
            return True
    return False


_ENVS: dict[tuple[int, int], Any] = {}


def _env(task: int, resolution: int) -> Any:
    if (task, resolution) not in _ENVS:
        from sim.config import SimConfig
        from sim.env import CpuEnv
        _ENVS[task, resolution] = CpuEnv(SimConfig(backend="cpu", resolution=resolution), task)
    return _ENVS[task, resolution]


def _replays(job: tuple[int, int, np.ndarray, np.ndarray, list[tuple[str, np.ndarray]]]) -> list[bool]:
    """One start's replays: ``(task, resolution, flat, actions, [(object or "", offset_xy), ...])``."""
    task, resolution, flat, actions, moves = job
    env = _env(task, resolution)
    adr = {"bowl": free_joint_qpos(env.mj_model, env.bowl_body), "plate": free_joint_qpos(env.mj_model, env.plate_body)}
    return [replay(env, flat if not obj else displaced(flat, adr[obj], off), actions) for obj, off in moves]


def directions(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` unit vectors in the plane, uniform in angle."""
    angle = rng.uniform(0.0, 2.0 * np.pi, count)
    return np.stack([np.cos(angle), np.sin(angle)], axis=1)


def summarise(groups: dict[str, np.ndarray], reference: np.ndarray, succeeded: dict[str, np.ndarray]) -> dict:
    """Per group (a boolean mask over starts): its starts and reference success and, per perturbation
    (``succeeded[name]`` ``[starts, draws]``: 1.0 where a perturbed replay succeeded, NaN where not replayed), the
    share of its perturbed replays whose outcome differs from the reference (``flipped``), of its starts with any
    flip, of the perturbed replays of its reference successes that still succeed (``kept``) and of those of its
    reference failures that succeed (``false_success``); each ``None`` where nothing was replayed."""
    def share(x: np.ndarray) -> float | None:
        x = x[~np.isnan(x)]
        return float(x.mean()) if x.size else None

    out = {}
    for name, mask in groups.items():
        ref = reference[mask]
        row = {"starts": int(mask.sum()), "reference_success": float(ref.mean()) if mask.any() else None,
               "flipped": {}, "starts_with_a_flip": {}, "kept": {}, "false_success": {}, "measured_starts": {}}
        for key, got in succeeded.items():
            got = got[mask]
            measured = ~np.isnan(got).all(1)
            flip = np.where(np.isnan(got), np.nan, got != ref[:, None])
            row["flipped"][key] = share(flip[measured])
            row["starts_with_a_flip"][key] = (float((np.nan_to_num(flip[measured]) > 0).any(1).mean())
                                              if measured.any() else None)
            row["kept"][key] = share(got[measured & ref])
            row["false_success"][key] = share(got[measured & ~ref])
            row["measured_starts"][key] = int(measured.sum())
        out[name] = row
    return out


def parse(argv: Sequence[str]) -> argparse.Namespace:
    p = cli.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--policy", required=True, help="the supervised policy (.npz)")
    p.add_argument("--config", default="sword:small")
    p.add_argument("--out", required=True, help="folder for outcome_determinacy.json")
    p.add_argument("--episodes", type=int, default=120)
    p.add_argument("--starts", type=int, default=256)
    p.add_argument("--horizon", type=int, default=12, help="decisions replayed from each start")
    p.add_argument("--starts-before", type=int, default=0,
                   help="draw starts only from the episodes' first this many decisions (0: from all)")
    p.add_argument("--actions-per-decision", type=int, default=4)
    p.add_argument("--temperature", type=float, default=0.5)
    p.add_argument("--draws", type=int, default=4, help="perturbed replays per start, object and scale")
    p.add_argument("--scales-px", default="0.25,0.5,1,2", help="displacements in pixels of the agent-view camera")
    p.add_argument("--tiny-m", type=float, default=1e-6, help="a displacement in metres far below a pixel (0: none)")
    p.add_argument("--over-m", type=float, default=0.05, help="over the plate: bowl within this of it in xy")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    try:
        args.scales_px = [float(s) for s in args.scales_px.split(",") if s]
    except ValueError:
        raise cli.UsageError(f"--scales-px must be a comma list of numbers, got {args.scales_px!r}") from None
    if (args.episodes < 1 or args.starts < 1 or args.horizon < 1 or args.draws < 1 or args.tiny_m < 0
            or args.starts_before < 0 or args.workers < 1 or any(s <= 0 for s in args.scales_px)
            or not args.scales_px):
        raise cli.UsageError("--episodes, --starts, --horizon, --draws and --workers must be >= 1, --scales-px "
                             "positive, --tiny-m and --starts-before >= 0")
    from benchmarks.bench_failure_phases import check_policy_args

    check_policy_args(args)
    return args


def main(argv: Sequence[str] | None = None) -> dict:
    import sys
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    args = parse(sys.argv[1:] if argv is None else list(argv))
    from benchmarks.bench_failure_phases import START_STAGES, Recording, branch_points, rollouts, start_stages
    from benchmarks.bench_value_signal import Probe
    from sword_jax.rl.env_rollout import max_decisions

    class Acting(Recording):
        """:class:`Recording` that also keeps every decision's executed actions."""

        def reset(self, *a):
            self.actions = []
            return super().reset(*a)

        def step(self, actions):
            self.actions.append(np.asarray(actions, np.float64))
            return super().step(actions)

    probe = Probe(argparse.Namespace(config=args.config, temperature=args.temperature, group_size=8,
                                     groups=8, policy=args.policy, seed=args.seed, workers=args.workers),
                  "outcome-determinacy", execute_steps=args.actions_per_decision)
    limit, k, resolution = probe.limit, probe.rl.env.execute_steps, probe.cfg.sim.resolution
    os.makedirs(args.out, exist_ok=True)
    seconds = {}

    t0 = time.perf_counter()
    rest = probe.rest_starts(args.episodes, "outcome_determinacy/rest")
    real, rec = rollouts(probe, rest, max_steps=limit, stream=1, workers=args.workers, recording=Acting)
    seconds["episodes_s"] = round(time.perf_counter() - t0, 1)
    steps = max_decisions(probe.rl, limit)
    state, held = rec.stacked("state", steps), rec.stacked("held", steps)
    bowl, plate = rec.stacked("bowl", steps), rec.stacked("plate", steps)
    actions = np.stack(rec.actions, axis=1)  # [n, taken, k, 7]
    valid = np.asarray(real.valid)[:, : actions.shape[1]] > 0
    tasks = np.array([int(t) for t, _ in rest])
    print(f"[outcome-determinacy] {len(tasks)} episodes from rest: success {np.mean(real.success):.3f} "
          f"({seconds['episodes_s']:.0f} s)", flush=True)

    rng = np.random.default_rng(args.seed)
    window = valid.copy()
    if args.starts_before:
        window[:, args.starts_before:] = False
    ep, at = branch_points(~window, args.starts, rng)
    stage = start_stages(held[ep, at], bowl[ep, at], plate[ep, at],
                         np.array([held[e, :a].any() for e, a in zip(ep, at)]), over_m=args.over_m)
    scales = [(f"{s:g} px", s, None) for s in args.scales_px] + ([(f"{args.tiny_m:g} m", None, args.tiny_m)]
                                                                   if args.tiny_m else [])
    jobs, keys, pixel_m = [], [], {o: [] for o in OBJECTS}
    for e, a in zip(ep, at):
        run = valid[e, a: a + args.horizon]
        acts = actions[e, a: a + int(run.sum())].reshape(-1, actions.shape[-1])
        env = _env(int(tasks[e]), resolution)
        data = env.restore(state[e, a]).data
        m_px = {o: metres_per_pixel(env.mj_model, data, pos[e, a], resolution) for o, pos in (("bowl", bowl),
                                                                                                ("plate", plate))}
        for o in OBJECTS:
            pixel_m[o].append(m_px[o])
        moves: list[tuple[str, np.ndarray]] = [("", np.zeros(2))]
        start_keys = [None]
        for o in OBJECTS:
            if o == "bowl" and held[e, a]:
                continue  # moving a held bowl would push it into the fingers
            for name, px, metres in scales:
                unit = directions(rng, args.draws)
                for d in unit:
                    moves.append((o, d * (metres if metres is not None else px * m_px[o])))
                    start_keys.append(f"{o}, {name}")
        jobs.append((int(tasks[e]), resolution, state[e, a], acts, moves))
        keys.append(start_keys)
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=get_context("spawn")) as pool:
        outcomes = list(pool.map(_replays, jobs, chunksize=4))
    seconds["replays_s"] = round(time.perf_counter() - t0, 1)

    names = [f"{o}, {n}" for o in OBJECTS for n, _, _ in scales]
    reference = np.array([o[0] for o in outcomes], bool)
    succeeded = {n: np.full((len(jobs), args.draws), np.nan) for n in names}
    for i, (out, ks) in enumerate(zip(outcomes, keys)):
        seen: dict[str, int] = {}
        for got, key in zip(out[1:], ks[1:]):
            j = seen.get(key, 0)
            succeeded[key][i, j] = float(got)
            seen[key] = j + 1
    # the recorded episode's own outcome over the same actions: a replay from the restored state should repeat it
    recorded = np.array([bool(real.success[e]) and valid[e, a:].sum() <= args.horizon for e, a in zip(ep, at)])
    step = at * k
    groups = {f"stage: {n}": stage == i for i, n in enumerate(START_STAGES)}
    groups.update({f"start's step in its episode: {lo}-{hi - 1}" if hi else f"start's step in its episode: {lo}+":
                   (step >= lo) & (step < (hi if hi else np.inf)) for lo, hi in STEP_BINS})
    groups["all"] = np.ones(len(jobs), bool)
    result = {"config": probe.cfg.name, "policy": args.policy, "temperature": args.temperature, "proprio": "missing",
              "actions_per_decision": k, "episode_limit": limit, "horizon_decisions": args.horizon, "over_m": args.over_m,
              "starts_before_decision": args.starts_before or None, "episodes": len(tasks),
              "episode_success": float(np.mean(real.success)), "starts": len(jobs),
              "draws": args.draws, "scales_px": args.scales_px, "tiny_m": args.tiny_m, "resolution": resolution,
              "metres_per_pixel": {o: {"median": float(np.median(v)), "min": float(np.min(v)),
                                       "max": float(np.max(v))} for o, v in pixel_m.items()},
              "replay_repeats_recorded": float(np.mean(reference == recorded)),
              "seed": args.seed, "device": "CPU (MuJoCo C engine)", "seconds": seconds,
              "groups": summarise(groups, reference, succeeded),
              # per start: its stage, its action step in its episode, its reference outcome and, per perturbation,
              # how many of its perturbed replays succeeded (None where none was replayed)
              "per_start": {"stage": [START_STAGES[i] for i in stage], "step": step.tolist(),
                            "reference": reference.tolist(),
                            "succeeded": {n: [None if np.isnan(r).all() else int(np.nansum(r)) for r in v]
                                          for n, v in succeeded.items()}}}
    print(f"[outcome-determinacy] one pixel at the bowl: {result['metres_per_pixel']['bowl']['median'] * 1000:.1f} mm "
          f"(median); replays from the recorded states repeat the episodes' outcome in "
          f"{result['replay_repeats_recorded']:.3f} ({seconds['replays_s']:.0f} s)", flush=True)
    for name, row in result["groups"].items():
        cells = ", ".join(f"{key} {v:.2f}" + ("" if row["kept"][key] is None else f" (kept {row['kept'][key]:.2f})")
                          for key, v in row["flipped"].items() if v is not None)
        print(f"[outcome-determinacy] {name}: {row['starts']} starts, reference success "
              f"{row['reference_success'] if row['reference_success'] is None else round(row['reference_success'], 3)}"
              f"; flipped: {cells}", flush=True)
    write_json_atomic(os.path.join(args.out, "outcome_determinacy.json"), result)
    return result


if __name__ == "__main__":
    cli.run(main)
