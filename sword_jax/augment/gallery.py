"""Gallery: one frame under several training and several held-out styles, as a labelled PNG grid.

    python -m train.gallery --out gallery.png [--source auto|sim|synthetic]
        [--size 128] [--styles 4] [--seed 0] [--intensity 1.0]

``--source sim`` renders a LIBERO-Spatial-like frame with ``sim/render.py`` (agent-view camera,
task 0's scene); ``synthetic`` uses the synthetic tabletop; ``auto`` tries sim first. The library
does not import ``sim``: :func:`main` takes the renderer as ``sim_frame`` (``train.gallery``
passes it); ``python -m sword_jax.augment.gallery`` has none, so it draws the synthetic scene. Row 1:
the original and training styles; row 2: the structure maps (depth, segmentation) and held-out
styles. Each tile is labelled with its split and table / background textures and the
structure-preservation scores against the original.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax import cli
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


def main(argv: list[str] | None = None, *, sim_frame: Callable[[int, int], Frame] | None = None) -> int:
    """Parses ``argv`` and writes the gallery PNG.

    Args:
      argv: the command line (default ``sys.argv[1:]``).
      sim_frame: ``(size, seed) -> Frame``, the simulator's rendered frame for ``--source sim|auto``
        (``train.gallery.sim_frame``); None: only the synthetic scene is available.
    """
    parser = cli.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="PNG path")
    parser.add_argument("--source", choices=("auto", "sim", "synthetic"), default="auto")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--styles", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--intensity", type=float, default=1.0)
    args = parser.parse_args(argv)
    if not 0.0 <= args.intensity <= 1.0:
        parser.error(f"--intensity must be in [0, 1], got {args.intensity}")
    if args.size < 16 or args.styles < 1:
        parser.error("--size must be >= 16 and --styles >= 1")
    if args.source == "sim" and sim_frame is None:
        parser.error("--source sim needs the simulator's renderer: run python -m train.gallery")
    source = args.source
    frame = None
    if source == "auto" and sim_frame is None:
        print("gallery: no sim renderer here (python -m train.gallery has one); using the synthetic scene",
              file=sys.stderr)
    elif source in ("auto", "sim"):
        try:
            frame = sim_frame(args.size, args.seed)
            source = "sim"
        except Exception as err:  # noqa: BLE001 - auto falls back to the synthetic scene
            if source == "sim":
                raise
            print(f"gallery: sim render unavailable ({type(err).__name__}: {err}); using the synthetic scene",
                  file=sys.stderr)
    if frame is None:
        ep = synthetic_episode(1, args.size)
        frame = (ep["frames"], ep["depth"], ep["seg"], DEFAULT_CLASSES, 45.0)
        source = "synthetic"
    frames, depth, seg, classes, fov = frame
    grid = build_gallery(frames, depth, seg, classes=classes, fov_deg=fov, num_styles=args.styles,
                         seed=args.seed, intensity=args.intensity)
    import cv2

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    if not cv2.imwrite(args.out, grid[..., ::-1]):
        raise OSError(f"gallery: could not write {args.out}")
    print(f"gallery: wrote {args.out} ({grid.shape[1]}x{grid.shape[0]}, source={source})")
    return 0


if __name__ == "__main__":
    cli.run(main)
