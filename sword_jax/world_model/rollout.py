"""Autoregressive latent rollouts of the world model, one ``lax.scan`` over chunks inside one jit.

Each chunk predicts ``p`` future latents from ``[episode first-frame latent, context latent(s)]``;
the next chunk's context is the last predicted latent(s), so the rollout never leaves latent space.
With ``FlowConfig.pixel_round_trip`` the context instead goes through WoVR's decode -> re-encode
round trip (a function built from the VAE, see :func:`make_pixel_round_trip`), for comparisons.
:func:`rollout_video` wraps it in the VAE: given frames in, decoded frames out.

Action layout (per video frame, like the training segments): a rollout of ``n`` chunks with ``k``
context and ``p`` future latents per chunk takes ``1 + 4k + 4pn`` actions: the first frame's, the
context frames', then every future frame's. Chunk ``i`` sees
``[a_0] + a[1 + 4pi : 1 + 4k + 4p(i+1)]`` (its context frames and its future frames).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.world_model import sampler
from sword_jax.world_model.config import FlowConfig

# (first_latent [b,1,h,w,c], chunk future latents [b,p,h,w,c]) -> next context latents [b,k,h,w,c]
RoundTripFn = Callable[[Array, Array], Array]


def num_chunks_for(num_actions: int, num_context: int, num_future: int) -> int:
    """Number of chunks a rollout with ``num_actions`` per-frame actions covers (validated)."""
    body = num_actions - 1 - 4 * num_context
    if body <= 0 or body % (4 * num_future):
        raise ValueError(
            f"rollout: {num_actions} actions do not fit 1 + 4*{num_context} + 4*{num_future}*n frames for any n >= 1"
        )
    return body // (4 * num_future)


def chunk_actions(actions: Float[Array, "b t a"], chunk: Array | int, num_context: int, num_future: int) -> Float[Array, "b s a"]:
    """The ``1 + 4(k + p)`` per-frame actions that chunk ``chunk`` of a rollout sees."""
    span = 4 * (num_context + num_future)
    start = 1 + 4 * num_future * jnp.asarray(chunk, jnp.int32)
    body = jax.lax.dynamic_slice_in_dim(actions, start, span, axis=1)
    return jnp.concatenate([actions[:, :1], body], axis=1)


def predict_chunk(
    model_fn: sampler.ModelFn,
    first_latent: Float[Array, "b 1 h w c"],
    context_latents: Float[Array, "b k h w c"],
    actions: Float[Array, "b s a"],
    *,
    key: jax.Array,
    num_future: int,
    cfg: FlowConfig,
    num_steps: int | None = None,
    guidance_scale: float | None = None,
) -> Float[Array, "b p h w c"]:
    """Samples one chunk's future latents from the first-frame latent and the context latent(s)."""
    cond = jnp.concatenate([first_latent.astype(jnp.float32), context_latents.astype(jnp.float32)], axis=1)
    return sampler.sample(model_fn, cond, actions, key=key, num_future=num_future, cfg=cfg,
                          num_steps=num_steps, guidance_scale=guidance_scale)


def _as_frames(latent: Array, name: str) -> Array:
    if latent.ndim == 4:
        return latent[:, None]
    if latent.ndim != 5:
        raise ValueError(f"rollout: {name} must be [b, h, w, c] or [b, n, h, w, c], got {latent.shape}")
    return latent


def rollout(
    graphdef: nnx.GraphDef,
    state: Any,
    first_latent: Float[Array, "b h w c"] | Float[Array, "b 1 h w c"],
    context_latent: Float[Array, "b h w c"] | Float[Array, "b k h w c"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    cfg: FlowConfig,
    num_future: int = 2,
    num_steps: int | None = None,
    guidance_scale: float | None = None,
    round_trip: RoundTripFn | None = None,
) -> Float[Array, "b n h w c"]:
    """Rolls the world model out autoregressively; jit it as a whole (the chunk loop is a scan).

    Args:
      graphdef: static graph of the world model.
      state: the model state for ``nnx.merge`` (one state / pure dict, or a tuple of them).
      first_latent: the episode's first-frame latent, ``[b, h, w, c]`` or ``[b, 1, h, w, c]``.
      context_latent: the initial context latent(s), ``[b, h, w, c]`` or ``[b, k, h, w, c]``.
      actions: per-video-frame actions ``[b, 1 + 4k + 4pn, a]`` (see the module docstring).
      key: sampling key; chunk ``i`` uses ``jax.random.split(key, n)[i]``.
      cfg: flow settings; ``cfg.pixel_round_trip`` routes the context through ``round_trip``.
      num_future: latents predicted per chunk ``p`` (2 = 8 video frames).
      num_steps: Euler steps per chunk (default ``cfg.sample_steps``).
      guidance_scale: action guidance (default ``cfg.guidance_scale``).
      round_trip: WoVR's decode -> re-encode of the context (required iff ``cfg.pixel_round_trip``).

    Returns:
      All predicted latents in order, ``[b, n * p, h, w, c]`` float32.
    """
    first = _as_frames(first_latent, "first_latent").astype(jnp.float32)
    context = _as_frames(context_latent, "context_latent").astype(jnp.float32)
    num_context = context.shape[1]
    if cfg.pixel_round_trip and round_trip is None:
        raise ValueError("rollout: flow.pixel_round_trip is set but no round_trip function was given "
                         "(build one with make_pixel_round_trip(vae_graphdef, vae_state))")
    num_chunks = num_chunks_for(actions.shape[1], num_context, num_future)
    model_fn = sampler.model_fn_from_state(graphdef, state)
    chunk_keys = jax.random.split(key, num_chunks)

    def one_chunk(context, inputs):
        chunk, chunk_key = inputs
        future = predict_chunk(model_fn, first, context, chunk_actions(actions, chunk, num_context, num_future),
                               key=chunk_key, num_future=num_future, cfg=cfg, num_steps=num_steps,
                               guidance_scale=guidance_scale)
        if cfg.pixel_round_trip:
            next_context = round_trip(first, future).astype(jnp.float32)
        else:
            next_context = jnp.concatenate([context, future], axis=1)[:, -num_context:]
        return next_context, future

    _, futures = jax.lax.scan(one_chunk, context, (jnp.arange(num_chunks, dtype=jnp.int32), chunk_keys))
    # (n, b, p, h, w, c) -> (b, n * p, h, w, c)
    futures = jnp.moveaxis(futures, 0, 1)
    return futures.reshape((futures.shape[0], num_chunks * num_future) + futures.shape[3:])


def make_pixel_round_trip(vae_graphdef: nnx.GraphDef, vae_state: Any, num_context: int = 1) -> RoundTripFn:
    """WoVR's context round trip: decode ``[first, chunk]`` to frames, re-encode, keep the last ``k`` latents.

    The causal VAE decodes ``1 + p`` latents to ``1 + 4p`` frames and encodes them back to ``1 + p``
    latents, so the next context is what an encoder would make of the generated pixels.
    """
    from sword_jax.vae import api as vae_api

    def round_trip(first_latent: Array, future: Array) -> Array:
        latents = jnp.concatenate([first_latent, future], axis=1).astype(jnp.float32)
        frames = vae_api.decode(vae_graphdef, vae_state, latents, clamp=True, check_values=False)
        reencoded = vae_api.encode(vae_graphdef, vae_state, frames, check_values=False)
        return reencoded[:, -num_context:]

    return round_trip


def decode_rollout(
    vae_graphdef: nnx.GraphDef, vae_state: Any, first_latent: Float[Array, "b h w c"] | Float[Array, "b 1 h w c"],
    predicted: Float[Array, "b n h w c"], *, latents_per_chunk: int = 2, clamp: bool = True,
) -> Float[Array, "b t hh ww 3"]:
    """Decodes ``[first-frame latent, predicted latents]`` to video with the VAE's streaming decoder.

    The first chunk (the first-frame latent) gives 1 frame; each following chunk of
    ``latents_per_chunk`` latents gives ``4 * latents_per_chunk`` frames, carried through one
    ``lax.scan`` with the decoder's feature cache.

    Returns:
      Frames ``[b, 1 + 4n, 16h, 16w, 3]`` float32 (clamped to [-1, 1] unless ``clamp=False``).
    """
    from sword_jax.vae import api as vae_api

    first = _as_frames(first_latent, "first_latent").astype(jnp.float32)
    batch, num_latents = predicted.shape[:2]
    if num_latents % latents_per_chunk:
        raise ValueError(f"decode_rollout: {num_latents} latents are not whole chunks of {latents_per_chunk}")
    cache = vae_api.init_decode_cache(vae_graphdef, vae_state, batch, first.shape[2], first.shape[3])
    first_frames, cache = vae_api.decode_chunk(vae_graphdef, vae_state, first, cache, clamp=clamp, check_values=False)
    chunks = predicted.astype(jnp.float32).reshape(
        (batch, num_latents // latents_per_chunk, latents_per_chunk) + predicted.shape[2:])

    def decode_one(features, chunk):
        frames, new_cache = vae_api.decode_chunk(
            vae_graphdef, vae_state, chunk, vae_api.StreamCache(features, started=True), clamp=clamp,
            check_values=False)
        return new_cache.features, frames

    _, frames = jax.lax.scan(decode_one, cache.features, jnp.moveaxis(chunks, 1, 0))
    frames = jnp.moveaxis(frames, 0, 1)  # (b, chunks, 4m, H, W, 3)
    frames = frames.reshape((batch, -1) + frames.shape[3:])
    return jnp.concatenate([first_frames, frames], axis=1)


def decode_chunk_size(num_context: int, num_future: int) -> int:
    """Largest latents-per-decode-chunk dividing ``k + p n`` for every n (gcd of k and p)."""
    return math.gcd(num_context, num_future)


def rollout_video(
    graphdef: nnx.GraphDef,
    state: Any,
    vae_graphdef: nnx.GraphDef,
    vae_state: Any,
    given_video: Float[Array, "b g hh ww 3"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    cfg: FlowConfig,
    num_future: int = 2,
    num_steps: int | None = None,
) -> tuple[Float[Array, "b t hh ww 3"], Float[Array, "b n hh2 ww2 c"], Float[Array, "b k1 hh2 ww2 c"]]:
    """Pixels in, pixels out: encode the given frames, :func:`rollout`, decode; jit it as a whole.

    Args:
      graphdef / state: the world model, as for :func:`rollout`.
      vae_graphdef / vae_state: the video VAE.
      given_video: the episode's first frame and ``4k`` context frames, ``[b, 1 + 4k, H, W, 3]``
        float in [-1, 1] (``k`` context latents).
      actions: per-frame actions ``[b, 1 + 4k + 4pn, a]`` (see the module docstring).
      key, cfg, num_future, num_steps: as for :func:`rollout`.

    Returns:
      ``(video, predicted, given_latents)``: ``video [b, 1 + 4k + 4pn, H, W, 3]`` float32 in [-1, 1]
      (the given frames as the VAE reconstructs them, then the predicted ones), the predicted
      latents ``[b, pn, h, w, c]`` and the given frames' latents ``[b, 1 + k, h, w, c]``.
    """
    from sword_jax.vae import api as vae_api

    given = vae_api.encode(vae_graphdef, vae_state, given_video, check_values=False)
    num_context = given.shape[1] - 1
    if num_context < 1:
        raise ValueError(f"rollout_video: given_video needs 1 + 4k frames with k >= 1, got {given_video.shape}")
    first, context = given[:, :1], given[:, 1:]
    round_trip = make_pixel_round_trip(vae_graphdef, vae_state, num_context) if cfg.pixel_round_trip else None
    predicted = rollout(graphdef, state, first, context, actions, key=key, cfg=cfg, num_future=num_future,
                        num_steps=num_steps, round_trip=round_trip)
    video = decode_rollout(vae_graphdef, vae_state, first, jnp.concatenate([context, predicted], axis=1),
                           latents_per_chunk=decode_chunk_size(num_context, num_future))
    return video, predicted, given
