"""Gallery: one frame under several training and several held-out styles, as a labelled PNG grid.

The command line is ``python -m train.gallery``, which passes the simulator's rendered frame (the
library does not import ``sim``); :func:`synthetic_frame` is the synthetic tabletop. Row 1: the
original and training styles; row 2: the structure maps (depth, segmentation) and held-out styles.
Each tile is labelled with its split and table / background textures and the structure-preservation
scores against the original.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax.augment.style import DEFAULT_CLASSES, TEXTURES, SegClasses, sample_styles
from sword_jax.augment.structure import structure_scores
from sword_jax.augment.synthetic import synthetic_episode
from sword_jax.augment.transforms import augment_styles
from sword_jax.rng import stream_key

# (frames [1, H, W, 3] in [0, 1], depth [1, H, W], seg [1, H, W], classes, vertical fov in degrees)
Frame = tuple[np.ndarray, np.ndarray, np.ndarray, SegClasses, float]


def _label(tile: np.ndarray, lines: list[str]) -> np.ndarray:
    import cv2

    band = np.full((16 * len(lines) + 4, tile.shape[1], 3), 255, np.uint8)
    for i, line in enumerate(lines):
        cv2.putText(band, line, (4, 14 + 16 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, tile], axis=0)


def _tile(image: np.ndarray, scale: int) -> np.ndarray:
    return np.kron((np.clip(image, 0, 1) * 255).round().astype(np.uint8), np.ones((scale, scale, 1), np.uint8))


def _colorize(values: np.ndarray) -> np.ndarray:
    import matplotlib

    return matplotlib.colormaps["viridis"](values)[..., :3].astype(np.float32)


def build_gallery(
    frames: np.ndarray, depth: np.ndarray, seg: np.ndarray, *, classes: SegClasses, fov_deg: float,
    num_styles: int = 4, seed: int = 0, intensity: float = 1.0, tile_px: int = 256,
) -> np.ndarray:
    """The grid as an RGB uint8 image."""
    scale = max(1, round(tile_px / frames.shape[1]))
    rows = []
    for split in ("train", "heldout"):
        styles = sample_styles(stream_key(jax.random.key(seed), f"gallery/{split}_styles"), num_styles, split)
        # Inputs are arguments, not closed-over constants, so XLA does not constant-fold them.
        styled = jax.jit(lambda f, d, g, st: augment_styles(f, d, g, st, intensity=intensity, classes=classes,
                                                            fov_deg=fov_deg))(frames, depth, seg, styles)
        scores = jax.jit(jax.vmap(lambda f, out, g: structure_scores(f, out, g, classes), in_axes=(None, 0, None)))(
            jnp.asarray(frames), styled, jnp.asarray(seg))
        if split == "train":
            row = [_label(_tile(frames[0], scale), ["original (raw)", "", "", ""])]
        else:
            finite = np.where(np.isfinite(depth[0]), depth[0], depth[0][np.isfinite(depth[0])].max())
            d = np.log(np.clip(finite, 0.1, None))
            d = (d - d.min()) / max(d.max() - d.min(), 1e-6)
            seg_vis = (seg[0].astype(np.float32) % 10) / 9.0
            structure = np.concatenate([_colorize(1 - d)[: frames.shape[1] // 2], _colorize(seg_vis)[frames.shape[1] // 2:]])
            row = [_label(_tile(structure, scale), ["structure kept by augment:", "depth (top half)", "segmentation (bottom half)", ""])]
        for i in range(num_styles):
            tex_table = TEXTURES[int(styles.table.texture[i])]
            tex_bg = TEXTURES[int(styles.background.texture[i])]
            lines = [f"{split} style #{i}",
                     f"table {tex_table} / bg {tex_bg}",
                     f"hue {float(styles.hue_shift[i]):+.2f} sat {float(styles.saturation[i]):.2f}"
                     f" temp {float(styles.temperature[i]):+.2f}",
                     f"boundary recall {float(scores['boundary_recall'][i]):.2f}"]
            row.append(_label(_tile(np.asarray(styled[i, 0]), scale), lines))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)


def synthetic_frame(size: int) -> Frame:
    """The synthetic tabletop's first frame at ``size`` x ``size``, as a :data:`Frame` (45 degree fov)."""
    episode = synthetic_episode(1, size)
    return episode["frames"], episode["depth"], episode["seg"], DEFAULT_CLASSES, 45.0


def write_gallery(path: str, frame: Frame, *, num_styles: int = 4, seed: int = 0,
                  intensity: float = 1.0) -> np.ndarray:
    """Builds the grid of ``frame`` (:func:`build_gallery`), writes it to ``path`` as a PNG and returns it.

    Raises:
      OSError: the PNG could not be written.
    """
    import cv2

    frames, depth, seg, classes, fov = frame
    grid = build_gallery(frames, depth, seg, classes=classes, fov_deg=fov, num_styles=num_styles, seed=seed,
                         intensity=intensity)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if not cv2.imwrite(path, grid[..., ::-1]):
        raise OSError(f"gallery: could not write {path}")
    return grid
