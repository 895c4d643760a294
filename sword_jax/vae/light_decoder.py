"""A light causal video decoder for imagined rollouts: the VAE's latents -> frames at a chosen resolution.

The Wan 2.2-style decoder spends over a TFLOP per 256 px frame (3-D convolutions at full width up to
the full resolution), while GRPO's policy and success detector read 64 px frames. This decoder, in
the manner of the tiny video autoencoders (TAEHV / taew2.2), is built of 2-D convolutions per frame
with a one-frame memory:

* a soft clamp (``3 tanh(x / 3)``: predicted latents that drift far stay bounded), a 3x3 conv to
  ``width`` channels;
* stages of *memory blocks*, ``x + conv(act(conv([x, x_prev])))``: each frame sees its own features and
  the previous frame's (zeros before the stream's first), so a frame never depends on a later one;
* between stages, a *time grow* (a 1x1 conv to twice the channels, split into two frames: latent ``t``
  becomes frames ``2t, 2t + 1``) and/or a nearest x2 upsample followed by a 3x3 conv; channels halve
  each stage down to ``max(width / 4, 8)``; time grows take the last transitions, so the early stages
  run once per latent;
* a head (act, 3x3 conv to ``3 * 2 * 2``, depth-to-space) that does the last x2 of the resolution.

Time follows the VAE: ``temporal_factor`` frames per latent, of which the stream's first latent keeps
only the last, so latents ``[B, 1 + k, h, w, z]`` give ``1 + 4k`` frames with frame 0 from latent 0
(the decoder makes the stream's first frames and drops ``temporal_factor - 1``).

Streaming: the memory blocks' last input frames are the whole state between chunks
(:class:`~sword_jax.vae.api.StreamCache`): :func:`decode_chunk` over consecutive chunks gives the frames
:func:`decode` gives for the whole sequence, so the learned simulator decodes each predicted chunk once,
as with the VAE's own streaming decode.

Functional API (``graphdef, state = nnx.split(decoder)``; channels-last; jittable): :func:`decode`,
:func:`init_stream_cache`, :func:`decode_chunk`; construction :func:`create_light_decoder`,
:func:`abstract_light_decoder`. Latents are the VAE's normalised latents (what the world model
predicts); frames are ``[-1, 1]`` video like :func:`sword_jax.vae.api.decode`'s (unclamped).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax import lax
from jaxtyping import Array, Float

from sword_jax.vae.api import StreamCache, check_latents
from sword_jax.vae.config import LightDecoderConfig
from sword_jax.vae.model import vae_rngs

HEAD_PATCH = 2  # the head's depth-to-space: the last x2 of the resolution
_INIT = nnx.initializers.variance_scaling(1.0, "fan_in", "truncated_normal")


def _log2(value: int, what: str) -> int:
    if value < 1 or value & (value - 1):
        raise ValueError(f"light decoder: {what} must be a power of two, got {value}")
    return int(math.log2(value))


def stage_plan(cfg: LightDecoderConfig, *, scale: int, temporal_factor: int
               ) -> tuple[list[int], list[tuple[bool, bool]], int]:
    """``(channels per stage, (time grow, spatial x2) per transition, head patch)`` for ``scale`` pixels per
    latent pixel and ``temporal_factor`` frames per latent (both powers of two)."""
    spatial = _log2(scale, "the frame size over the latent size")
    temporal = _log2(temporal_factor, "the VAE's temporal factor")
    head = HEAD_PATCH if spatial else 1
    conv_ups = spatial - (1 if spatial else 0)
    stages = max(conv_ups, temporal) + 1
    floor = min(cfg.width, max(cfg.width // 4, 8))
    channels = [max(cfg.width // 2 ** s, floor) for s in range(stages)]
    last = stages - 1
    transitions = [(j >= last - temporal, j >= last - conv_ups) for j in range(last)]
    return channels, transitions, head


def _conv(x: Float[Array, "b t h w ci"], kernel: Array, bias: Array, *, dtype) -> Float[Array, "b t h w co"]:
    """Per-frame 2-D convolution, zero ``same`` padding; float32 runs at the highest precision."""
    b, t, h, w, c = x.shape
    precision = lax.Precision.HIGHEST if jnp.dtype(dtype) == jnp.float32 else lax.Precision.DEFAULT
    y = lax.conv_general_dilated(x.reshape(b * t, h, w, c).astype(dtype), kernel.astype(dtype), (1, 1), "SAME",
                                 dimension_numbers=("NHWC", "HWIO", "NHWC"), precision=precision)
    y = y + bias.astype(dtype)
    return y.reshape(b, t, h, w, y.shape[-1])  # (B, T, H, W, C')


class Conv(nnx.Module):
    """A ``size x size`` per-frame convolution (kernel ``[size, size, in, out]``); ``zero`` starts it at 0."""

    def __init__(self, in_dim: int, out_dim: int, size: int = 3, *, zero: bool = False, rngs: nnx.Rngs):
        init = nnx.initializers.zeros if zero else _INIT
        self.kernel = nnx.Param(nnx.with_partitioning(init, ("kernel", "kernel", "conv_in", "conv_out"))(
            rngs.params(), (size, size, in_dim, out_dim)))
        self.bias = nnx.Param(nnx.with_partitioning(nnx.initializers.zeros, ("conv_out",))(rngs.params(), (out_dim,)))

    def __call__(self, x, *, dtype):
        return _conv(x, self.kernel[...], self.bias[...], dtype=dtype)


class MemoryBlock(nnx.Module):
    """``x + conv(silu(conv([x_t, x_{t-1}])))``: the residual starts at zero (the block starts as the identity)."""

    def __init__(self, dim: int, *, rngs: nnx.Rngs):
        self.mix = Conv(2 * dim, dim, rngs=rngs)
        self.out = Conv(dim, dim, zero=True, rngs=rngs)

    def __call__(self, x: Float[Array, "b t h w c"], past: Float[Array, "b 1 h w c"], *, dtype):
        previous = jnp.concatenate([past.astype(x.dtype), x[:, :-1]], axis=1)  # frame t-1 beside frame t
        h = jax.nn.silu(self.mix(jnp.concatenate([x, previous.astype(x.dtype)], axis=-1), dtype=dtype))
        return x + self.out(h, dtype=dtype).astype(x.dtype), x[:, -1:]


class Transition(nnx.Module):
    """Between two stages: an optional time grow (1x1 conv to 2C, split into two frames), an optional nearest
    x2 upsample, then a 3x3 conv to the next stage's channels."""

    def __init__(self, in_dim: int, out_dim: int, *, grow_time: bool, upsample: bool, rngs: nnx.Rngs):
        self.grow = Conv(in_dim, 2 * in_dim, size=1, rngs=rngs) if grow_time else None
        self.upsample = upsample
        self.conv = Conv(in_dim, out_dim, rngs=rngs)

    def __call__(self, x, *, dtype):
        if self.grow is not None:
            y = self.grow(x, dtype=dtype)
            b, t, h, w, c2 = y.shape
            # channels [0, C) -> frame 2t, [C, 2C) -> frame 2t + 1
            x = y.reshape(b, t, h, w, 2, c2 // 2).transpose(0, 1, 4, 2, 3, 5).reshape(b, 2 * t, h, w, c2 // 2)
        if self.upsample:
            x = jnp.repeat(jnp.repeat(x, 2, axis=2), 2, axis=3)
        return self.conv(x, dtype=dtype)


class LightDecoder(nnx.Module):
    """Normalised latents ``[B, T, h, w, z]`` -> video ``[B, T * temporal_factor, h * scale, w * scale, 3]`` (the
    stream's first ``temporal_factor - 1`` frames are dropped by the API, not here).

    Attributes (Python, static): ``z_dim``, ``scale`` (pixels per latent pixel), ``temporal_factor``,
    ``compute_dtype`` (the API's default; the simulator's builder sets it).
    """

    def __init__(self, cfg: LightDecoderConfig, *, z_dim: int, scale: int, temporal_factor: int, rngs: nnx.Rngs):
        cfg.validate()
        channels, transitions, head = stage_plan(cfg, scale=scale, temporal_factor=temporal_factor)
        self.z_dim, self.scale, self.temporal_factor, self.head_patch = z_dim, scale, temporal_factor, head
        self.compute_dtype = cfg.compute_dtype
        self.conv_in = Conv(z_dim, channels[0], rngs=rngs)
        self.stages = nnx.List([nnx.List([MemoryBlock(c, rngs=rngs) for _ in range(cfg.blocks)]) for c in channels])
        self.transitions = nnx.List([
            Transition(channels[j], channels[j + 1], grow_time=grow, upsample=up, rngs=rngs)
            for j, (grow, up) in enumerate(transitions)])
        self.head = Conv(channels[-1], 3 * head * head, rngs=rngs)

    def __call__(self, latents: Float[Array, "b t h w z"], memory: tuple | None, *, dtype
                 ) -> tuple[Float[Array, "b f H W 3"], tuple]:
        """Latents of one chunk and the memory blocks' last input frames (None: zeros) -> all
        ``T * temporal_factor`` frames (float32) and the new memory."""
        x = jnp.float32(3.0) * jnp.tanh(latents.astype(jnp.float32) / jnp.float32(3.0))
        x = self.conv_in(x, dtype=dtype)
        new_memory, index = [], 0
        for s, blocks in enumerate(self.stages):
            for block in blocks:
                past = jnp.zeros_like(x[:, :1]) if memory is None else memory[index]
                x, last = block(x, past, dtype=dtype)
                new_memory.append(last)
                index += 1
            if s < len(self.transitions):
                x = self.transitions[s](x, dtype=dtype)
        y = self.head(jax.nn.silu(x), dtype=dtype).astype(jnp.float32)
        b, f, h, w, _ = y.shape
        p = self.head_patch
        y = y.reshape(b, f, h, w, p, p, 3).transpose(0, 1, 2, 4, 3, 5, 6).reshape(b, f, h * p, w * p, 3)
        return y, tuple(new_memory)


def create_light_decoder(cfg: LightDecoderConfig, *, z_dim: int, scale: int, temporal_factor: int,
                         key: jax.Array) -> LightDecoder:
    """A :class:`LightDecoder` with fresh parameters (unsharded; drawn as the VAE's are,
    :func:`~sword_jax.vae.model.vae_rngs`)."""
    with nnx.use_eager_sharding(False):
        return LightDecoder(cfg, z_dim=z_dim, scale=scale, temporal_factor=temporal_factor, rngs=vae_rngs(key))


def abstract_light_decoder(cfg: LightDecoderConfig, *, z_dim: int, scale: int, temporal_factor: int) -> LightDecoder:
    """The module with ``ShapeDtypeStruct`` leaves: no allocation."""
    with nnx.use_eager_sharding(False):
        return nnx.eval_shape(lambda: LightDecoder(cfg, z_dim=z_dim, scale=scale, temporal_factor=temporal_factor,
                                                   rngs=nnx.Rngs(0)))


# Python attributes per graphdef (one entry per distinct decoder architecture in the process).
_ATTRS: dict = {}


def attributes(graphdef: nnx.GraphDef, state: Any) -> tuple[int, int, int, str]:
    """``(z_dim, scale, temporal_factor, compute_dtype)`` of a split light decoder."""
    if graphdef not in _ATTRS:
        model = nnx.merge(graphdef, jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), state))
        _ATTRS[graphdef] = (model.z_dim, model.scale, model.temporal_factor, model.compute_dtype)
    return _ATTRS[graphdef]


def _dtype(graphdef, state, compute_dtype: str | None) -> str:
    name = compute_dtype or attributes(graphdef, state)[3]
    if name not in ("float32", "bfloat16"):
        raise ValueError(f"light decoder: compute_dtype must be 'float32' or 'bfloat16', got {name!r}")
    return name


def _check_latents(latents, graphdef, state, *, name: str = "latents") -> None:
    check_latents(latents, attributes(graphdef, state)[0], name=name, who="light decoder")


@functools.partial(jax.jit, static_argnames=("graphdef", "first", "dtype"))
def _decode_impl(graphdef, state, latents, memory, *, first: bool, dtype: str):
    model = nnx.merge(graphdef, state)
    video, memory = model(latents, memory, dtype=jnp.dtype(dtype))
    return (video[:, model.temporal_factor - 1:] if first else video), memory


def decode(graphdef: nnx.GraphDef, state: Any, latents: Float[Array, "b tl hl wl z"], *,
           compute_dtype: str | None = None) -> Float[Array, "b t h w 3"]:
    """Decodes normalised latents ``[B, 1 + k, h, w, z]`` to video ``[B, 1 + tf k, h s, w s, 3]`` (float32,
    unclamped; ``tf`` the temporal factor, ``s`` the scale), frame 0 from latent 0."""
    _check_latents(latents, graphdef, state)
    return _decode_impl(graphdef, state, latents, None, first=True, dtype=_dtype(graphdef, state, compute_dtype))[0]


def init_stream_cache(graphdef: nnx.GraphDef, state: Any, batch: int, latent_height: int, latent_width: int, *,
                      compute_dtype: str | None = None) -> StreamCache:
    """Empty memory for a stream of ``[batch, *, latent_height, latent_width, z]`` latent chunks."""
    dtype = _dtype(graphdef, state, compute_dtype)
    probe = jax.ShapeDtypeStruct((batch, 1, latent_height, latent_width, attributes(graphdef, state)[0]), jnp.float32)
    _check_latents(probe, graphdef, state)
    abstract = jax.eval_shape(lambda s, z: _decode_impl(graphdef, s, z, None, first=True, dtype=dtype)[1], state, probe)
    return StreamCache(jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), abstract), started=False)


def decode_chunk(graphdef: nnx.GraphDef, state: Any, latent_chunk: Float[Array, "b tl hl wl z"], cache: StreamCache, *,
                 compute_dtype: str | None = None) -> tuple[Float[Array, "b t h w 3"], StreamCache]:
    """Streams latent frames through the decoder: the first chunk (``cache.started`` False) of ``1 + m``
    latents gives ``1 + tf m`` frames, later chunks of ``m >= 1`` latents ``tf m`` frames; the outputs
    concatenated equal :func:`decode` of the concatenated latents."""
    _check_latents(latent_chunk, graphdef, state, name="latent_chunk")
    dtype = _dtype(graphdef, state, compute_dtype)
    memory = cache.features if cache.started else None
    video, memory = _decode_impl(graphdef, state, latent_chunk, memory, first=not cache.started, dtype=dtype)
    return video, StreamCache(memory, started=True)


def param_count(state: Any) -> int:
    """Parameters of a split light decoder's state (every leaf is a trained weight)."""
    return int(sum(np.prod(x.shape) for x in jax.tree.leaves(state)))
