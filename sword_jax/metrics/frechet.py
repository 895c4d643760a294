"""Frechet distance between Gaussian fits of feature sets (FID, FVD), in float64 on the host.

``d^2 = |mu1 - mu2|^2 + tr(S1) + tr(S2) - 2 tr((S1 S2)^{1/2})``. The trace of the square root is
computed stably as ``tr((A^{1/2} B A^{1/2})^{1/2})`` -- the same eigenvalues as ``S1 S2`` but a
symmetric PSD matrix, so two symmetric eigendecompositions (tiny negative eigenvalues from rounding
clipped to 0) replace scipy's non-symmetric ``sqrtm``; it agrees with pytorch-fid's scipy path to
~1e-13 on well-conditioned and ~1e-8 on rank-deficient covariances.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float


@dataclasses.dataclass(frozen=True)
class GaussianStats:
    """Mean and covariance of a feature set, float64."""

    mu: np.ndarray  # (D,)
    sigma: np.ndarray  # (D, D)
    count: int


def feature_stats(features: Float[np.ndarray, "n d"], *, unbiased: bool = True) -> GaussianStats:
    """Mean and covariance (float64) of ``features``.

    Args:
      features: one feature vector per sample.
      unbiased: divide by N - 1 (``numpy.cov``, pytorch-fid, common_metrics) or by N (StyleGAN-V).
    """
    feats = np.asarray(features, np.float64)
    if feats.ndim != 2:
        raise ValueError(f"features must be [N, D], got shape {feats.shape}")
    if not np.isfinite(feats).all():
        raise ValueError("features contain NaN or Inf")
    n = feats.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 samples for a covariance, got {n}")
    mu = feats.mean(axis=0)
    centred = feats - mu
    sigma = centred.T @ centred / (n - 1 if unbiased else n)
    return GaussianStats(mu, sigma, n)


def _psd_sqrt(matrix: np.ndarray) -> np.ndarray:
    vals, vecs = np.linalg.eigh((matrix + matrix.T) / 2)
    return (vecs * np.sqrt(np.clip(vals, 0, None))) @ vecs.T


def frechet_distance(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2), float64.

    Raises:
      ValueError: mismatched shapes or non-finite statistics.
    """
    mu1, mu2 = np.asarray(mu1, np.float64), np.asarray(mu2, np.float64)
    sigma1, sigma2 = np.asarray(sigma1, np.float64), np.asarray(sigma2, np.float64)
    if mu1.shape != mu2.shape or sigma1.shape != sigma2.shape or sigma1.shape != mu1.shape * 2:
        raise ValueError(f"statistics shapes differ: mu {mu1.shape}/{mu2.shape}, sigma {sigma1.shape}/{sigma2.shape}")
    for name, arr in (("mu1", mu1), ("mu2", mu2), ("sigma1", sigma1), ("sigma2", sigma2)):
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} contains NaN or Inf")
    root1 = _psd_sqrt(sigma1)
    inner = root1 @ sigma2 @ root1
    eigvals = np.linalg.eigvalsh((inner + inner.T) / 2)
    tr_covmean = float(np.sqrt(np.clip(eigvals, 0, None)).sum())
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(sigma1) + np.trace(sigma2) - 2.0 * tr_covmean)


def frechet_distance_from_features(feats1: Float[np.ndarray, "n d"], feats2: Float[np.ndarray, "m d"], *,
                                   unbiased: bool = True) -> float:
    """Frechet distance between two feature sets (FID: pool3 features; FVD: I3D logits)."""
    s1, s2 = feature_stats(feats1, unbiased=unbiased), feature_stats(feats2, unbiased=unbiased)
    return frechet_distance(s1.mu, s1.sigma, s2.mu, s2.sigma)
