"""Tile culling for ``sim/render.py``'s camera rays: each ray tests only the geoms whose screen-space
bound covers its pixel tile, and the work done follows how many (tile, geom) pairs overlap, not the
worst tile.

Per frame, every drawn geom's local bounding box (a capsule's, a cylinder's, a mesh stand-in's) is
projected through the camera; the rectangle of its 8 projected corners contains everything of it a
camera ray can hit (a perspective projection maps the box's convex hull into its corners' hull). A
geom with a corner at or behind the camera's near limit covers every tile; one wholly behind the
camera covers none (no hit has ray parameter, the planar depth, below ``_EPS``). The image is cut
into ``tile x tile`` pixel tiles; a tile's rays test a geom only if their directions' rectangle meets
the geom's.

The schedule, per geom type (one ``lax.while_loop``, so it runs under ``jit`` and ``vmap``):

* ``level k`` is the set of tiles that more than k geoms overlap, which, with the tiles sorted by
  overlap count, is a prefix of that order;
* each loop step takes ``chunk`` tiles of one level, gathers their rays' running nearest hit, tests
  each tile's k-th overlapping geom (in rank order, found from the tile's overlap row), and scatters
  the result back. A tile appears once per level, so a step's tiles are distinct and the update needs
  no atomics;
* the loop runs sum_k ceil(level_k / chunk) steps: the overlapping pairs, not (tiles x geoms). Under
  ``vmap`` a ``custom_vmap`` rule runs it to the batch's longest schedule with one predicate
  (``_culled_loop``).

Ties between equally near geoms go to the lower rank as in the dense test (``sim/render.py``), and the
same arithmetic computes each ray's ray parameter, so the frames are those of testing every geom.

Measured on LIBERO agentview states (27 rollout states of tasks 0/4/7, 128 px, 8-px tiles): a tile
overlaps on average 0.67 of the 43 moving boxes and 0.46 of the 13 capsules; the busiest tile 15 and 9.
One H100, batch 4096, 128 px (``benchmarks/bench_sim.py --tile-variants``): 359k frames/s against 173k
testing every geom, side by side.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sim.render_hits import (_BOX, _CAPSULE, _CYLINDER, _ELLIPSOID, _EPS, _HIT, _PLANE, _SPHERE, _rotate_rows,
                             camera_dirs, hit_order, ranks_of_type)

_NEAR = 1e-3  # a geom with a bounding-box corner closer than this (planar depth, m) covers every tile
_MARGIN = 1e-4  # tan-space slack on every overlap test (a pixel is 2 tan(fovy/2) / height, ~6.5e-3 at 128 px)

_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float32)  # (8, 3)


class TileLayout(NamedTuple):
    """Camera rays regrouped into square pixel tiles (edge tiles padded by repeating an edge pixel).

    Attributes:
      dirs: camera-frame ray directions in tile order, (T, P, 3), P = tile * tile.
      pixel_slot: each pixel's index into the flattened (T * P) tile order, (R,).
      slot_pixel: each slot's pixel, (T * P,).
      rect: the tile's ray directions' x/y range in the camera frame (x_lo, x_hi, y_lo, y_hi), (T, 4).
    """

    dirs: np.ndarray
    pixel_slot: np.ndarray
    slot_pixel: np.ndarray
    rect: np.ndarray


@functools.lru_cache(maxsize=32)
def tile_layout(fovy: float, height: int, width: int, tile: int) -> TileLayout:
    """The tiling of a ``height x width`` camera image into ``tile x tile`` pixel tiles.

    Raises:
      ValueError: a non-positive tile or image size.
    """
    if tile <= 0 or height <= 0 or width <= 0:
        raise ValueError(f"tile and image size must be positive, got tile {tile} for {height}x{width}")
    dirs = camera_dirs(fovy, height, width)
    rows, cols = -(-height // tile), -(-width // tile)
    tile_row, tile_col, in_row, in_col = np.meshgrid(np.arange(rows), np.arange(cols), np.arange(tile),
                                                     np.arange(tile), indexing="ij")
    y = np.minimum(tile_row * tile + in_row, height - 1)  # (rows, cols, tile, tile)
    x = np.minimum(tile_col * tile + in_col, width - 1)
    slot_pixel = (y * width + x).reshape(-1)
    real = (tile_row * tile + in_row < height) & (tile_col * tile + in_col < width)
    pixel_slot = np.empty(height * width, np.int64)
    pixel_slot[slot_pixel[real.reshape(-1)]] = np.nonzero(real.reshape(-1))[0]
    tiled = dirs[slot_pixel].reshape(rows * cols, tile * tile, 3)
    rect = np.stack([tiled[..., 0].min(1), tiled[..., 0].max(1), tiled[..., 1].min(1), tiled[..., 1].max(1)], -1)
    out = TileLayout(tiled, pixel_slot.astype(np.int32), slot_pixel.astype(np.int32), rect.astype(np.float32))
    for array in out:
        array.setflags(write=False)
    return out


def bound_half_extents(geom_type: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Half extents (n, 3) of a box in each geom's local frame (about its ``offset``) that contains it;
    ``inf`` for an infinite plane (size 0 along an axis)."""
    half = np.array(size, np.float32, copy=True)
    for i, gtype in enumerate(geom_type):
        radius, length = size[i, 0], size[i, 1]
        if gtype == _SPHERE:
            half[i] = radius
        elif gtype == _CAPSULE:
            half[i] = (radius, radius, length + radius)
        elif gtype == _CYLINDER:
            half[i] = (radius, radius, length)
        elif gtype == _PLANE:
            half[i] = (size[i, 0] if size[i, 0] > 0 else np.inf, size[i, 1] if size[i, 1] > 0 else np.inf, 0.0)
        elif gtype not in (_BOX, _ELLIPSOID):
            raise ValueError(f"no bound for geom type {gtype}")
    return half


def geom_rects(pos, mat, offset: np.ndarray, half: np.ndarray, cam_pos, cam_mat):
    """Each geom's screen-space bound (x_lo, x_hi, y_lo, y_hi), (n, 4), in the camera frame's tangent
    units (a ray direction (x, y, -1) can hit the geom only if x and y fall inside): the range of its
    bounding box's projected corners; everything where a corner is nearer than ``_NEAR`` or the bound is
    infinite, nothing where the whole box is behind ``_EPS``."""
    local = jnp.asarray(offset)[:, None, :] + jnp.asarray(np.where(np.isfinite(half), half, 0.0))[:, None, :] * _CORNERS
    world = pos[:, None, :] + _rotate_rows(local, jnp.swapaxes(mat, -1, -2)[:, None])  # mat @ v, row-wise v @ mat^T
    camera = _rotate_rows(world - cam_pos, cam_mat)  # (n, 8, 3): x right, y up, -z forward
    depth = -camera[..., 2]
    safe = jnp.where(depth > _NEAR, depth, jnp.float32(1.0))
    x, y = camera[..., 0] / safe, camera[..., 1] / safe
    rect = jnp.stack([x.min(1), x.max(1), y.min(1), y.max(1)], -1)
    everything = jnp.asarray([-jnp.inf, jnp.inf, -jnp.inf, jnp.inf], jnp.float32)
    nothing = jnp.asarray([jnp.inf, -jnp.inf, jnp.inf, -jnp.inf], jnp.float32)
    infinite = jnp.asarray(~np.all(np.isfinite(half), -1))[:, None]
    rect = jnp.where(infinite | jnp.any(depth <= _NEAR, 1, keepdims=True), everything, rect)
    return jnp.where(jnp.all(depth <= _EPS, 1, keepdims=True) & ~infinite, nothing, rect)


class _Plan(NamedTuple):
    """One frame's culled schedule for one geom type (n of its geoms, T tiles)."""

    overlap: Any  # (T, n) bool: the tile's rays can hit the geom (the type's geoms in rank order)
    tile_order: Any  # (T,): tiles by overlap count, descending; level k is its first level_size[k]
    level_size: Any  # (n,): tiles with more than k overlapping geoms
    level_end: Any  # (n,): loop steps up to and including level k
    geom_o: Any  # (n, 3): the camera position in each geom's local frame
    geom_d: Any  # (n, 3, 3): camera-frame ray directions -> local frame
    geom_size: Any  # (n, 3)
    geom_rank: Any  # (n,): rank in hit_order


def _culled_step(hit, chunk: int, tile_dirs, plan: _Plan, j, best_t, best_r):
    """Loop step j of one frame: ``chunk`` tiles of one level test their level's geom. A step past the
    frame's schedule changes nothing (every slot writes to the spare row)."""
    n_tiles, n_type = plan.overlap.shape
    # (a compare and a sum: jnp.searchsorted lowers to a loop of its own, one more per step on a GPU)
    level = jnp.minimum(jnp.sum(plan.level_end <= j, dtype=jnp.int32), n_type - 1)
    first = jnp.where(level > 0, plan.level_end[jnp.maximum(level - 1, 0)], 0)
    slot = (j - first) * chunk + jnp.arange(chunk)  # (C,) positions in the level's tile prefix
    valid = slot < plan.level_size[level]
    tiles = plan.tile_order[jnp.minimum(slot, n_tiles - 1)]
    # each tile's level-th overlapping geom: the first whose running overlap count passes the level
    geom = jnp.argmax(jnp.cumsum(plan.overlap[tiles], -1, dtype=jnp.int32) > level, -1)  # (C,)
    target = jnp.where(valid, tiles, n_tiles)
    local_d = _rotate_rows(jnp.asarray(tile_dirs)[tiles], plan.geom_d[geom][:, None])  # (C, P, 3)
    t = hit(plan.geom_o[geom][:, None, :], local_d, plan.geom_size[geom][:, None, :])  # (C, P)
    rank = plan.geom_rank[geom][:, None]
    cur_t, cur_r = best_t[target], best_r[target]
    closer = valid[:, None] & ((t < cur_t) | ((t == cur_t) & (rank < cur_r) & jnp.isfinite(t)))
    return best_t.at[target].set(jnp.where(closer, t, cur_t)), best_r.at[target].set(jnp.where(closer, rank, cur_r))


def _culled_loop(hit, chunk: int, tile_dirs: np.ndarray, plan: _Plan, best_t, best_r):
    """Runs one frame's schedule. Under ``vmap`` the loop runs to the batch's longest schedule with one
    predicate for the whole batch: a ``while_loop`` whose predicate differs per frame would instead
    select every frame's running nearest hit (the whole carry, 512 MB at 4096 x 128 px) on every
    step, which measured 2.3x slower than testing every geom on an H100. Steps past a frame's own
    schedule change nothing, so the result is the same."""

    def run(plan, best_t, best_r, total):
        def body(carry):
            j, best_t, best_r = carry
            return (j + 1, *jax.vmap(functools.partial(_culled_step, hit, chunk, tile_dirs), (0, None, 0, 0))(
                plan, j, best_t, best_r))

        _, best_t, best_r = jax.lax.while_loop(lambda carry: carry[0] < total, body, (jnp.int32(0), best_t, best_r))
        return best_t, best_r

    @jax.custom_batching.custom_vmap
    def one_frame(plan, best_t, best_r):
        lead = lambda x: x[None]  # noqa: E731
        best_t, best_r = run(jax.tree.map(lead, plan), best_t[None], best_r[None], plan.level_end[-1])
        return best_t[0], best_r[0]

    @one_frame.def_vmap
    def batched(axis_size, in_batched, plan, best_t, best_r):
        spread = lambda x, batched: x if batched else jnp.broadcast_to(x, (axis_size, *x.shape))  # noqa: E731
        plan = jax.tree.map(spread, plan, _Plan(*in_batched[0]))
        best_t, best_r = spread(best_t, in_batched[1]), spread(best_r, in_batched[2])
        return run(plan, best_t, best_r, jnp.max(plan.level_end[:, -1])), (True, True)

    return one_frame(plan, best_t, best_r)


def nearest_culled(geom_type: np.ndarray, size: np.ndarray, offset: np.ndarray, pos, mat, cam_pos, cam_mat, *,
                   fovy: float, height: int, width: int, tile: int = 8, chunk: int = 16,
                   which: np.ndarray | None = None, start: tuple[Any, Any] | None = None):
    """Nearest hit of every camera ray over the geoms ``which`` selects, testing each ray only against the
    geoms whose bound covers its tile (module docstring). The same result as
    ``sim.render._nearest_ranked(..., dir_frame=cam_mat)`` on the camera's rays.

    Args:
      geom_type, size, offset: the scene's drawn geoms (``RenderScene`` fields), (n,), (n, 3), (n, 3).
      pos, mat: their world poses, (n, 3), (n, 3, 3). cam_pos, cam_mat: the camera's, (3,), (3, 3).
      fovy, height, width: the camera image. tile: tile side in pixels. chunk: tiles per loop step.
      which: bool (n,) geoms to test (``None``: all). start: (t (R,), rank (R,)) to continue from.

    Returns:
      (t (R,), rank (R,)) per pixel, row-major: the nearest ray parameter (+inf on a miss) and the
      winner's rank in ``hit_order`` (n on a miss).

    Raises:
      ValueError: a non-positive tile or chunk.
    """
    if chunk <= 0:
        raise ValueError(f"chunk must be positive, got {chunk}")
    order = hit_order(geom_type)
    layout = tile_layout(fovy, height, width, tile)
    n_tiles, per_tile = layout.dirs.shape[:2]
    if start is None:
        best_t = jnp.full((n_tiles, per_tile), jnp.inf, jnp.float32)
        best_r = jnp.full((n_tiles, per_tile), len(order), jnp.int32)
    else:
        best_t = start[0][layout.slot_pixel].reshape(n_tiles, per_tile)
        best_r = start[1][layout.slot_pixel].reshape(n_tiles, per_tile)
    # one spare row that the steps' unused slots write to
    best_t = jnp.concatenate([best_t, jnp.zeros((1, per_tile), jnp.float32)])
    best_r = jnp.concatenate([best_r, jnp.zeros((1, per_tile), jnp.int32)])
    rects = geom_rects(pos, mat, offset, bound_half_extents(geom_type, size), cam_pos, cam_mat)  # (n, 4)
    tile_rect = jnp.asarray(layout.rect)
    for gtype, hit in _HIT.items():
        ranks, idx = ranks_of_type(order, geom_type, gtype, which)
        if ranks.size == 0:
            continue
        n_type = len(idx)
        rect = rects[idx]
        overlap = ((rect[None, :, 0] <= tile_rect[:, 1:2] + _MARGIN) & (rect[None, :, 1] >= tile_rect[:, 0:1] - _MARGIN)
                   & (rect[None, :, 2] <= tile_rect[:, 3:4] + _MARGIN) & (rect[None, :, 3] >= tile_rect[:, 2:3] - _MARGIN))
        count = overlap.sum(1, dtype=jnp.int32)  # (T,)
        tile_order = jnp.argsort(-count, stable=True).astype(jnp.int32)  # {count > k} is a prefix of it
        level_size = jnp.sum(count[None, :] > jnp.arange(n_type)[:, None], 1, dtype=jnp.int32)  # (n_type,)
        plan = _Plan(overlap, tile_order, level_size, jnp.cumsum(-(-level_size // chunk)),
                     _rotate_rows(cam_pos[None, :] - pos[idx], mat[idx]) - jnp.asarray(offset[idx]),  # camera, local
                     jnp.einsum("ji,njk->nik", cam_mat, mat[idx]),  # camera-frame directions -> local frame
                     jnp.asarray(size[idx]), jnp.asarray(ranks, jnp.int32))
        best_t, best_r = _culled_loop(hit, chunk, layout.dirs, plan, best_t, best_r)
    slot_of_pixel = jnp.asarray(layout.pixel_slot)
    return best_t[:-1].reshape(-1)[slot_of_pixel], best_r[:-1].reshape(-1)[slot_of_pixel]
