"""Where a world model's held-out error lies: its fixed segments' own errors joined with their episodes' outcomes.

A world-model run with ``--trainer.eval_segments=true`` writes, at its end, every fixed evaluation segment's own
sample error with its episode and start (``<pipeline>/world_model/heldout_segments.json``). A split's figure is
their energy-weighted mean, and a few segments can carry it. This joins them with what happened in their episodes
and groups them:

* ``outcomes``: reads an episode file (HDF5, the pipeline's ``data/policy_heldout.hdf5`` or ``data/heldout.hdf5``)
  in the order the latents stage encoded it and keeps what the join needs, small enough for a record: per episode
  its task, initial state, first success (``-1``: none), per-step rewards and actions, and per step the stage its
  recorded state is in (``stages``: an index into ``bench_failure_phases.START_STAGES``, before the grasp, grasped,
  over the plate, after a release; read on the C engine from the finger pads' contacts) (``.npz``).
* ``join``: per segment of every split, its frames (the future frames it predicts: ``f (start + k - 1) + 1`` to
  ``f (start + k + p - 1)`` with ``k`` context and ``p`` future latents of ``f`` frames each, the VAE's temporal
  factor), its error at each Euler step count, and
  where an outcomes file is given for its split: whether its episode succeeded, the segment's phase (``before
  success``: its future frames all precede the first success; ``spans success``; ``after success``; ``failed
  episode``), the stage of the state its prediction starts from (the last context frame's), whether its future
  lies within the first ``--early-actions`` actions (GRPO's imagined horizon from rest) and the arm's motion there
  (mean absolute translation action). Then per split and group: the segments, their
  energy-weighted error (the evaluation's figure, over that group), median, and the group's share of the split's
  figure. Writes ``segments.json``::

    python -m benchmarks.segment_errors outcomes runs/p/pipeline/data/policy_heldout.hdf5 runs/p/policy_outcomes.npz
    python -m benchmarks.segment_errors join --pipeline runs/p/pipeline --outcomes policy=runs/p/policy_outcomes.npz \\
        --out runs/p/segments.json

Not recorded to ``latest.json``; report table ``world-model-segments``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

import numpy as np

from benchmarks.bench_failure_phases import START_STAGES, start_stages
from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic

PHASES = ("before success", "spans success", "after success", "failed episode")
OUTCOME_KEYS = ("task_id", "init_state_id", "first_success", "rewards", "actions")  # "stages" where read


def step_stages(states: np.ndarray, task_ids: np.ndarray, *, over_m: float = 0.05) -> np.ndarray:
    """Per episode and step, the stage of the recorded flat state ``states [N, T, 1 + nq + nv]`` of task
    ``task_ids [N]`` (``int8``, an index into ``bench_failure_phases.START_STAGES``): the state restored on the C
    engine, the bowl held where both finger pads touch it, over the plate within ``over_m`` in xy, let go where it
    was held at an earlier step (``bench_failure_phases.start_stages`` of ``sim.lockstep.pose``)."""
    from sim.config import SimConfig
    from sim.env import CpuEnv
    from sim.lockstep import grasp_geoms, pose

    states = np.asarray(states, np.float64)
    envs: dict[int, CpuEnv] = {}
    out = np.zeros(states.shape[:2], np.int8)
    for e, task in enumerate(np.asarray(task_ids, np.int64)):
        if int(task) not in envs:
            envs[int(task)] = CpuEnv(SimConfig(resolution=16), int(task))
        env = envs[int(task)]
        grasp = grasp_geoms(env)
        bowl, _, plate, held = zip(*(pose(env, env.restore(flat).data, grasp) for flat in states[e]))
        held = np.asarray(held, bool)
        before = np.concatenate([[False], np.cumsum(held)[:-1] > 0])
        out[e] = start_stages(held, np.stack(bowl), np.stack(plate), before, over_m=over_m)
    return out


def episode_outcomes(path: str, *, over_m: float = 0.05) -> dict[str, np.ndarray]:
    """Per episode of the dataset ``path``, in its demo order (the latents stage's): ``task_id``,
    ``init_state_id`` (``-1`` where the file does not say), ``first_success`` (the first step whose reward is
    set, ``-1``: none), ``rewards`` ``[N, T]``, ``actions`` ``[N, T, A]`` and ``stages`` ``[N, T]``
    (:func:`step_stages`; all cut to the shortest episode)."""
    from sim.dataset import read_dataset

    _, episodes = read_dataset(path)
    if not episodes:
        raise ValueError(f"segment errors: {path} holds no episodes")
    n = min(len(e.rewards) for e in episodes)
    rewards = np.stack([np.asarray(e.rewards[:n], np.uint8) for e in episodes])
    first = np.array([int(np.argmax(r > 0)) if (r > 0).any() else -1 for r in
                      (np.asarray(e.rewards) for e in episodes)], np.int64)
    task_ids = np.array([-1 if e.task_id is None else e.task_id for e in episodes], np.int64)
    if (task_ids < 0).any():
        raise ValueError(f"segment errors: {path} has episodes without a task_id (their stages cannot be read)")
    stages = step_stages(np.stack([np.asarray(e.states[:n], np.float64) for e in episodes]), task_ids,
                            over_m=over_m)
    return {"task_id": task_ids, "stages": stages,
            "init_state_id": np.array([-1 if e.init_state_id is None else e.init_state_id for e in episodes], np.int64),
            "first_success": first, "rewards": rewards,
            "actions": np.stack([np.asarray(e.actions[:n], np.float64) for e in episodes])}


def segment_phase(first_frame: int, last_frame: int, first_success: int) -> str:
    """Where frames ``first_frame..last_frame`` lie against the episode's first success (:data:`PHASES`)."""
    if first_success < 0:
        return "failed episode"
    if last_frame < first_success:
        return "before success"
    return "after success" if first_frame >= first_success else "spans success"


def _figure(error: np.ndarray, energy: np.ndarray) -> float | None:
    return float((error * energy).sum() / energy.sum()) if len(error) and energy.sum() > 0 else None


def join(record: dict, outcomes: dict[str, dict[str, np.ndarray]], *, context_latents: int, future_latents: int,
         euler: int, early_actions: int, frames_per_latent: int = 4) -> dict:
    """``record`` (``heldout_segments.json``) per segment and per group (module docstring); ``outcomes`` per split
    (:func:`episode_outcomes`) where known. ``euler`` picks the error the groups report; ``frames_per_latent`` is
    the VAE's temporal factor (every latent after the first)."""
    name = f"sample_error_{euler}"
    out: dict = {"step": record.get("step"), "euler": euler, "early_actions": early_actions, "splits": {}}
    for split, rows in record["splits"].items():
        if name not in rows:
            raise ValueError(f"segment errors: split {split!r} has no {name} (has "
                             f"{sorted(k for k in rows if k.startswith('sample_error_'))})")
        episodes, starts = np.asarray(rows["episodes"], np.int64), np.asarray(rows["starts"], np.int64)
        energy, error = np.asarray(rows["energy"], np.float64), np.asarray(rows[name], np.float64)
        first_frames = frames_per_latent * (starts + context_latents - 1) + 1
        last_frames = frames_per_latent * (starts + context_latents + future_latents - 1)
        known = outcomes.get(split)
        if known is not None and len(episodes) and episodes.max() >= len(known["first_success"]):
            raise ValueError(f"segment errors: split {split!r} names episode {int(episodes.max())}, its outcomes "
                             f"hold {len(known['first_success'])} episodes")
        segments, groups = [], {}
        for i in range(len(episodes)):
            seg = {"episode": int(episodes[i]), "start": int(starts[i]), "frames": [int(first_frames[i]),
                                                                                   int(last_frames[i])],
                   "energy": float(energy[i]),
                   **{k: float(np.asarray(v, np.float64)[i]) for k, v in rows.items() if k.startswith("sample_error_")},
                   "early": bool(last_frames[i] <= early_actions)}
            keys = ["all", f"first {early_actions} actions" if seg["early"] else f"after {early_actions} actions"]
            if known is not None:
                first = int(known["first_success"][episodes[i]])
                acts = np.asarray(known["actions"][episodes[i], first_frames[i] - 1:last_frames[i], :3], np.float64)
                seg.update(success=first >= 0, first_success=first,
                           phase=segment_phase(int(first_frames[i]), int(last_frames[i]), first),
                           motion=float(np.abs(acts).mean()) if acts.size else None)
                keys.append(seg["phase"])
                if "stages" in known:  # the state the prediction starts from: the last context frame's
                    seg["stage"] = START_STAGES[int(known["stages"][episodes[i], first_frames[i] - 1])]
                    keys.append(f"stage: {seg['stage']}")
                if seg["phase"] == "failed episode":
                    keys.append(f"failed episode, {keys[1]}")
            for key in keys:
                groups.setdefault(key, []).append(i)
            segments.append(seg)
        total = float((error * energy).sum())
        summary = {}
        for key, idx in groups.items():
            idx = np.asarray(idx)
            motions = [segments[i]["motion"] for i in idx if segments[i].get("motion") is not None]
            summary[key] = {"segments": int(len(idx)), "error": _figure(error[idx], energy[idx]),
                            "median": float(np.median(error[idx])),
                            "share": float((error[idx] * energy[idx]).sum() / total) if total > 0 else None,
                            "motion": float(np.mean(motions)) if motions else None}
        if known is not None and len(segments) > 2:
            motion = np.array([s["motion"] for s in segments], np.float64)
            summary["all"]["motion_error_correlation"] = (float(np.corrcoef(motion, error)[0, 1])
                                                          if motion.std() > 0 and error.std() > 0 else None)
        out["splits"][split] = {"groups": summary, "segments": segments}
    return out


def _latents_per_segment(pipeline: str) -> tuple[int, int, int]:
    """``(context latents, future latents, frames per latent)`` of the pipeline's world model."""
    from sword_jax.load import section_from_dict
    from sword_jax.vae.config import VAEConfig
    from sword_jax.world_model.config import DataConfig

    with open(os.path.join(pipeline, "config.json")) as f:
        config = json.load(f)
    data = section_from_dict(DataConfig, config["data"])
    factor = section_from_dict(VAEConfig, config["vae"]).temporal_factor
    return data.context_frames // factor, data.predict_frames // factor, factor


def parse(argv: Sequence[str]) -> argparse.Namespace:
    p = cli.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    o = sub.add_parser("outcomes", help="an episode file's outcomes, small enough for a record (.npz)")
    o.add_argument("episodes", help="the episodes (HDF5), in the latents stage's order")
    o.add_argument("out", help="the .npz to write")
    o.add_argument("--over-m", type=float, default=0.05, help="over the plate: the bowl within this of it in xy")
    j = sub.add_parser("join", help="segments.json: the segments' errors joined with their episodes' outcomes")
    j.add_argument("--pipeline", required=True, help="the pipeline's work dir (config.json, world_model/)")
    j.add_argument("--outcomes", action="append", default=[], metavar="SPLIT=FILE",
                   help="a split's episode outcomes (from the outcomes command), e.g. policy=policy_outcomes.npz")
    j.add_argument("--out", required=True, help="segments.json to write")
    j.add_argument("--euler", type=int, default=5, help="the Euler step count whose error the groups report")
    j.add_argument("--early-actions", type=int, default=48, help="GRPO's imagined horizon from rest, in actions")
    args = p.parse_args(argv)
    if args.command == "outcomes":
        if not os.path.isfile(args.episodes):
            raise cli.UsageError(f"outcomes: {args.episodes}: no such file")
        if args.over_m <= 0:
            raise cli.UsageError("--over-m must be > 0")
        return args
    if args.euler < 1 or args.early_actions < 1:
        raise cli.UsageError("--euler and --early-actions must be >= 1")
    for path in (os.path.join(args.pipeline, "config.json"),
                 os.path.join(args.pipeline, "world_model", "heldout_segments.json")):
        if not os.path.isfile(path):
            raise cli.UsageError(f"--pipeline {args.pipeline}: no {os.path.relpath(path, args.pipeline)} (the "
                                 "world model's per-segment record needs --trainer.eval_segments=true)")
    parsed = {}
    for item in args.outcomes:
        split, sep, path = item.partition("=")
        if not sep or not split or not os.path.isfile(path):
            raise cli.UsageError(f"--outcomes takes SPLIT=FILE with an existing file, got {item!r}")
        parsed[split] = path
    args.outcomes = parsed
    return args


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse(sys.argv[1:] if argv is None else list(argv))
    if args.command == "outcomes":
        try:
            made = episode_outcomes(args.episodes, over_m=args.over_m)
        except ValueError as error:
            raise cli.UsageError(str(error)) from None
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        np.savez(args.out, **made)
        print(f"[segment-errors] {len(made['first_success'])} episodes ({(made['first_success'] >= 0).mean():.0%} "
              f"successful) -> {args.out}", flush=True)
        return {"episodes": int(len(made["first_success"]))}
    outcomes = {}
    for split, path in args.outcomes.items():
        with np.load(path) as data:
            missing = [k for k in OUTCOME_KEYS if k not in data.files]
            if missing:
                raise cli.UsageError(f"--outcomes {split}={path}: missing {missing} (write it with the outcomes "
                                     "command)")
            outcomes[split] = {k: data[k] for k in (*OUTCOME_KEYS, "stages") if k in data.files}
    with open(os.path.join(args.pipeline, "world_model", "heldout_segments.json")) as f:
        record = json.load(f)
    unknown = sorted(set(outcomes) - set(record["splits"]))
    if unknown:
        raise cli.UsageError(f"--outcomes: the record has no split {unknown} (has {sorted(record['splits'])})")
    context, future, factor = _latents_per_segment(args.pipeline)
    try:
        result = join(record, outcomes, context_latents=context, future_latents=future, euler=args.euler,
                      early_actions=args.early_actions, frames_per_latent=factor)
    except ValueError as error:
        raise cli.UsageError(str(error)) from None
    write_json_atomic(args.out, result)
    for split, row in result["splits"].items():
        cells = "; ".join(f"{k} {g['segments']} at {g['error']:.4f} ({g['share']:.0%})"
                          for k, g in row["groups"].items() if g["error"] is not None and g["share"] is not None)
        print(f"[segment-errors] {split}: {cells}", flush=True)
    return result


if __name__ == "__main__":
    cli.run(main)
