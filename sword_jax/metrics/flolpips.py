"""FloLPIPS (Danier, Zhang, Bull, PCS 2022): LPIPS whose spatial mean is weighted by flow error.

For frames t = 0..T-2 of a reference video R and a distorted video D: ``Delta = flow(R_t -> R_t+1) -
flow(D_t -> D_t+1)``; LPIPS-Alex v0.1 lin maps ``L_k`` of (R_t, D_t); ``Delta`` bilinearly resized
to each ``(h_k, w_k)`` (vector values not rescaled), magnitude ``M``, normalised per sample to sum 1:
``W_k = M / sum(M)``; frame score ``sum_k sum(L_k * W_k)``; video score = mean over t.

Deviations from danier97/flolpips, both documented:
  * Flow: OpenCV Farneback on 8-bit grayscale frames instead of PWC-Net (its weights are not
    obtainable offline); the aggregation itself matches the reference to float32 rounding.
  * Zero flow difference (``sum(M) = 0``): the original divides 0/0 (NaN). Here the weights fall
    back to uniform, i.e. the layer term becomes plain LPIPS's spatial mean. Identical videos
    therefore score 0 (up to float32 rounding).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import cv2
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from sword_jax.metrics.lpips import LPIPS
from sword_jax.metrics.preprocess import resize_bilinear_torch

FARNEBACK = dict(pyr_scale=0.5, levels=3, winsize=15, iterations=3, poly_n=5, poly_sigma=1.2, flags=0)


def farneback_flow(video: Float[np.ndarray, "t h w 3"]) -> Float[np.ndarray, "tm1 h w 2"]:
    """Forward optical flow between consecutive frames, (dx, dy) in pixels, OpenCV Farneback.

    Args:
      video: RGB frames in [0, 1] (host array).

    Returns:
      ``flow[t]`` = flow from frame t to frame t + 1, float32.
    """
    video = np.asarray(video, np.float32)
    if video.ndim != 4 or video.shape[-1] != 3:
        raise ValueError(f"flow expects [T, H, W, 3] frames, got {video.shape}")
    if video.shape[0] < 2:
        raise ValueError(f"flow needs at least 2 frames, got {video.shape[0]}")
    gray = [
        cv2.cvtColor(np.clip(np.rint(frame * 255.0), 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY) for frame in video
    ]
    flows = [cv2.calcOpticalFlowFarneback(a, b, None, **FARNEBACK) for a, b in zip(gray[:-1], gray[1:])]
    return np.stack(flows).astype(np.float32)


def farneback_flows(videos: Sequence[np.ndarray], *, workers: int | None = None) -> list[np.ndarray]:
    """:func:`farneback_flow` of every video, on ``workers`` host threads (default: every core).

    OpenCV releases the GIL inside Farneback, so threads scale with cores; the result is identical to
    calling :func:`farneback_flow` on each video in turn.
    """
    workers = workers or os.cpu_count() or 1
    if workers <= 1 or len(videos) <= 1:
        return [farneback_flow(v) for v in videos]
    with ThreadPoolExecutor(max_workers=min(workers, len(videos))) as pool:
        return list(pool.map(farneback_flow, videos))


def flow_weighted_lpips(lpips: LPIPS, frames_ref: Float[Array, "n h w 3"], frames_dis: Float[Array, "n h w 3"],
                        flow_diff: Float[Array, "n h w 2"]) -> Float[Array, " n"]:
    """FloLPIPS' per-frame score on given flow differences (``FloLPIPS.forward(..., normalize=True)``).

    Args:
      lpips: an AlexNet LPIPS v0.1 module.
      frames_ref, frames_dis: frames t of the reference and distorted videos, RGB in [0, 1].
      flow_diff: ``flow_ref - flow_dis`` at frame t, (dx, dy) pixels.

    Returns:
      One score per frame pair.
    """
    if flow_diff.shape[:3] != frames_ref.shape[:3] or flow_diff.shape[-1] != 2:
        raise ValueError(f"flow_diff {flow_diff.shape} must be [N, H, W, 2] matching frames {frames_ref.shape}")
    maps = lpips.lin_maps(frames_ref, frames_dis, normalize=True)
    total = jnp.zeros((frames_ref.shape[0],), jnp.float32)
    for lin_map in maps:
        delta = resize_bilinear_torch(flow_diff, lin_map.shape[1:3])
        magnitude = jnp.sqrt(jnp.sum(delta * delta, axis=-1))  # (N, h, w)
        mass = jnp.sum(magnitude, axis=(1, 2), keepdims=True)
        uniform = jnp.full_like(magnitude, jnp.float32(1.0 / (magnitude.shape[1] * magnitude.shape[2])))
        weights = jnp.where(mass > 0, magnitude / jnp.where(mass > 0, mass, jnp.float32(1)), uniform)
        total = total + jnp.sum(lin_map * weights, axis=(1, 2))
    return total


def flolpips_video(lpips: LPIPS, ref_video: Float[np.ndarray, "t h w 3"], dis_video: Float[np.ndarray, "t h w 3"],
                   *, score_fn=None, ref_flow: np.ndarray | None = None,
                   dis_flow: np.ndarray | None = None) -> Float[np.ndarray, " tm1"]:
    """Per-frame FloLPIPS of one video pair (its mean over t is the video's FloLPIPS).

    Args:
      lpips: AlexNet LPIPS v0.1.
      ref_video, dis_video: RGB videos in [0, 1], same shape, T >= 2.
      score_fn: optional compiled ``(frames_ref, frames_dis, flow_diff) -> [N]`` (defaults to an
        eager call of :func:`flow_weighted_lpips`).
      ref_flow, dis_flow: the videos' :func:`farneback_flow`, where already computed.

    Returns:
      Scores for t = 0..T-2 (host float32).
    """
    ref_video, dis_video = np.asarray(ref_video, np.float32), np.asarray(dis_video, np.float32)
    if ref_video.shape != dis_video.shape:
        raise ValueError(f"videos differ in shape: {ref_video.shape} vs {dis_video.shape}")
    ref_flow = farneback_flow(ref_video) if ref_flow is None else ref_flow
    dis_flow = farneback_flow(dis_video) if dis_flow is None else dis_flow
    flow_diff = ref_flow - dis_flow
    fn = score_fn or (lambda r, d, f: flow_weighted_lpips(lpips, r, d, f))
    return np.asarray(fn(jnp.asarray(ref_video[:-1]), jnp.asarray(dis_video[:-1]), jnp.asarray(flow_diff)))
