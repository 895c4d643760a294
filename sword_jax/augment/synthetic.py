"""A tiny synthetic tabletop scene with frames, depth and segmentation (tests, gallery, benchmarks).

Layout (default :data:`~sword_jax.augment.style.DEFAULT_CLASSES` ids): a far wall (background,
id 0) over a table plane receding in depth (id 1), a "robot" arm blob sweeping across the table
(id 2), two coloured boxes (objects, id 3) and a cabinet (fixture, id 4). Deterministic numpy.
"""

from __future__ import annotations

import numpy as np

from sword_jax.augment.style import DEFAULT_CLASSES, SegClasses

OBJECT_COLORS = np.array([[0.85, 0.15, 0.15], [0.15, 0.35, 0.85]], np.float32)


def synthetic_episode(
    num_frames: int = 4,
    size: int = 32,
    *,
    classes: SegClasses = DEFAULT_CLASSES,
    phase: float = 0.0,
) -> dict[str, np.ndarray]:
    """One episode: ``frames [T, H, W, 3]`` in [0, 1], ``depth [T, H, W]`` metres, ``seg [T, H, W]`` int32,
    ``actions [T, 7]`` float32."""
    h = w = size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    yn, xn = ys / h, xs / w  # [0, 1)
    horizon = 0.35
    frames = np.zeros((num_frames, h, w, 3), np.float32)
    depth = np.zeros((num_frames, h, w), np.float32)
    seg = np.zeros((num_frames, h, w), np.int32)
    actions = np.zeros((num_frames, 7), np.float32)
    for t in range(num_frames):
        wall = yn < horizon
        # Wall: flat at 3 m, light grey with a soft vertical falloff.
        depth[t][wall] = 3.0
        frames[t][wall] = np.array([0.70, 0.72, 0.75], np.float32) * (0.85 + 0.15 * yn[wall] / horizon)[:, None]
        seg[t][wall] = classes.background[0]
        # Table: depth ramps from 2.0 m (far edge) to 0.7 m (near edge); wood-ish brown.
        table = ~wall
        ramp = (yn - horizon) / (1 - horizon)
        depth[t][table] = 2.0 - 1.3 * ramp[table]
        frames[t][table] = np.array([0.55, 0.40, 0.25], np.float32) * (0.8 + 0.3 * ramp[table])[:, None]
        seg[t][table] = classes.table[0]
        # Fixture: a cabinet on the left, in front of the wall.
        cabinet = (xn > 0.05) & (xn < 0.25) & (yn > 0.2) & (yn < 0.5)
        depth[t][cabinet] = 1.8
        frames[t][cabinet] = np.array([0.35, 0.35, 0.4], np.float32)
        seg[t][cabinet] = classes.fixtures[0]
        # Objects: two boxes on the table (slightly closer than the table under them).
        for i, (cx, cy) in enumerate(((0.45, 0.7), (0.75, 0.6))):
            box = (np.abs(xn - cx) < 0.08) & (np.abs(yn - cy) < 0.08)
            depth[t][box] = depth[t][box] - 0.05
            shade = 0.8 + 0.2 * (xn[box] - cx + 0.08) / 0.16
            frames[t][box] = OBJECT_COLORS[i] * shade[:, None]
            seg[t][box] = classes.objects[0]
        # Robot: a vertical arm from the top with a gripper block, sweeping left-right over time.
        x0 = 0.35 + 0.3 * (0.5 + 0.5 * np.sin(phase + 2 * np.pi * t / max(num_frames, 2)))
        arm = (np.abs(xn - x0) < 0.05) & (yn < 0.55)
        gripper = (np.abs(xn - x0) < 0.09) & (yn >= 0.55) & (yn < 0.65)
        robot = arm | gripper
        depth[t][robot] = 0.9 + 0.3 * yn[robot]
        frames[t][robot] = np.array([0.9, 0.9, 0.9], np.float32) * (0.7 + 0.3 * (1 - np.abs(xn[robot] - x0) / 0.09))[:, None]
        seg[t][robot] = classes.robot[0]
        actions[t] = [x0, 0.0, 0.0, 0.0, 0.0, 0.0, float(t % 2)]
    return {"frames": np.clip(frames, 0.0, 1.0), "depth": depth, "seg": seg, "actions": actions}


def synthetic_episodes(num: int, num_frames: int = 4, size: int = 32, **kwargs) -> dict[str, np.ndarray]:
    """``num`` episodes stacked on a leading axis, with ``episode_ids`` 0..num-1."""
    eps = [synthetic_episode(num_frames, size, phase=0.7 * i, **kwargs) for i in range(num)]
    out = {k: np.stack([e[k] for e in eps]) for k in eps[0]}
    out["episode_ids"] = np.arange(num, dtype=np.int64)
    return out
