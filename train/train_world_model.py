"""Trains the action-conditioned world model: teacher forcing, or DLB when ``cache.enabled``.

Usage::

    python -m train.train_world_model --config sword:tiny --workdir DIR [--synthetic] [--model.num_layers=1 ...]
    python -m train.train_world_model --config cache_ablation:linear-ema-single --workdir DIR --data.path latents.npz

The latent dataset comes from ``--data.path`` (``.npz``/``.h5`` with ``latents [E, L, h, w, c]`` and
``actions [E, 1 + 4(L-1), a]``) or, with ``--synthetic``, from action-dependent synthetic latents.
The training is :func:`sword_jax.pipeline.world_model.run_world_model`; its loop is
:func:`sword_jax.train_loop.run_steps`; the batch of a step is a pure function of it. The run
auto-resumes from ``<workdir>/checkpoints`` (train state with the DLB cache, data position, RNG root,
config). Metrics are read one log step late and appended to ``<workdir>/metrics.jsonl`` and
TensorBoard event files in ``<workdir>/tensorboard``.
A non-finite loss stops the run (``trainer.on_nonfinite=stop``) naming the step; the last good
checkpoint stays, and the faulty step's update was never applied (``skip`` goes on without it).
Every ``trainer.eval_every`` steps the run also logs the flow loss and the sampler's error on fixed segments of
training and of held-out episodes (``--data.heldout_path``; synthetic ones of another seed with ``--synthetic``),
:mod:`sword_jax.world_model.heldout`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import configs
from configs.base import ExperimentConfig
from sword_jax.pipeline.world_model import run_world_model
from train import distributed


def _parse(argv: Sequence[str]) -> tuple[ExperimentConfig, str, bool]:
    parser = configs.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--synthetic", action="store_true", help="train on action-dependent synthetic latents")
    cfg, rest = configs.from_argv(argv)
    args = parser.parse_args(rest)
    return cfg, cfg.workdir, args.synthetic


def main(argv: Sequence[str] | None = None) -> dict:
    """Runs (or resumes) training; returns a summary (final step, last logged metrics)."""
    cfg, _, synthetic = _parse(sys.argv[1:] if argv is None else argv)
    distributed.initialize(cfg.mesh)
    return run(cfg, synthetic=synthetic)


def run(cfg: ExperimentConfig, *, synthetic: bool = False) -> dict:
    """:func:`sword_jax.pipeline.world_model.run_world_model` (process setup is :func:`main`'s)."""
    return run_world_model(cfg, synthetic=synthetic)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
