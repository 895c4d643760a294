"""Training of the action-following probe (frames -> end-effector, gripper, target bowl) on simulator episodes.

:func:`run_probe` is what ``python -m train.train_probe`` and the pipeline's probe stage run. Targets
come from the recorded simulator state (:func:`sim.probe_targets.episode_targets`). A random ``holdout``
share of episodes (seeded) is held out and the probe's error there is reported next to a constant
predictor's (the training mean). Writes ``<out>/probe.npz``; training checkpoints go to
``<out>/probe_checkpoints`` and a rerun resumes there.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence

import numpy as np

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


def run_probe(cfg, demos: Sequence[str], out: str, probe_cfg: probe_lib.ProbeConfig, *,
              holdout: float = 0.2) -> dict:
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
