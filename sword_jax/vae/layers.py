"""Layers of the Wan 2.2 causal video VAE, channels-last, with an explicit streaming cache.

Every stateful layer is called as ``layer(x, cache, first=..., dtype=...) -> (y, new_cache)``:
``x`` is ``[B, T, H, W, C]`` (one chunk of frames), ``cache`` the layer's carried frames from the
previous chunk (``None`` = the stream starts here: zeros), ``first`` (static) says that the chunk
holds frame 0 of the stream. Processing a sequence in one call with ``first=True`` gives the
official whole-sequence rules (see ``/work/shared/reference/wan22/README.md``); splitting it into
chunks and threading the cache gives the same numbers.

Parameter layouts: Conv3d kernels ``[kt, kh, kw, in, out]``, Conv2d kernels ``[kh, kw, in, out]``,
1x1 projections ``[in, out]``, RMS-norm ``gamma`` ``[C]``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax import lax
from jaxtyping import Array, Float

_CONV_DIMS = ("NDHWC", "DHWIO", "NDHWC")
# Matches torch's default Conv init: U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
_TORCH_CONV_INIT = nnx.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


def _precision(dtype: jnp.dtype) -> lax.Precision:
    # float32 parity needs true fp32 convs on GPU (no TF32); bf16 uses the fast path.
    return lax.Precision.HIGHEST if jnp.dtype(dtype) == jnp.float32 else lax.Precision.DEFAULT


def _conv(x: Array, kernel: Array, bias: Array, *, stride=(1, 1, 1), spatial_pad=(0, 0), dtype) -> Array:
    """3-D conv, time unpadded (callers handle causality), symmetric spatial zero padding."""
    y = lax.conv_general_dilated(
        x.astype(dtype),
        kernel.astype(dtype),
        window_strides=stride,
        padding=((0, 0), (spatial_pad[0], spatial_pad[0]), (spatial_pad[1], spatial_pad[1])),
        dimension_numbers=_CONV_DIMS,
        precision=_precision(dtype),
    )
    return y + bias.astype(dtype)


def _zeros_frames(x: Array, frames: int, channels: int | None = None) -> Array:
    b, _, h, w, c = x.shape
    return jnp.zeros((b, frames, h, w, c if channels is None else channels), x.dtype)


class CausalConv3d(nnx.Module):
    """Conv3d with ``kt - 1`` causal frames (zeros, or the cache) before the chunk in time.

    ``spatial_pad`` pixels of zeros on each side in H and W (1 for 3x3x3 kernels). With
    ``kt == 1`` there is no cache (``()``).
    """

    def __init__(self, in_dim: int, out_dim: int, kernel: tuple[int, int, int], *, spatial_pad: int, rngs: nnx.Rngs):
        init = nnx.with_partitioning(_TORCH_CONV_INIT, ("kernel", "kernel", "kernel", "conv_in", "conv_out"))
        self.kernel = nnx.Param(init(rngs.params(), (*kernel, in_dim, out_dim)))
        self.bias = nnx.Param(nnx.with_partitioning(nnx.initializers.zeros, ("conv_out",))(rngs.params(), (out_dim,)))
        self.kt = kernel[0]
        self.spatial_pad = spatial_pad
        # "conv3d": one 3-D convolution. "conv2d": the kt time taps stacked as channels and one 2-D
        # convolution per output frame (the same sums; a layout some GPU conv libraries run faster).
        self.impl = "conv3d"

    def __call__(self, x: Float[Array, "b t h w ci"], cache, *, dtype) -> tuple[Array, object]:
        if self.kt == 1:
            return _conv(x, self.kernel[...], self.bias[...], dtype=dtype), ()
        context = _zeros_frames(x, self.kt - 1) if cache is None else cache.astype(x.dtype)
        seq = jnp.concatenate([context, x], axis=1)  # (B, kt-1+T, H, W, C)
        pad = (self.spatial_pad, self.spatial_pad)
        if self.impl == "conv2d":
            y = _time_stacked_conv(seq, self.kernel[...], self.bias[...], spatial_pad=pad, dtype=dtype)
        else:
            y = _conv(seq, self.kernel[...], self.bias[...], spatial_pad=pad, dtype=dtype)
        return y, seq[:, -(self.kt - 1):]


def _time_stacked_conv(seq: Array, kernel: Array, bias: Array, *, spatial_pad, dtype) -> Array:
    """A valid-in-time 3-D conv as one 2-D conv: output frame t sees frames t..t+kt-1 stacked as channels."""
    kt, kh, kw, c_in, c_out = kernel.shape
    b, frames, h, w, _ = seq.shape
    t = frames - kt + 1
    stacked = jnp.concatenate([seq[:, k:k + t] for k in range(kt)], axis=-1)  # (B, T, H, W, kt*C), tap-major
    stacked = stacked.reshape(b * t, 1, h, w, kt * c_in)
    kernel2d = kernel.transpose(1, 2, 0, 3, 4).reshape(1, kh, kw, kt * c_in, c_out)
    y = _conv(stacked, kernel2d, bias, spatial_pad=spatial_pad, dtype=dtype)  # (B*T, 1, H', W', out)
    return y.reshape(b, t, *y.shape[2:])


class RMSNorm(nnx.Module):
    """``x / max(||x||_2, 1e-12) * sqrt(C) * gamma`` over channels (F.normalize style), in float32."""

    def __init__(self, dim: int, *, rngs: nnx.Rngs):
        self.gamma = nnx.Param(nnx.with_partitioning(nnx.initializers.ones, ("channels",))(rngs.params(), (dim,)))

    def __call__(self, x: Float[Array, "... c"]) -> Float[Array, "... c"]:
        x32 = x.astype(jnp.float32)
        norm = jnp.sqrt(jnp.sum(x32 * x32, axis=-1, keepdims=True))
        scale = jnp.float32(math.sqrt(x.shape[-1]))
        y = x32 / jnp.maximum(norm, jnp.float32(1e-12)) * scale * self.gamma[...].astype(jnp.float32)
        return y.astype(x.dtype)


class ResidualBlock(nnx.Module):
    """RMSNorm, SiLU, 3x3x3 causal conv, RMSNorm, SiLU, 3x3x3 causal conv; 1x1x1 shortcut if in != out."""

    def __init__(self, in_dim: int, out_dim: int, *, rngs: nnx.Rngs):
        self.norm1 = RMSNorm(in_dim, rngs=rngs)
        self.conv1 = CausalConv3d(in_dim, out_dim, (3, 3, 3), spatial_pad=1, rngs=rngs)
        self.norm2 = RMSNorm(out_dim, rngs=rngs)
        self.conv2 = CausalConv3d(out_dim, out_dim, (3, 3, 3), spatial_pad=1, rngs=rngs)
        self.shortcut = (
            CausalConv3d(in_dim, out_dim, (1, 1, 1), spatial_pad=0, rngs=rngs) if in_dim != out_dim else None
        )

    def __call__(self, x, cache, *, dtype):
        cache = (None, None) if cache is None else cache
        skip = x if self.shortcut is None else self.shortcut(x, None, dtype=dtype)[0]
        h, cache1 = self.conv1(jax.nn.silu(self.norm1(x)), cache[0], dtype=dtype)
        h, cache2 = self.conv2(jax.nn.silu(self.norm2(h)), cache[1], dtype=dtype)
        return skip + h, (cache1, cache2)


class AttentionBlock(nnx.Module):
    """Per-frame single-head self-attention over the H*W positions, plus the input."""

    def __init__(self, dim: int, *, rngs: nnx.Rngs):
        self.norm = RMSNorm(dim, rngs=rngs)
        dense_init = nnx.with_partitioning(_TORCH_CONV_INIT, ("conv_in", "conv_out"))
        bias_init = nnx.with_partitioning(nnx.initializers.zeros, ("conv_out",))
        self.qkv_kernel = nnx.Param(dense_init(rngs.params(), (dim, 3 * dim)))
        self.qkv_bias = nnx.Param(bias_init(rngs.params(), (3 * dim,)))
        # The official init zeroes the output projection: the block starts as the identity.
        zero_init = nnx.with_partitioning(nnx.initializers.zeros, ("conv_in", "conv_out"))
        self.proj_kernel = nnx.Param(zero_init(rngs.params(), (dim, dim)))
        self.proj_bias = nnx.Param(bias_init(rngs.params(), (dim,)))

    def __call__(self, x: Float[Array, "b t h w c"], *, dtype) -> Float[Array, "b t h w c"]:
        b, t, h, w, c = x.shape
        normed = self.norm(x).reshape(b * t, h * w, c).astype(dtype)  # (B*T, N, C)
        prec = _precision(dtype)
        qkv = jnp.einsum("bnc,cd->bnd", normed, self.qkv_kernel[...].astype(dtype), precision=prec)
        qkv = qkv + self.qkv_bias[...].astype(dtype)
        q, k, v = jnp.split(qkv, 3, axis=-1)
        logits = jnp.einsum("bqc,bkc->bqk", q, k, precision=prec, preferred_element_type=jnp.float32)
        probs = jax.nn.softmax(logits * jnp.float32(1.0 / math.sqrt(c)), axis=-1)
        attended = jnp.einsum("bqk,bkc->bqc", probs.astype(dtype), v, precision=prec)
        out = jnp.einsum("bnc,cd->bnd", attended, self.proj_kernel[...].astype(dtype), precision=prec)
        out = out + self.proj_bias[...].astype(dtype)
        return x + out.reshape(b, t, h, w, c).astype(x.dtype)


class Resample(nnx.Module):
    """Spatial x2 down/up sampling per frame, optionally with the temporal x2 rule.

    ``mode``: ``downsample2d``/``downsample3d`` (pad right+bottom by 1, 3x3 stride-2 conv;
    3d: frame 0 passes, then a valid stride-2 kernel-3 time conv), ``upsample2d``/``upsample3d``
    (3d first: frame 0 passes, later frames -> two frames each through a causal C -> 2C time
    conv that never sees frame 0; then nearest x2 and a 3x3 conv).
    """

    def __init__(self, dim: int, mode: str, *, rngs: nnx.Rngs):
        if mode not in ("downsample2d", "downsample3d", "upsample2d", "upsample3d"):
            raise ValueError(f"Resample: unknown mode {mode!r}")
        self.mode = mode
        init = nnx.with_partitioning(_TORCH_CONV_INIT, ("kernel", "kernel", "conv_in", "conv_out"))
        self.conv_kernel = nnx.Param(init(rngs.params(), (3, 3, dim, dim)))
        self.conv_bias = nnx.Param(nnx.with_partitioning(nnx.initializers.zeros, ("conv_out",))(rngs.params(), (dim,)))
        if mode == "downsample3d":
            self.time_conv = CausalConv3d(dim, dim, (3, 1, 1), spatial_pad=0, rngs=rngs)
        elif mode == "upsample3d":
            self.time_conv = CausalConv3d(dim, 2 * dim, (3, 1, 1), spatial_pad=0, rngs=rngs)
        else:
            self.time_conv = None
        # "repeat": nearest x2, then the 3x3 conv (the official order). "subpixel": the same result
        # computed on the low-resolution frame: each of the four output phases sees a 2x2 neighbourhood
        # whose taps are sums of the 3x3 kernel's, so the conv does 4/9 of the multiply-adds.
        self.upsample_impl = "repeat"

    def _spatial(self, x, *, dtype):
        kernel = self.conv_kernel[...][None]  # (1, 3, 3, C, C)
        if self.mode.startswith("down"):
            x = jnp.pad(x, ((0, 0), (0, 0), (0, 1), (0, 1), (0, 0)))
            return _conv(x, kernel, self.conv_bias[...], stride=(1, 2, 2), dtype=dtype)
        if self.upsample_impl == "subpixel":
            return _subpixel_upsample_conv(x, self.conv_kernel[...], self.conv_bias[...], dtype=dtype)
        x = jnp.repeat(jnp.repeat(x, 2, axis=2), 2, axis=3)
        return _conv(x, kernel, self.conv_bias[...], spatial_pad=(1, 1), dtype=dtype)

    def _time_down(self, x, cache, first: bool, *, dtype):
        if first:
            head, rest, prev = x[:, :1], x[:, 1:], x[:, :1]
        else:
            head, rest, prev = x[:, :0], x, cache.astype(x.dtype)
        if rest.shape[1] % 2:
            raise ValueError(f"temporal downsample: {rest.shape[1]} frames after frame 0 in a chunk; need an even count")
        seq = jnp.concatenate([prev, rest], axis=1)  # (B, 1+2m, h, w, C)
        tc = self.time_conv
        y = _conv(seq, tc.kernel[...], tc.bias[...], stride=(2, 1, 1), dtype=dtype) if rest.shape[1] else rest
        return jnp.concatenate([head.astype(y.dtype), y], axis=1), seq[:, -1:]

    def _time_up(self, x, cache, first: bool, *, dtype):
        head, rest = (x[:, :1], x[:, 1:]) if first else (x[:, :0], x)
        if rest.shape[1] == 0:
            return head, _zeros_frames(x, 2) if cache is None else cache
        y, new_cache = self.time_conv(rest, cache, dtype=dtype)  # (B, T', h, w, 2C)
        b, t, h, w, c2 = y.shape
        # Channels [0, C) -> frame 2t-1, [C, 2C) -> frame 2t: interleave the halves in time.
        y = y.reshape(b, t, h, w, 2, c2 // 2).transpose(0, 1, 4, 2, 3, 5).reshape(b, 2 * t, h, w, c2 // 2)
        return jnp.concatenate([head.astype(y.dtype), y], axis=1), new_cache

    def __call__(self, x, cache, *, first: bool, dtype):
        if self.mode == "upsample3d":
            x, cache = self._time_up(x, cache, first, dtype=dtype)
            return self._spatial(x, dtype=dtype), cache
        x = self._spatial(x, dtype=dtype)
        if self.mode == "downsample3d":
            return self._time_down(x, cache, first, dtype=dtype)
        return x, ()


# Row taps of the 3x3 kernel that land on low-resolution rows (i - 1 + a, i + a) for output row 2i + a:
# phase 0 reads row i-1 with tap 0 and row i with taps 1 and 2; phase 1 row i with taps 0 and 1, row i+1 with tap 2.
_PHASE_TAPS = np.array([[[1, 0, 0], [0, 1, 1]], [[1, 1, 0], [0, 0, 1]]], np.float32)  # (phase, 2 rows, 3 taps)


def _subpixel_upsample_conv(x: Float[Array, "b t h w c"], kernel: Array, bias: Array, *, dtype) -> Array:
    """``conv3x3(nearest_x2(x))`` with zero padding 1, computed as one 2x2 conv to 4 phases, then depth-to-space."""
    b, t, h, w, c = x.shape
    c_out = kernel.shape[-1]
    taps = jnp.asarray(_PHASE_TAPS)
    # (a, rows, b, cols, C, out): the 2x2 kernel of output phase (a, b); sums taken in float32.
    phases = jnp.einsum("aiy,bjx,yxco->ijcabo", taps, taps, kernel.astype(jnp.float32))
    phase_kernel = phases.reshape(1, 2, 2, c, 4 * c_out)
    padded = jnp.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1), (0, 0)))
    y = _conv(padded, phase_kernel, jnp.tile(bias, 4), dtype=dtype)  # (B, T, H+1, W+1, 4*out)
    y = y.reshape(b, t, h + 1, w + 1, 2, 2, c_out)
    # Output (2i + a, 2j + b) is y[i + a, j + b, a, b].
    rows = jnp.stack([y[:, :, a:a + h, :, a] for a in range(2)], axis=3)  # (B, T, H, 2, W+1, 2, out)
    out = jnp.stack([rows[:, :, :, :, p:p + w, p] for p in range(2)], axis=5)  # (B, T, H, 2, W, 2, out)
    return out.reshape(b, t, 2 * h, 2 * w, c_out)


def avg_down_3d(x: Float[Array, "b t h w ci"], out_dim: int, factor_t: int, factor_s: int, *, first: bool) -> Array:
    """AvgDown3D shortcut: space/time-to-channel (order c, f_t, f_h, f_w), mean over channel groups.

    The first chunk (odd length 1+2m) gets ``factor_t - 1`` zero frames in front.
    """
    b, t, h, w, c = x.shape
    pad_t = (factor_t - t % factor_t) % factor_t
    if pad_t and not first:
        raise ValueError(f"AvgDown3D: a later chunk of {t} frames is not a multiple of {factor_t}")
    x = jnp.pad(x, ((0, 0), (pad_t, 0), (0, 0), (0, 0), (0, 0)))
    t = t + pad_t
    factor = factor_t * factor_s * factor_s
    x = x.reshape(b, t // factor_t, factor_t, h // factor_s, factor_s, w // factor_s, factor_s, c)
    x = x.transpose(0, 1, 3, 5, 7, 2, 4, 6)  # (B, T', H', W', C, ft, fs, fs)
    x = x.reshape(b, t // factor_t, h // factor_s, w // factor_s, out_dim, c * factor // out_dim)
    return jnp.mean(x.astype(jnp.float32), axis=-1).astype(x.dtype)


def dup_up_3d(x: Float[Array, "b t h w ci"], out_dim: int, factor_t: int, factor_s: int, *, first: bool) -> Array:
    """DupUp3D shortcut: repeat channels, channel-to-space/time; the first chunk drops ``factor_t-1`` frames."""
    b, t, h, w, c = x.shape
    repeats = out_dim * factor_t * factor_s * factor_s // c
    x = jnp.repeat(x, repeats, axis=-1).reshape(b, t, h, w, out_dim, factor_t, factor_s, factor_s)
    x = x.transpose(0, 1, 5, 2, 6, 3, 7, 4)  # (B, T, ft, H, fs, W, fs, C)
    x = x.reshape(b, t * factor_t, h * factor_s, w * factor_s, out_dim)
    return x[:, factor_t - 1:] if first else x


def patchify(video: Float[Array, "b t h w 3"], patch: int = 2) -> Float[Array, "b t h2 w2 c"]:
    """[B, T, H, W, C] -> [B, T, H/p, W/p, C*p*p], channel = c*p*p + col*p + row (official (c, r, q))."""
    b, t, h, w, c = video.shape
    x = video.reshape(b, t, h // patch, patch, w // patch, patch, c)  # (B, T, H', q, W', r, C)
    x = x.transpose(0, 1, 2, 4, 6, 5, 3)  # (B, T, H', W', C, r, q)
    return x.reshape(b, t, h // patch, w // patch, c * patch * patch)


def unpatchify(x: Float[Array, "b t h2 w2 c"], patch: int = 2) -> Float[Array, "b t h w c3"]:
    """Inverse of :func:`patchify`."""
    b, t, h, w, cpp = x.shape
    c = cpp // (patch * patch)
    x = x.reshape(b, t, h, w, c, patch, patch)  # (B, T, H', W', C, r, q)
    x = x.transpose(0, 1, 2, 6, 3, 5, 4)  # (B, T, H', q, W', r, C)
    return x.reshape(b, t, h * patch, w * patch, c)
