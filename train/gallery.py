"""Style gallery: one frame under several training and several held-out styles, as a labelled PNG grid.

    python -m train.gallery --out gallery.png [--source auto|sim|synthetic]
        [--size 128] [--styles 4] [--seed 0] [--intensity 1.0]

``--source sim`` renders a LIBERO-Spatial-like frame with ``sim/render.py`` (agent-view camera, task 0's
scene); ``synthetic`` uses the synthetic tabletop; ``auto`` (the default) tries sim first and falls back
to the synthetic tabletop when the render fails. The grid is :func:`sword_jax.augment.gallery.build_gallery`'s.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np

from sword_jax import cli
from sword_jax.augment import gallery
from sword_jax.augment.style import SegClasses

FIXTURE_WORDS = ("cabinet", "stove", "drawer", "shelf", "rack")  # scene objects that count as fixtures


def sim_frame(size: int, seed: int) -> gallery.Frame:
    """One rendered agent-view frame of the LIBERO-like scene: (rgb [1, H, W, 3], depth, seg, classes, fovy)."""
    import mujoco

    from sim import render
    from sim.config import SimConfig
    from sim.env import make_env

    env = make_env(SimConfig(resolution=size), 0)
    scene = render.build_scene(env.mj_model)
    data = mujoco.MjData(env.mj_model)
    data.qpos[:] = env.initial_qpos(np.random.default_rng(seed))
    mujoco.mj_forward(env.mj_model, data)
    frame = render.render_mjdata(scene, [data], "agentview", height=size, width=size)
    fixtures = tuple(n for n in scene.class_names[3:] if any(w in n for w in FIXTURE_WORDS))
    classes = SegClasses.from_class_names(scene.class_names, fixtures=fixtures)
    rgb = np.asarray(frame.rgb, np.float32) / 255.0
    return rgb, np.asarray(frame.depth, np.float32), np.asarray(frame.seg, np.int32), classes, scene.cameras["agentview"][1]


def main(argv: Sequence[str] | None = None) -> int:
    parser = cli.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="PNG path")
    parser.add_argument("--source", choices=("auto", "sim", "synthetic"), default="auto")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--styles", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--intensity", type=float, default=1.0)
    args = parser.parse_args(None if argv is None else list(argv))
    if not 0.0 <= args.intensity <= 1.0:
        parser.error(f"--intensity must be in [0, 1], got {args.intensity}")
    if args.size < 16 or args.styles < 1:
        parser.error("--size must be >= 16 and --styles >= 1")
    frame, source = None, args.source
    if source in ("auto", "sim"):
        try:
            frame, source = sim_frame(args.size, args.seed), "sim"
        except Exception as err:  # noqa: BLE001 - auto falls back to the synthetic scene
            if source == "sim":
                raise
            print(f"gallery: sim render unavailable ({type(err).__name__}: {err}); using the synthetic scene",
                  file=sys.stderr)
    if frame is None:
        frame, source = gallery.synthetic_frame(args.size), "synthetic"
    grid = gallery.write_gallery(args.out, frame, num_styles=args.styles, seed=args.seed, intensity=args.intensity)
    print(f"gallery: wrote {args.out} ({grid.shape[1]}x{grid.shape[0]}, source={source})")
    return 0


if __name__ == "__main__":
    cli.run(main)
