"""A random tiny VAE (``sword:tiny``'s) for the tests of how start latents are encoded from real frames, its
encoders bound as a GRPO setup binds them, and the latents the latents stage makes of whole episodes."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

import configs
from sword_jax.rl.world_model_sim import encode_history, encode_prefix
from sword_jax.vae import api as vae_api


@functools.lru_cache(maxsize=1)
def tiny_vae():
    """``(cfg, graphdef, state)``: the tiny VAE with random weights, built once per process."""
    cfg = configs.get("sword:tiny")
    graphdef, state = nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(1)))
    return cfg, graphdef, state


def encoders(num_context: int = 1):
    """``(encode, encode_prefix)`` of :func:`tiny_vae`: the window and prefix start encoders."""
    _, graphdef, state = tiny_vae()
    return (lambda first, history: encode_history(graphdef, state, first, history, num_context=num_context),
            lambda prefix, index: encode_prefix(graphdef, state, prefix, index, num_context=num_context))


def whole_latents(frames: np.ndarray) -> np.ndarray:
    """``[n, 1 + L, h, w, z]`` the latents of whole uint8 episodes ``[n, 1 + 4 L, H, W, 3]``, as the latents stage
    encodes them."""
    _, graphdef, state = tiny_vae()
    video = jnp.asarray(frames, jnp.float32) / jnp.float32(255.0) * 2.0 - 1.0
    return np.asarray(vae_api.encode(graphdef, state, video, check_values=False))


def relative_error(latents, truth) -> float:
    """The largest difference over the largest entry of ``truth``."""
    latents, truth = np.asarray(latents, np.float32), np.asarray(truth, np.float32)
    return float(np.max(np.abs(latents - truth)) / np.max(np.abs(truth)))
