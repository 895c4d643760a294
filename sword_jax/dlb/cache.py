"""The device-resident latent cache of Dynamic Latent Bootstrapping: layout, sharding, read, write.

The cache holds one predicted latent per (episode, latent frame) slot of the latent dataset
(:mod:`sword_jax.world_model.data` indexes the same slots) plus a ``filled`` flag per slot. It lives
in the train state, is donated into the jitted step and returned updated, and is never copied to
the host (only checkpoints serialise it). The episode axis carries the logical name ``episodes``
(mapped to ``data``/``fsdp``); it is padded to a multiple of that shard count so every device holds
an equal slice. Reads and writes are plain gathers/scatters inside the step: XLA partitions them
so that only the batch-sized updates and results cross devices, never the cache.

Duplicate writes: when several samples of one batch write the same slot, the sample that comes
LAST in batch order wins (the others are dropped before the scatter), so the result does not depend
on scatter ordering. With ``ema`` replacement the winner blends with the slot's value from before
the step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from flax import struct
from jax.sharding import Mesh, NamedSharding
from jaxtyping import Array, Bool, Float, Int

from sword_jax import sharding as shd
from sword_jax.dlb.config import CacheConfig

CACHE_LOGICAL_AXES = ("episodes", "time", "height", "width", "channels")


@struct.dataclass
class LatentCache:
    """Predicted latents per slot and which slots hold one.

    Attributes:
      latents: ``[E_padded, L, h, w, c]`` in ``CacheConfig.dtype``.
      filled: ``[E_padded, L]`` bool; False = never written (never read).
    """

    latents: Float[Array, "e l h w c"]
    filled: Bool[Array, "e l"]


def episode_shards(mesh: Mesh | None, rules: Sequence = shd.DEFAULT_RULES) -> int:
    """How many ways the ``episodes`` axis is split over ``mesh`` (1 without a mesh)."""
    if mesh is None:
        return 1
    table = dict(rules)
    return math.prod(mesh.shape[a] for a in table.get("episodes", ()))


def padded_episodes(num_episodes: int, mesh: Mesh | None, rules: Sequence = shd.DEFAULT_RULES) -> int:
    """Episode count rounded up to a multiple of the episode shard count."""
    shards = episode_shards(mesh, rules)
    return -(-num_episodes // shards) * shards


def cache_shape(dataset_shape: Sequence[int], mesh: Mesh | None, rules: Sequence = shd.DEFAULT_RULES) -> tuple[int, ...]:
    """Padded cache shape for a latent dataset of shape ``(E, L, h, w, c)``."""
    if len(dataset_shape) != 5 or min(dataset_shape) <= 0:
        raise ValueError(f"latent cache: dataset_shape must be (E, L, h, w, c) > 0, got {tuple(dataset_shape)}")
    return (padded_episodes(dataset_shape[0], mesh, rules),) + tuple(int(d) for d in dataset_shape[1:])


def cache_bytes_per_device(
    cfg: CacheConfig, dataset_shape: Sequence[int], mesh: Mesh | None, rules: Sequence = shd.DEFAULT_RULES
) -> int:
    """Bytes of cache (latents + filled flags) each device holds for a dataset ``(E, L, h, w, c)``."""
    shape = cache_shape(dataset_shape, mesh, rules)
    shards = episode_shards(mesh, rules)
    itemsize = jnp.dtype(cfg.dtype).itemsize
    per_device_episodes = shape[0] // shards
    return per_device_episodes * math.prod(shape[1:]) * itemsize + per_device_episodes * shape[1]


def cache_shardings(dataset_shape: Sequence[int], mesh: Mesh, rules: Sequence = shd.DEFAULT_RULES) -> LatentCache:
    """``NamedSharding`` of each cache field (episodes over ``data``/``fsdp``)."""
    shape = cache_shape(dataset_shape, mesh, rules)
    return LatentCache(
        latents=shd.logical_sharding(mesh, CACHE_LOGICAL_AXES, rules, shape),
        filled=shd.logical_sharding(mesh, CACHE_LOGICAL_AXES[:2], rules, shape[:2]),
    )


def init_cache(
    cfg: CacheConfig, dataset_shape: Sequence[int], mesh: Mesh | None = None, rules: Sequence = shd.DEFAULT_RULES
) -> LatentCache:
    """An empty cache, created directly in its sharded layout (never materialised on one device)."""
    shape = cache_shape(dataset_shape, mesh, rules)

    def make():
        return LatentCache(latents=jnp.zeros(shape, jnp.dtype(cfg.dtype)), filled=jnp.zeros(shape[:2], jnp.bool_))

    if mesh is None:
        return jax.jit(make)()
    return jax.jit(make, out_shardings=cache_shardings(dataset_shape, mesh, rules))()


def _slot_index(episodes: Int[Array, " b"], frames: Int[Array, "b k"]) -> tuple[Array, Array]:
    return jnp.broadcast_to(episodes[:, None], frames.shape), frames


def read_context(
    cache: LatentCache,
    context_latents: Float[Array, "b k h w c"],
    episodes: Int[Array, " b"],
    context_frames: Int[Array, "b k"],
    read_prob: Float[Array, ""],
    *,
    key: jax.Array,
) -> tuple[Float[Array, "b k h w c"], Bool[Array, "b k"]]:
    """Replaces ground-truth context latents by cached predictions with probability ``read_prob``.

    One Bernoulli draw per sample decides whether that sample reads; a context latent is then taken
    from the cache only where its slot is filled.

    Returns:
      ``(context, read_mask)``: the (partly) replaced context in the input dtype and where it was read.
    """
    episode_idx, frame_idx = _slot_index(episodes, context_frames)
    cached = cache.latents[episode_idx, frame_idx]  # (B, k, h, w, c)
    filled = cache.filled[episode_idx, frame_idx]  # (B, k)
    draw = jax.random.bernoulli(key, read_prob, (context_latents.shape[0],))
    read_mask = draw[:, None] & filled
    context = jnp.where(read_mask[..., None, None, None], cached.astype(context_latents.dtype), context_latents)
    return context, read_mask


def last_writer_mask(episode_idx: Int[Array, " n"], frame_idx: Int[Array, " n"], valid: Bool[Array, " n"]) -> Bool[Array, " n"]:
    """True for each valid write that no later valid write (in flattened batch order) overrides."""
    n = episode_idx.shape[0]
    same = (episode_idx[:, None] == episode_idx[None, :]) & (frame_idx[:, None] == frame_idx[None, :])
    later = jnp.arange(n)[None, :] > jnp.arange(n)[:, None]
    overridden = jnp.any(same & later & valid[None, :], axis=1)
    return valid & ~overridden


def write_predictions(
    cache: LatentCache,
    cfg: CacheConfig,
    predictions: Float[Array, "b p h w c"],
    episodes: Int[Array, " b"],
    first_future_frame: Int[Array, " b"],
    enabled: Bool[Array, ""] | bool = True,
) -> LatentCache:
    """Writes the model's predictions of the future latents into their slots.

    Args:
      cache: the cache (sharded or not).
      cfg: ``scope`` (single: first predicted latent only; all: every one) and ``replacement``.
      predictions: clean future-latent estimates ``[b, p, h, w, c]`` (gradients are stopped here).
      episodes: episode index of each sample ``[b]``.
      first_future_frame: latent-frame index of each sample's first future latent ``[b]``.
      enabled: gate, a scalar (False writes nothing: a non-finite step) or one per sample ``[b]`` (False: that
        sample writes nothing, e.g. one trained without its actions).

    Returns:
      The updated cache (same shapes, dtypes and shardings).
    """
    predictions = jax.lax.stop_gradient(predictions)
    num_write = 1 if cfg.scope == "single" else predictions.shape[1]
    predictions = predictions[:, :num_write]
    frames = first_future_frame[:, None] + jnp.arange(num_write, dtype=first_future_frame.dtype)[None, :]
    episode_idx, frame_idx = _slot_index(episodes, frames)
    episode_flat, frame_flat = episode_idx.reshape(-1), frame_idx.reshape(-1)
    values = predictions.reshape((-1,) + predictions.shape[2:]).astype(jnp.float32)
    enabled = jnp.asarray(enabled, jnp.bool_)
    if enabled.ndim == 1:  # one gate per sample, for each of its written latents
        enabled = jnp.broadcast_to(enabled[:, None], episode_idx.shape)
    valid = jnp.broadcast_to(enabled, episode_idx.shape).reshape(-1)
    keep = last_writer_mask(episode_flat, frame_flat, valid)
    if cfg.replacement == "ema":
        old = cache.latents[episode_flat, frame_flat].astype(jnp.float32)
        was_filled = cache.filled[episode_flat, frame_flat][:, None, None, None]
        rate = jnp.float32(cfg.ema_rate)
        values = jnp.where(was_filled, (jnp.float32(1.0) - rate) * old + rate * values, values)
    # Dropped writes point past the last episode; mode="drop" discards them.
    target_episode = jnp.where(keep, episode_flat, cache.latents.shape[0])
    latents = cache.latents.at[target_episode, frame_flat].set(values.astype(cache.latents.dtype), mode="drop")
    filled = cache.filled.at[target_episode, frame_flat].set(True, mode="drop")
    return LatentCache(latents=latents, filled=filled)


def filled_fraction(cache: LatentCache, num_episodes: int) -> Float[Array, ""]:
    """Share of the real (unpadded) slots holding a prediction."""
    return jnp.mean(cache.filled[:num_episodes].astype(jnp.float32))
