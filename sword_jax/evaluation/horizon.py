"""Metrics as a function of rollout horizon, from plain arrays (no model code).

Per-frame metrics (LPIPS, PSNR, SSIM, FloLPIPS) give a ``[B, T]`` array per model; the curve is
their mean (and standard error) over episodes at each frame. Set metrics (FID, FVD) are computed
per horizon window: FID over all frames of a window, FVD over each window's clips.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float


@dataclasses.dataclass(frozen=True)
class Curve:
    """One metric against horizon.

    Attributes:
      frames: horizon of each point (frame index, or a window's centre frame).
      mean: metric mean at each point.
      stderr: standard error over episodes (0 for set metrics).
    """

    frames: np.ndarray
    mean: np.ndarray
    stderr: np.ndarray

    def to_dict(self) -> dict:
        return {"frames": self.frames.tolist(), "mean": self.mean.tolist(), "stderr": self.stderr.tolist()}


def per_frame_curve(values: Float[np.ndarray, "b t"], *, frame_offset: int = 0) -> Curve:
    """Mean and standard error over episodes of a per-frame metric, at every frame.

    Args:
      values: metric per episode and frame (NaN-free).
      frame_offset: horizon of column 0 (e.g. 0 for frame metrics compared from the first frame).
    """
    values = np.asarray(values, np.float64)
    if values.ndim != 2:
        raise ValueError(f"per-frame metric must be [episodes, frames], got {values.shape}")
    if not np.isfinite(values).all():
        raise ValueError("per-frame metric contains NaN or Inf")
    n = values.shape[0]
    stderr = values.std(axis=0, ddof=1) / np.sqrt(n) if n > 1 else np.zeros(values.shape[1])
    return Curve(np.arange(values.shape[1]) + frame_offset, values.mean(axis=0), stderr)


def horizon_windows(num_frames: int, window: int, *, start: int = 0) -> list[tuple[int, int]]:
    """Consecutive ``[lo, hi)`` frame windows of length ``window`` covering ``start..num_frames``
    (a trailing remainder shorter than ``window`` is dropped)."""
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    return [(lo, lo + window) for lo in range(start, num_frames - window + 1, window)]


def binned(curve: Curve, bins: int) -> Curve:
    """A per-frame curve averaged into ``bins`` equal horizon ranges (for compact tables)."""
    edges = np.linspace(0, len(curve.frames), min(bins, len(curve.frames)) + 1).astype(int)
    frames, mean, stderr = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        frames.append(curve.frames[lo:hi].mean())
        mean.append(curve.mean[lo:hi].mean())
        stderr.append(np.sqrt(np.mean(curve.stderr[lo:hi] ** 2)))
    return Curve(np.asarray(frames), np.asarray(mean), np.asarray(stderr))
