"""Distils the light rollout decoder from a trained VAE on the world model's training latents.

Usage::

    python -m train.train_light_decoder --config sword:small --workdir DIR --vae RUN/vae_run/vae \
        --latents RUN/data/latents.npz [--light_decoder.train_steps=2000 --light_decoder.frame_size=64]

The student (:mod:`sword_jax.vae.light_decoder`) decodes the VAE's latents straight to
``light_decoder.frame_size`` frames (default the policy's ``rl.image_size``); the target is the VAE's
decode resized to that size. The run auto-resumes from ``<workdir>/checkpoints`` (exactly: a batch is a
function of its step); the newest checkpoint there is the trained decoder, which ``train.grpo
--light-decoder <workdir>`` loads with ``--rl.imagined.decoder=light``. The training is
:func:`sword_jax.pipeline.light_decoder.run_light_decoder`, the pipeline's ``light_decoder`` stage.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import configs
from sword_jax.pipeline.light_decoder import run_light_decoder
from train import distributed


def main(argv: Sequence[str] | None = None) -> dict:
    parser = configs.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae", default="", help="the VAE's saved state (train_vae's <workdir>/vae); "
                                                  "not needed with --vae.checkpoint")
    parser.add_argument("--latents", required=True, help="the world model's training latents (.npz or .h5)")
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(rest)
    distributed.initialize(cfg.mesh)
    return run_light_decoder(cfg, vae=args.vae, latents=args.latents)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
