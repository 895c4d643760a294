"""Style gallery of a rendered LIBERO-Spatial-like frame: :mod:`sword_jax.augment.gallery` with the sim.

    python -m train.gallery --out gallery.png [--source auto|sim|synthetic]
        [--size 128] [--styles 4] [--seed 0] [--intensity 1.0]

``--source sim`` renders task 0's scene from the agent-view camera with ``sim/render.py``;
``auto`` (the default) falls back to the synthetic tabletop when the render fails.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

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
    return gallery.main(None if argv is None else list(argv), sim_frame=sim_frame)


if __name__ == "__main__":
    from sword_jax.cli import run

    run(main)
