"""PSNR and SSIM per frame (JAX), images in [0, 1].

SSIM follows Wang et al. 2004 as scikit-image's ``structural_similarity(gaussian_weights=True,
sigma=1.5, use_sample_covariance=False, data_range=1)`` computes it: 11 x 11 Gaussian window
(sigma 1.5), K1 = 0.01, K2 = 0.03, 'valid' filtering, mean over positions and channels.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def psnr(pred: Float[Array, "*b h w c"], target: Float[Array, "*b h w c"], *, max_value: float = 1.0,
         eps: float = 1e-10) -> Float[Array, "*b"]:
    """Peak signal-to-noise ratio in dB per image (identical images give ``10 log10(max^2 / eps)``)."""
    if pred.shape != target.shape:
        raise ValueError(f"PSNR inputs differ in shape: {pred.shape} vs {target.shape}")
    mse = jnp.mean((pred.astype(jnp.float32) - target.astype(jnp.float32)) ** 2, axis=(-3, -2, -1))
    return jnp.float32(10) * jnp.log10(jnp.float32(max_value**2) / (mse + jnp.float32(eps)))


def _gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    coords = np.arange(size, dtype=np.float64) - (size - 1) / 2
    g = np.exp(-(coords**2) / (2 * sigma**2))
    return (g / g.sum()).astype(np.float32)


def _filter(x: Array, window: Array) -> Array:
    """Separable 'valid' Gaussian filter over H, W of [N, H, W, C] (depthwise)."""
    n, h, w, c = x.shape
    x = jnp.moveaxis(x, -1, 1).reshape(n * c, h, w, 1)
    kh = window.reshape(-1, 1, 1, 1)
    kw = window.reshape(1, -1, 1, 1)
    dn = ("NHWC", "HWIO", "NHWC")
    hi = jax.lax.Precision.HIGHEST
    x = jax.lax.conv_general_dilated(x, kh, (1, 1), "VALID", dimension_numbers=dn, precision=hi)
    x = jax.lax.conv_general_dilated(x, kw, (1, 1), "VALID", dimension_numbers=dn, precision=hi)
    return jnp.moveaxis(x.reshape(n, c, *x.shape[1:3]), 1, -1)


def ssim(pred: Float[Array, "*b h w c"], target: Float[Array, "*b h w c"], *, max_value: float = 1.0,
         window_size: int = 11, sigma: float = 1.5) -> Float[Array, "*b"]:
    """Structural similarity per image (1 for identical images)."""
    if pred.shape != target.shape:
        raise ValueError(f"SSIM inputs differ in shape: {pred.shape} vs {target.shape}")
    if min(pred.shape[-3:-1]) < window_size:
        raise ValueError(f"SSIM needs images of at least {window_size} px per side, got {pred.shape[-3:-1]}")
    batch = pred.shape[:-3]
    x = pred.reshape(-1, *pred.shape[-3:]).astype(jnp.float32)
    y = target.reshape(-1, *target.shape[-3:]).astype(jnp.float32)
    window = jnp.asarray(_gaussian_window(window_size, sigma))
    c1 = jnp.float32((0.01 * max_value) ** 2)
    c2 = jnp.float32((0.03 * max_value) ** 2)
    mu_x, mu_y = _filter(x, window), _filter(y, window)
    var_x = _filter(x * x, window) - mu_x * mu_x
    var_y = _filter(y * y, window) - mu_y * mu_y
    cov = _filter(x * y, window) - mu_x * mu_y
    num = (jnp.float32(2) * mu_x * mu_y + c1) * (jnp.float32(2) * cov + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    return jnp.mean(num / den, axis=(1, 2, 3)).reshape(batch)
