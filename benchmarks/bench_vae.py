"""Wan 2.2 VAE encode / decode throughput (frames/s) and peak memory.

    python -m benchmarks.bench_vae                  # full-size VAE (dim 160, dec 256, z 48), 256x256, bf16, GPU
    python -m benchmarks.bench_vae --batch 4 --frames 33
    python -m benchmarks.bench_vae --tiny           # CPU smoke run of the same code path (no results file)

Cases: whole-clip encode of ``[B, 1+4k, H, W, 3]``, whole-clip decode of its ``[B, 1+k, H/16, W/16, 48]``
latents, and streaming decode of one rollout chunk (2 latents -> 8 frames, cache carried), the way
imagined rollouts decode. frames/s counts video frames in (encode) or out (decode); time is the
median of ``--iters`` calls after ``--warmup``, each blocked until ready. Writes
``vae_encode_frames_per_s``, ``vae_decode_frames_per_s`` and ``vae_decode_chunk_frames_per_s``.
"""

from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
from flax import nnx

from benchmarks import common
from sword_jax import vae


def run(cfg: vae.VAEConfig, *, batch: int, frames: int, size: int, warmup: int, iters: int) -> list[dict]:
    graphdef, state = nnx.split(vae.create_vae(cfg, key=jax.random.key(0)))
    state = jax.device_put(state, jax.devices()[0])
    video = jax.random.uniform(jax.random.key(1), (batch, frames, size, size, 3), jnp.float32, -1.0, 1.0)
    latent_frames = 1 + (frames - 1) // cfg.temporal_factor
    latent_hw = size // cfg.spatial_factor
    latents = jax.random.normal(jax.random.key(2), (batch, latent_frames, latent_hw, latent_hw, cfg.z_dim), jnp.float32)
    rows = []

    def add(case: str, fn, frames_per_call: int) -> None:
        timing = common.time_fn(fn, warmup=warmup, iters=iters)
        rows.append({"case": case, "batch": batch, "frames": frames_per_call, "size": size,
                     "ms": 1e3 * timing["median_s"], "frames_per_s": batch * frames_per_call / timing["median_s"],
                     "peak_mem_gb": common.peak_memory_gb()})

    add("encode", lambda: vae.encode(graphdef, state, video, check_values=False), frames)
    add("decode", lambda: vae.decode(graphdef, state, latents, check_values=False), frames)
    # Streaming: the cache after the first latent frame, then one 2-latent rollout chunk per call.
    cache = vae.init_decode_cache(graphdef, state, batch, latent_hw, latent_hw)
    _, cache = vae.decode_chunk(graphdef, state, latents[:, :1], cache, check_values=False)
    chunk = jnp.repeat(latents[:, :1], 2, axis=1)
    add("decode_chunk", lambda: vae.decode_chunk(graphdef, state, chunk, cache, check_values=False),
        2 * cfg.temporal_factor)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="tiny VAE on CPU (smoke run, no results file)")
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--frames", type=int, default=17, help="video frames, 1 + 4k")
    parser.add_argument("--size", type=int, default=256, help="frame height = width, multiple of 16")
    parser.add_argument("--dtype", default="bfloat16", choices=["bfloat16", "float32"])
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--iters", type=int, default=10)
    args = parser.parse_args(argv)
    if args.tiny:
        cfg = vae.tiny_config(compute_dtype=args.dtype)
        batch, frames, size, warmup, iters = 1, 5, 32, 1, 2
    else:
        cfg = dataclasses.replace(vae.VAEConfig(), compute_dtype=args.dtype)
        batch, frames, size, warmup, iters = args.batch, args.frames, args.size, args.warmup, args.iters
    rows = run(cfg, batch=batch, frames=frames, size=size, warmup=warmup, iters=iters)
    print(f"Wan 2.2 VAE dim {cfg.dim}/{cfg.dec_dim}, z {cfg.z_dim}, {cfg.compute_dtype}, "
          f"{vae.param_count(cfg) / 1e6:.1f}M params, on {common.device_name()}")
    common.print_table(rows, ["case", "batch", "frames", "size", "ms", "frames_per_s", "peak_mem_gb"])
    if args.tiny:
        return
    entries = {}
    for row in rows:
        key = f"vae_{row['case']}_frames_per_s"
        entries[key] = common.record(key, row["frames_per_s"], None, batch=row["batch"], frames=row["frames"],
                                     size=row["size"], dtype=cfg.compute_dtype, ms=row["ms"],
                                     peak_mem_gb=row["peak_mem_gb"])
    print("results ->", common.merge_results(entries))


if __name__ == "__main__":
    main()
