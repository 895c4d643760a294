"""Imagine a rollout with a trained world model and save it as a GIF.

    python examples/imagine_rollout.py --run RUN [--episodes FILE.hdf5] [--chunks 3] [--out rollout.gif]

RUN: a ``python -m train.pipeline`` work dir (or a world-model work dir / checkpoint). Without
``--run`` a tiny model is trained first (``_tiny_run.py``; under a minute on a CPU). The rollout
starts from the first ``spec.given_frames`` frames of each video and follows its actions:
LIBERO-layout episodes with ``--episodes`` (e.g. ``RUN/data/heldout_*.hdf5``), else moving
squares (what the tiny VAE saw) with random actions. The GIF shows the real video beside the
imagined one; frames ``given_frames`` onwards are the world model's.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import sword_jax
from _tiny_run import tiny_run


def start_videos(spec, args, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """``(frames [B, T, H, W, 3] in [0, 1], actions [B, T, a])`` to start from and compare against."""
    if args.episodes:
        from sim.dataset import read_dataset

        episodes = read_dataset(args.episodes)[1][: args.batch]
        frames = np.stack([ep.agentview_rgb[:num_frames] for ep in episodes]).astype(np.float32) / 255.0
        return frames, np.stack([ep.actions[:num_frames] for ep in episodes]).astype(np.float32)
    from sword_jax.vae.train import moving_squares

    video = moving_squares(key=jax.random.key(args.seed), batch=args.batch, frames=num_frames, size=spec.image_size)
    actions = jax.random.uniform(jax.random.key(args.seed + 1), (args.batch, num_frames, spec.action_dim),
                                 minval=-1.0, maxval=1.0)
    return (np.asarray(video) + 1.0) / 2.0, np.asarray(actions)


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", help="trained run (default: train a tiny one)")
    parser.add_argument("--workdir", default="runs/examples-tiny", help="where the tiny run goes")
    parser.add_argument("--train-steps", type=int, default=10, help="steps of the tiny run")
    parser.add_argument("--episodes", help="LIBERO-layout HDF5 to start from (default: moving squares)")
    parser.add_argument("--chunks", type=int, default=3, help="predicted chunks (4 * spec.num_future frames each)")
    parser.add_argument("--batch", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="rollout.gif")
    args = parser.parse_args(argv)

    model = sword_jax.load_world_model(tiny_run(args.run, workdir=args.workdir, steps=args.train_steps))
    spec = model.spec
    num_frames = spec.num_actions(args.chunks)
    frames, actions = start_videos(spec, args, num_frames)
    imagined = sword_jax.rollout(model, frames[:, : spec.given_frames], actions, key=jax.random.key(args.seed))
    imagined = np.asarray(imagined)  # [B, T, H, W, 3] float32 in [0, 1]
    print(f"imagined {imagined.shape} from {spec.given_frames} given frames and {num_frames} actions "
          f"({model.loaded_from.world_model}, step {model.loaded_from.step})")

    from sword_jax.evaluation.report import write_gif

    write_gif(args.out, {"real": frames[0], "imagined": imagined[0]})
    print(f"wrote {args.out}")
    return args.out


if __name__ == "__main__":
    main()
