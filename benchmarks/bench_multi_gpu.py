"""Multi-GPU: the DLB train step at full TI2V-5B size (FSDP + data), and 1 -> N GPU scaling.

    python -m benchmarks.bench_multi_gpu                    # on a machine with >= 2 GPUs
    python -m benchmarks.bench_multi_gpu --tiny             # CPU smoke run on fake devices

Part 1 builds the 30-layer, dim-3072 world model with AdamW state born sharded over an
``fsdp`` axis spanning every device, the latent cache sharded over episodes, and times the DLB
step (step time, MFU against the per-GPU bf16 peak measured in the same run, memory per device).
Part 2 times the small config with a fixed per-device batch on 1 and on all devices (pure data
parallel) and reports the scaling efficiency ``t_1 / t_N`` (1.0 = linear).
"""

from __future__ import annotations


import jax
import numpy as np
from flax import nnx

from benchmarks import common
from benchmarks.bench_dit_train import forward_flops
from sword_jax import cli
from sword_jax import sharding as shd
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dit.config import DiTConfig
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import train_state, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig


def time_dlb_step(model_cfg: DiTConfig, mesh, batch: int, hw: tuple[int, int], iters: int,
                  num_episodes: int = 64, num_latents: int = 32) -> dict:
    trainer_cfg = TrainerConfig(steps=1000, warmup_steps=10)
    cache_cfg = CacheConfig(enabled=True, read_prob_start=0.5, read_prob_end=0.5)
    dataset_shape = (num_episodes, num_latents, hw[0], hw[1], model_cfg.in_dim)
    graphdef, state, shardings = train_state.create_train_state(
        lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0)), trainer_cfg, cache_cfg, dataset_shape, mesh)
    rng = np.random.default_rng(0)
    host = {"latents": rng.standard_normal((batch, 4, hw[0], hw[1], model_cfg.in_dim), dtype=np.float32),
            "actions": rng.uniform(-1, 1, (batch, 13, model_cfg.action_dim)).astype(np.float32),
            "episode": rng.integers(0, num_episodes, batch).astype(np.int32),
            "start": rng.integers(1, num_latents - 2, batch).astype(np.int32)}
    data_shardings = {k: shd.batch_sharding(mesh, v.ndim) for k, v in host.items()}
    data = {k: shd.put(v, data_shardings[k]) for k, v in host.items()}
    fn = train_step.make_train_step(graphdef, flow_cfg=FlowConfig(), trainer_cfg=trainer_cfg, cache_cfg=cache_cfg,
                                    num_context=1, num_episodes=num_episodes)
    step = train_step.compile_train_step(fn, shardings, data_shardings, mesh)
    key = shd.put(jax.random.key(0), shd.replicated(mesh))
    holder = {"state": state}

    def one():
        holder["state"], metrics = step(holder["state"], data, key)
        return metrics["loss"]

    seconds = common.time_fn(one, warmup=2, iters=iters)["median_s"]
    loss = float(one())
    if not np.isfinite(loss):
        raise RuntimeError(f"non-finite loss {loss}")
    params = sum(x.size for x in jax.tree.leaves(holder["state"].params))
    memory = [d.memory_stats().get("peak_bytes_in_use", 0) / 1e9 if d.memory_stats() else None for d in mesh.devices.flat]
    return {"step_s": seconds, "params": params, "loss": loss, "peak_gb_per_device": memory,
            "flops": 3 * forward_flops(model_cfg, batch, 4, hw, 13)}


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__)
    parser.add_argument("--tiny", action="store_true")
    parser.add_argument("--batch-per-device", type=int, default=8)
    parser.add_argument("--layers", type=int, default=30)
    parser.add_argument("--iters", type=int, default=5)
    args = parser.parse_args(argv)
    devices = jax.devices()
    n = len(devices)
    peak = common.measured_matmul_tflops()
    print(f"{n} x {common.device_name()}: measured bf16 matmul {peak:.1f} TFLOP/s per device")
    if args.tiny:
        full = DiTConfig(dim=64, ffn_dim=128, num_heads=4, num_layers=2, text_dim=16, text_len=8, compute_dtype="float32")
        small = full
        hw = (4, 4)
    else:
        full = DiTConfig(num_layers=args.layers, remat="full")
        small = DiTConfig(dim=512, ffn_dim=2048, num_heads=8, num_layers=8, text_dim=64, text_len=16)
        hw = (16, 16)
    fsdp_mesh = shd.make_mesh(shd.MeshConfig(data=1, fsdp=-1))
    big = time_dlb_step(full, fsdp_mesh, args.batch_per_device * n, hw, args.iters)
    big_mfu = big["flops"] / big["step_s"] / 1e12 / (peak * n)
    print(f"5B DLB step over {n} devices (fsdp={n}): {big['params'] / 1e9:.3f}B params, {big['step_s'] * 1e3:.1f} ms, "
          f"MFU {big_mfu:.3f}, peak GB per device {big['peak_gb_per_device']}")

    small_hw = (8, 8) if not args.tiny else hw
    per_device = 32 if not args.tiny else 2
    one = time_dlb_step(small, shd.make_mesh(shd.MeshConfig(data=1), devices=devices[:1]), per_device, small_hw, args.iters)
    many = time_dlb_step(small, shd.make_mesh(shd.MeshConfig(data=-1)), per_device * n, small_hw, args.iters)
    efficiency = one["step_s"] / many["step_s"]
    print(f"small config, {per_device} per device: 1 device {one['step_s'] * 1e3:.2f} ms, {n} devices "
          f"{many['step_s'] * 1e3:.2f} ms -> scaling efficiency {efficiency:.3f} (1.0 = linear)")
    if args.tiny:
        return
    common.merge_results({
        "multi_gpu_5b_dlb_step_s": common.record("multi_gpu_5b_dlb_step_s", big["step_s"], None, mfu=big_mfu,
                                                 params=big["params"], devices=n, batch=args.batch_per_device * n,
                                                 layers=full.num_layers, peak_gb_per_device=big["peak_gb_per_device"]),
        "multi_gpu_scaling_efficiency_small": common.record(
            "multi_gpu_scaling_efficiency_small", efficiency, 0.9, devices=n, per_device_batch=per_device,
            one_device_step_s=one["step_s"], all_devices_step_s=many["step_s"]),
    })


if __name__ == "__main__":
    cli.run(main)
