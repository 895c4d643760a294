"""Comparing two renders of one scene made by two XLA programs (or two pose computations).

The same arithmetic compiled into another program may round differently on another CPU, so a pixel
on a silhouette can hit the neighbouring surface, and a grazing hit can move its depth by more than
a rounding step. Such frames agree on every pixel but a bounded share of silhouette pixels; those
must still hit the same surface within a stated depth tolerance, or count against the share.
"""

from __future__ import annotations

import numpy as np

SILHOUETTE_SHARE = 0.002  # of the pixels; at least 2 pixels are always allowed
SILHOUETTE_DEPTH_ATOL = 1e-3  # metres, on a pixel whose surface agrees but whose hit grazes it


def assert_frames_agree(depth, ref_depth, ids, ref_ids, *, depth_atol: float = 1e-5,
                        share: float = SILHOUETTE_SHARE, silhouette_depth_atol: float = SILHOUETTE_DEPTH_ATOL,
                        rgb=None, ref_rgb=None, rgb_mean_atol: float = 0.3) -> None:
    """All pixels but a bounded number agree: the same surface id and depth within ``depth_atol``;
    the others (at most ``share`` of the pixels, at least 2) may hit another surface, or the same
    surface within ``silhouette_depth_atol``. Optional colours agree on average within ``rgb_mean_atol``.

    Args:
      depth / ref_depth: ``(..., H, W)`` float depths.
      ids / ref_ids: ``(..., H, W)`` the surface each pixel hit (geom id or segmentation class).
    """
    depth, ref_depth = np.asarray(depth, np.float64), np.asarray(ref_depth, np.float64)
    ids, ref_ids = np.asarray(ids), np.asarray(ref_ids)
    assert depth.shape == ref_depth.shape and ids.shape == ref_ids.shape == depth.shape, (depth.shape, ids.shape)
    same_surface = ids == ref_ids
    error = np.abs(depth - ref_depth)
    exact = same_surface & (error <= depth_atol)
    allowed = max(2, int(share * depth.size))
    outliers = int((~exact).sum())
    assert outliers <= allowed, (f"{outliers} of {depth.size} pixels differ (allowed {allowed}): "
                                 f"{int((~same_surface).sum())} hit another surface, largest depth error "
                                 f"{float(error[same_surface].max(initial=0.0)):.3g}")
    grazing = error[same_surface & ~exact]
    assert grazing.size == 0 or grazing.max() <= silhouette_depth_atol, (
        f"a pixel on the same surface is {grazing.max():.3g} deep off (allowed {silhouette_depth_atol})")
    if rgb is not None:
        assert np.abs(np.asarray(rgb, np.int32) - np.asarray(ref_rgb, np.int32)).mean() < rgb_mean_atol
