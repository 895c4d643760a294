"""Trains the action-following probe (frames -> end-effector, gripper, target bowl) on simulator episodes.

    python -m train.train_probe --config sword:small --demos train.hdf5 [--out DIR] [--steps 400]

Targets come from the recorded simulator state: ``ee_states[:, :3]``, the finger distance
``gripper_states[:, 0] - gripper_states[:, 1]`` and the target bowl's free-joint position in
``states`` (a root body's free-joint qpos is its world position). A random ``--holdout`` share of
episodes (seeded) is held out and the probe's error there is reported next to a constant predictor's (the
training mean). Writes ``<out>/probe.npz`` (default ``<workdir>/probe``) for ``train.evaluate_world_model --probe``.
Training checkpoints go to ``<out>/probe_checkpoints``; a rerun resumes there and ends bit-identical to an
uninterrupted run.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Sequence

import numpy as np

import configs
from sim.probe_targets import episode_targets
from sword_jax.evaluation import probe as probe_lib

MAX_TRAIN_FRAMES = 20000  # frames are strided down to at most this many


def _errors(pred: np.ndarray, truth: np.ndarray, closed_below: float) -> dict[str, float]:
    ee = 100 * np.linalg.norm(pred[:, probe_lib.EE] - truth[:, probe_lib.EE], axis=-1).mean()
    bowl = 100 * np.linalg.norm(pred[:, probe_lib.BOWL] - truth[:, probe_lib.BOWL], axis=-1).mean()
    grip = np.mean((pred[:, probe_lib.GRIPPER] < closed_below) == (truth[:, probe_lib.GRIPPER] < closed_below))
    return {"ee_cm": float(ee), "bowl_cm": float(bowl), "gripper_acc": float(grip)}


def probe_config(cfg, steps: int = probe_lib.ProbeConfig.steps) -> probe_lib.ProbeConfig:
    """The probe's settings for an experiment config: its seed, frames no larger than the config's."""
    return dataclasses.replace(probe_lib.ProbeConfig(), steps=steps, seed=cfg.seed,
                               image_size=min(probe_lib.ProbeConfig.image_size, cfg.data.image_size)).validate()


def run(cfg, demos: Sequence[str], out: str, probe_cfg: probe_lib.ProbeConfig, *, holdout: float = 0.2) -> dict:
    """Trains on ``demos``, reports held-out error, saves; returns the summary."""
    from sim.dataset import read_dataset

    episodes = [ep for path in demos for ep in read_dataset(path)[1]]
    n_hold = int(round(holdout * len(episodes))) if len(episodes) > 1 else 0
    order = np.random.default_rng(probe_cfg.seed).permutation(len(episodes))
    train_eps, hold_eps = [episodes[i] for i in order[n_hold:]], [episodes[i] for i in order[:n_hold]]
    frames = np.concatenate([ep.agentview_rgb for ep in train_eps])
    targets = np.concatenate([episode_targets(ep) for ep in train_eps])
    stride = -(-len(frames) // MAX_TRAIN_FRAMES)
    frames, targets = frames[::stride], targets[::stride]
    os.makedirs(out, exist_ok=True)
    graphdef, params, stats, metrics = probe_lib.train_probe(frames, targets, probe_cfg,
                                                             checkpoint_dir=os.path.join(out, "probe_checkpoints"))
    path = probe_lib.save_probe(os.path.join(out, "probe.npz"), params, stats, probe_cfg, demos=list(demos))
    summary = {"path": path, "steps": probe_cfg.steps, "train_frames": int(len(frames)), "final_loss": metrics["loss"]}
    if hold_eps:
        hold_frames = np.concatenate([ep.agentview_rgb for ep in hold_eps])
        truth = np.concatenate([episode_targets(ep) for ep in hold_eps])
        pred = probe_lib.predict(graphdef, params, stats, hold_frames, image_size=probe_cfg.image_size)
        constant = np.broadcast_to(targets.mean(axis=0), truth.shape)
        closed_below = probe_cfg.gripper_closed_below
        summary.update({f"holdout_{k}": v for k, v in _errors(pred, truth, closed_below).items()})
        summary.update({f"holdout_constant_{k}": v for k, v in _errors(constant, truth, closed_below).items()})
    print("[probe] " + ", ".join(f"{k}={v:.4g}" for k, v in summary.items() if isinstance(v, float)), flush=True)
    return summary


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 episodes (repeatable)")
    parser.add_argument("--out", default="", help="output directory (default <workdir>/probe)")
    parser.add_argument("--steps", type=int, default=probe_lib.ProbeConfig.steps)
    parser.add_argument("--holdout", type=float, default=0.2, help="share of episodes held out")
    args = parser.parse_args(rest)
    return run(cfg, args.demos, args.out or os.path.join(cfg.workdir, "probe"), probe_config(cfg, args.steps),
               holdout=args.holdout)


if __name__ == "__main__":
    from sword_jax.cli import run as cli_run

    cli_run(main)
