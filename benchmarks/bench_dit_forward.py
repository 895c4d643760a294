"""World-model DiT forward: latency, tokens/s and model FLOP utilisation per attention implementation.

    python -m benchmarks.bench_dit_forward            # TI2V-5B shapes (30 layers, dim 3072), bf16, on GPU
    python -m benchmarks.bench_dit_forward --tiny     # CPU smoke run of the same code path

The input is a training segment (first frame + context + 2 future latent frames, 13 actions) of
256x256 video (16x16 latents), plus a longer 81-frame 480x832-like clip (21 latent frames) to show
attention-dominated scaling. FLOPs count matmuls and attention (multiply-add = 2); MFU is judged
against a bf16 matmul peak measured in the same process.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from benchmarks import common
from sword_jax import cli
from sword_jax import sharding
from sword_jax.dit.action_dit import WorldModel, num_video_frames, world_model_apply
from sword_jax.dit.config import DiTConfig


def forward_flops(cfg: DiTConfig, batch: int, frames: int, hw: tuple[int, int]) -> float:
    """Matmul + attention FLOPs of one world-model forward."""
    d, ffn, layers = cfg.dim, cfg.ffn_dim, cfg.num_layers
    tokens = frames * (hw[0] // cfg.patch_size[1]) * (hw[1] // cfg.patch_size[2])
    actions = num_video_frames(frames)
    per_layer = tokens * (2 * 4 * d * d + 2 * 2 * d * d + 2 * 2 * d * ffn)  # self q/k/v/o, cross q/o, FFN
    per_layer += 2 * 2 * tokens * tokens * d + 2 * 2 * tokens * actions * d  # attention scores and values
    per_layer += actions * 2 * 2 * d * d  # cross-attention k/v of the action tokens
    patch = cfg.patch_size[1] * cfg.patch_size[2] * cfg.in_dim
    total = layers * per_layer + tokens * 2 * 2 * patch * d  # patch embedding and head
    return float(batch * total)


def _inputs(cfg: DiTConfig, batch: int, frames: int, hw: tuple[int, int]):
    rng = np.random.default_rng(0)
    latents = jnp.asarray(rng.standard_normal((batch, frames, *hw, cfg.in_dim)), jnp.float32)
    timesteps = jnp.asarray(np.concatenate([np.zeros((batch, 2)), np.full((batch, frames - 2), 500.0)], 1), jnp.float32)
    actions = jnp.asarray(rng.uniform(-1, 1, (batch, num_video_frames(frames), cfg.action_dim)), jnp.float32)
    return latents, timesteps, actions


def run(cfg: DiTConfig, cases: list[tuple[str, int, int, tuple[int, int]]], impls: list[str], iters: int):
    graphdef, state = sharding.create_sharded(
        lambda: WorldModel(cfg, rngs=nnx.Rngs(0)),
        sharding.make_mesh(sharding.MeshConfig(data=1), devices=jax.devices()[:1]),
        sharding.DEFAULT_RULES,
    )
    peak = common.measured_matmul_tflops()
    rows = []
    for impl in impls:
        impl_graphdef = nnx.graphdef(sharding.abstract_module(
            lambda: WorldModel(dataclasses.replace(cfg, attention_impl=impl), rngs=nnx.Rngs(0))))
        forward = jax.jit(world_model_apply, static_argnums=0)
        for name, batch, frames, hw in cases:
            inputs = _inputs(cfg, batch, frames, hw)
            try:
                timing = common.time_fn(lambda: forward(impl_graphdef, state, *inputs), warmup=2, iters=iters)
            except Exception as err:  # noqa: BLE001 - e.g. cudnn unavailable for this shape/dtype
                rows.append({"case": name, "attention": impl, "error": type(err).__name__})
                continue
            seconds = timing["min_s"]
            tokens = batch * frames * (hw[0] // 2) * (hw[1] // 2)
            tflops = forward_flops(cfg, batch, frames, hw) / seconds / 1e12
            rows.append({"case": name, "attention": impl, "batch": batch, "tokens": tokens,
                         "ms": 1e3 * seconds, "tokens_per_s": tokens / seconds, "tflops": tflops,
                         "mfu": tflops / peak, "peak_mem_gb": common.peak_memory_gb()})
    return rows, peak


def main(argv=None) -> None:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="tiny config on CPU (smoke run, no results file)")
    parser.add_argument("--layers", type=int, default=None, help="override num_layers (default: config's)")
    parser.add_argument("--iters", type=int, default=10)
    args = parser.parse_args(argv)
    if args.tiny:
        cfg = DiTConfig(dim=32, ffn_dim=64, freq_dim=32, num_heads=2, num_layers=2, text_dim=16, text_len=8)
        cases = [("segment_32px", 2, 4, (2, 2))]
        impls, iters = ["xla"], 2
    else:
        cfg = DiTConfig()
        cases = [("segment_256px", 8, 4, (16, 16)), ("clip_21x30x52", 1, 21, (30, 52))]
        impls, iters = ["xla", "cudnn"], args.iters
    if args.layers:
        cfg = dataclasses.replace(cfg, num_layers=args.layers)
    rows, peak = run(cfg, cases, impls, iters)
    print(f"DiT forward, dim {cfg.dim}, {cfg.num_layers} layers, {cfg.compute_dtype}; bf16 matmul peak {peak:.1f} TFLOP/s")
    common.print_table(rows, ["case", "attention", "batch", "tokens", "ms", "tokens_per_s", "tflops", "mfu",
                              "peak_mem_gb", "error"])
    if args.tiny:
        return
    entries = {}
    for row in rows:
        if "error" in row:
            continue
        key = f"dit_forward_{row['case']}_{row['attention']}"
        entries[key + "_mfu"] = common.record(key + "_mfu", row["mfu"], 0.4, layers=cfg.num_layers)
        entries[key + "_ms"] = common.record(key + "_ms", row["ms"], None, layers=cfg.num_layers)
    print("results ->", common.merge_results(entries))


if __name__ == "__main__":
    cli.run(main)
