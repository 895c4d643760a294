"""FID's InceptionV3 as pytorch-fid 0.3.0 defines it (pool3, 2048-d), channels-last.

``fid_inception_v3()``: torchvision ``Inception3(num_classes=1008, aux_logits=False)`` with the FID
blocks (FIDInceptionA/C/E_1/E_2: average pools exclude padding, Mixed_7c's pool branch is a max pool);
Mixed_6a / Mixed_7a are torchvision's InceptionB / InceptionD. Every conv is a BasicConv2d
(bias-free conv, BatchNorm eps 1e-3, ReLU). Input: [0, 1] RGB, bilinearly resized to 299 x 299
(PyTorch convention, no antialias), mapped to [-1, 1]. Keys are those of
``pt_inception-2015-12-05-6726825d.pth``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.metrics.layers import ConvBNReLU, avg_pool_exclude_pad, max_pool
from sword_jax.metrics.preprocess import resize_bilinear_torch

_EPS = 1e-3


class _Block(nnx.Module):
    """A named set of BasicConv2d units; subclasses define the wiring."""

    def _units(self, rngs: nnx.Rngs, spec: dict[str, tuple]) -> None:
        self.names = tuple(spec)
        for name, (cin, cout, kernel, stride, pad) in spec.items():
            setattr(self, name, ConvBNReLU(cin, cout, kernel, stride=stride, padding=pad, eps=_EPS, rngs=rngs))

    def load_torch(self, state: dict[str, np.ndarray], prefix: str) -> None:
        for name in self.names:
            getattr(self, name).load_torch(state, f"{prefix}{name}.")


class FIDInceptionA(_Block):
    def __init__(self, cin: int, pool_features: int, *, rngs: nnx.Rngs):
        self._units(rngs, {
            "branch1x1": (cin, 64, 1, 1, 0),
            "branch5x5_1": (cin, 48, 1, 1, 0), "branch5x5_2": (48, 64, 5, 1, 2),
            "branch3x3dbl_1": (cin, 64, 1, 1, 0), "branch3x3dbl_2": (64, 96, 3, 1, 1),
            "branch3x3dbl_3": (96, 96, 3, 1, 1),
            "branch_pool": (cin, pool_features, 1, 1, 0),
        })

    def __call__(self, x):
        b1 = self.branch1x1(x)
        b5 = self.branch5x5_2(self.branch5x5_1(x))
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        bp = self.branch_pool(avg_pool_exclude_pad(x, 3, 1, 1))
        return jnp.concatenate([b1, b5, b3, bp], axis=-1)


class InceptionB(_Block):
    def __init__(self, cin: int, *, rngs: nnx.Rngs):
        self._units(rngs, {
            "branch3x3": (cin, 384, 3, 2, 0),
            "branch3x3dbl_1": (cin, 64, 1, 1, 0), "branch3x3dbl_2": (64, 96, 3, 1, 1),
            "branch3x3dbl_3": (96, 96, 3, 2, 0),
        })

    def __call__(self, x):
        b3 = self.branch3x3(x)
        bd = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return jnp.concatenate([b3, bd, max_pool(x, (3, 3), (2, 2))], axis=-1)


class FIDInceptionC(_Block):
    def __init__(self, cin: int, c7: int, *, rngs: nnx.Rngs):
        k17, k71 = ((1, 7), 1, (0, 3)), ((7, 1), 1, (3, 0))
        self._units(rngs, {
            "branch1x1": (cin, 192, 1, 1, 0),
            "branch7x7_1": (cin, c7, 1, 1, 0), "branch7x7_2": (c7, c7, *k17), "branch7x7_3": (c7, 192, *k71),
            "branch7x7dbl_1": (cin, c7, 1, 1, 0), "branch7x7dbl_2": (c7, c7, *k71),
            "branch7x7dbl_3": (c7, c7, *k17), "branch7x7dbl_4": (c7, c7, *k71),
            "branch7x7dbl_5": (c7, 192, *k17),
            "branch_pool": (cin, 192, 1, 1, 0),
        })

    def __call__(self, x):
        b1 = self.branch1x1(x)
        b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
        bd = x
        for i in range(1, 6):
            bd = getattr(self, f"branch7x7dbl_{i}")(bd)
        bp = self.branch_pool(avg_pool_exclude_pad(x, 3, 1, 1))
        return jnp.concatenate([b1, b7, bd, bp], axis=-1)


class InceptionD(_Block):
    def __init__(self, cin: int, *, rngs: nnx.Rngs):
        self._units(rngs, {
            "branch3x3_1": (cin, 192, 1, 1, 0), "branch3x3_2": (192, 320, 3, 2, 0),
            "branch7x7x3_1": (cin, 192, 1, 1, 0), "branch7x7x3_2": (192, 192, (1, 7), 1, (0, 3)),
            "branch7x7x3_3": (192, 192, (7, 1), 1, (3, 0)), "branch7x7x3_4": (192, 192, 3, 2, 0),
        })

    def __call__(self, x):
        b3 = self.branch3x3_2(self.branch3x3_1(x))
        b7 = x
        for i in range(1, 5):
            b7 = getattr(self, f"branch7x7x3_{i}")(b7)
        return jnp.concatenate([b3, b7, max_pool(x, (3, 3), (2, 2))], axis=-1)


class FIDInceptionE(_Block):
    """FIDInceptionE_1 (``max_pool_branch=False``) or FIDInceptionE_2 (``True``)."""

    def __init__(self, cin: int, *, max_pool_branch: bool, rngs: nnx.Rngs):
        self.max_pool_branch = max_pool_branch
        self._units(rngs, {
            "branch1x1": (cin, 320, 1, 1, 0),
            "branch3x3_1": (cin, 384, 1, 1, 0), "branch3x3_2a": (384, 384, (1, 3), 1, (0, 1)),
            "branch3x3_2b": (384, 384, (3, 1), 1, (1, 0)),
            "branch3x3dbl_1": (cin, 448, 1, 1, 0), "branch3x3dbl_2": (448, 384, 3, 1, 1),
            "branch3x3dbl_3a": (384, 384, (1, 3), 1, (0, 1)), "branch3x3dbl_3b": (384, 384, (3, 1), 1, (1, 0)),
            "branch_pool": (cin, 192, 1, 1, 0),
        })

    def __call__(self, x):
        b1 = self.branch1x1(x)
        b3 = self.branch3x3_1(x)
        b3 = jnp.concatenate([self.branch3x3_2a(b3), self.branch3x3_2b(b3)], axis=-1)
        bd = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        bd = jnp.concatenate([self.branch3x3dbl_3a(bd), self.branch3x3dbl_3b(bd)], axis=-1)
        if self.max_pool_branch:
            pooled = max_pool(x, (3, 3), (1, 1), ((1, 1), (1, 1)))
        else:
            pooled = avg_pool_exclude_pad(x, 3, 1, 1)
        return jnp.concatenate([b1, b3, bd, self.branch_pool(pooled)], axis=-1)


class FIDInceptionV3(nnx.Module):
    """pytorch-fid's InceptionV3 up to pool3.

    Args:
      rngs: random initial weights (replace them with :meth:`load_torch`).
    """

    STEM = {
        "Conv2d_1a_3x3": (3, 32, 3, 2, 0), "Conv2d_2a_3x3": (32, 32, 3, 1, 0), "Conv2d_2b_3x3": (32, 64, 3, 1, 1),
        "Conv2d_3b_1x1": (64, 80, 1, 1, 0), "Conv2d_4a_3x3": (80, 192, 3, 1, 0),
    }
    MIXED = ("Mixed_5b", "Mixed_5c", "Mixed_5d", "Mixed_6a", "Mixed_6b", "Mixed_6c", "Mixed_6d", "Mixed_6e",
             "Mixed_7a", "Mixed_7b", "Mixed_7c")

    def __init__(self, *, rngs: nnx.Rngs):
        for name, (cin, cout, k, s, p) in self.STEM.items():
            setattr(self, name, ConvBNReLU(cin, cout, k, stride=s, padding=p, eps=_EPS, rngs=rngs))
        self.Mixed_5b = FIDInceptionA(192, 32, rngs=rngs)
        self.Mixed_5c = FIDInceptionA(256, 64, rngs=rngs)
        self.Mixed_5d = FIDInceptionA(288, 64, rngs=rngs)
        self.Mixed_6a = InceptionB(288, rngs=rngs)
        self.Mixed_6b = FIDInceptionC(768, 128, rngs=rngs)
        self.Mixed_6c = FIDInceptionC(768, 160, rngs=rngs)
        self.Mixed_6d = FIDInceptionC(768, 160, rngs=rngs)
        self.Mixed_6e = FIDInceptionC(768, 192, rngs=rngs)
        self.Mixed_7a = InceptionD(768, rngs=rngs)
        self.Mixed_7b = FIDInceptionE(1280, max_pool_branch=False, rngs=rngs)
        self.Mixed_7c = FIDInceptionE(2048, max_pool_branch=True, rngs=rngs)

    def endpoints(self, images: Float[Array, "b h w 3"]) -> dict[str, Array]:
        """Every block output (for debugging parity); ``"pool3"`` is the FID feature [B, 2048]."""
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"Inception expects [B, H, W, 3] images in [0, 1], got {images.shape}")
        out: dict[str, Array] = {}
        x = resize_bilinear_torch(images, (299, 299))
        out["resized_input"] = x
        x = x * jnp.float32(2) - jnp.float32(1)
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))
        x = out["block0"] = max_pool(x, (3, 3), (2, 2))
        x = self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x))
        x = out["block1"] = max_pool(x, (3, 3), (2, 2))
        for name in self.MIXED:
            x = out[name] = getattr(self, name)(x)
        out["block2"] = out["Mixed_6e"]
        out["pool3"] = jnp.mean(x, axis=(1, 2))
        return out

    def __call__(self, images: Float[Array, "b h w 3"]) -> Float[Array, "b 2048"]:
        """pool3 features of [0, 1] RGB images of any size (resized to 299)."""
        return self.endpoints(images)["pool3"]

    def load_torch(self, state: dict[str, np.ndarray]) -> None:
        """Loads a pytorch-fid ``pt_inception`` state dict (float16/32; ``fc.*`` is unused)."""
        for name in self.STEM:
            getattr(self, name).load_torch(state, f"{name}.")
        for name in self.MIXED:
            getattr(self, name).load_torch(state, f"{name}.")
