"""Flow matching for the world model: Wan's shifted schedule, noising, targets and the loss.

Conventions (Wan 2.x / rectified flow):

* ``sigma`` in [0, 1] is the noise level; ``x_sigma = (1 - sigma) * x0 + sigma * noise``.
* The model sees timesteps in Wan units, ``t = sigma * num_train_timesteps`` (0 .. 1000);
  conditioning frames (first frame, context) are clean and get ``t = 0``.
* Wan's shift warps a uniform ``s`` towards high noise:
  ``sigma = shift * s / (1 + (shift - 1) * s)``.
* ``prediction="velocity"``: the model predicts ``v = noise - x0`` (Wan's target), so the clean
  estimate is ``x0 = x_sigma - sigma * v``.
* ``prediction="epsilon"``: the paper's objective ``E || eps - eps_theta(x_t, t, a) ||^2``; the model
  output is read as the noise. Conversion to the sampler's velocity:
  ``x0 = (x_sigma - sigma * eps) / (1 - sigma)`` and ``v = eps - x0 = (eps - x_sigma) / (1 - sigma)``;
  ``1 - sigma`` is clamped at ``1 / num_train_timesteps`` so the conversion stays finite at sigma = 1.

Segment layout along the latent-frame axis: ``[first-frame latent, context latent(s), future
latent(s)]``; the loss covers the future latents only.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from sword_jax.world_model.config import FlowConfig


def shift_sigma(s: Float[Array, "..."], shift: float) -> Float[Array, "..."]:
    """Wan's timestep shift ``sigma = shift * s / (1 + (shift - 1) * s)`` (identity for shift 1)."""
    s = jnp.asarray(s, jnp.float32)
    shift_f = jnp.float32(shift)
    return shift_f * s / (jnp.float32(1.0) + (shift_f - jnp.float32(1.0)) * s)


def to_timesteps(sigma: Float[Array, "..."], cfg: FlowConfig) -> Float[Array, "..."]:
    """Noise level -> Wan timestep units (``sigma * num_train_timesteps``)."""
    return sigma * jnp.float32(cfg.num_train_timesteps)


def sample_sigmas(batch: int, cfg: FlowConfig, *, key: jax.Array) -> Float[Array, " b"]:
    """Training noise levels: ``s ~ U(1/N, 1)`` then shifted (one level per sample)."""
    low = 1.0 / cfg.num_train_timesteps
    s = jax.random.uniform(key, (batch,), jnp.float32, minval=low, maxval=1.0)
    return shift_sigma(s, cfg.shift)


def sampling_sigmas(num_steps: int, shift: float) -> Float[Array, " n1"]:
    """Sampler grid: ``num_steps + 1`` shifted levels from 1 down to 0."""
    if not 1 <= num_steps <= 50:
        raise ValueError(f"sampler: num_steps must be in [1, 50], got {num_steps}")
    return shift_sigma(jnp.linspace(1.0, 0.0, num_steps + 1, dtype=jnp.float32), shift)


def add_noise(
    x0: Float[Array, "b f h w c"], noise: Float[Array, "b f h w c"], sigma: Float[Array, " b"]
) -> Float[Array, "b f h w c"]:
    """``x_sigma = (1 - sigma) * x0 + sigma * noise`` with one sigma per sample."""
    s = sigma.astype(jnp.float32)[:, None, None, None, None]
    return (jnp.float32(1.0) - s) * x0.astype(jnp.float32) + s * noise.astype(jnp.float32)


def _one_minus(sigma: Array, cfg: FlowConfig) -> Array:
    return jnp.maximum(jnp.float32(1.0) - sigma, jnp.float32(1.0 / cfg.num_train_timesteps))


def to_velocity(prediction: Array, x_sigma: Array, sigma: Array, cfg: FlowConfig) -> Array:
    """Model output -> velocity ``v = noise - x0`` (sigma broadcastable to the latents)."""
    prediction = prediction.astype(jnp.float32)
    if cfg.prediction == "velocity":
        return prediction
    return (prediction - x_sigma.astype(jnp.float32)) / _one_minus(sigma, cfg)


def to_clean(prediction: Array, x_sigma: Array, sigma: Array, cfg: FlowConfig) -> Array:
    """Model output -> clean estimate ``x0`` (velocity: ``x_sigma - sigma * v``)."""
    prediction = prediction.astype(jnp.float32)
    x_sigma = x_sigma.astype(jnp.float32)
    if cfg.prediction == "velocity":
        return x_sigma - sigma * prediction
    return (x_sigma - sigma * prediction) / _one_minus(sigma, cfg)


def target(x0: Array, noise: Array, cfg: FlowConfig) -> Array:
    """Regression target of the model output: ``noise - x0`` (velocity) or ``noise`` (epsilon)."""
    if cfg.prediction == "velocity":
        return noise.astype(jnp.float32) - x0.astype(jnp.float32)
    return noise.astype(jnp.float32)


def frame_timesteps(sigma: Float[Array, " b"], num_cond: int, num_future: int, cfg: FlowConfig) -> Float[Array, "b f"]:
    """Per-frame timesteps: 0 for the ``num_cond`` clean frames, ``sigma * N`` for the future ones."""
    batch = sigma.shape[0]
    cond = jnp.zeros((batch, num_cond), jnp.float32)
    future = jnp.broadcast_to(to_timesteps(sigma, cfg)[:, None], (batch, num_future))
    return jnp.concatenate([cond, future], axis=1)


def noisy_segment(
    latents: Float[Array, "b f h w c"], noise: Float[Array, "b p h w c"], sigma: Float[Array, " b"],
    num_cond: int, cfg: FlowConfig,
) -> tuple[Float[Array, "b f h w c"], Float[Array, "b f"]]:
    """Noises the future latents of a segment; keeps the ``num_cond`` conditioning latents clean.

    Returns:
      ``(model_input, timesteps)``: input ``[b, f, h, w, c]`` float32, timesteps ``[b, f]``.
    """
    cond = latents[:, :num_cond].astype(jnp.float32)
    future = add_noise(latents[:, num_cond:], noise, sigma)
    timesteps = frame_timesteps(sigma, num_cond, future.shape[1], cfg)
    return jnp.concatenate([cond, future], axis=1), timesteps


def flow_loss(
    prediction: Float[Array, "b f h w c"], latents: Float[Array, "b f h w c"], noise: Float[Array, "b p h w c"],
    num_cond: int, cfg: FlowConfig,
) -> Float[Array, ""]:
    """Mean squared error on the future latents only (float32)."""
    future_pred = prediction[:, num_cond:].astype(jnp.float32)
    return jnp.mean(jnp.square(future_pred - target(latents[:, num_cond:], noise, cfg)))
