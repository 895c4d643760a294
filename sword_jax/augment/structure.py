"""Measures of structure preservation between original and styled frames.

* ``edge_f1``: F1 of the colour-edge map of the styled frames against the original's, with a
  1-pixel matching tolerance (BSDS-style). Textures add edges inside surfaces, so this is the
  measure for untextured changes (colour, lighting, robot colour).
* ``boundary_recall``: share of segmentation-boundary pixels (where the region group changes)
  that are still on an edge of the styled frames (1-pixel tolerance): object outlines stay
  visible. Reported next to the original frames' own recall (``boundary_recall_original``).
* ``depth_edge_recall``: the same for depth discontinuities (relative second difference > 2%):
  geometry stays visible (``depth_edge_recall_original`` for the raw frames).
* ``off_boundary_new_edges``: share of non-texture-region pixels that are edges in the styled
  frames, away from every original edge: made-up structure on untextured surfaces.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from sword_jax.augment.style import DEFAULT_CLASSES, SegClasses

EDGE_THRESHOLD = 0.08  # Sobel magnitude (per colour channel, [0, 1] frames) that counts as an edge
_SOBEL_X = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], np.float32) / 4
_GROUPS = ("background", "table", "robot", "objects", "fixtures")


def _dilate(mask: Bool[Array, "t h w"], radius: int = 1) -> Bool[Array, "t h w"]:
    size = 2 * radius + 1
    out = jax.lax.reduce_window(mask.astype(jnp.float32), -jnp.inf, jax.lax.max, (1, size, size), (1, 1, 1), "SAME")
    return out > 0


def edge_map(frames: Float[Array, "t h w 3"], threshold: float = EDGE_THRESHOLD) -> Bool[Array, "t h w"]:
    """Pixels whose strongest per-channel Sobel gradient exceeds ``threshold``."""
    channels = jnp.moveaxis(frames.astype(jnp.float32), -1, 1)  # (T, 3, H, W)
    t, c, h, w = channels.shape
    x = channels.reshape(t * c, 1, h, w)
    padded = jnp.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1)), mode="edge")
    kx = jnp.asarray(_SOBEL_X)[None, None]
    ky = jnp.asarray(_SOBEL_X.T.copy())[None, None]
    gx = jax.lax.conv_general_dilated(padded, kx, (1, 1), "VALID")
    gy = jax.lax.conv_general_dilated(padded, ky, (1, 1), "VALID")
    magnitude = jnp.sqrt(gx * gx + gy * gy).reshape(t, c, h, w).max(axis=1)
    return magnitude > threshold


def segmentation_boundaries(seg: Int[Array, "t h w"], classes: SegClasses = DEFAULT_CLASSES) -> Bool[Array, "t h w"]:
    """Pixels with a 4-neighbour in another region group (ids of one group do not split)."""
    group = jnp.full(seg.shape, -1, jnp.int32)
    for index, name in enumerate(_GROUPS):
        group = jnp.where(classes.mask(seg, name), index, group)
    group = jnp.where(group < 0, seg.astype(jnp.int32) + 100, group)
    down = group[:, 1:, :] != group[:, :-1, :]
    right = group[:, :, 1:] != group[:, :, :-1]
    boundary = jnp.zeros(seg.shape, bool)
    boundary = boundary.at[:, 1:, :].set(boundary[:, 1:, :] | down).at[:, :-1, :].set(boundary[:, :-1, :] | down)
    boundary = boundary.at[:, :, 1:].set(boundary[:, :, 1:] | right).at[:, :, :-1].set(boundary[:, :, :-1] | right)
    return boundary


def depth_edges(depth: Float[Array, "t h w"], relative_step: float = 0.02) -> Bool[Array, "t h w"]:
    """Pixels at a depth discontinuity: relative second difference above ``relative_step``.

    A second difference ignores smooth slopes (a table receding in depth) and fires at steps.
    """
    d = jnp.clip(jnp.where(jnp.isfinite(depth), depth, 1e3), 1e-3, 1e3)
    padded = jnp.pad(d, ((0, 0), (1, 1), (1, 1)), mode="edge")
    second_y = padded[:, 2:, 1:-1] - 2 * d + padded[:, :-2, 1:-1]
    second_x = padded[:, 1:-1, 2:] - 2 * d + padded[:, 1:-1, :-2]
    return jnp.maximum(jnp.abs(second_y), jnp.abs(second_x)) / d > relative_step


def edge_f1(reference: Bool[Array, "t h w"], candidate: Bool[Array, "t h w"], tolerance: int = 1) -> jax.Array:
    """F1 of ``candidate`` edges against ``reference`` edges, matching within ``tolerance`` pixels."""
    ref = reference.astype(jnp.float32)
    cand = candidate.astype(jnp.float32)
    precision = jnp.sum(cand * _dilate(reference, tolerance).astype(jnp.float32)) / jnp.maximum(jnp.sum(cand), 1.0)
    recall = jnp.sum(ref * _dilate(candidate, tolerance).astype(jnp.float32)) / jnp.maximum(jnp.sum(ref), 1.0)
    return 2 * precision * recall / jnp.maximum(precision + recall, 1e-8)


def structure_scores(
    original: Float[Array, "t h w 3"],
    styled: Float[Array, "t h w 3"],
    seg: Int[Array, "t h w"],
    classes: SegClasses = DEFAULT_CLASSES,
    textured: tuple[str, ...] = ("table", "background"),
    depth: Float[Array, "t h w"] | None = None,
) -> dict[str, jax.Array]:
    """The three structure measures of the module docstring (scalars in [0, 1])."""
    edges_before = edge_map(original)
    edges_after = edge_map(styled)
    boundary = segmentation_boundaries(seg, classes).astype(jnp.float32)
    n_boundary = jnp.maximum(jnp.sum(boundary), 1.0)
    untextured = jnp.ones(seg.shape, bool)
    for name in textured:
        untextured &= ~classes.mask(seg, name)
    untextured &= ~(boundary > 0)
    new_edges = edges_after & ~_dilate(edges_before, 1) & untextured
    scores = {}
    if depth is not None:
        step = depth_edges(depth).astype(jnp.float32)
        n_step = jnp.maximum(jnp.sum(step), 1.0)
        scores["depth_edge_recall"] = jnp.sum(step * _dilate(edges_after, 1).astype(jnp.float32)) / n_step
        scores["depth_edge_recall_original"] = jnp.sum(step * _dilate(edges_before, 1).astype(jnp.float32)) / n_step
    return scores | {
        "edge_f1": edge_f1(edges_before, edges_after),
        "boundary_recall": jnp.sum(boundary * _dilate(edges_after, 1).astype(jnp.float32)) / n_boundary,
        "boundary_recall_original": jnp.sum(boundary * _dilate(edges_before, 1).astype(jnp.float32)) / n_boundary,
        "off_boundary_new_edges": jnp.sum(new_edges.astype(jnp.float32)) / jnp.maximum(jnp.sum(untextured.astype(jnp.float32)), 1.0),
    }
