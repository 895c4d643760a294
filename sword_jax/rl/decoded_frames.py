"""Episodes' frames as the world model's decoder shows them: each episode round-tripped through the causal video VAE.

GRPO in the learned world model feeds the policy frames decoded by the VAE, and a policy trained on real frames
only succeeds far less often on them (``benchmarks.bench_policy_view``, view ``vae``). Decoder-aware SFT
(``rl.sft.decoded_fraction``, :func:`sword_jax.rl.sft.train_sft`) trains on a share of such frames: the same
episode, the same time index, after :func:`round_trip_episodes`.

An episode is encoded as one video, as the world model's data is: ``1 + 4k`` frames (the causal VAE's first latent
holds one frame, each later one four), the end padded by repeating the last frame up to the next ``1 + 4k``, then
decoded and cropped back. The causal encoder and decoder let no frame see a later one outside its own latent, so
the padding changes only the frames of the last latent, as it does for the world model's padded episodes. Lengths
are rounded up to buckets of ``bucket_latents`` latents, so one program is compiled per bucket, not per episode,
and episodes go through ``episodes_per_call`` at a time, so memory stays bounded by a few episodes.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Int, UInt8

from sword_jax.vae import api as vae_api


def add_options(parser, scope: str = "") -> None:
    """``--vae`` and ``--world-model``, the checkpoints decoder-aware SFT reads (:func:`require_vae` checks them),
    on an ``argparse`` parser; ``scope`` starts their help (e.g. ``"sft: "`` where other stages ignore them)."""
    parser.add_argument("--vae", default="", help=f"{scope}VAE checkpoint directory (train_vae; a pipeline's "
                        "vae_run/vae) whose round trip rl.sft.decoded_fraction of each batch's frames go through")
    parser.add_argument("--world-model", default="", help=f"{scope}with rl.sft.decoded_source=world_model: the world "
                        "model (a pipeline's world_model) the episodes' actions are replayed in for the decoded frames")


def require_vae(decoded_fraction: float, vae: str, world_model: str = "", source: str = "vae") -> None:
    """Refuses a VAE checkpoint ``vae`` that ``rl.sft.decoded_fraction`` will not read, and a fraction above 0
    without one (the frames would otherwise come from an untrained VAE, or the VAE would be silently ignored);
    likewise the world model ``world_model``, read exactly when the fraction is above 0 and ``source``
    (``rl.sft.decoded_source``) is ``world_model`` (:mod:`sword_jax.rl.imagined_frames`, whose frames the VAE
    decodes).

    Raises:
      ValueError: naming ``--vae``, ``--world-model`` and the ``rl.sft`` setting.
    """
    if decoded_fraction > 0 and not vae:
        raise ValueError(f"rl.sft.decoded_fraction={decoded_fraction} trains on frames decoded by a trained VAE: give "
                         "its checkpoint directory with --vae (e.g. runs/<pipeline>/vae_run/vae)")
    if vae and decoded_fraction <= 0:
        raise ValueError(f"--vae {vae} is read only by decoder-aware SFT: set rl.sft.decoded_fraction in (0, 1] "
                         "(e.g. --rl.sft.decoded_fraction=0.5), or leave --vae out")
    if decoded_fraction > 0 and source == "world_model" and not world_model:
        raise ValueError("rl.sft.decoded_source=world_model replays the episodes in a trained world model: give its "
                         "checkpoint directory with --world-model (e.g. runs/<pipeline>/world_model)")
    if world_model and not (decoded_fraction > 0 and source == "world_model"):
        raise ValueError(f"--world-model {world_model} is read only with rl.sft.decoded_source=world_model and "
                         "rl.sft.decoded_fraction in (0, 1]; set both, or leave --world-model out")


def padded_length(length: int, temporal_factor: int, bucket_latents: int = 8) -> int:
    """The frames an episode of ``length`` frames is encoded as: ``1 + temporal_factor * k`` with ``k`` the
    smallest multiple of ``bucket_latents`` that holds it (``length`` 1: one frame)."""
    if length < 1 or temporal_factor < 1 or bucket_latents < 1:
        raise ValueError(f"padded_length: length, temporal_factor and bucket_latents must be >= 1, got "
                         f"{length}, {temporal_factor}, {bucket_latents}")
    latents = -(-(length - 1) // temporal_factor)
    return 1 + temporal_factor * (-(-latents // bucket_latents) * bucket_latents)


@functools.partial(jax.jit, static_argnames=("graphdef",))
def round_trip_videos(graphdef: nnx.GraphDef, state: nnx.State,
                      videos: UInt8[Array, "n t h w 3"]) -> UInt8[Array, "n t h w 3"]:
    """``videos`` (``T = 1 + 4k`` uint8 frames each) encoded by :func:`sword_jax.vae.api.encode` (latent means) and
    decoded by :func:`sword_jax.vae.api.decode` (clamped), back to uint8 with the scaling the world model's
    frames use (``x / 255 * 2 - 1``). Compiled once per shape."""
    video = videos.astype(jnp.float32) / jnp.float32(255.0) * 2.0 - 1.0
    latents = vae_api.encode(graphdef, state, video, check_values=False)
    decoded = vae_api.decode(graphdef, state, latents, clamp=True, check_values=False)
    return jnp.clip(jnp.round((decoded + 1.0) * jnp.float32(127.5)), 0, 255).astype(jnp.uint8)


def round_trip_episodes(
    vae_graphdef: nnx.GraphDef,
    vae_state: nnx.State,
    frames: UInt8[np.ndarray, "e t h w 3"],
    lengths: Int[np.ndarray, " e"] | None = None,
    *,
    episodes_per_call: int = 1,
    bucket_latents: int = 8,
    log: Callable[[str], object] | None = None,
) -> UInt8[np.ndarray, "e t h w 3"]:
    """Every episode's frames after the VAE's video round trip, the same shape and dtype as ``frames``.

    Args:
      vae_graphdef, vae_state: the VAE (``nnx.split``; e.g. :func:`sword_jax.load.experiment_vae`).
      frames: ``[E, T, H, W, 3]`` uint8 episodes (H and W multiples of the VAE's spatial factor).
      lengths: ``[E]`` true lengths (an ``EpisodeSet``'s; default all ``T``). Frames ``0 .. length - 1`` of an
        episode are encoded as one video (padded as :func:`padded_length` says, by repeating frame
        ``length - 1``); the frames after it repeat its decoded last frame, as an ``EpisodeSet``'s padding does.
      episodes_per_call: episodes of one bucket encoded together (the last call of a bucket repeats an episode
        to keep the shape).
      bucket_latents: lengths are rounded up to multiples of this many latents (one compile per bucket).
      log: progress lines with an ETA, if given.

    Returns:
      ``[E, T, H, W, 3]`` uint8.
    """
    frames = np.asarray(frames)
    if frames.ndim != 5 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"round_trip_episodes: frames must be [E, T, H, W, 3] uint8, got {frames.shape} {frames.dtype}")
    e, t = frames.shape[:2]
    lengths = np.full(e, t, np.int64) if lengths is None else np.asarray(lengths, np.int64)
    if lengths.shape != (e,) or np.any(lengths < 1) or np.any(lengths > t):
        raise ValueError(f"round_trip_episodes: lengths must be {e} values in [1, {t}], got {lengths}")
    if episodes_per_call < 1:
        raise ValueError(f"round_trip_episodes: episodes_per_call must be >= 1, got {episodes_per_call}")
    temporal, _ = vae_api.factors(vae_graphdef, vae_state)
    padded = np.asarray([padded_length(int(n), temporal, bucket_latents) for n in lengths])
    out = np.empty_like(frames)
    start, done = time.time(), 0
    for bucket in np.unique(padded):
        members = np.flatnonzero(padded == bucket)
        for lo in range(0, len(members), episodes_per_call):
            group = members[np.arange(lo, lo + episodes_per_call) % len(members)]
            keep = min(episodes_per_call, len(members) - lo)
            # (n, bucket): frames up to each episode's length, then its last frame repeated
            index = np.minimum(np.arange(bucket)[None], lengths[group, None] - 1)
            videos = frames[group[:, None], index]
            decoded = np.asarray(jax.device_get(round_trip_videos(vae_graphdef, vae_state, jnp.asarray(videos))))
            for row, episode in enumerate(group[:keep]):
                n = lengths[episode]
                out[episode, :n] = decoded[row, :n]
                out[episode, n:] = decoded[row, n - 1]
            every = max(1, e // 10)
            done += keep
            if log is not None and (done // every > (done - keep) // every or done == e):
                elapsed = time.time() - start
                log(f"VAE round trip: {done}/{e} episodes ({bucket} frames a video) "
                    f"eta {elapsed / done * (e - done):.0f}s")
    return out
