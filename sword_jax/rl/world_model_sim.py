"""The world model + VAE as a :class:`~sword_jax.rl.learned_simulator.LearnedSimulator`.

Per step (one action chunk of 8 actions = 2 latent frames):

1. the flow-matching sampler (:func:`sword_jax.world_model.rollout.predict_chunk`, a few Euler
   steps) predicts the next ``p`` latents from ``[first-frame latent, k context latents]`` and the
   per-frame actions ``[a_0, context actions (4k), future actions (4p)]``, aligned as in training
   (:mod:`sword_jax.world_model.data`): each video frame carries the action taken AFTER it is
   seen. The policy acts on the last context frame ``4j``, so its first action ``a_4j`` belongs to
   that frame (the last context slot) and ``a_4j+1 .. a_4j+7`` to the predicted frames; the last
   predicted frame's own action is not known yet and holds ``a_4j+7`` until the next chunk's first
   action replaces it;
2. the causal VAE decoder streams those latents to ``4p`` frames with its feature cache
   (:func:`sword_jax.vae.api.decode_chunk`), so pixels are produced once per frame; with a light decoder
   (``light_decoder``, :mod:`sword_jax.vae.light_decoder`) that one streams them instead, at its own
   resolution, and the simulator's parameters are the world model's and the light decoder's;
3. the context becomes the last ``k`` predicted latents (the rollout stays in latent space).

State is per trajectory; the VAE / DiT calls inside take a batch of one, and the imagined
rollout ``vmap``s over trajectories (XLA folds the vmapped axis into the batch dimension).
The decoder cache is warmed in ``init`` by decoding the start latents, so its static
``started`` flag is True for every step and the ``lax.scan`` carry has a fixed structure.

The world model cannot report proprio. With ``proprio_reckoning`` the simulator integrates it from
the start state's proprio and the executed actions (:mod:`sword_jax.rl.proprio_reckoning`) and
``observe`` reports it valid; without, ``observe`` marks it invalid (the policy then uses its
learned "missing proprio" embedding, trained by proprio dropout in SFT).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.dit.config import FRAMES_PER_LATENT  # the world model's actions per latent
from sword_jax.rl.learned_simulator import LearnedSimulator, StartState
from sword_jax.rl.proprio_reckoning import ReckoningConfig, reckon
from sword_jax.vae import api as vae_api
from sword_jax.vae import light_decoder as light
from sword_jax.world_model import sampler as wm_sampler
from sword_jax.world_model.config import FlowConfig
from sword_jax.world_model.rollout import make_pixel_round_trip, predict_chunk


# frames [n, H, W, 3] in [0, 1] -> the same frames as a codec shows them
RoundTrip = Callable[[Float[Array, "n h w 3"]], Float[Array, "n h w 3"]]


class WMState(NamedTuple):
    first_latent: Float[Array, "1 1 h w c"]
    context: Float[Array, "1 k h w c"]
    first_action: Float[Array, "1 1 a"]  # the action of the episode's first frame (training's a_0)
    context_actions: Float[Array, "1 s a"]  # actions of the context latents' video frames
    decode_cache: Any  # the decoder's StreamCache for a batch of one
    proprio: Float[Array, " p"]


class StreamDecoder(NamedTuple):
    """How the simulator turns latents into frames, for a batch of one: ``init(params, h, w) -> cache`` and
    ``decode(params, latent_chunk, cache) -> (video in [-1, 1], cache)`` (the first chunk holds the stream's
    first latent), with ``params`` the simulator's second parameter entry."""

    init: Callable[..., Any]
    decode: Callable[..., Any]


def vae_stream_decoder(vae_graphdef: nnx.GraphDef) -> StreamDecoder:
    """The VAE's own streaming decode (:func:`sword_jax.vae.api.decode_chunk`)."""
    return StreamDecoder(
        init=lambda params, h, w: vae_api.init_decode_cache(vae_graphdef, params, 1, h, w),
        decode=lambda params, z, cache: vae_api.decode_chunk(vae_graphdef, params, z, cache, check_values=False))


def light_stream_decoder(graphdef: nnx.GraphDef) -> StreamDecoder:
    """The light decoder's streaming decode (:func:`sword_jax.vae.light_decoder.decode_chunk`)."""
    return StreamDecoder(init=lambda params, h, w: light.init_stream_cache(graphdef, params, 1, h, w),
                         decode=lambda params, z, cache: light.decode_chunk(graphdef, params, z, cache))


def to_unit(video: Float[Array, "..."]) -> Float[Array, "..."]:
    """VAE video in [-1, 1] -> frames in [0, 1]."""
    return jnp.clip((video.astype(jnp.float32) + 1.0) * jnp.float32(0.5), 0.0, 1.0)


def still_round_trip(codec: Callable[[Array], Array], frames_per_latent: int) -> RoundTrip:
    """Frames ``[n, H, W, 3]`` in [0, 1] each held still for ``1 + frames_per_latent`` frames (the causal VAE's
    first latent holds one frame, each later one ``frames_per_latent``; the world model's frames come from later
    latents), passed through ``codec`` (video ``[n, T, H, W, 3]`` in [-1, 1] -> the same) and the last frame
    back in [0, 1] (:func:`to_unit`)."""

    def round_trip(frames: Float[Array, "n h w 3"]) -> Float[Array, "n h w 3"]:
        still = jnp.repeat(frames.astype(jnp.float32)[:, None] * 2.0 - 1.0, 1 + frames_per_latent, axis=1)
        return to_unit(codec(still)[:, -1])

    return round_trip


def vae_round_trip(vae_graphdef: nnx.GraphDef, vae_state: Any) -> RoundTrip:
    """:func:`still_round_trip` through the VAE: :func:`sword_jax.vae.api.encode` as a still keyframe is encoded
    for the world model (:func:`encode_keyframes`), then ``decode`` (clamped). The frame the VAE shows of a real
    one: what a world model that predicted the real scene's latents exactly would show, decoded by this VAE."""

    def codec(video: Array) -> Array:
        latents = vae_api.encode(vae_graphdef, vae_state, video, check_values=False)
        return vae_api.decode(vae_graphdef, vae_state, latents, clamp=True, check_values=False)

    return still_round_trip(codec, vae_api.factors(vae_graphdef, vae_state)[0])


def encode_keyframes(
    vae_graphdef: nnx.GraphDef, vae_state: Any, frames: Float[Array, "n h w 3"], *, num_context: int = 1
) -> Float[Array, "n l hl wl z"]:
    """Start latents ``[first, k context]`` for keyframes: the frame held still for ``1 + 4k`` frames.

    A fallback for keyframes without history; :func:`encode_history` uses the real one.
    """
    video = jnp.repeat(frames.astype(jnp.float32)[:, None] * 2.0 - 1.0, 1 + FRAMES_PER_LATENT * num_context, axis=1)
    return vae_api.encode(vae_graphdef, vae_state, video, check_values=False)


def encode_history(
    vae_graphdef: nnx.GraphDef,
    vae_state: Any,
    first_frames: Float[Array, "n h w 3"],
    history: Float[Array, "n f h w 3"],
    *,
    num_context: int = 1,
) -> Float[Array, "n l hl wl z"]:
    """Start latents ``[first, k context]`` from a keyframe's real past.

    Args:
      first_frames: each episode's first frame (the world model's anchor), in [0, 1].
      history: the ``4 (k + 1)`` frames up to and including the keyframe, in [0, 1]; the oldest
        four only warm the causal encoder's cache (their latent is dropped), so the context
        latents see the motion that led to the keyframe, as the dataset's latents do.

    Returns:
      ``[n, 1 + k, h, w, z]``: the first-frame latent and the ``k`` latents ending at the keyframe.
    """
    need = FRAMES_PER_LATENT * (num_context + 1)
    if history.shape[1] != need:
        raise ValueError(f"encode_history: history must hold {need} frames, got {history.shape}")
    video = jnp.concatenate([first_frames[:, None], history], axis=1).astype(jnp.float32) * 2.0 - 1.0
    latents = vae_api.encode(vae_graphdef, vae_state, video, check_values=False)  # (n, 2 + k, ...)
    return jnp.concatenate([latents[:, :1], latents[:, 2:]], axis=1)


def encode_prefix(
    vae_graphdef: nnx.GraphDef,
    vae_state: Any,
    prefix: Float[Array, "n f h w 3"],
    latent_index: Any,
    *,
    num_context: int = 1,
    frames_per_call: int = 2048,
) -> Float[Array, "n l hl wl z"]:
    """Start latents ``[first, k context]`` encoded from each episode's first frame on, as training saw them.

    The latents stage encodes whole episodes with the causal VAE, so a context latent carries everything its
    encoder cache saw since frame 0; :func:`encode_history`'s short window gives it only four frames of that.
    Here the VAE encodes ``prefix`` (``[n, 1 + 4 S, H, W, 3]`` in [0, 1], from frame 0;
    :func:`~sword_jax.rl.data.keyframe_window` with ``prefix_latents``) and each row keeps its latent 0 and the
    ``k`` latents ending at ``latent_index [n]``. The encoder is causal, so the frames after the keyframe (whatever
    they are) change none of them: they equal the whole episode's latents there. The rows are encoded a slice at a
    time, at most ``frames_per_call`` frames each (long prefixes of many starts would not fit at once).
    """
    index = jnp.asarray(latent_index, jnp.int32)
    rows_per_call = max(1, int(frames_per_call) // int(prefix.shape[1]))
    latents = jnp.concatenate([
        vae_api.encode(vae_graphdef, vae_state, jnp.asarray(prefix[i:i + rows_per_call], jnp.float32) * 2.0 - 1.0,
                       check_values=False)
        for i in range(0, prefix.shape[0], rows_per_call)])  # (n, 1 + S, ...)
    if latents.shape[1] <= int(num_context):
        raise ValueError(f"encode_prefix: a prefix of {prefix.shape[1]} frames holds no {num_context} context latents")
    rows = index[:, None] - num_context + 1 + jnp.arange(num_context)[None]  # (n, k): the context latents' indices
    context = jnp.take_along_axis(latents, rows.reshape(rows.shape + (1,) * (latents.ndim - 2)), axis=1)
    return jnp.concatenate([latents[:, :1], context], axis=1)


def world_model_simulator(
    wm_graphdef: nnx.GraphDef,
    wm_state: Any,
    vae_graphdef: nnx.GraphDef,
    vae_state: Any,
    *,
    flow_cfg: FlowConfig,
    frame_size: int,
    num_context: int = 1,
    num_future: int = 2,
    sample_steps: int | None = None,
    action_dim: int = 7,
    latent_size: int | None = None,
    proprio_dim: int = 8,
    execute_latents: int | None = None,
    proprio_reckoning: ReckoningConfig | None = None,
    light_decoder: tuple[nnx.GraphDef, Any] | None = None,
) -> LearnedSimulator:
    """Builds the learned simulator from a split WorldModel and a split WanVAE.

    Args:
      wm_graphdef / wm_state: ``nnx.split`` of :class:`sword_jax.dit.action_dit.WorldModel`.
      vae_graphdef / vae_state: ``nnx.split`` of the VAE.
      flow_cfg: flow-matching settings (shift, prediction type, guidance; ``pixel_round_trip`` makes
        each next context the VAE's re-encoding of the decoded chunk, as in evaluation).
      frame_size: decoded frame size (the VAE's spatial factor times the latent size).
      num_context / num_future: context and predicted latents per chunk (future 2 = 8 frames).
      sample_steps: Euler steps per chunk (default ``flow_cfg.sample_steps``).
      latent_size: latent height/width (default ``frame_size`` over the VAE's spatial factor).
      proprio_dim: size of the proprio the policy receives.
      execute_latents: predicted latents kept per step (default ``num_future``: the whole chunk).
        Fewer re-plans sooner: the world model predicts all ``num_future`` latents from the chunk's
        actions, the first ``execute_latents`` (``4 x`` as many frames and actions) are executed and
        become context, the rest is discarded (the simulator's ``execute_len``).
      proprio_reckoning: the action convention to dead-reckon proprio with (8-D, LIBERO layout); None
        marks proprio invalid.
      light_decoder: ``(graphdef, state)`` of a light decoder that decodes the frames instead of the VAE
        (:mod:`sword_jax.vae.light_decoder`); ``frame_size`` is then its output size and ``latent_size``
        (default ``frame_size`` over its scale) the world model's. The simulator's parameters are
        ``(wm_state, light_state)``; ``flow_cfg.pixel_round_trip`` (which re-encodes the VAE's frames) is refused.

    With the VAE's decoder the simulator's ``round_trip`` is :func:`vae_round_trip` through its own VAE weights
    (as it decodes them, its second parameter entry; the builder's ``fast`` precision encodes in bfloat16 too):
    the frame it would show of a real one if its latents were the real scene's. With a light decoder it has none
    (its parameters hold no VAE encoder).

    ``StartState.latents`` is ``[1 + num_context, h, w, z]`` (then every conditioning frame carries
    a zero action, as for a keyframe held still: :func:`encode_keyframes`) or a pair ``(latents,
    actions [1 + 4 num_context, action_dim])`` with the actions the episode's first frame and the
    context frames really carried, laid out as a training segment's (:func:`encode_history`).
    """
    execute_latents = num_future if execute_latents is None else int(execute_latents)
    if proprio_reckoning is not None:
        proprio_reckoning.validate()
        if proprio_dim != 8:
            raise ValueError(f"world-model sim: proprio reckoning needs the 8-D proprio, got proprio_dim={proprio_dim}")
    if not 1 <= execute_latents <= num_future:
        raise ValueError(f"world-model sim: execute_latents must be in [1, num_future={num_future}], got "
                         f"{execute_latents}")
    if flow_cfg.pixel_round_trip and execute_latents < num_context:
        raise ValueError(f"world-model sim: flow.pixel_round_trip re-encodes the {execute_latents} executed latents "
                         f"as the next context, fewer than its num_context={num_context}")
    chunk_len = FRAMES_PER_LATENT * num_future  # actions per call
    execute_len = FRAMES_PER_LATENT * execute_latents  # executed actions (= frames returned) per step
    if light_decoder is None:
        decoder, decoder_state = vae_stream_decoder(vae_graphdef), vae_state
        scale = vae_api.factors(vae_graphdef, vae_state)[1]
    else:
        if flow_cfg.pixel_round_trip:
            raise ValueError("world-model sim: flow.pixel_round_trip re-encodes the VAE's decoded frames; it needs the "
                             "full decoder, not a light one")
        light_graphdef, decoder_state = light_decoder
        decoder = light_stream_decoder(light_graphdef)
        scale = light.attributes(light_graphdef, decoder_state)[1]
    hl = latent_size or frame_size // scale
    if light_decoder is not None and hl * scale != frame_size:
        raise ValueError(f"world-model sim: frame_size={frame_size} is not the light decoder's scale {scale} times "
                         f"the latent size {hl}")

    def init_fn(params, start: StartState) -> WMState:
        wm_params, decoder_params = params
        if isinstance(start.latents, (tuple, list)):
            latents, actions = start.latents
            actions = jnp.asarray(actions, jnp.float32)
            if actions.shape != (1 + FRAMES_PER_LATENT * num_context, action_dim):
                raise ValueError(f"world-model sim: start actions must be [{1 + FRAMES_PER_LATENT * num_context}, "
                                 f"{action_dim}], got {actions.shape}")
        else:
            latents, actions = start.latents, jnp.zeros((1 + FRAMES_PER_LATENT * num_context, action_dim))
        latents = jnp.asarray(latents, jnp.float32)
        if latents.ndim != 4 or latents.shape[0] != 1 + num_context:
            raise ValueError(f"world-model sim: start.latents must be [{1 + num_context}, h, w, z], got {latents.shape}")
        cache = decoder.init(decoder_params, hl, hl)
        _, cache = decoder.decode(decoder_params, latents[None], cache)
        return WMState(latents[None, :1], latents[None, 1:], actions[None, :1], actions[None, 1:], cache,
                       jnp.asarray(start.proprio, jnp.float32))

    def step_fn(params, state: WMState, chunk, key):
        wm_params, decoder_params = params
        chunk = chunk.astype(jnp.float32)[None]  # (1, T, A): a_4j .. a_4j+T-1, acting on frame 4j
        # a_4j is the last context frame's action; the predicted frames carry a_4j+1 .. and a placeholder
        context_actions = state.context_actions.at[:, -1].set(chunk[:, 0])
        future_actions = jnp.concatenate([chunk[:, 1:], chunk[:, -1:]], axis=1)
        actions = jnp.concatenate([state.first_action, context_actions, future_actions], axis=1)
        model_fn = wm_sampler.model_fn_from_state(wm_graphdef, wm_params, cache_actions=True)  # actions once per chunk
        future = predict_chunk(model_fn, state.first_latent, state.context, actions, key=key, num_future=num_future,
                               cfg=flow_cfg, num_steps=sample_steps)
        future = future[:, :execute_latents]  # executed; the rest of the prediction is discarded
        video, cache = decoder.decode(decoder_params, future, state.decode_cache)
        if flow_cfg.pixel_round_trip:  # WoVR: the next context is the re-encoded generated pixels (full decoder)
            context = make_pixel_round_trip(vae_graphdef, decoder_params, num_context)(state.first_latent, future)
            context = context.astype(jnp.float32)
        else:
            context = jnp.concatenate([state.context, future], axis=1)[:, -num_context:]
        executed_actions = future_actions[:, :execute_len]
        context_actions = jnp.concatenate([context_actions, executed_actions],
                                          axis=1)[:, -FRAMES_PER_LATENT * num_context:]
        frames = to_unit(video[0])  # (T, H, W, 3)
        proprio = state.proprio
        if proprio_reckoning is not None:  # after the executed actions a_4j .. a_4j+execute_len-1
            proprio = reckon(proprio[:8], chunk[0, :execute_len], proprio_reckoning)[-1]
            proprio = jnp.concatenate([proprio, state.proprio[8:]]).astype(state.proprio.dtype)
        return WMState(state.first_latent, context, state.first_action, context_actions, cache, proprio), frames

    def observe_fn(params, state: WMState):
        del params
        return state.proprio[:proprio_dim], jnp.float32(0.0 if proprio_reckoning is None else 1.0)

    def round_trip_fn(params, frames):
        return vae_round_trip(vae_graphdef, params[1])(frames)

    return LearnedSimulator(params=(wm_state, decoder_state), init_fn=init_fn, step_fn=step_fn, observe_fn=observe_fn,
                            chunk_len=chunk_len, frame_size=frame_size, execute_len=execute_len, action_dim=action_dim,
                            round_trip_fn=round_trip_fn if light_decoder is None else None)
