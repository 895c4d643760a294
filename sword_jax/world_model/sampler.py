"""Shifted Euler flow-matching sampler for one world-model chunk, as one ``lax.scan``.

The model is called through a plain function ``model_fn(latents, timesteps, actions) -> prediction``
(see :func:`model_fn_from_state`), so the sampler is independent of how parameters are stored.
Conditioning latents (episode first frame + context) are re-imposed, clean with ``t = 0``, at every
step; only the future latents are integrated from sigma = 1 to 0 on Wan's shifted grid.

The actions are the same at every step of a chunk, so a :class:`ConditionedModelFn`
(``model_fn_from_state(..., cache_actions=True)``) has their work -- the action tokens and every
block's cross-attention keys and values of them, the AdaLN offset -- done once per chunk, before the
steps, instead of once per step. The predictions are the same.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.world_model import flow
from sword_jax.world_model.config import FlowConfig

ModelFn = Callable[[Array, Array, Array], Array]


class ConditionedModelFn(NamedTuple):
    """A model function whose action conditioning is computed once and reused.

    ``condition(actions) -> conditioning`` (a pytree); ``apply(latents, timesteps, conditioning) ->
    prediction``. Called as a plain :data:`ModelFn` it does both, so it goes wherever one does;
    :func:`sample` calls ``condition`` once per chunk and ``apply`` at every Euler step.
    """

    condition: Callable[[Array], Any]
    apply: Callable[[Array, Array, Any], Array]

    def __call__(self, latents, timesteps, actions):
        return self.apply(latents, timesteps, self.condition(actions))


def model_fn_from_state(graphdef: nnx.GraphDef, state: Any, *, cache_actions: bool = False) -> ModelFn:
    """Builds ``model_fn(latents, timesteps, actions)`` by merging ``graphdef`` with ``state``.

    Args:
      graphdef: static graph of the world model.
      state: what ``nnx.merge`` takes after the graphdef: one state / pure dict, or a tuple of them
        (e.g. ``(params, buffers)``).
      cache_actions: return a :class:`ConditionedModelFn` (the world model's
        :meth:`~sword_jax.dit.action_dit.WorldModel.condition` / ``apply_conditioned``), so the sampler
        works on the actions once per chunk. Off: a plain function (the training path's).
    """
    states = state if isinstance(state, tuple) else (state,)

    def model_fn(latents, timesteps, actions):
        return nnx.merge(graphdef, *states)(latents, timesteps, actions)

    if not cache_actions:
        return model_fn
    return ConditionedModelFn(
        condition=lambda actions: nnx.merge(graphdef, *states).condition(actions),
        apply=lambda latents, timesteps, cond: nnx.merge(graphdef, *states).apply_conditioned(latents, timesteps, cond))


def null_actions(actions: Float[Array, "b t a"]) -> Float[Array, "b t a"]:
    """Unconditional branch of classifier-free guidance: all-zero actions."""
    return jnp.zeros_like(actions)


def guided_velocity(
    model_fn: ModelFn, latents: Array, timesteps: Array, actions: Array, sigma: Array,
    num_cond: int, cfg: FlowConfig, guidance_scale: float,
) -> Float[Array, "b p h w c"]:
    """Velocity of the future latents, with classifier-free guidance when ``guidance_scale != 1``.

    The conditional and null-action passes share one batched model call.
    """
    future = latents[:, num_cond:]
    if guidance_scale == 1.0:
        prediction = model_fn(latents, timesteps, actions)[:, num_cond:]
        return flow.to_velocity(prediction, future, sigma, cfg)
    both = model_fn(
        jnp.concatenate([latents, latents], axis=0),
        jnp.concatenate([timesteps, timesteps], axis=0),
        jnp.concatenate([actions, null_actions(actions)], axis=0),
    )[:, num_cond:]
    velocity = flow.to_velocity(both, jnp.concatenate([future, future], axis=0), sigma, cfg)
    cond_v, null_v = jnp.split(velocity, 2, axis=0)
    return null_v + jnp.float32(guidance_scale) * (cond_v - null_v)


def sample(
    model_fn: ModelFn,
    cond_latents: Float[Array, "b k h w c"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    num_future: int,
    cfg: FlowConfig,
    num_steps: int | None = None,
    guidance_scale: float | None = None,
    noise: Float[Array, "b p h w c"] | None = None,
) -> Float[Array, "b p h w c"]:
    """Samples the future latents of one chunk with shifted Euler steps (one ``lax.scan``).

    Args:
      model_fn: ``(latents [b,f,h,w,c], timesteps [b,f], actions [b,t,a]) -> prediction [b,f,h,w,c]``.
      cond_latents: clean conditioning latents ``[first frame, context...]``, ``[b, k, h, w, c]``.
      actions: per-video-frame actions of the segment, ``[b, 1 + 4 (k + p - 1), a]``.
      key: noise key (ignored when ``noise`` is given).
      num_future: number of future latents ``p`` to sample.
      cfg: flow settings (prediction type, the grid's shift ``sample_shift`` or else ``shift``, default steps and
        guidance).
      num_steps: Euler steps (1..50); default ``cfg.sample_steps``.
      guidance_scale: classifier-free guidance on the actions (1 = off); default ``cfg.guidance_scale``.
      noise: optional initial noise ``[b, p, h, w, c]``; drawn or given, it is scaled by ``cfg.noise_scale``.

    Returns:
      Clean future latents ``[b, p, h, w, c]`` (float32).
    """
    num_steps = cfg.sample_steps if num_steps is None else num_steps
    guidance_scale = cfg.guidance_scale if guidance_scale is None else float(guidance_scale)
    batch, num_cond = cond_latents.shape[:2]
    expected_actions = 1 + 4 * (num_cond + num_future - 1)
    if actions.shape[:2] != (batch, expected_actions):
        raise ValueError(
            f"sample: actions must be [b={batch}, {expected_actions}, a] for {num_cond} conditioning + "
            f"{num_future} future latents, got {actions.shape}"
        )
    cond = cond_latents.astype(jnp.float32)
    if noise is None:
        noise = jax.random.normal(key, (batch, num_future) + cond.shape[2:], jnp.float32)
    elif noise.shape != (batch, num_future) + cond.shape[2:]:
        raise ValueError(f"sample: noise shape {noise.shape} != {(batch, num_future) + cond.shape[2:]}")
    if cfg.noise_scale != 1.0:  # a lower-temperature draw (0: the deterministic path from the prior's mean)
        noise = noise * jnp.float32(cfg.noise_scale)
    sigmas = flow.sampling_sigmas(num_steps, cfg.sample_shift or cfg.shift)
    step_fn = model_fn
    if isinstance(model_fn, ConditionedModelFn):  # the actions' work once per chunk, not once per step
        both = actions if guidance_scale == 1.0 else jnp.concatenate([actions, null_actions(actions)], axis=0)
        conditioning = model_fn.condition(both)  # laid out as guided_velocity batches its model call

        def step_fn(latents, timesteps, _actions):
            return model_fn.apply(latents, timesteps, conditioning)

    def euler_step(future, sigma_pair):
        sigma, sigma_next = sigma_pair[0], sigma_pair[1]
        latents = jnp.concatenate([cond, future], axis=1)  # conditioning re-imposed every step
        timesteps = flow.frame_timesteps(jnp.full((batch,), sigma), num_cond, num_future, cfg)
        velocity = guided_velocity(step_fn, latents, timesteps, actions, sigma, num_cond, cfg, guidance_scale)
        return future + (sigma_next - sigma) * velocity, None

    pairs = jnp.stack([sigmas[:-1], sigmas[1:]], axis=1)  # (steps, 2)
    future, _ = jax.lax.scan(euler_step, noise.astype(jnp.float32), pairs)
    return future
