"""Long-horizon evaluation of world-model checkpoints on LIBERO-Original / LIBERO-Mixed.

Usage::

    python -m train.evaluate_world_model --config sword:tiny --out DIR --synthetic
    python -m train.evaluate_world_model --config sword:base --out DIR \
        --model baseline=runs/wm_tf --model sword=runs/wm_dlb \
        --episodes original=heldout_original.hdf5 --episodes mixed=heldout_mixed.hdf5 [--vae-checkpoint DIR]

For every held-out episode and model: encode the first frame and the first context chunk, roll the
world model out with the ground-truth actions for ``eval.horizon_frames`` frames (cut to the
longest ``1 + context + predict * n`` that fits), decode, and score LPIPS / FloLPIPS / PSNR / SSIM /
FID / FVD against ground truth, overall and against horizon. Writes ``report.md``/``report.html``
(+ plots, strips, GIFs, results.json) to ``--out``.

Episodes: LIBERO-layout HDF5 (``agentview_rgb`` + ``actions``, via :mod:`sim.dataset`) or ``.npz``
with ``frames [E, T, H, W, 3]`` (uint8 or [0, 1]) and ``actions [E, T, a]``. ``--synthetic``
generates both splits (moving textures; "mixed" re-styled) and, without ``--model``, evaluates a
randomly initialised world model: a smoke run of the whole pipeline. Models: a world-model
workdir (``<workdir>/checkpoints``, EMA params when present). VAE: ``--vae-checkpoint`` (an orbax
checkpoint of the VAE's pure-dict state written by ``sword_jax.checkpoint.Checkpointer``) or a
random initialisation, which the report then states.

Action-following fidelity (optional): ``--probe PATH`` (``train.train_probe``'s ``probe.npz``) adds
the probe's end-effector / bowl distance (cm) and gripper agreement between predicted and
ground-truth frames against horizon, and its own floor where episodes carry the true state
(HDF5, or npz with ``targets``); ``--reward-model DIR`` adds the success detector's agreement
between imagined and real frames, and precision / recall against the episodes' ``rewards``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import configs
from configs.base import ExperimentConfig
from sim.world_model_eval import EvalInputs, run_evaluation
from sword_jax.metrics.suite import ALL_METRICS


def _parse(argv: Sequence[str]) -> tuple[argparse.Namespace, ExperimentConfig]:
    parser = configs.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="", help="report directory (default: eval.report_dir, else <workdir>/eval)")
    parser.add_argument("--model", action="append", default=[], metavar="NAME=WORKDIR")
    parser.add_argument("--episodes", action="append", default=[], metavar="SPLIT=PATH")
    parser.add_argument("--vae-checkpoint", default="")
    parser.add_argument("--synthetic", action="store_true")
    parser.add_argument("--metrics", default="", help=f"comma-separated subset of {','.join(ALL_METRICS)} "
                        "(default: eval.metrics)")
    parser.add_argument("--probe", default="", help="action-following probe (train.train_probe's probe.npz)")
    parser.add_argument("--reward-model", default="", help="success detector (train.train_reward's reward_model dir)")
    cfg, rest = configs.from_argv(list(argv))
    return parser.parse_args(rest), cfg.validate()


def main(argv: Sequence[str] | None = None) -> str:
    args, cfg = _parse(sys.argv[1:] if argv is None else argv)
    inputs = EvalInputs(models=dict(item.split("=", 1) for item in args.model),
                        episodes=dict(item.partition("=")[::2] for item in args.episodes), out=args.out,
                        vae_checkpoint=args.vae_checkpoint, synthetic=args.synthetic,
                        metrics=tuple(m for m in args.metrics.split(",") if m), probe=args.probe,
                        reward_model=args.reward_model)
    return run(cfg, inputs)["report"]


def run(cfg: ExperimentConfig, inputs: EvalInputs) -> dict:
    """:func:`sim.world_model_eval.run_evaluation`: ``{"report": path of report.md, "out": the report directory}``."""
    return run_evaluation(cfg, inputs)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
