"""The Wan 2.2 VAE (``WanVAE_``) as Flax NNX modules: Encoder3d, Decoder3d and the latent wrapper.

Module attribute names follow the official ``state_dict`` tree where they can (``downsamples``,
``upsamples``, ``middle_*``, ``head_*``, ``conv1``, ``conv2``), so the converter's key map is
mechanical (see :mod:`sword_jax.convert.wan22_vae`). Each ``__call__`` takes one chunk of frames
and the chunk's cache (see :mod:`sword_jax.vae.layers`) and returns ``(y, new_cache)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax import nn as jnn
from jaxtyping import Array, Float

from sword_jax.vae.config import VAEConfig
from sword_jax.vae.latent_norm import WAN22_LATENT_MEAN, WAN22_LATENT_STD
from sword_jax.vae.layers import (
    AttentionBlock,
    CausalConv3d,
    Resample,
    ResidualBlock,
    RMSNorm,
    avg_down_3d,
    dup_up_3d,
)

PATCH = 2  # 2x2 patchify: 3 -> 12 channels


class LatentStat(nnx.Variable):
    """Fixed per-channel latent statistics (not trained, not in the optimizer)."""


def default_latent_stats(z_dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, inv_std): the official Wan 2.2 constants for z_dim 48, else zeros / ones."""
    if z_dim == len(WAN22_LATENT_MEAN):
        mean = np.asarray(WAN22_LATENT_MEAN, np.float32)
        return mean, (np.float32(1.0) / np.asarray(WAN22_LATENT_STD, np.float32)).astype(np.float32)
    return np.zeros(z_dim, np.float32), np.ones(z_dim, np.float32)


def vae_rngs(key: jax.Array) -> nnx.Rngs:
    """Init streams for :class:`WanVAE` from a root key: one threefry draw seeds an RBG key.

    Threefry kernels for ~100 differently shaped parameters take minutes to compile on a small
    CPU; the RBG generator compiles in seconds. Deterministic for a given key and backend.
    """
    seed = jax.random.bits(key, (), jnp.uint32)
    return nnx.Rngs(params=jax.random.key(seed, impl="rbg"))


class DownBlock(nnx.Module):
    """Down_ResidualBlock: residual blocks, optional Resample, plus the AvgDown3D shortcut of the input."""

    def __init__(self, in_dim: int, out_dim: int, num_res: int, *, t_down: bool, down: bool, rngs: nnx.Rngs):
        self.downsamples = nnx.List(
            [ResidualBlock(in_dim if i == 0 else out_dim, out_dim, rngs=rngs) for i in range(num_res)]
        )
        self.resample = Resample(out_dim, "downsample3d" if t_down else "downsample2d", rngs=rngs) if down else None
        self.out_dim = out_dim
        self.factor_t = 2 if t_down else 1
        self.factor_s = 2 if down else 1

    def __call__(self, x, cache, *, first: bool, dtype):
        cache = cache or (None,) * (len(self.downsamples) + 1)
        h, new_cache = x, []
        for block, block_cache in zip(self.downsamples, cache):
            h, c = block(h, block_cache, dtype=dtype)
            new_cache.append(c)
        if self.resample is not None:
            h, c = self.resample(h, cache[-1], first=first, dtype=dtype)
        else:
            c = ()
        new_cache.append(c)
        shortcut = avg_down_3d(x, self.out_dim, self.factor_t, self.factor_s, first=first)
        return h + shortcut.astype(h.dtype), tuple(new_cache)


class UpBlock(nnx.Module):
    """Up_ResidualBlock: residual blocks, optional Resample; DupUp3D shortcut only when upsampling."""

    def __init__(self, in_dim: int, out_dim: int, num_res: int, *, t_up: bool, up: bool, rngs: nnx.Rngs):
        self.upsamples = nnx.List(
            [ResidualBlock(in_dim if i == 0 else out_dim, out_dim, rngs=rngs) for i in range(num_res)]
        )
        self.resample = Resample(out_dim, "upsample3d" if t_up else "upsample2d", rngs=rngs) if up else None
        self.out_dim = out_dim
        self.factor_t = 2 if t_up else 1
        self.up = up

    def __call__(self, x, cache, *, first: bool, dtype):
        cache = cache or (None,) * (len(self.upsamples) + 1)
        h, new_cache = x, []
        for block, block_cache in zip(self.upsamples, cache):
            h, c = block(h, block_cache, dtype=dtype)
            new_cache.append(c)
        if self.resample is not None:
            h, c = self.resample(h, cache[-1], first=first, dtype=dtype)
        else:
            c = ()
        new_cache.append(c)
        if self.up:
            h = h + dup_up_3d(x, self.out_dim, self.factor_t, 2, first=first).astype(h.dtype)
        return h, tuple(new_cache)


class Middle(nnx.Module):
    """ResidualBlock, AttentionBlock, ResidualBlock at the lowest resolution."""

    def __init__(self, dim: int, *, rngs: nnx.Rngs):
        self.res0 = ResidualBlock(dim, dim, rngs=rngs)
        self.attn = AttentionBlock(dim, rngs=rngs)
        self.res1 = ResidualBlock(dim, dim, rngs=rngs)

    def __call__(self, x, cache, *, dtype):
        cache = cache or (None, None)
        x, c0 = self.res0(x, cache[0], dtype=dtype)
        x = self.attn(x, dtype=dtype)
        x, c1 = self.res1(x, cache[1], dtype=dtype)
        return x, (c0, c1)


class Encoder3d(nnx.Module):
    """Patchified video (12 channels) -> 2*z_dim channels at 1/8 spatial (1/16 of pixels), 1/4 time."""

    def __init__(self, cfg: VAEConfig, *, rngs: nnx.Rngs):
        dims = [cfg.dim * m for m in (1, *cfg.dim_mult)]
        self.conv1 = CausalConv3d(3 * PATCH * PATCH, dims[0], (3, 3, 3), spatial_pad=1, rngs=rngs)
        levels = len(cfg.dim_mult)
        self.downsamples = nnx.List(
            [
                DownBlock(
                    dims[i], dims[i + 1], cfg.num_res_blocks,
                    t_down=i < len(cfg.temporal_downsample) and cfg.temporal_downsample[i],
                    down=i != levels - 1, rngs=rngs,
                )
                for i in range(levels)
            ]
        )
        self.middle = Middle(dims[-1], rngs=rngs)
        self.head_norm = RMSNorm(dims[-1], rngs=rngs)
        self.head_conv = CausalConv3d(dims[-1], 2 * cfg.z_dim, (3, 3, 3), spatial_pad=1, rngs=rngs)

    def __call__(self, x, cache, *, first: bool, dtype, taps: dict | None = None):
        cache = cache or (None,) * 4
        x, c_in = self.conv1(x, cache[0], dtype=dtype)
        level_caches = []
        for i, block in enumerate(self.downsamples):
            x, c = block(x, cache[1][i] if cache[1] else None, first=first, dtype=dtype)
            level_caches.append(c)
            if taps is not None:
                taps[f"enc_down{i}_out"] = x
        x, c_mid = self.middle(x, cache[2], dtype=dtype)
        if taps is not None:
            taps["enc_middle_out"] = x
        x, c_head = self.head_conv(jnn.silu(self.head_norm(x)), cache[3], dtype=dtype)
        return x, (c_in, tuple(level_caches), c_mid, c_head)


class Decoder3d(nnx.Module):
    """z_dim latent channels -> 12 patchified channels, x8 spatial, x4 time (first frame -> 1 frame)."""

    def __init__(self, cfg: VAEConfig, *, rngs: nnx.Rngs):
        dims = [cfg.dec_dim * m for m in (cfg.dim_mult[-1], *cfg.dim_mult[::-1])]
        t_up = tuple(cfg.temporal_downsample[::-1])
        levels = len(cfg.dim_mult)
        self.conv1 = CausalConv3d(cfg.z_dim, dims[0], (3, 3, 3), spatial_pad=1, rngs=rngs)
        self.middle = Middle(dims[0], rngs=rngs)
        self.upsamples = nnx.List(
            [
                UpBlock(
                    dims[i], dims[i + 1], cfg.num_res_blocks + 1,
                    t_up=i < len(t_up) and t_up[i], up=i != levels - 1, rngs=rngs,
                )
                for i in range(levels)
            ]
        )
        self.head_norm = RMSNorm(dims[-1], rngs=rngs)
        self.head_conv = CausalConv3d(dims[-1], 3 * PATCH * PATCH, (3, 3, 3), spatial_pad=1, rngs=rngs)

    def __call__(self, x, cache, *, first: bool, dtype, taps: dict | None = None):
        cache = cache or (None,) * 4
        x, c_in = self.conv1(x, cache[0], dtype=dtype)
        if taps is not None:
            taps["dec_conv1_out"] = x
        x, c_mid = self.middle(x, cache[1], dtype=dtype)
        if taps is not None:
            taps["dec_middle_out"] = x
        level_caches = []
        for i, block in enumerate(self.upsamples):
            x, c = block(x, cache[2][i] if cache[2] else None, first=first, dtype=dtype)
            level_caches.append(c)
            if taps is not None:
                taps[f"dec_up{i}_out"] = x
        x, c_head = self.head_conv(jnn.silu(self.head_norm(x)), cache[3], dtype=dtype)
        return x, (c_in, c_mid, tuple(level_caches), c_head)


def set_conv_impl(model: nnx.Module, *, causal_conv: str, upsample: str) -> None:
    """Selects how ``model``'s causal convolutions and upsampling convs run (``VAEConfig.causal_conv`` /
    ``upsample``); the parameters are untouched, so a loaded VAE can switch before ``nnx.split``."""
    for _, module in nnx.iter_modules(model):
        if isinstance(module, CausalConv3d):
            module.impl = causal_conv
        elif isinstance(module, Resample):
            module.upsample_impl = upsample


class WanVAE(nnx.Module):
    """``WanVAE_``: encoder, ``conv1`` (2z -> 2z, gives mu | log_var), ``conv2`` (z -> z), decoder.

    ``latent_mean``/``latent_inv_std`` (``LatentStat``) normalise mu as (mu - mean) * inv_std;
    they default to the official Wan 2.2 constants when ``z_dim == 48``, else 0 / 1.
    """

    def __init__(self, cfg: VAEConfig, *, rngs: nnx.Rngs):
        cfg.validate()
        self.z_dim = cfg.z_dim
        self.temporal_factor = cfg.temporal_factor
        self.spatial_factor = cfg.spatial_factor
        self.compute_dtype = cfg.compute_dtype
        self.encoder = Encoder3d(cfg, rngs=rngs)
        self.conv1 = CausalConv3d(2 * cfg.z_dim, 2 * cfg.z_dim, (1, 1, 1), spatial_pad=0, rngs=rngs)
        self.conv2 = CausalConv3d(cfg.z_dim, cfg.z_dim, (1, 1, 1), spatial_pad=0, rngs=rngs)
        self.decoder = Decoder3d(cfg, rngs=rngs)
        mean, inv_std = default_latent_stats(cfg.z_dim)
        self.latent_mean = LatentStat(jnp.asarray(mean))
        self.latent_inv_std = LatentStat(jnp.asarray(inv_std))
        set_conv_impl(self, causal_conv=cfg.causal_conv, upsample=cfg.upsample)

    def encode_moments(self, frames, cache, *, first: bool, dtype, taps: dict | None = None):
        """Patchified frames ``[B, T, H/2, W/2, 12]`` -> raw ``(mu, log_var)`` float32, new cache."""
        h, cache = self.encoder(frames, cache, first=first, dtype=dtype, taps=taps)
        if taps is not None:
            taps["enc_out"] = h
        moments, _ = self.conv1(h, None, dtype=dtype)
        moments = moments.astype(jnp.float32)
        return moments[..., : self.z_dim], moments[..., self.z_dim:], cache

    def normalise(self, mu_raw: Float[Array, "... z"]) -> Float[Array, "... z"]:
        return (mu_raw - self.latent_mean[...]) * self.latent_inv_std[...]

    def denormalise(self, latents: Float[Array, "... z"]) -> Float[Array, "... z"]:
        # A division by inv_std, exactly as the official decode (not a multiplication by std).
        return latents / self.latent_inv_std[...] + self.latent_mean[...]

    def decode_raw(self, z_raw, cache, *, first: bool, dtype, taps: dict | None = None):
        """Raw (de-normalised) latents ``[B, T', h, w, z]`` -> patchified frames (12 ch.), new cache."""
        x, _ = self.conv2(z_raw.astype(jnp.float32), None, dtype=dtype)
        if taps is not None:
            taps["dec_conv2_out"] = x
        return self.decoder(x, cache, first=first, dtype=dtype, taps=taps)
