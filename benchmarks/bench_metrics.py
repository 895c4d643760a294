"""Throughput of the metric networks (random weights: same cost as real ones).

    python -m benchmarks.bench_metrics --tiny     # CPU, small batches, no results written
    python -m benchmarks.bench_metrics            # one GPU; merges metrics.* into results/latest.json

Reports frames/s for LPIPS-Alex and LPIPS-VGG (pairs at ``--size``), images/s for the FID
InceptionV3 (resized to 299) and clips/s for the FVD I3D (16 x 224 x 224), all at full float32
precision (``Precision.HIGHEST``, as parity requires), plus the implied time to score one paper-size
evaluation split (50 episodes x 128 predicted frames).
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
from flax import nnx

from benchmarks.common import merge_results, print_table, record, time_fn
from sword_jax import cli
from sword_jax.metrics.i3d import InceptionI3d
from sword_jax.metrics.inception import FIDInceptionV3
from sword_jax.metrics.lpips import LPIPS
from sword_jax.metrics.networks import random_fill


def _compiled(factory, fn):
    module = random_fill(nnx.eval_shape(factory), seed=0)
    graphdef, state = nnx.split(module)
    f = jax.jit(lambda state, *args: fn(nnx.merge(graphdef, state), *args))
    return lambda *args: f(state, *args)


def main(argv: list[str] | None = None) -> int:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true")
    parser.add_argument("--size", type=int, default=256, help="frame side for LPIPS")
    parser.add_argument("--batch", type=int, default=32)
    args = parser.parse_args(argv)
    batch = 2 if args.tiny else args.batch
    size = 64 if args.tiny else args.size
    iters = 2 if args.tiny else 10
    key = jax.random.key(0)
    frames = jax.random.uniform(key, (batch, size, size, 3), jnp.float32)
    rows = []
    for net in ("alex", "vgg"):
        fn = _compiled(lambda net=net: LPIPS(net, rngs=nnx.Rngs(0)), lambda m, a, b: m(a, b, normalize=True)[0])
        t = time_fn(lambda: fn(frames, frames[::-1]), warmup=1, iters=iters)["median_s"]
        rows.append({"metric": f"lpips_{net}", "unit": f"frames/s @{size}", "throughput": batch / t})
    inc = _compiled(lambda: FIDInceptionV3(rngs=nnx.Rngs(0)), lambda m, x: m(x))
    t = time_fn(lambda: inc(frames), warmup=1, iters=iters)["median_s"]
    rows.append({"metric": "fid_inception", "unit": "images/s", "throughput": batch / t})
    clip_batch = 1 if args.tiny else max(1, batch // 8)
    clip_side = 193 if args.tiny else 224
    clips = jax.random.uniform(key, (clip_batch, 16, clip_side, clip_side, 3), jnp.float32, -1, 1)
    i3d = _compiled(lambda: InceptionI3d(400, rngs=nnx.Rngs(0)), lambda m, x: m(x))
    t = time_fn(lambda: i3d(clips), warmup=1, iters=iters)["median_s"]
    rows.append({"metric": "fvd_i3d", "unit": f"clips/s @16x{clip_side}", "throughput": clip_batch / t})
    frames_per_split = 50 * 128
    per_split = (frames_per_split / rows[0]["throughput"] + frames_per_split / rows[2]["throughput"]
                 + frames_per_split / 16 / rows[3]["throughput"])
    rows.append({"metric": "paper_split_seconds", "unit": "s (LPIPS+FID+FVD, 50x128 frames)", "throughput": per_split})
    print_table(rows, ["metric", "unit", "throughput"])
    if not args.tiny:
        entries = {f"metrics.{r['metric']}": record(f"metrics.{r['metric']}", r["throughput"], None, unit=r["unit"])
                   for r in rows}
        merge_results(entries)
    return 0


if __name__ == "__main__":
    cli.run(main)
