"""Where the world-model train step's time goes at 5B width: GEMMs, attention, everything else.

    python -m benchmarks.bench_dit_breakdown                       # 8 layers, batch 96, remat dots (GPU)
    python -m benchmarks.bench_dit_breakdown --tiny                # CPU smoke run

Three timings in one process, against the bf16 matmul peak measured in the same run:

1. the full train step (flow matching, teacher forcing, AdamW), as ``bench_dit_train`` times it;
2. the step's GEMMs alone: per layer the same ``[tokens, dim] x [dim, dim]`` (q, k, v, o and the
   cross-attention q, o), ``[tokens, dim] x [dim, ffn]`` and ``[tokens, ffn] x [ffn, dim]`` products,
   forward and backward (input and weight gradients), scanned over the layers with nothing else;
3. the self-attention kernel alone, forward and backward, at the step's shapes.

``gemm_mfu`` is the ceiling the model's MFU could reach if nothing but GEMMs took time; the
shares say how much of the step the GEMMs, the attention and the rest (norms, modulation,
RoPE, GELU, residual adds, rematerialised elementwise work, the optimizer) take. Key
``dit_train_breakdown``.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from benchmarks import common
from benchmarks.bench_dit_train import forward_flops, run_config
from sword_jax import cli
from sword_jax.dit.config import DiTConfig
from sword_jax.dit.layers import attention


def gemm_chain(cfg: DiTConfig, tokens: int, context_tokens: int):
    """``(fn, args, flops)``: value-and-grad of the layer stack's GEMMs alone (3x forward FLOPs)."""
    d, ffn, layers = cfg.dim, cfg.ffn_dim, cfg.num_layers
    keys = jax.random.split(jax.random.key(0), 6)
    bf16 = jnp.bfloat16

    def init(key, shape):
        return (jax.random.normal(key, (layers, *shape), jnp.float32) / jnp.sqrt(shape[-2])).astype(bf16)

    weights = {"square": init(keys[0], (6, d, d)), "ctx": init(keys[1], (d, 2 * d)),
               "up": init(keys[2], (d, ffn)), "down": init(keys[3], (ffn, d))}
    x = jax.random.normal(keys[4], (tokens, d), jnp.float32).astype(bf16)
    context = jax.random.normal(keys[5], (context_tokens, d), jnp.float32).astype(bf16)

    def layer(h, w):
        squares = [h @ w["square"][i] for i in range(6)]  # q, k, v, o, cross q, cross o: separate, as in the model
        kv = context @ w["ctx"]  # cross-attention k, v of the action tokens
        hidden = h @ w["up"]
        out = hidden @ w["down"]
        mixed = out + sum(squares[1:], squares[0]) + jnp.mean(kv, axis=0, dtype=jnp.float32).astype(bf16)[:d]
        return mixed, None

    def loss(weights, x):
        y, _ = jax.lax.scan(layer, x, weights)
        return jnp.mean(y.astype(jnp.float32))

    fn = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    forward = layers * (2 * tokens * d * (6 * d + 2 * ffn) + 2 * context_tokens * d * 2 * d)
    return fn, (weights, x), 3.0 * forward


def attention_only(cfg: DiTConfig, batch: int, length: int):
    """``(fn, args, flops)``: forward + backward of the self-attention kernel over every layer."""
    heads, head_dim = cfg.num_heads, cfg.dim // cfg.num_heads
    shape = (cfg.num_layers, batch, length, heads, head_dim)
    keys = jax.random.split(jax.random.key(1), 3)
    q, k, v = (jax.random.normal(key, shape, jnp.float32).astype(jnp.bfloat16) for key in keys)

    def loss(q, k, v):
        def body(total, qkv):
            out = attention(*qkv, key_lengths=None, impl=cfg.attention_impl)
            return total + jnp.sum(out.astype(jnp.float32)), None

        total, _ = jax.lax.scan(body, jnp.float32(0), (q, k, v))
        return total

    fn = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))
    forward = cfg.num_layers * batch * 2 * 2 * length * length * cfg.dim
    return fn, (q, k, v), 3.0 * forward


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true")
    parser.add_argument("--layers", type=int, default=8)
    parser.add_argument("--batch", type=int, default=96)
    parser.add_argument("--remat", default="dots")
    parser.add_argument("--iters", type=int, default=5)
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    peak = common.measured_matmul_tflops()
    if args.tiny:
        cfg = DiTConfig(dim=64, ffn_dim=128, freq_dim=32, num_heads=4, num_layers=2, text_dim=16, text_len=8,
                        compute_dtype="float32")
        batch, hw, iters = 2, (4, 4), 2
    else:
        cfg = DiTConfig(num_layers=args.layers, remat=args.remat)
        batch, hw, iters = args.batch, (16, 16), args.iters
    length = 4 * (hw[0] // cfg.patch_size[1]) * (hw[1] // cfg.patch_size[2])
    step_row = run_config("5b-width", cfg, batch, hw, peak_tflops=peak, iters=iters, with_dlb=False)
    step_s = step_row["tf_step_s"]
    model_flops = 3 * forward_flops(cfg, batch, 4, hw, 13)

    rows = [{"part": "full train step", "seconds": step_s, "tflops": model_flops / step_s / 1e12,
             "mfu": model_flops / step_s / 1e12 / peak, "share_of_step": 1.0}]
    for name, (fn, fn_args, flops) in (("GEMMs alone", gemm_chain(cfg, batch * length, batch * 13)),
                                       ("self-attention alone", attention_only(cfg, batch, length))):
        seconds = common.time_fn(lambda: fn(*fn_args), warmup=2, iters=iters)["median_s"]
        rows.append({"part": name, "seconds": seconds, "tflops": flops / seconds / 1e12,
                     "mfu": flops / seconds / 1e12 / peak, "share_of_step": seconds / step_s})
    rest = step_s - rows[1]["seconds"] - rows[2]["seconds"]
    rows.append({"part": "everything else (by difference)", "seconds": rest, "share_of_step": rest / step_s})
    print(f"device {common.device_name()}: measured bf16 matmul peak {peak:.1f} TFLOP/s; "
          f"{cfg.num_layers} layers, batch {batch}, {length} video tokens, remat {cfg.remat}")
    common.print_table(rows, ["part", "seconds", "tflops", "mfu", "share_of_step"])
    if args.tiny or args.no_record:
        return
    common.merge_results({"dit_train_breakdown": common.record(
        "dit_train_breakdown", rows[1]["mfu"], None, measured_peak_tflops=peak, layers=cfg.num_layers, batch=batch,
        remat=cfg.remat, step_mfu=rows[0]["mfu"], gemm_mfu=rows[1]["mfu"], attention_mfu=rows[2]["mfu"],
        gemm_share=rows[1]["share_of_step"], attention_share=rows[2]["share_of_step"],
        other_share=rows[3]["share_of_step"], rows=rows)})


if __name__ == "__main__":
    cli.run(main)
