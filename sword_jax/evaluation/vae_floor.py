"""The VAE's reconstruction floor: the ground truth encoded and decoded, scored like a prediction.

A world model predicts latents; its frames reach the metrics through the VAE's decoder. The
encode-decode of the ground truth (through the same streaming decoder, in the same chunks as the
rollout) is what a world model with perfect latents would score, so the report shows it next to
every model on each split: the gap above the floor is the world model's error, the floor itself the
VAE's. On LIBERO-Mixed the floor also shows how well the VAE reconstructs held-out styles it never
trained on.
"""

from __future__ import annotations

import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Float

from sword_jax.evaluation.results import ModelResult
from sword_jax.metrics.config import EvalConfig

@functools.lru_cache(maxsize=4)
def _reconstruct_fn(vae_graphdef: nnx.GraphDef, latents_per_chunk: int):
    """One compiled encode -> streaming decode per (VAE graph, decode chunk)."""
    from sword_jax.vae import api as vae_api
    from sword_jax.world_model import rollout as wm_rollout

    @jax.jit
    def run(vae_state, video):
        latents = vae_api.encode(vae_graphdef, vae_state, video * jnp.float32(2) - jnp.float32(1), check_values=False)
        out = wm_rollout.decode_rollout(vae_graphdef, vae_state, latents[:, :1], latents[:, 1:],
                                        latents_per_chunk=latents_per_chunk)
        return (out + jnp.float32(1)) / jnp.float32(2)

    return run


def reconstruct_videos(vae_graphdef: nnx.GraphDef, vae_state, frames: Float[np.ndarray, "b t h w 3"], *,
                       num_context: int, num_future: int, batch: int = 16) -> Float[np.ndarray, "b t h w 3"]:
    """Encode-decode of ``frames`` (in [0, 1], ``T = 1 + 4m``) through the rollout's decode path, in [0, 1].

    Episodes go through in batches of ``batch`` (the last one padded, so one compile); latents are
    decoded in chunks of ``gcd(num_context, num_future)`` as :func:`harness.rollout_videos` does.
    """
    frames = np.asarray(frames, np.float32)
    b = frames.shape[0]
    batch = max(1, min(batch, b))
    run = _reconstruct_fn(vae_graphdef, math.gcd(num_context, num_future))
    out = []
    for lo in range(0, b, batch):
        chunk = frames[lo:lo + batch]
        pad = batch - chunk.shape[0]
        if pad:
            chunk = np.concatenate([chunk, np.repeat(chunk[-1:], pad, axis=0)])
        out.append(np.asarray(run(vae_state, jnp.asarray(chunk)))[:batch - pad])
    return np.clip(np.concatenate(out), 0.0, 1.0)


def vae_floor(eval_cfg: EvalConfig, metrics: tuple[str, ...], vae_graphdef: nnx.GraphDef, vae_state,
              gt_by_split: dict[str, np.ndarray], *, num_context: int, num_future: int,
              given_frames: int, batch: int = 16) -> tuple[dict[str, ModelResult], float]:
    """The reconstruction floor per split, on the same scored frames as the predictions.

    Args:
      eval_cfg: metric-network weights (the networks are shared with the main suite: compiled once),
        and ``floor_metrics``.
      metrics: the evaluation's metrics; the floor scores those among ``eval_cfg.floor_metrics``. Its set
        statistics (FVD, FID) are over the same episodes as the predictions', so a model's FVD reads
        against the FVD of perfect latents.
      vae_graphdef, vae_state: the VAE the predictions were decoded with.
      gt_by_split: ``{split: [B, T, H, W, 3]}`` ground truth in [0, 1] (the evaluated horizon).
      num_context, num_future: the rollout's latents of context / prediction per chunk (decode chunking).
      given_frames: leading frames excluded from the metrics, as for the predictions.
      batch: episodes per VAE call (:func:`reconstruct_videos`).

    Returns:
      ``({split: ModelResult}, seconds)``; empty when none of the floor's metrics is evaluated.
    """
    from sword_jax.evaluation.harness import evaluate_model
    from sword_jax.metrics.suite import MetricSuite

    start = time.perf_counter()
    names = tuple(m for m in metrics if m in eval_cfg.floor_metrics)
    if not names:
        return {}, 0.0
    suite = MetricSuite(eval_cfg, metrics=names)
    floor = {}
    for split, gt in gt_by_split.items():
        recon = reconstruct_videos(vae_graphdef, vae_state, gt, num_context=num_context, num_future=num_future,
                                   batch=batch)
        floor[split] = evaluate_model(suite, gt, recon, given_frames=given_frames)
    return floor, time.perf_counter() - start
