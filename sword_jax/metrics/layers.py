"""Channels-last conv / BatchNorm / pooling layers with PyTorch's conventions, for the metric nets.

The metric networks (AlexNet, VGG16, InceptionV3, I3D) are ports of PyTorch models, so their layers
follow PyTorch's numerics: explicit integer paddings (or TF-style 'SAME' for I3D), floor-mode pools,
eval-mode BatchNorm ``(x - mean) / sqrt(var + eps) * weight + bias``. Convolutions run at
``Precision.HIGHEST``: TF32/bf16 defaults on GPU are far outside the 1e-4 parity bar.
Each layer knows how to take its values from a PyTorch state dict (``load_torch``).
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

Padding = str | Sequence[tuple[int, int]]


def _tuple(value: int | Sequence[int], ndim: int) -> tuple[int, ...]:
    return (value,) * ndim if isinstance(value, int) else tuple(value)


def _dimension_numbers(ndim: int) -> tuple[str, str, str]:
    return ("NHWC", "HWIO", "NHWC") if ndim == 2 else ("NDHWC", "DHWIO", "NDHWC")


class Conv(nnx.Module):
    """An N-d convolution (N = 2 or 3) on channels-last input, PyTorch weight conventions.

    Args:
      in_features, out_features: channel counts.
      kernel_size: int or per-spatial-dim tuple.
      stride: int or tuple.
      padding: ``"SAME"`` (TF rule: extra pad at the end) or an int / per-dim ints (symmetric).
      use_bias: whether the conv has a bias.
      ndim: 2 or 3 spatial dims.
      rngs: for the He-normal initial kernel (random-weight networks).
    """

    def __init__(self, in_features: int, out_features: int, kernel_size, *, stride=1, padding=0,
                 use_bias: bool = True, ndim: int = 2, rngs: nnx.Rngs):
        self.ndim = ndim
        self.kernel_size = _tuple(kernel_size, ndim)
        self.stride = _tuple(stride, ndim)
        if isinstance(padding, str):
            self.padding: Padding = padding
        else:
            self.padding = tuple((p, p) for p in _tuple(padding, ndim))
        fan_in = in_features * int(np.prod(self.kernel_size))
        shape = self.kernel_size + (in_features, out_features)
        self.kernel = nnx.Param(
            jax.random.normal(rngs.params(), shape, jnp.float32) * jnp.float32(np.sqrt(2.0 / fan_in))
        )
        self.bias = nnx.Param(jnp.zeros((out_features,), jnp.float32)) if use_bias else None

    def __call__(self, x: Float[Array, "b *spatial c"]) -> Float[Array, "b *spatial o"]:
        y = jax.lax.conv_general_dilated(
            x, self.kernel[...], self.stride, self.padding,
            dimension_numbers=_dimension_numbers(self.ndim), precision=jax.lax.Precision.HIGHEST,
        )
        if self.bias is not None:
            y = y + self.bias[...]
        return y

    def load_torch(self, weight: np.ndarray, bias: np.ndarray | None = None) -> None:
        """Takes a PyTorch ``[out, in, *k]`` weight (and ``[out]`` bias)."""
        expected = (self.kernel.shape[-1], self.kernel.shape[-2]) + self.kernel_size
        if tuple(weight.shape) != expected:
            raise ValueError(f"conv weight shape {tuple(weight.shape)} != expected {expected}")
        perm = tuple(range(2, 2 + self.ndim)) + (1, 0)
        self.kernel.set_value(jnp.asarray(np.transpose(weight, perm), jnp.float32))
        if self.bias is not None:
            if bias is None:
                raise ValueError("conv has a bias but none was given")
            self.bias.set_value(jnp.asarray(bias, jnp.float32).reshape(self.bias.shape))


class BatchNormEval(nnx.Module):
    """Eval-mode BatchNorm over the last axis: ``(x - mean) / sqrt(var + eps) * weight + bias``."""

    def __init__(self, features: int, *, eps: float):
        self.eps = eps
        self.weight = nnx.Param(jnp.ones((features,), jnp.float32))
        self.bias = nnx.Param(jnp.zeros((features,), jnp.float32))
        self.mean = nnx.BatchStat(jnp.zeros((features,), jnp.float32))
        self.var = nnx.BatchStat(jnp.ones((features,), jnp.float32))

    def __call__(self, x: Float[Array, "... c"]) -> Float[Array, "... c"]:
        inv = jax.lax.rsqrt(self.var[...] + jnp.float32(self.eps))
        return (x - self.mean[...]) * (inv * self.weight[...]) + self.bias[...]

    def load_torch(self, state: dict[str, np.ndarray], prefix: str) -> None:
        """Takes ``<prefix>weight/bias/running_mean/running_var`` (``num_batches_tracked`` is unused)."""
        for attr, key in (("weight", "weight"), ("bias", "bias"), ("mean", "running_mean"), ("var", "running_var")):
            value = state[prefix + key]
            getattr(self, attr).set_value(jnp.asarray(value, jnp.float32).reshape(-1))


class ConvBNReLU(nnx.Module):
    """Bias-free conv -> eval BatchNorm -> ReLU (Inception's BasicConv2d, I3D's Unit3D)."""

    def __init__(self, in_features: int, out_features: int, kernel_size, *, stride=1, padding=0,
                 eps: float, ndim: int = 2, rngs: nnx.Rngs):
        self.conv = Conv(in_features, out_features, kernel_size, stride=stride, padding=padding,
                         use_bias=False, ndim=ndim, rngs=rngs)
        self.bn = BatchNormEval(out_features, eps=eps)

    def __call__(self, x: Float[Array, "b *spatial c"]) -> Float[Array, "b *spatial o"]:
        return jax.nn.relu(self.bn(self.conv(x)))

    def load_torch(self, state: dict[str, np.ndarray], prefix: str, conv_name: str = "conv") -> None:
        """Takes ``<prefix><conv_name>.weight`` and ``<prefix>bn.*``."""
        self.conv.load_torch(state[f"{prefix}{conv_name}.weight"])
        self.bn.load_torch(state, prefix + "bn.")


def max_pool(x: Float[Array, "b *spatial c"], window: Sequence[int], strides: Sequence[int],
             padding: Padding = "VALID") -> Float[Array, "b *spatial c"]:
    """Max pool over the spatial dims; padding never wins (``-inf``), floor mode for 'VALID'."""
    pads = padding if isinstance(padding, str) else ((0, 0),) + tuple(padding) + ((0, 0),)
    return jax.lax.reduce_window(
        x, -jnp.inf, jax.lax.max, (1, *window, 1), (1, *strides, 1), pads
    ).astype(x.dtype)


def avg_pool_exclude_pad(x: Float[Array, "b h w c"], window: int, stride: int, pad: int) -> Float[Array, "b h w c"]:
    """2-D average pool with ``count_include_pad=False`` (the FID Inception blocks' pool)."""
    dims, strides = (1, window, window, 1), (1, stride, stride, 1)
    pads = ((0, 0), (pad, pad), (pad, pad), (0, 0))
    total = jax.lax.reduce_window(x, jnp.float32(0), jax.lax.add, dims, strides, pads)
    ones = jnp.ones((1, *x.shape[1:3], 1), x.dtype)
    count = jax.lax.reduce_window(ones, jnp.float32(0), jax.lax.add, dims, strides, pads)
    return total / count
