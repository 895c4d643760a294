"""Behaviour cloning (SFT) of the VLA policy on expert demonstrations: the GRPO starting point.

    python -m train.train_policy --config sword:small --demos demos.hdf5 [--rl.sft.steps=2000]
        [--rl.sft.episodes_per_task=10] [--workdir DIR] [--eval-episodes 10]

    # decoder-aware fine-tuning of a trained policy: half of each batch's frames round-tripped through the VAE
    python -m train.train_policy --config sword:small --demos demos.hdf5 --rl.sft.init=policy.npz \
        --rl.sft.decoded_fraction=0.5 --vae runs/<pipeline>/vae_run/vae --rl.sft.steps=1000

The knobs that set how good the starting policy is: ``rl.sft.steps`` and
``rl.sft.episodes_per_task`` (demonstrations per instruction). Writes ``<workdir>/rl/policy_sft``
(orbax) and, with ``--eval-episodes``, the ground-truth success in the MuJoCo sim. The train state
is checkpointed to ``<workdir>/rl/sft_checkpoints`` every ``rl.sft.checkpoint_every`` steps and a
rerun resumes from there, ending bit-identical to an uninterrupted run; a non-finite loss stops
the run naming the step, the last good checkpoint kept.

``--rl.sft.init`` starts from a trained policy (its parameters, a fresh optimizer). ``--rl.sft.decoded_fraction``
(decoder-aware SFT) replaces that share of each batch's frames by their round trip through the VAE ``--vae`` (the
whole episode encoded and decoded as one video, as the world model's frames are); ``--vae`` is required with it and
refused without it. With ``--rl.sft.decoded_source=world_model`` those frames are the ones the world model
``--world-model`` shows when each demonstration's actions are replayed in it from its real frames, in windows of
``rl.sft.decoded_window`` actions (an imagined rollout's by default; :mod:`sword_jax.rl.imagined_frames`)::

    python -m train.train_policy --config sword:small --demos demos.hdf5 --rl.sft.init=policy.npz \
        --rl.sft.decoded_fraction=0.5 --rl.sft.decoded_source=world_model --vae runs/<pipeline>/vae_run/vae \
        --world-model runs/<pipeline>/world_model --rl.sft.steps=1000
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import configs
from sim.policy_training import run_sft_policy
from sword_jax.rl import decoded_frames


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 demos (repeatable)")
    parser.add_argument("--eval-episodes", type=int, default=0, help="fixed evaluation initial states per task")
    parser.add_argument("--eval-workers", type=int, default=0, help="C-engine processes for the evaluation")
    parser.add_argument("--renderer", choices=("jax", "gl"), default="jax",
                        help="evaluation renderer: the one the demonstrations were rendered with")
    parser.add_argument("--holdout", type=float, default=0.1, help="fraction of demonstrations held out")
    decoded_frames.add_options(parser)
    args = parser.parse_args(rest)
    try:
        decoded_frames.require_vae(cfg.rl.sft.decoded_fraction, args.vae, args.world_model, cfg.rl.sft.decoded_source)
    except ValueError as err:
        parser.error(str(err))
    return run(cfg, args.demos, eval_episodes=args.eval_episodes, eval_workers=args.eval_workers,
               renderer=args.renderer, holdout=args.holdout, vae=args.vae, world_model=args.world_model)


def run(cfg, demos: Sequence[str], *, eval_episodes: int = 0, eval_workers: int = 0, renderer: str = "jax",
        holdout: float = 0.1, vae: str = "", world_model: str = "") -> dict:
    """:func:`sim.policy_training.run_sft_policy`."""
    return run_sft_policy(cfg, demos, eval_episodes=eval_episodes, eval_workers=eval_workers, renderer=renderer,
                          holdout=holdout, vae=vae, world_model=world_model)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
