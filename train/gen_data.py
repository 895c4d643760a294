"""Expert demonstrations in LIBERO's HDF5 layout (+ depth and segmentation).

    python -m train.gen_data --task 0|all --episodes N --out FILE.hdf5 \\
        [--stop-at-success] [--max-steps 220] [--noise 0.0] [--noisy-share 1.0] \\
        [--init-split train|eval|heldout] [--init-start 0] [--init-seed 0] \\
        [--backend cpu|mjx] [--resolution 128] [--seed 0] [--renderer jax|gl] [--no-wrist] [--overwrite]

The command line of :func:`sim.datagen.generate`; its docstring says what the episodes are.
``--episodes`` is per task; without ``--stop-at-success`` every episode is ``--max-steps`` long
(world-model data), with it an episode ends at its first success (behaviour-cloning demos).
``--renderer auto`` picks MuJoCo's OpenGL renderer on the CPU backend where a context can be made.
"""

from __future__ import annotations

import sys

from sim.dataset import read_info
from sim.datagen import GenDataConfig, generate
from sword_jax.cli import ArgumentParser


def _parse(argv: list[str] | None) -> GenDataConfig:
    parser = ArgumentParser(prog="python -m train.gen_data", description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="0", help="task id 0-9, a comma list, or 'all'")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per task")
    parser.add_argument("--out", required=True, help="output .hdf5 file")
    parser.add_argument("--backend", choices=("cpu", "mjx"), default="cpu")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--noise", type=float, default=0.0, help="expert action noise std (0-1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--renderer", choices=("auto", "jax", "gl"), default="auto")
    parser.add_argument("--max-steps", type=int, default=220,
                        help="steps per episode (with --stop-at-success: at most)")
    parser.add_argument("--stop-at-success", action="store_true",
                        help="end each episode at its first success (behaviour-cloning demos)")
    parser.add_argument("--noisy-share", type=float, default=1.0, help="share of episodes with --noise (0-1)")
    parser.add_argument("--no-wrist", action="store_true", help="skip the eye_in_hand camera")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--init-split", choices=("train", "eval", "heldout"), default="train",
                        help="initial states: train (demos), heldout (world-model evaluation) or eval (the 50 fixed)")
    parser.add_argument("--init-start", type=int, default=0, help="first initial state of the split")
    parser.add_argument("--init-seed", type=int, default=0, help="seed of the initial-state splits")
    args = parser.parse_args(argv)
    if args.task == "all":
        task_ids = tuple(range(10))
    else:
        try:
            task_ids = tuple(int(t) for t in args.task.split(","))
        except ValueError:
            parser.error(f"--task must be 0-9, a comma list or 'all', got {args.task!r}")
    cfg = GenDataConfig(out=args.out, tasks=task_ids, episodes=args.episodes, backend=args.backend,
                        resolution=args.resolution, noise=args.noise, seed=args.seed, renderer=args.renderer,
                        max_steps=args.max_steps, wrist_camera=not args.no_wrist, overwrite=args.overwrite,
                        stop_at_success=args.stop_at_success, noisy_share=args.noisy_share,
                        init_split=args.init_split, init_start=args.init_start, init_seed=args.init_seed)
    try:
        cfg.validate()
    except ValueError as err:  # bad values are usage errors (exit 2)
        parser.error(str(err))
    return cfg


def run(cfg: GenDataConfig) -> dict:
    """Writes ``cfg.out``; returns ``{"path", "episodes", "steps"}`` as the file holds them."""
    path = generate(cfg)
    info = read_info(path)
    return {"path": path, "episodes": info.num_demos, "steps": info.total}


def main(argv: list[str] | None = None) -> dict:
    summary = run(_parse(argv))
    print(f"wrote {summary['episodes']} episodes ({summary['steps']} steps) to {summary['path']}", file=sys.stderr)
    return summary


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main, runtime_errors=(FileExistsError,))
