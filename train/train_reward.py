"""Trains the success detector (reward model) on simulator episodes with success labels.

    python -m train.train_reward --config sword:small --demos episodes.hdf5 [--rl.reward_model.steps=1000]

Labels follow ``rl.reward_model.labels``: ``state`` (default) marks each frame whose state solves the task
(the simulator's per-step success, read over whole episodes, so fixed-length episodes that keep
moving after success give solved and unsolved-again frames); ``tail`` marks the last
``rl.reward_model.positive_tail`` frames of successful episodes read up to their first success. Batches are class-balanced, the batch of step ``s`` drawn from its own stream
(``reward/batches``, ``s``). Writes ``<workdir>/rl/reward_model`` and a held-out report. The train
state is checkpointed to ``<workdir>/rl/reward_checkpoints`` every
``rl.reward_model.checkpoint_every`` steps and a rerun resumes from there, ending bit-identical to
an uninterrupted run; a non-finite loss stops the run naming the step, the last good checkpoint kept.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import configs
from sim.reward_training import run_reward_model


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 episodes (repeatable)")
    parser.add_argument("--holdout", type=float, default=0.2, help="fraction of episodes held out")
    args = parser.parse_args(rest)
    return run(cfg, args.demos, holdout=args.holdout)


def run(cfg, demos: Sequence[str], *, holdout: float = 0.2) -> dict:
    """:func:`sim.reward_training.run_reward_model`."""
    return run_reward_model(cfg, demos, holdout=holdout)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
