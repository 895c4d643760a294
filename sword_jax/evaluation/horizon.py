"""Metrics as a function of rollout horizon, from plain arrays (no model code).

Per-frame metrics (LPIPS, PSNR, SSIM, FloLPIPS) give a ``[B, T]`` array per model; the curve is
their mean over episodes at each frame, with the standard error and a percentile bootstrap
interval over episodes (episodes resampled with replacement; the same resamples for every frame, so
the whole-horizon mean gets an interval too). Set metrics (FID, FVD) are computed per horizon
window: FID over all frames of a window, FVD over each window's clips (no interval).
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
      ci_low, ci_high: bootstrap interval of the mean over episodes at each point (``None`` for set
        metrics); ``ci_level`` its coverage.
      overall_ci: bootstrap interval of the mean over episodes and every frame, ``(low, high)``.
    """

    frames: np.ndarray
    mean: np.ndarray
    stderr: np.ndarray
    ci_low: np.ndarray | None = None
    ci_high: np.ndarray | None = None
    ci_level: float | None = None
    overall_ci: tuple[float, float] | None = None

    def to_dict(self) -> dict:
        out = {"frames": self.frames.tolist(), "mean": self.mean.tolist(), "stderr": self.stderr.tolist()}
        if self.ci_low is not None:
            out.update(ci_low=self.ci_low.tolist(), ci_high=self.ci_high.tolist(), ci_level=self.ci_level,
                       overall_ci=list(self.overall_ci))
        return out


# Resamples of the episode bootstrap, and its coverage: 2,000 x 100 episodes x 64 frames is ~0.1 s.
BOOTSTRAP_SAMPLES = 2000
BOOTSTRAP_LEVEL = 0.95


def bootstrap_mean_interval(values: Float[np.ndarray, "b *t"], *, samples: int = BOOTSTRAP_SAMPLES,
                            level: float = BOOTSTRAP_LEVEL, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Percentile bootstrap interval of the mean over episodes (axis 0), resampling episodes with replacement.

    Args:
      values: metric per episode (and per frame, ...).
      samples: bootstrap resamples.
      level: coverage, e.g. 0.95.
      seed: resampling seed (host numpy; deterministic).

    Returns:
      ``(low, high)``, each shaped ``values.shape[1:]``; both equal the mean for a single episode.
    """
    values = np.asarray(values, np.float64)
    n = values.shape[0]
    if n < 2:
        return values.mean(axis=0), values.mean(axis=0)
    index = np.random.default_rng(seed).integers(0, n, (samples, n))
    # Counts per episode per resample: the resampled means are one matmul, not a [S, N, T] gather.
    counts = np.zeros((samples, n), np.float64)
    np.add.at(counts, (np.arange(samples)[:, None], index), 1.0)
    means = (counts @ values.reshape(n, -1) / n).reshape((samples,) + values.shape[1:])
    tail = (1.0 - level) / 2.0
    low, high = np.quantile(means, [tail, 1.0 - tail], axis=0)
    return low, high


def per_frame_curve(values: Float[np.ndarray, "b t"], *, frame_offset: int = 0, samples: int = BOOTSTRAP_SAMPLES,
                    level: float = BOOTSTRAP_LEVEL, seed: int = 0) -> Curve:
    """Mean, standard error and bootstrap interval over episodes of a per-frame metric, at every frame.

    Args:
      values: metric per episode and frame (NaN-free).
      frame_offset: horizon of column 0 (e.g. 0 for frame metrics compared from the first frame).
      samples, level, seed: of the bootstrap over episodes (:func:`bootstrap_mean_interval`).
    """
    values = np.asarray(values, np.float64)
    if values.ndim != 2:
        raise ValueError(f"per-frame metric must be [episodes, frames], got {values.shape}")
    if not np.isfinite(values).all():
        raise ValueError("per-frame metric contains NaN or Inf")
    n = values.shape[0]
    stderr = values.std(axis=0, ddof=1) / np.sqrt(n) if n > 1 else np.zeros(values.shape[1])
    # Frame columns and the whole-horizon mean from the same resamples.
    with_overall = np.concatenate([values, values.mean(axis=1, keepdims=True)], axis=1)
    low, high = bootstrap_mean_interval(with_overall, samples=samples, level=level, seed=seed)
    return Curve(np.arange(values.shape[1]) + frame_offset, values.mean(axis=0), stderr, low[:-1], high[:-1],
                 float(level), (float(low[-1]), float(high[-1])))


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
