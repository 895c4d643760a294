"""World-model train step: step time, model FLOP utilisation, DLB overhead, peak memory.

    python -m benchmarks.bench_dit_train                 # 5B width (dim 3072) + small config, on GPU
    python -m benchmarks.bench_dit_train --tiny          # CPU smoke run
    python -m benchmarks.bench_dit_train --small-sweep 512x8,768x12,1024x16 --skip-wide   # world models to scale to

Model FLOPs are counted the standard way: 3x the forward matmul and attention FLOPs (recomputation
not counted), over the whole 1 + 1 + 2 latent-frame segment the step runs. MFU is judged against a
bf16 matmul peak measured in the same process. The teacher-forcing and DLB steps run side by side
on the same model, batch and data, so their ratio is not disturbed by drift between runs.

``--small-sweep DIMxLAYERS,...`` times world models of other widths and depths at ``small``'s own geometry (the 8x
VAE's 16 x 16 latents, batch 32, a DLB step as ``small`` trains; its model config with heads of 64 channels, FFN 4x
and unrolled layers), side by side in one process: their parameters, step time and what 30,000 steps (``small``'s
training) would take, each against the first (``dit_train_small_sweep``).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from flax import nnx

from benchmarks import common
from sword_jax import cli
from sword_jax import sharding as shd
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dit.config import DiTConfig
from sword_jax.dlb import cache as dlb_cache
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import train_state, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig


def forward_flops(cfg: DiTConfig, batch: int, latent_frames: int, latent_hw: tuple[int, int], action_tokens: int) -> float:
    """Forward matmul + attention FLOPs of the world model for one batch (multiply-add = 2)."""
    d, ffn, n_layers = cfg.dim, cfg.ffn_dim, cfg.num_layers
    tokens = latent_frames * (latent_hw[0] // cfg.patch_size[1]) * (latent_hw[1] // cfg.patch_size[2])
    per_token_layer = (
        2 * 4 * d * d  # self-attention q, k, v, o
        + 2 * 2 * d * d  # cross-attention q, o
        + 2 * 2 * d * ffn  # FFN
        + 2 * 2 * tokens * d  # self-attention scores and values
        + 2 * 2 * action_tokens * d  # cross-attention scores and values
    )
    per_sample = tokens * n_layers * per_token_layer
    per_sample += n_layers * action_tokens * 2 * 2 * d * d  # cross-attention k, v of the action tokens
    patch = cfg.patch_size[1] * cfg.patch_size[2] * cfg.in_dim
    per_sample += tokens * (2 * patch * d + 2 * d * patch)  # patch embedding and head
    per_sample += tokens * (2 * cfg.freq_dim * d + 2 * d * d + 2 * d * 6 * d)  # per-token time embedding + projection
    return float(batch * per_sample)


def _batch(cfg: DiTConfig, batch: int, hw: tuple[int, int], num_episodes: int, num_latents: int, mesh):
    rng = np.random.default_rng(0)
    latents = rng.standard_normal((batch, 4, hw[0], hw[1], cfg.in_dim), dtype=np.float32)
    actions = rng.uniform(-1, 1, (batch, 13, cfg.action_dim)).astype(np.float32)
    episode = rng.integers(0, num_episodes, batch).astype(np.int32)
    start = rng.integers(1, num_latents - 2, batch).astype(np.int32)
    host = {"latents": latents, "actions": actions, "episode": episode, "start": start}
    shardings = {k: shd.batch_sharding(mesh, v.ndim) for k, v in host.items()}
    return {k: jax.device_put(v, shardings[k]) for k, v in host.items()}, shardings


def run_config(label: str, model_cfg: DiTConfig, batch: int, hw: tuple[int, int], *, peak_tflops: float,
               iters: int, num_episodes: int = 64, num_latents: int = 32, with_dlb: bool = True,
               mu_dtype: str = "float32") -> dict:
    mesh = shd.make_mesh(shd.MeshConfig(data=-1))
    trainer_cfg = TrainerConfig(steps=1000, warmup_steps=10, adam_mu_dtype=mu_dtype)
    flow_cfg = FlowConfig()
    dataset_shape = (num_episodes, num_latents, hw[0], hw[1], model_cfg.in_dim)
    data, data_shardings = _batch(model_cfg, batch, hw, num_episodes, num_latents, mesh)
    key = jax.random.key(0)
    row: dict = {"config": label, "layers": model_cfg.num_layers, "dim": model_cfg.dim, "batch": batch,
                 "params": 0,
                 "remat": model_cfg.remat, "attention": model_cfg.attention_impl,
                 "residual": model_cfg.residual_dtype, "adam_mu": mu_dtype}
    times = {}
    variants = [("tf", CacheConfig(enabled=False))]
    if with_dlb:
        variants.append(("dlb", CacheConfig(enabled=True, read_prob_start=0.5, read_prob_end=0.5)))
    for name, cache_cfg in variants:
        graphdef, state, shardings = train_state.create_train_state(
            lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0)), trainer_cfg, cache_cfg, dataset_shape, mesh)
        row["params"] = int(sum(np.prod(x.shape) for x in jax.tree.leaves(state.params)))
        fn = train_step.make_train_step(graphdef, flow_cfg=flow_cfg, trainer_cfg=trainer_cfg, cache_cfg=cache_cfg,
                                        num_context=1, num_episodes=num_episodes)
        step = train_step.compile_train_step(fn, shardings, data_shardings, mesh)
        holder = {"state": state}

        def one():
            holder["state"], metrics = step(holder["state"], data, key)
            return metrics["loss"]

        times[name] = common.time_fn(one, warmup=2, iters=iters)["median_s"]
        loss = float(one())
        if not np.isfinite(loss):
            raise RuntimeError(f"{label}/{name}: non-finite loss {loss}")
        if name == "dlb":
            row["cache_mib_per_device"] = dlb_cache.cache_bytes_per_device(cache_cfg, dataset_shape, mesh) / 2**20
        holder.clear()  # frees the train state before the next variant
        del state
    flops = 3 * forward_flops(model_cfg, batch, 4, hw, 13)
    row.update(tf_step_s=times["tf"], model_tflops=flops / times["tf"] / 1e12,
               mfu=flops / times["tf"] / 1e12 / peak_tflops,
               mfu_nominal_peak=common.mfu(flops, 1.0 / times["tf"], common.nominal_peak_tflops()),
               peak_mem_gb=common.peak_memory_gb())
    if with_dlb:
        row.update(dlb_step_s=times["dlb"], dlb_overhead=times["dlb"] / times["tf"] - 1)
    return row


def _lever_rows(label: str, cfg: DiTConfig, batch: int, hw: tuple[int, int], peak: float, iters: int) -> list[dict]:
    """The same setting with a bf16 residual stream, bf16 Adam first moments, and both."""
    bf16 = dataclasses.replace(cfg, residual_dtype="bfloat16")
    return [run_config(f"{label}+bf16-residual", bf16, batch, hw, peak_tflops=peak, iters=iters, with_dlb=False),
            run_config(f"{label}+bf16-adam-mu", cfg, batch, hw, peak_tflops=peak, iters=iters, with_dlb=False,
                       mu_dtype="bfloat16"),
            run_config(f"{label}+both", bf16, batch, hw, peak_tflops=peak, iters=iters, with_dlb=False,
                       mu_dtype="bfloat16")]


SMALL_STEPS = 30_000  # small's world-model training, what the sweep's time per run is for


def small_sweep(text: str, *, tiny: bool, peak: float, iters: int, attention: str = "auto") -> list[dict]:
    """``--small-sweep``'s rows: each ``DIMxLAYERS`` at ``small``'s geometry (``tiny``: the CPU smoke shapes), its
    DLB step time, parameters, and seconds for :data:`SMALL_STEPS` steps and step time against the first row's."""
    try:
        shapes = [tuple(int(v) for v in item.split("x")) for item in text.split(",") if item]
    except ValueError:
        shapes = []
    if not shapes or any(len(sh) != 2 or sh[0] < 64 or sh[0] % 64 or sh[1] < 1 for sh in shapes):
        raise SystemExit(f"bench_dit_train: --small-sweep takes DIMxLAYERS,... with DIM a multiple of 64, got {text!r}")
    import configs

    batch, hw = (8, (4, 4)) if tiny else (32, (16, 16))  # tiny: a batch the test suite's 8 CPU devices split
    base = configs.get("sword:tiny" if tiny else "sword:small").model  # the rest of the world model as configured
    rows = []
    for dim, layers in shapes:
        cfg = dataclasses.replace(base, dim=dim, ffn_dim=4 * dim, num_heads=dim // 64, num_layers=layers,
                                  attention_impl=attention, scan_layers=False)
        row = run_config(f"small-{dim}x{layers}", cfg, batch, hw, peak_tflops=peak, iters=iters)
        rows.append(dict(row, s_per_small_run=row["dlb_step_s"] * SMALL_STEPS))
    for row in rows:
        row.update(params_vs_first=row["params"] / rows[0]["params"],
                   step_vs_first=row["dlb_step_s"] / rows[0]["dlb_step_s"])
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    parser = cli.ArgumentParser(description=__doc__)
    parser.add_argument("--tiny", action="store_true", help="CPU smoke run on tiny shapes")
    parser.add_argument("--layers", type=int, default=8, help="layers at 5B width (as many as fit one GPU)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--remat", default="dots")
    parser.add_argument("--sweep", default="", help="extra 5B-width settings to try first, LAYERSxBATCHxREMAT,...;"
                        " the fastest (by MFU) is then measured with and without DLB and recorded")
    parser.add_argument("--attention", default="auto")
    parser.add_argument("--iters", type=int, default=10)
    parser.add_argument("--no-record", action="store_true")
    parser.add_argument("--adam-mu", default="float32", choices=("float32", "bfloat16"),
                        help="Adam first-moment dtype of every 5B-width row (trainer.adam_mu_dtype)")
    parser.add_argument("--residual", default="float32", choices=("float32", "bfloat16"),
                        help="residual-stream dtype of every 5B-width row (model.residual_dtype)")
    parser.add_argument("--skip-small", action="store_true", help="no small-config row")
    parser.add_argument("--skip-wide", action="store_true", help="no 5B-width row (with --small-sweep)")
    parser.add_argument("--small-sweep", default="", metavar="DIMxLAYERS,...",
                        help="world models of these widths and depths at small's geometry, side by side (module "
                             "docstring)")
    parser.add_argument("--levers", action="store_true",
                        help="after the 5B-width row, the same setting with a bf16 residual stream, bf16 Adam first "
                             "moments and both, side by side (teacher-forcing step; recorded as dit_train_levers)")
    args = parser.parse_args(argv)

    if args.skip_wide and not args.small_sweep:
        raise SystemExit("bench_dit_train: --skip-wide leaves rows only with --small-sweep")
    peak = common.measured_matmul_tflops()
    copy_gbps = common.measured_copy_gbps()
    print(f"device {common.device_name()}: measured bf16 matmul {peak:.1f} TFLOP/s, copy {copy_gbps:.0f} GB/s")
    rows = []
    if args.small_sweep:
        swept = small_sweep(args.small_sweep, tiny=args.tiny, peak=peak, iters=2 if args.tiny else args.iters,
                            attention=args.attention)
        common.print_table(swept, ["config", "params", "batch", "dlb_step_s", "step_vs_first", "params_vs_first",
                                   "s_per_small_run", "mfu", "peak_mem_gb"])
        if not (args.no_record or args.tiny):
            common.merge_results({"dit_train_small_sweep": common.record(
                "dit_train_small_sweep", swept[-1]["step_vs_first"], None, rows=swept, steps_per_run=SMALL_STEPS,
                value_is=f"the last row's DLB step time over the first's ({swept[-1]['config']} against "
                         f"{swept[0]['config']}), at small's geometry: 16 x 16 latents, batch 32, one device")})
        if args.skip_wide:
            return swept
        rows += swept
    if args.tiny:
        tiny = DiTConfig(dim=64, ffn_dim=128, freq_dim=32, num_heads=4, num_layers=2, text_dim=16, text_len=8,
                         compute_dtype="float32")
        rows.append(run_config("tiny", tiny, 4, (4, 4), peak_tflops=peak, iters=2))
        if args.levers:
            rows += _lever_rows("tiny", tiny, 4, (4, 4), peak, 2)
    else:
        best = (args.layers, args.batch, args.remat)
        if args.sweep:
            trials = [best] + [(int(l), int(b), r) for l, b, r in (t.split("x") for t in args.sweep.split(","))]
            scored = []
            for layers, batch, remat in trials:
                cfg = DiTConfig(num_layers=layers, remat=remat, attention_impl=args.attention,
                                residual_dtype=args.residual)
                try:
                    row = run_config("sweep", cfg, batch, (16, 16), peak_tflops=peak, iters=args.iters, with_dlb=False,
                                     mu_dtype=args.adam_mu)
                except Exception as err:  # noqa: BLE001 - out of memory etc.: report and go on
                    print(f"sweep {layers}x{batch}x{remat}: failed ({type(err).__name__}: {str(err)[:120]})")
                    continue
                rows.append(row)
                scored.append((row["mfu"], (layers, batch, remat)))
            best = max(scored)[1] if scored else best
        layers, batch, remat = best
        wide = DiTConfig(num_layers=layers, remat=remat, attention_impl=args.attention, residual_dtype=args.residual)
        rows.insert(0, run_config("5b-width", wide, batch, (16, 16), peak_tflops=peak, iters=args.iters,
                                  mu_dtype=args.adam_mu))
        if not args.skip_small:
            small = DiTConfig(dim=512, ffn_dim=2048, num_heads=8, num_layers=8, text_dim=64, text_len=16,
                              attention_impl=args.attention)
            rows.append(run_config("small", small, 64, (8, 8), peak_tflops=peak, iters=args.iters))
        if args.levers:
            rows += _lever_rows("5b-width", wide, batch, (16, 16), peak, args.iters)
    common.print_table(rows, ["config", "layers", "batch", "remat", "attention", "residual", "adam_mu", "tf_step_s",
                              "dlb_step_s", "dlb_overhead", "model_tflops", "mfu", "peak_mem_gb"])
    if args.no_record or args.tiny:
        return rows
    wide = rows[0]
    extra = {"measured_peak_tflops": peak, "copy_gbps": copy_gbps, "rows": rows}
    levers = {r["config"]: r for r in rows if r["config"].startswith("5b-width+")}
    full_depth = wide["layers"] == DiTConfig().num_layers
    if levers:  # the 8-layer key keeps its meaning: full-depth levers get their own
        levers_key = "dit_train_levers_5b_full" if full_depth else "dit_train_levers"
        common.merge_results({levers_key: common.record(
            levers_key, max(r["mfu"] for r in levers.values()), 0.55 if full_depth else 0.65, baseline_mfu=wide["mfu"],
            mfu={name: r["mfu"] for name, r in levers.items()},
            peak_mem_gb={name: r["peak_mem_gb"] for name, r in levers.items()}, measured_peak_tflops=peak,
            value_is="best MFU of the 5B-width setting with the bf16 levers (teacher-forcing step); peak memory "
                     "is the process's running maximum")})
    if full_depth:  # the full TI2V-5B depth: its own key, the 8-layer figure stays
        common.merge_results({"dit_train_mfu_5b_full_h200": common.record(
            "dit_train_mfu_5b_full_h200", wide["mfu"], 0.55, **extra,
            note="full 30-layer TI2V-5B world model, one device; the key names the H200 the target is set on, "
                 "device says where it ran")})
        return rows
    common.merge_results({
        "dit_train_mfu_vs_measured_peak": common.record("dit_train_mfu_vs_measured_peak", wide["mfu"], 0.65, **extra),
        "dlb_overhead_ratio": common.record("dlb_overhead_ratio", wide["dlb_overhead"], 0.03,
                                            tf_step_s=wide["tf_step_s"], dlb_step_s=wide["dlb_step_s"]),
    })
    return rows


if __name__ == "__main__":
    cli.run(main)
