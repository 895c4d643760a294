"""Trains the Wan 2.2-style video VAE from scratch on simulator videos (or loads official weights).

Usage::

    python -m train.train_vae --config sword:tiny --workdir DIR --episodes data.hdf5 [--episodes more.hdf5]
    python -m train.train_vae --config sword:tiny --workdir DIR --synthetic        # moving squares
    python -m train.train_vae --config sword:paper --workdir DIR --vae.checkpoint=Wan2.2_VAE.safetensors

Clips of ``1 + 4k`` frames (``k`` = 2 by default) are cut at random from the episodes' agentview
frames; with ``vae.train_styles`` (default) a ``vae.styled_fraction`` share of them is restyled in
*training* styles (:mod:`sword_jax.vae.data`; held-out styles and held-out episodes never reach the VAE). The state (params, latent statistics, optimiser state, step) is an orbax checkpoint under
``<workdir>/checkpoints``; the run auto-resumes from it. The training is :func:`sim.vae_training.run_vae`;
its loop is :func:`sword_jax.train_loop.run_steps`: metrics one log step late to ``<workdir>/metrics.jsonl``
and TensorBoard, and a non-finite loss stops the run naming the step, the last good checkpoint kept.
``<workdir>/vae/`` holds the final pure-dict VAE state that ``train.evaluate_world_model`` and the pipeline load.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import configs
from configs.base import ExperimentConfig
from sim.vae_training import run_vae
from train import distributed


def main(argv: Sequence[str] | None = None) -> dict:
    parser = configs.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", action="append", default=[], help="LIBERO-layout HDF5 (repeatable)")
    parser.add_argument("--synthetic", action="store_true", help="train on moving squares")
    parser.add_argument("--clip-latents", type=int, default=2, help="k of the 1+4k-frame training clips")
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(rest)
    distributed.initialize(cfg.mesh)
    return run(cfg, args.episodes, synthetic=args.synthetic, clip_latents=args.clip_latents)


def run(cfg: ExperimentConfig, episodes: Sequence[str] = (), *, synthetic: bool = False,
        clip_latents: int = 2) -> dict:
    """:func:`sim.vae_training.run_vae` (process setup is :func:`main`'s)."""
    return run_vae(cfg, episodes, synthetic=synthetic, clip_latents=clip_latents)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
