"""Pure functional API of the VAE: whole-sequence and streaming encode/decode on ``(graphdef, state)``.

Shapes (channels-last): video ``[B, T, H, W, 3]`` in [-1, 1] with ``T = 1 + 4k``; latents
``[B, 1 + k, H/16, W/16, z]`` (official per-channel normalisation). All functions are jitted
(``graphdef`` and options static) and may be called inside another jit.

Validation: shapes are checked at trace time (always). Values (NaN/Inf; video outside
[-1 - VIDEO_RANGE_TOL, 1 + VIDEO_RANGE_TOL]) are checked on the host when ``check_values=True``
and the input is a concrete array; under an outer jit (tracers) the value check is skipped,
so call :func:`check_video_values` / :func:`check_latent_values` before entering your jit.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.vae.config import VAEConfig
from sword_jax.vae.layers import patchify, unpatchify
from sword_jax.vae.model import WanVAE, vae_rngs

VIDEO_RANGE_TOL = 1e-3


@functools.partial(jax.tree_util.register_dataclass, data_fields=["features"], meta_fields=["started"])
@dataclasses.dataclass(frozen=True)
class StreamCache:
    """Feature cache carried between streaming chunks (a pytree; ``started`` is static).

    Attributes:
      features: nested tuples of arrays, the last input frames each causal layer needs.
      started: False before the first chunk (which must then hold frame 0 of the stream).
    """

    features: Any
    started: bool


def create_vae(cfg: VAEConfig, *, key: jax.Array) -> WanVAE:
    """Builds a :class:`WanVAE` with fresh parameters (unsharded; see sharding.create_sharded for sharded)."""
    with nnx.use_eager_sharding(False):
        return WanVAE(cfg, rngs=vae_rngs(key))


def abstract_vae(cfg: VAEConfig) -> WanVAE:
    """The module with ``ShapeDtypeStruct`` leaves: no allocation (works at full size)."""
    with nnx.use_eager_sharding(False):
        return nnx.eval_shape(lambda: WanVAE(cfg, rngs=nnx.Rngs(0)))


def param_count(cfg: VAEConfig) -> int:
    """Number of trainable parameters of the VAE for ``cfg`` (computed abstractly)."""
    params = nnx.state(abstract_vae(cfg), nnx.Param)
    return int(sum(np.prod(leaf.shape) for leaf in jax.tree.leaves(params)))


def _attrs(graphdef, state) -> tuple[int, int, int, str]:
    """(z_dim, temporal_factor, spatial_factor, compute_dtype) of the VAE."""
    if graphdef not in _ATTRS:
        model = nnx.merge(graphdef, jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state))
        _ATTRS[graphdef] = (model.z_dim, model.temporal_factor, model.spatial_factor, model.compute_dtype)
    return _ATTRS[graphdef]


def factors(graphdef, state) -> tuple[int, int]:
    """``(temporal_factor, spatial_factor)`` of a split VAE: frames per latent frame after the
    first, pixels per latent pixel (:class:`~sword_jax.vae.config.VAEConfig`'s, read from the model)."""
    _, temporal, spatial, _ = _attrs(graphdef, state)
    return temporal, spatial


# Python attributes per graphdef (small: one entry per distinct VAE architecture in the process).
_ATTRS: dict = {}


def _dtype(graphdef, state, compute_dtype: str | None) -> str:
    name = compute_dtype or _attrs(graphdef, state)[3]
    if name not in ("float32", "bfloat16"):
        raise ValueError(f"compute_dtype must be 'float32' or 'bfloat16', got {name!r}")
    return name


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_video_values(video, *, name: str = "video") -> None:
    """Host check: finite and within [-1, 1] (tolerance ``VIDEO_RANGE_TOL``). Raises ValueError."""
    values = np.asarray(jax.device_get(video), dtype=np.float32)
    if not np.isfinite(values).all():
        raise ValueError(f"{name} contains {int((~np.isfinite(values)).sum())} NaN/Inf values")
    lo, hi = float(values.min(initial=0.0)), float(values.max(initial=0.0))
    if lo < -1 - VIDEO_RANGE_TOL or hi > 1 + VIDEO_RANGE_TOL:
        raise ValueError(f"{name} values must lie in [-1, 1] (got min {lo:.4g}, max {hi:.4g}); scale pixels as x/127.5 - 1")


def check_latent_values(latents, *, name: str = "latents") -> None:
    """Host check: all latents finite. Raises ValueError."""
    values = np.asarray(jax.device_get(latents), dtype=np.float32)
    if not np.isfinite(values).all():
        raise ValueError(f"{name} contain {int((~np.isfinite(values)).sum())} NaN/Inf values")


def _check_video_shape(video, graphdef, state, *, first: bool, name: str = "video") -> None:
    _, tf, sf, _ = _attrs(graphdef, state)
    shape = tuple(video.shape)
    if len(shape) != 5:
        raise ValueError(f"{name} must be [B, T, H, W, 3] (channels-last), got shape {shape}")
    b, t, h, w, c = shape
    if c != 3:
        raise ValueError(f"{name} must have 3 channels (RGB) in the last axis, got {c} (shape {shape}); "
                         "is it channels-first [B, 3, T, H, W]?")
    if not jnp.issubdtype(video.dtype, jnp.floating):
        raise ValueError(f"{name} must be floating point in [-1, 1], got dtype {video.dtype}")
    if h % sf or w % sf or h == 0 or w == 0:
        raise ValueError(f"{name} height and width must be positive multiples of {sf}, got {h}x{w}")
    if first and (t < 1 or (t - 1) % tf):
        raise ValueError(f"{name} must have T = 1 + {tf}k frames (first frame alone, then chunks of {tf}), got T={t}")
    if not first and (t < tf or t % tf):
        raise ValueError(f"a later {name} chunk must have a positive multiple of {tf} frames, got T={t}")


def check_latents(latents, z: int, *, name: str = "latents", who: str = "") -> None:
    """Refuses ``latents`` that are not floating-point ``[B, T, h, w, z]`` with at least one frame and pixel;
    the message names ``name`` (and ``who``, the decoder it was given to)."""
    head = f"{who}: {name}" if who else name
    shape = tuple(latents.shape)
    if len(shape) != 5:
        raise ValueError(f"{head} must be [B, T, h, w, {z}] (channels-last), got shape {shape}")
    if shape[-1] != z:
        raise ValueError(f"{head} must be [B, T, h, w, {z}]: must have {z} channels in the last axis, got "
                         f"{shape[-1]} (shape {shape})")
    if shape[1] < 1 or shape[2] < 1 or shape[3] < 1:
        raise ValueError(f"{head} must have at least one frame and pixel, got shape {shape}")
    if not jnp.issubdtype(latents.dtype, jnp.floating):
        raise ValueError(f"{head} must be floating point, got dtype {latents.dtype}")


def _check_latent_shape(latents, graphdef, state, *, name: str = "latents") -> None:
    check_latents(latents, _attrs(graphdef, state)[0], name=name)


@functools.partial(jax.jit, static_argnames=("graphdef", "first", "dtype"))
def _encode_impl(graphdef, state, video, cache, *, first: bool, dtype: str):
    model = nnx.merge(graphdef, state)
    frames = patchify(video.astype(jnp.float32))
    mu, _, cache = model.encode_moments(frames, cache, first=first, dtype=jnp.dtype(dtype))
    return model.normalise(mu), cache


@functools.partial(jax.jit, static_argnames=("graphdef", "first", "dtype", "clamp"))
def _decode_impl(graphdef, state, latents, cache, *, first: bool, dtype: str, clamp: bool):
    model = nnx.merge(graphdef, state)
    z_raw = model.denormalise(latents.astype(jnp.float32))
    out, cache = model.decode_raw(z_raw, cache, first=first, dtype=jnp.dtype(dtype))
    video = unpatchify(out.astype(jnp.float32))
    return (jnp.clip(video, -1.0, 1.0) if clamp else video), cache


def encode(
    graphdef: nnx.GraphDef, state: nnx.State, video: Float[Array, "b t h w 3"], *,
    compute_dtype: str | None = None, check_values: bool = True,
) -> Float[Array, "b tl hl wl z"]:
    """Encodes a whole video to normalised latent means (the official ``encode``: mu, no sampling).

    Args:
      graphdef, state: from ``nnx.split(vae)``.
      video: ``[B, 1 + 4k, H, W, 3]`` in [-1, 1], H and W multiples of 16.
      compute_dtype: override the config's 'float32' / 'bfloat16'.
      check_values: host-check NaN/range when ``video`` is concrete.

    Returns:
      ``[B, 1 + k, H/16, W/16, z]`` float32, ``(mu_raw - mean) * inv_std``.
    """
    _check_video_shape(video, graphdef, state, first=True)
    if check_values and _is_concrete(video):
        check_video_values(video)
    return _encode_impl(graphdef, state, video, None, first=True, dtype=_dtype(graphdef, state, compute_dtype))[0]


def encoder(graphdef: nnx.GraphDef, state: nnx.State) -> functools.partial:
    """``video [B, 1 + 4k, H, W, 3] in [-1, 1] -> latents`` (as :func:`encode`) compiled once.

    The weights are an argument of the jit (bound with ``functools.partial``), not constants baked
    into the program as a jitted closure over ``state`` would make them.
    """
    return functools.partial(_encoder_jit(graphdef), state)


@functools.lru_cache(maxsize=8)
def _encoder_jit(graphdef: nnx.GraphDef):
    return jax.jit(lambda state, video: encode(graphdef, state, video, check_values=False))


def decode(
    graphdef: nnx.GraphDef, state: nnx.State, latents: Float[Array, "b tl hl wl z"], *,
    clamp: bool = False, compute_dtype: str | None = None, check_values: bool = True,
) -> Float[Array, "b t h w 3"]:
    """Decodes normalised latents ``[B, 1 + k, h, w, z]`` to video ``[B, 1 + 4k, 16h, 16w, 3]`` (float32).

    Not clamped unless ``clamp`` (the official wrapper clamps to [-1, 1]).
    """
    _check_latent_shape(latents, graphdef, state)
    if check_values and _is_concrete(latents):
        check_latent_values(latents)
    dtype = _dtype(graphdef, state, compute_dtype)
    return _decode_impl(graphdef, state, latents, None, first=True, dtype=dtype, clamp=clamp)[0]


def _zero_cache(abstract_cache) -> Any:
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), abstract_cache)


def init_encode_cache(
    graphdef: nnx.GraphDef, state: nnx.State, batch: int, height: int, width: int, *,
    compute_dtype: str | None = None, video_dtype=jnp.float32,
) -> StreamCache:
    """Empty encoder cache for a stream of ``[batch, *, height, width, 3]`` video chunks."""
    dtype = _dtype(graphdef, state, compute_dtype)
    probe = jax.ShapeDtypeStruct((batch, 1, height, width, 3), video_dtype)
    _check_video_shape(probe, graphdef, state, first=True)
    abstract = jax.eval_shape(lambda s, v: _encode_impl(graphdef, s, v, None, first=True, dtype=dtype)[1], state, probe)
    return StreamCache(_zero_cache(abstract), started=False)


def init_decode_cache(
    graphdef: nnx.GraphDef, state: nnx.State, batch: int, latent_height: int, latent_width: int, *,
    compute_dtype: str | None = None,
) -> StreamCache:
    """Empty decoder cache for a stream of ``[batch, *, latent_height, latent_width, z]`` latent chunks."""
    dtype = _dtype(graphdef, state, compute_dtype)
    z = _attrs(graphdef, state)[0]
    probe = jax.ShapeDtypeStruct((batch, 1, latent_height, latent_width, z), jnp.float32)
    _check_latent_shape(probe, graphdef, state)
    abstract = jax.eval_shape(
        lambda s, v: _decode_impl(graphdef, s, v, None, first=True, dtype=dtype, clamp=False)[1], state, probe
    )
    return StreamCache(_zero_cache(abstract), started=False)


def encode_chunk(
    graphdef: nnx.GraphDef, state: nnx.State, video_chunk: Float[Array, "b t h w 3"], cache: StreamCache, *,
    compute_dtype: str | None = None, check_values: bool = True,
) -> tuple[Float[Array, "b tl hl wl z"], StreamCache]:
    """Streams one chunk through the causal encoder.

    The first chunk (``cache.started`` False) has ``1 + 4m`` frames and gives ``1 + m`` latents;
    later chunks have ``4m`` frames (m >= 1) and give ``m`` latents. Concatenating the outputs
    equals :func:`encode` of the concatenated video.
    """
    first = not cache.started
    _check_video_shape(video_chunk, graphdef, state, first=first, name="video_chunk")
    if check_values and _is_concrete(video_chunk):
        check_video_values(video_chunk, name="video_chunk")
    dtype = _dtype(graphdef, state, compute_dtype)
    latents, features = _encode_impl(graphdef, state, video_chunk, cache.features, first=first, dtype=dtype)
    return latents, StreamCache(features, started=True)


def decode_chunk(
    graphdef: nnx.GraphDef, state: nnx.State, latent_chunk: Float[Array, "b tl hl wl z"], cache: StreamCache, *,
    clamp: bool = False, compute_dtype: str | None = None, check_values: bool = True,
) -> tuple[Float[Array, "b t h w 3"], StreamCache]:
    """Streams latent frames through the causal decoder.

    The first chunk (``cache.started`` False) of ``1 + m`` latents gives ``1 + 4m`` frames; later
    chunks of ``m >= 1`` latents give ``4m`` frames. Concatenating the outputs equals
    :func:`decode` of the concatenated latents.
    """
    first = not cache.started
    _check_latent_shape(latent_chunk, graphdef, state, name="latent_chunk")
    if check_values and _is_concrete(latent_chunk):
        check_latent_values(latent_chunk, name="latent_chunk")
    dtype = _dtype(graphdef, state, compute_dtype)
    frames, features = _decode_impl(
        graphdef, state, latent_chunk, cache.features, first=first, dtype=dtype, clamp=clamp
    )
    return frames, StreamCache(features, started=True)


def encode_moments(
    graphdef: nnx.GraphDef, state: nnx.State, video: Float[Array, "b t h w 3"], *, compute_dtype: str | None = None,
) -> tuple[Float[Array, "b tl hl wl z"], Float[Array, "b tl hl wl z"]]:
    """Raw (un-normalised) posterior ``(mu, log_var)`` of a whole video, float32 (for training)."""
    _check_video_shape(video, graphdef, state, first=True)
    model = nnx.merge(graphdef, state)
    dtype = jnp.dtype(_dtype(graphdef, state, compute_dtype))
    mu, log_var, _ = model.encode_moments(patchify(video.astype(jnp.float32)), None, first=True, dtype=dtype)
    return mu, log_var


def decode_raw(
    graphdef: nnx.GraphDef, state: nnx.State, z_raw: Float[Array, "b tl hl wl z"], *, compute_dtype: str | None = None,
) -> Float[Array, "b t h w 3"]:
    """Decodes raw (de-normalised) latents, e.g. posterior samples in training. Float32, unclamped."""
    _check_latent_shape(z_raw, graphdef, state, name="z_raw")
    model = nnx.merge(graphdef, state)
    dtype = jnp.dtype(_dtype(graphdef, state, compute_dtype))
    out, _ = model.decode_raw(z_raw, None, first=True, dtype=dtype)
    return unpatchify(out.astype(jnp.float32))


@functools.partial(jax.jit, static_argnames=("graphdef",))
def reference_taps(
    graphdef: nnx.GraphDef, state: nnx.State, video: Float[Array, "b t h w 3"], latents: Float[Array, "b tl hl wl z"],
) -> dict[str, Array]:
    """Intermediates named as in the reference ``vae_case.npz`` (channels-last), for debugging parity.

    Encoder taps come from encoding ``video``; decoder taps from decoding ``latents``.
    """
    _check_video_shape(video, graphdef, state, first=True)
    _check_latent_shape(latents, graphdef, state)
    model = nnx.merge(graphdef, state)
    taps: dict[str, Array] = {}
    mu, log_var, _ = model.encode_moments(patchify(video.astype(jnp.float32)), None, first=True,
                                          dtype=jnp.float32, taps=taps)
    taps["mu_raw"], taps["log_var_raw"] = mu, log_var
    model.decode_raw(model.denormalise(latents.astype(jnp.float32)), None, first=True, dtype=jnp.float32, taps=taps)
    return taps
