"""Training of the success detector (reward model) on simulator episodes with success labels.

:func:`run_reward_model` is what ``python -m train.train_reward`` and the pipeline's reward-model stage
run. Labels follow ``rl.reward_model.labels`` (``state``: each frame whose simulator state solves the
task; ``tail``: the last ``rl.reward_model.positive_tail`` frames of successful episodes read up to
their first success). Writes ``<workdir>/rl/reward_model`` and a held-out report; the train state is
checkpointed to ``<workdir>/rl/reward_checkpoints`` and a rerun resumes from there.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

import jax
import numpy as np

from sim.dataset import read_dataset
from sword_jax import sharding as shd
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import save_params
from sword_jax.rl.reward_model import (as_reward_model, build_detector, detector_report, score_episodes,
                                      train_detector)
from sword_jax.rng import stream_rng


def run_reward_model(cfg, demos: Sequence[str], *, holdout: float = 0.2) -> dict:
    """Trains (or resumes) the success detector on ``demos`` in ``<cfg.workdir>/rl``; returns the summary
    (also written to ``<cfg.workdir>/rl/reward_result.json``)."""
    demos, rl = list(demos), cfg.rl
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    episodes = rl_data.load_episodes(demos, read=read_dataset, stop_at_success=rl.reward_model.labels == "tail")
    order = rng.permutation(episodes.num_episodes)
    n_hold = int(round(holdout * episodes.num_episodes)) if episodes.num_episodes > 1 else 0
    train_eps, hold_eps = episodes.subset(np.sort(order[n_hold:])), episodes.subset(np.sort(order[:n_hold]))
    labels = rl_data.success_labels(train_eps, rl.reward_model.positive_tail, rl.reward_model.labels)
    if not (labels == 1).any():
        raise ValueError(f"reward model data: no positive frame under rl.reward_model.labels={rl.reward_model.labels} in "
                         f"{demos}: " + ("no episode shows a solved state (episodes that end at their "
                                         "success never do; add fixed-length episodes that go on after it)"
                                         if rl.reward_model.labels == "state" else "no episode succeeded"))
    graphdef, params = build_detector(rl, seed=cfg.seed)
    key = jax.random.key(cfg.seed)

    def batch_at(step: int) -> dict:
        return rl_data.sample_reward_batch(train_eps, labels, rl.reward_model.batch_size,
                                           stream_rng(cfg.seed, "reward/batches", step))

    state, _ = train_detector(graphdef, params, rl, batch_at, key=key, log=lambda line: print(line, flush=True),
                              checkpoint_dir=os.path.join(workdir, "reward_checkpoints"), mesh=shd.make_mesh(cfg.mesh),
                              rules=cfg.mesh.rules)
    path = os.path.join(workdir, "reward_model")
    save_params(path, state.params, rl, kind="reward_model", step=int(state.step))
    result = {"steps": rl.reward_model.steps, "train_episodes": train_eps.num_episodes, "path": path,
              "labels": rl.reward_model.labels}
    if n_hold:
        result["holdout"] = holdout_report(as_reward_model(graphdef, state.params).score, hold_eps, rl)
        print("held out:", json.dumps(result["holdout"]))
    with open(os.path.join(workdir, "reward_result.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


def holdout_report(score, episodes: rl_data.EpisodeSet, rl) -> dict:
    """Agreement of the detector with its own labels and with true success on held-out episodes (the latter
    under the imagined-success rule: ``rl.imagined.success_frames`` consecutive frames)."""
    labels = rl_data.success_labels(episodes, rl.reward_model.positive_tail, rl.reward_model.labels)
    scores = score_episodes(jax.jit(score), episodes.frames)
    valid = labels >= 0
    truth, pred = labels[valid] == 1, scores[valid] >= rl.success_threshold
    report = {"frames": int(valid.sum()), "positives": int(truth.sum()),
              "precision_at_threshold": float((pred & truth).sum() / max(pred.sum(), 1)),
              "recall_at_threshold": float((pred & truth).sum() / max(truth.sum(), 1)),
              "accuracy_at_0.5": float(((scores[valid] >= 0.5) == truth).mean())}
    report["true_success"] = detector_report(scores, episodes, rl.success_threshold,
                                             success_frames=rl.imagined.success_frames)
    return report
