"""Input preprocessing the reference metric codes apply: PyTorch bilinear resize, FVD clip prep.

``jax.image.resize`` antialiases when shrinking, PyTorch's ``interpolate(mode='bilinear',
align_corners=False)`` does not; pytorch-fid and the common FVD code use the latter, so it is
reimplemented here (half-pixel centres, source coordinate clamped below at 0, upper neighbour
clamped to the last pixel, float32 arithmetic).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def _source_index(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lower/upper source indices and the upper blend weight for each output index (float32)."""
    scale = np.float32(in_size / out_size)
    src = (np.arange(out_size, dtype=np.float32) + np.float32(0.5)) * scale - np.float32(0.5)
    src = np.maximum(src, np.float32(0))
    lower = np.minimum(np.floor(src).astype(np.int32), in_size - 1)
    upper = np.minimum(lower + 1, in_size - 1)
    lam = (src - lower.astype(np.float32)).astype(np.float32)
    return lower, upper, lam


def _resize_axis(x: Array, axis: int, out_size: int) -> Array:
    in_size = x.shape[axis]
    if in_size == out_size:
        return x  # torch's scale is exactly 1: every source coordinate hits a pixel
    lower, upper, lam = _source_index(in_size, out_size)
    shape = [1] * x.ndim
    shape[axis] = out_size
    lam = jnp.asarray(lam).reshape(shape)
    x_lo = jnp.take(x, jnp.asarray(lower), axis=axis)
    x_hi = jnp.take(x, jnp.asarray(upper), axis=axis)
    return x_lo * (jnp.float32(1) - lam) + x_hi * lam


def resize_bilinear_torch(x: Float[Array, "b h w c"], size: tuple[int, int]) -> Float[Array, "b oh ow c"]:
    """PyTorch ``interpolate(x, size, mode='bilinear', align_corners=False)``, no antialias.

    Args:
      x: channels-last images (any leading batch dims before H, W, C).
      size: output ``(height, width)``.

    Returns:
      The resized images, float32.
    """
    x = jnp.asarray(x, jnp.float32)
    x = _resize_axis(x, x.ndim - 2, size[1])
    return _resize_axis(x, x.ndim - 3, size[0])


def fvd_resize_crop_size(height: int, width: int, resolution: int = 224) -> tuple[int, int]:
    """The resized ``(H, W)`` of common_metrics' styleganv ``preprocess_single`` (shorter side -> 224)."""
    scale = resolution / min(height, width)
    if height < width:
        return resolution, math.ceil(width * scale)
    return math.ceil(height * scale), resolution


def fvd_preprocess(video: Float[Array, "b t h w c"], resolution: int = 224) -> Float[Array, "b t r r c"]:
    """FVD clip preprocessing (common_metrics_on_video_quality, styleganv ``preprocess_single``).

    Resize each frame so the shorter side is ``resolution`` (bilinear, no antialias, target size
    ``ceil`` of the scaled longer side), center crop ``resolution`` x ``resolution`` starting at
    ``floor((size - resolution) / 2)``, then map [0, 1] -> [-1, 1].

    Args:
      video: videos in [0, 1], channels-last.
      resolution: the I3D input size.

    Returns:
      The I3D input in [-1, 1].
    """
    b, t, h, w, c = video.shape
    out_h, out_w = fvd_resize_crop_size(h, w, resolution)
    frames = resize_bilinear_torch(jnp.reshape(video, (b * t, h, w, c)), (out_h, out_w))
    top, left = (out_h - resolution) // 2, (out_w - resolution) // 2
    frames = frames[:, top : top + resolution, left : left + resolution]
    frames = (frames - jnp.float32(0.5)) * jnp.float32(2)
    return jnp.reshape(frames, (b, t, resolution, resolution, c))


def check_range(x, low: float, high: float, name: str, *, slack: float = 1e-3) -> None:
    """Raises ValueError if a host-visible array is non-finite or outside ``[low, high]`` (+ slack)."""
    arr = np.asarray(x)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    if arr.size and (arr.min() < low - slack or arr.max() > high + slack):
        raise ValueError(f"{name}: values in [{arr.min():.4g}, {arr.max():.4g}], expected [{low}, {high}]")
