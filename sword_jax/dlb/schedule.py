"""Read schedules of Dynamic Latent Bootstrapping.

The scheduled quantity is ``read_prob``: the probability that a training sample's context latent
is replaced by the cached prediction for its slot (where the slot holds one). The teacher-forcing
share is ``1 - read_prob``; the paper decays teacher forcing, so ``read_prob`` rises from
``cache.read_prob_start`` to ``cache.read_prob_end``:

* ``linear``: ``read_prob(step) = start + (end - start) * min(step / schedule_steps, 1)``.
* ``warmup_cosine``: ``start`` for ``step < warmup_steps``; then with
  ``u = min((step - warmup_steps) / schedule_steps, 1)``,
  ``read_prob = start + (end - start) * (1 - cos(pi * u)) / 2``.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from sword_jax.dlb.config import CacheConfig


def read_prob(cfg: CacheConfig, step: Int[Array, ""] | int) -> Float[Array, ""]:
    """Probability of reading the context from the cache at ``step`` (float32 scalar, traceable)."""
    step_f = jnp.asarray(step).astype(jnp.float32)
    start = jnp.float32(cfg.read_prob_start)
    end = jnp.float32(cfg.read_prob_end)
    if cfg.schedule == "linear":
        progress = jnp.clip(step_f / jnp.float32(cfg.schedule_steps), 0.0, 1.0)
    elif cfg.schedule == "warmup_cosine":
        u = jnp.clip((step_f - jnp.float32(cfg.warmup_steps)) / jnp.float32(cfg.schedule_steps), 0.0, 1.0)
        progress = (jnp.float32(1.0) - jnp.cos(jnp.float32(math.pi) * u)) / jnp.float32(2.0)
    else:
        raise ValueError(f"cache.schedule must be linear|warmup_cosine, got {cfg.schedule!r}")
    return start + (end - start) * progress


def teacher_forcing_share(cfg: CacheConfig, step: Int[Array, ""] | int) -> Float[Array, ""]:
    """``1 - read_prob(step)``: the expected share of samples trained on ground-truth context."""
    return jnp.float32(1.0) - read_prob(cfg, step)
