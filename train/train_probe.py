"""Trains the action-following probe (frames -> end-effector, gripper, target bowl) on simulator episodes.

    python -m train.train_probe --config sword:small --demos train.hdf5 [--out DIR] [--steps 400]

Targets come from the recorded simulator state: ``ee_states[:, :3]``, the finger distance
``gripper_states[:, 0] - gripper_states[:, 1]`` and the target bowl's free-joint position in
``states`` (a root body's free-joint qpos is its world position). A random ``--holdout`` share of
episodes (seeded) is held out and the probe's error there is reported next to a constant predictor's (the
training mean). Writes ``<out>/probe.npz`` (default ``<workdir>/probe``) for ``train.evaluate_world_model --probe``.
Training checkpoints go to ``<out>/probe_checkpoints``; a rerun resumes there and ends bit-identical to an
uninterrupted run.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import configs
from sim.probe_training import probe_config, run_probe
from sword_jax.evaluation import probe as probe_lib


def run(cfg, demos: Sequence[str], out: str, probe_cfg: probe_lib.ProbeConfig, *, holdout: float = 0.2) -> dict:
    """:func:`sim.probe_training.run_probe`."""
    return run_probe(cfg, demos, out, probe_cfg, holdout=holdout)


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 episodes (repeatable)")
    parser.add_argument("--out", default="", help="output directory (default <workdir>/probe)")
    parser.add_argument("--steps", type=int, default=probe_lib.ProbeConfig.steps)
    parser.add_argument("--holdout", type=float, default=0.2, help="share of episodes held out")
    args = parser.parse_args(rest)
    return run(cfg, args.demos, args.out or os.path.join(cfg.workdir, "probe"), probe_config(cfg, args.steps),
               holdout=args.holdout)


if __name__ == "__main__":
    from sword_jax.cli import run as cli_run

    cli_run(main)
