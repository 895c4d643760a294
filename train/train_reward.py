"""Trains the success detector (reward model) on simulator episodes with success labels.

    python -m train.train_reward --config sword:small --demos episodes.hdf5 [--rl.reward_model_steps=1000]

The last ``rl.positive_tail`` frames of successful episodes are positives, every other frame a
negative; batches are class-balanced, the batch of step ``s`` drawn from its own stream
(``reward/batches``, ``s``). Writes ``<workdir>/rl/reward_model`` and a held-out report. The train
state is checkpointed to ``<workdir>/rl/reward_checkpoints`` every
``rl.reward_model_checkpoint_every`` steps and a rerun resumes from there, ending bit-identical to
an uninterrupted run; a non-finite loss stops the run naming the step, the last good checkpoint kept.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import configs
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import save_params
from sword_jax.rl.reward_model import as_reward_model, build_detector, train_detector
from sword_jax.rng import stream_rng
from sword_jax.train_loop import NonFiniteLoss


def main(argv: Sequence[str] | None = None) -> dict:
    from sim.dataset import read_dataset

    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 episodes (repeatable)")
    parser.add_argument("--holdout", type=float, default=0.2, help="fraction of episodes held out")
    args = parser.parse_args(rest)
    rl = cfg.rl
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    episodes = rl_data.load_episodes(args.demos, read=read_dataset)
    order = rng.permutation(episodes.num_episodes)
    n_hold = int(round(args.holdout * episodes.num_episodes)) if episodes.num_episodes > 1 else 0
    train_eps, hold_eps = episodes.subset(np.sort(order[n_hold:])), episodes.subset(np.sort(order[:n_hold]))
    labels = rl_data.success_labels(train_eps, rl.positive_tail)
    graphdef, params = build_detector(rl, seed=cfg.seed)
    key = jax.random.key(cfg.seed)

    def batch_at(step: int) -> dict:
        return rl_data.sample_reward_batch(train_eps, labels, rl.reward_model_batch_size,
                                           stream_rng(cfg.seed, "reward/batches", step))

    state, _ = train_detector(graphdef, params, rl, batch_at, key=key, log=lambda line: print(line, flush=True),
                              checkpoint_dir=os.path.join(workdir, "reward_checkpoints"))
    path = os.path.join(workdir, "reward_model")
    save_params(path, state.params, rl, kind="reward_model", step=int(state.step))
    result = {"steps": rl.reward_model_steps, "train_episodes": train_eps.num_episodes, "path": path}
    if n_hold:
        hold_labels = rl_data.success_labels(hold_eps, rl.positive_tail)
        score = jax.jit(as_reward_model(graphdef, state.params).score)
        valid = hold_labels >= 0
        frames = hold_eps.frames[valid]
        scores = np.concatenate([np.asarray(score(jnp.asarray(frames[i:i + 256]))) for i in range(0, len(frames), 256)])
        truth = hold_labels[valid] == 1
        pred = scores >= rl.success_threshold
        result["holdout"] = {"frames": int(valid.sum()), "positives": int(truth.sum()),
                             "precision_at_threshold": float((pred & truth).sum() / max(pred.sum(), 1)),
                             "recall_at_threshold": float((pred & truth).sum() / max(truth.sum(), 1)),
                             "accuracy_at_0.5": float(((scores >= 0.5) == truth).mean())}
        print("held out:", json.dumps(result["holdout"]))
    with open(os.path.join(workdir, "reward_result.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    from sword_jax.cli import run

    run(main, runtime_errors=(NonFiniteLoss,))
