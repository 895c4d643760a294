"""Behaviour cloning (SFT) of the VLA policy on expert demonstrations: the GRPO starting point.

    python -m train.train_policy --config sword:small --demos demos.hdf5 [--rl.sft.steps=2000]
        [--rl.sft.episodes_per_task=10] [--workdir DIR] [--eval-episodes 10]

The knobs that set how good the starting policy is: ``rl.sft.steps`` and
``rl.sft.episodes_per_task`` (demonstrations per instruction). Writes ``<workdir>/rl/policy_sft``
(orbax) and, with ``--eval-episodes``, the ground-truth success in the MuJoCo sim. The train state
is checkpointed to ``<workdir>/rl/sft_checkpoints`` every ``rl.sft.checkpoint_every`` steps and a
rerun resumes from there, ending bit-identical to an uninterrupted run; a non-finite loss stops
the run naming the step, the last good checkpoint kept.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import configs
from sim.policy_training import run_sft_policy


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 demos (repeatable)")
    parser.add_argument("--eval-episodes", type=int, default=0, help="fixed evaluation initial states per task")
    parser.add_argument("--eval-workers", type=int, default=0, help="C-engine processes for the evaluation")
    parser.add_argument("--renderer", choices=("jax", "gl"), default="jax",
                        help="evaluation renderer: the one the demonstrations were rendered with")
    parser.add_argument("--holdout", type=float, default=0.1, help="fraction of demonstrations held out")
    args = parser.parse_args(rest)
    return run(cfg, args.demos, eval_episodes=args.eval_episodes, eval_workers=args.eval_workers,
               renderer=args.renderer, holdout=args.holdout)


def run(cfg, demos: Sequence[str], *, eval_episodes: int = 0, eval_workers: int = 0, renderer: str = "jax",
        holdout: float = 0.1) -> dict:
    """:func:`sim.policy_training.run_sft_policy`."""
    return run_sft_policy(cfg, demos, eval_episodes=eval_episodes, eval_workers=eval_workers, renderer=renderer,
                          holdout=holdout)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
