"""sword_jax.vae: the Wan 2.2 causal video VAE (z 48, 2x2 patchify, x16 spatial, x4 temporal).

Functional API (``graphdef, state = nnx.split(vae)``; channels-last; all jittable):
  ``encode(graphdef, state, video) -> latents``: ``[B, 1+4k, H, W, 3]`` in [-1, 1] ->
      normalised latent means ``[B, 1+k, H/16, W/16, 48]``, ``(mu - mean) * inv_std``.
  ``decode(graphdef, state, latents, clamp=False) -> video`` ``[B, 1+4k, H, W, 3]`` (unclamped).
  ``init_encode_cache / encode_chunk``: streaming encode, first chunk ``1+4m`` frames, then
      chunks of ``4m``; ``init_decode_cache / decode_chunk``: streaming decode, first chunk
      ``1+m`` latents, then any ``m >= 1``. ``(out, cache) = *_chunk(graphdef, state, x, cache)``;
      the outputs concatenated equal the whole-sequence call. ``StreamCache`` is a pytree
      (``started`` static), so later chunks can be decoded inside ``lax.scan``.
  ``encode_moments`` / ``decode_raw``: raw posterior and raw-latent decode (training).
  ``compute_dtype='bfloat16'`` runs convs/attention in bf16 (params, norms, softmax, outputs float32).
  Shapes are validated at trace time; NaN/range checks run on the host for concrete inputs
  (``check_values=True``), or call ``check_video_values`` before your own jit.

Construction: ``create_vae(cfg, key=...)``, ``abstract_vae(cfg)``, ``param_count(cfg)``,
``tiny_config()``. Official checkpoints: :mod:`sword_jax.convert.wan22_vae`. Training:
:mod:`sword_jax.vae.train`. A light causal decoder of the same latents for imagined rollouts
(``LightDecoderConfig``): :mod:`sword_jax.vae.light_decoder`, distilled from this decoder by
:mod:`sword_jax.vae.light_train`.
"""

import dataclasses

from sword_jax.vae.api import (
    StreamCache,
    abstract_vae,
    check_latent_values,
    check_video_values,
    create_vae,
    decode,
    decode_chunk,
    decode_raw,
    encode,
    encode_chunk,
    encode_moments,
    init_decode_cache,
    init_encode_cache,
    param_count,
    reference_taps,
)
from sword_jax.vae.config import LightDecoderConfig, VAEConfig
from sword_jax.vae.model import LatentStat, WanVAE


def tiny_config(**overrides) -> VAEConfig:
    """A tiny VAE for tests (dim 8, dec_dim 8, dim_mult (1, 2, 2, 2), 1 res block, z 48): fast to compile."""
    return dataclasses.replace(
        VAEConfig(dim=8, dec_dim=8, dim_mult=(1, 2, 2, 2), num_res_blocks=1, train_steps=30, batch_size=2),
        **overrides,
    )


__all__ = [
    "LatentStat", "LightDecoderConfig", "StreamCache", "VAEConfig", "WanVAE", "abstract_vae", "check_latent_values",
    "check_video_values", "create_vae", "decode", "decode_chunk", "decode_raw", "encode", "encode_chunk",
    "encode_moments", "init_decode_cache", "init_encode_cache", "param_count", "reference_taps", "tiny_config",
]
