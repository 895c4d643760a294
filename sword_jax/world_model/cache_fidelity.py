"""What DLB writes into the cache, and how far it is from the context inference would produce.

At inference the context of a chunk is the previous chunk's output of the flow sampler
(:func:`sword_jax.world_model.sampler.sample`, ``flow.sample_steps`` Euler steps). DLB replaces
teacher-forced context by cached latents; the cache is only faithful to inference if what it holds
looks like that sampler output. :func:`write_latents` makes the cache's values for either write
source, :func:`inference_context` the sampler's output for the same conditioning, and
:func:`latent_distance` compares them.

The comparison is between one cached value and one independent sample (fresh noise), so even a
perfect write source has a floor: the spread of the sampler itself (two independent samples; see
``benchmarks/bench_dlb.py --write-sources``). A blurred estimate (the ``one_step`` source at high
noise) can sit closer to a sample in mean squared error than a second sample does, while having
clearly less energy: ``norm_ratio`` (cached norm / inference norm) shows that.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import flow, sampler
from sword_jax.world_model.config import FlowConfig

DISTANCE_METRICS = ("rel_mse", "cosine", "norm_ratio")


def num_written(cfg: CacheConfig, num_future: int) -> int:
    """How many future latents per sample are written (``scope``)."""
    return 1 if cfg.scope == "single" else num_future


def sampler_steps(cfg: CacheConfig, flow_cfg: FlowConfig) -> int:
    """Euler steps of the ``sampler`` write source (``None`` = the inference setting)."""
    return flow_cfg.sample_steps if cfg.write_sample_steps is None else cfg.write_sample_steps


def write_latents(
    cfg: CacheConfig,
    flow_cfg: FlowConfig,
    model_fn: sampler.ModelFn,
    cond_latents: Float[Array, "b k h w c"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    prediction_future: Float[Array, "b p h w c"],
    noisy_future: Float[Array, "b p h w c"],
    sigma: Float[Array, " b"],
) -> Float[Array, "b p h w c"]:
    """The values DLB writes for the ``p`` future latents of each sample (float32, no gradient).

    Args:
      cfg: ``write_source`` and ``write_sample_steps``.
      flow_cfg: prediction type, shift, guidance.
      model_fn: the model at the step's (pre-update) params, for the ``sampler`` source.
      cond_latents: the conditioning the step trained on, ``[first frame, context...]``.
      actions: the segment's per-frame actions.
      key: sampler noise (``sampler`` source only).
      prediction_future: the training forward pass's output on the future latents.
      noisy_future: the noised future latents the forward pass saw.
      sigma: per-sample noise level of the forward pass ``[b]``.
    """
    if cfg.write_source == "sampler":
        written = sampler.sample(model_fn, cond_latents, actions, key=key, num_future=noisy_future.shape[1],
                                 cfg=flow_cfg, num_steps=sampler_steps(cfg, flow_cfg))
    else:
        sigma_b = sigma[:, None, None, None, None]
        written = flow.to_clean(prediction_future, noisy_future, sigma_b, flow_cfg)
    return jax.lax.stop_gradient(written.astype(jnp.float32))


def inference_context(
    flow_cfg: FlowConfig,
    model_fn: sampler.ModelFn,
    cond_latents: Float[Array, "b k h w c"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    num_future: int,
) -> Float[Array, "b p h w c"]:
    """What inference puts in the context for these future latents: the flow sampler with the
    inference settings (``flow.sample_steps``, ``flow.guidance_scale``) from fresh noise."""
    out = sampler.sample(model_fn, cond_latents, actions, key=key, num_future=num_future, cfg=flow_cfg)
    return jax.lax.stop_gradient(out)


def latent_distance(
    cached: Float[Array, "b n h w c"], reference: Float[Array, "b n h w c"]
) -> dict[str, Float[Array, ""]]:
    """Distance of cached latents from reference latents, relative to the reference's size.

    Returns float32 scalars:
      ``rel_mse``: ``sum |cached - reference|^2 / sum |reference|^2`` over the batch.
      ``cosine``: mean over (sample, latent) of the cosine between the flattened latents.
      ``norm_ratio``: ``sqrt(sum |cached|^2 / sum |reference|^2)`` (< 1: the cache is blurred).
    """
    cached = cached.astype(jnp.float32)
    reference = reference.astype(jnp.float32)
    flat_c = cached.reshape(cached.shape[:2] + (-1,))  # (B, n, h*w*c)
    flat_r = reference.reshape(reference.shape[:2] + (-1,))
    tiny = jnp.float32(1e-12)
    ref_energy = jnp.sum(flat_r * flat_r)
    rel_mse = jnp.sum(jnp.square(flat_c - flat_r)) / jnp.maximum(ref_energy, tiny)
    norms = jnp.linalg.norm(flat_c, axis=-1) * jnp.linalg.norm(flat_r, axis=-1)
    cosine = jnp.mean(jnp.sum(flat_c * flat_r, axis=-1) / jnp.maximum(norms, tiny))
    norm_ratio = jnp.sqrt(jnp.sum(flat_c * flat_c) / jnp.maximum(ref_energy, tiny))
    return {"rel_mse": rel_mse, "cosine": cosine, "norm_ratio": norm_ratio}


def stored(latents: Float[Array, "b n h w c"], cfg: CacheConfig) -> Float[Array, "b n h w c"]:
    """``latents`` as the cache stores them (``cfg.dtype``) and reads them back (float32)."""
    return latents.astype(jnp.dtype(cfg.dtype)).astype(jnp.float32)
