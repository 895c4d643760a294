"""DLB overhead: the DLB train step vs the teacher-forcing step, and the latent cache's size.

Both steps use the same model, batch and mesh; they are compiled in this process and timed in
alternating rounds (side by side), so ``dlb_overhead_ratio = t_DLB / t_TF - 1`` (target <= 0.03).
``latent_cache_gb_paper_dataset`` is the cache for the paper's dataset (1500 episodes x 128 latent
frames x 16x16x48, bfloat16 storage), computed by the same function the trainer prints
(:func:`sword_jax.dlb.cache.cache_bytes_per_device`), summed over devices (target <= 5 GB).

  python -m benchmarks.bench_dlb                 # GPU: sword:small model, batch from the config
  python -m benchmarks.bench_dlb --tiny          # CPU check: tiny model, a few iterations
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax
from flax import nnx

import configs
from benchmarks import common
from sword_jax import sharding as shd
from sword_jax.dit.world_model import WorldModel
from sword_jax.dlb import cache as dlb_cache
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import data, train_state, train_step

PAPER_DATASET = (1500, 128, 16, 16, 48)


def build_step(cfg, cache_cfg: CacheConfig, dataset: data.LatentDataset, mesh):
    graphdef, state, shardings = train_state.create_train_state(
        lambda: WorldModel(cfg.model, rngs=nnx.Rngs(cfg.seed)), cfg.trainer, cache_cfg, dataset.shape, mesh)
    sampler = data.SegmentSampler(dataset.shape[0], dataset.shape[1], 1, 2, cfg.data.batch_size, seed=cfg.seed)
    loader = data.SegmentLoader(dataset, sampler, 1, 2, mesh)
    fn = train_step.make_train_step(graphdef, flow_cfg=cfg.flow, trainer_cfg=cfg.trainer, cache_cfg=cache_cfg,
                                    num_context=1, num_episodes=dataset.shape[0])
    return train_step.compile_train_step(fn, shardings, loader.shardings, mesh), state, loader


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="CPU check with the tiny config")
    parser.add_argument("--config", default=None, help="experiment config (default sword:small, tiny with --tiny)")
    parser.add_argument("--rounds", type=int, default=None, help="alternating timing rounds")
    parser.add_argument("--iters", type=int, default=None, help="steps per round and variant")
    parser.add_argument("--no-write", action="store_true", help="do not merge into benchmarks/results/latest.json")
    parser.add_argument("--write", action="store_true", help="merge results even with --tiny")
    args = parser.parse_args()
    cfg = configs.get(args.config or ("sword:tiny" if args.tiny else "sword:small"))
    rounds = args.rounds or (3 if args.tiny else 10)
    iters = args.iters or (3 if args.tiny else 20)
    mesh = shd.make_mesh(cfg.mesh)
    side = cfg.data.image_size // 16
    num_latents = 1 + (cfg.data.episode_frames - 1) // 4
    dataset = data.synthetic_latent_dataset(cfg.data.num_episodes, num_latents, side, side, cfg.vae.z_dim,
                                            seed=cfg.seed, action_dim=cfg.model.action_dim)
    # Read probability fixed mid-way so reads really happen (0.5 from the first step).
    dlb_cfg = dataclasses.replace(cfg.cache, enabled=True, read_prob_start=0.5, read_prob_end=0.5)
    variants = {
        "teacher_forcing": build_step(cfg, CacheConfig(enabled=False), dataset, mesh),
        "dlb": build_step(cfg, dlb_cfg, dataset, mesh),
    }
    key = jax.random.key(0)
    states = {name: v[1] for name, v in variants.items()}
    batches = {name: [v[2].next() for _ in range(4)] for name, v in variants.items()}
    for name, (step, _, _) in variants.items():  # compile + warm up (fills part of the cache)
        for i in range(3):
            states[name], metrics = step(states[name], batches[name][i % 4], key)
        common.block(metrics)
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, (step, _, _) in variants.items():
            start = time.perf_counter()
            for i in range(iters):
                states[name], metrics = step(states[name], batches[name][i % 4], key)
            common.block((states[name].step, metrics))
            samples[name].append((time.perf_counter() - start) / iters)
    t_tf = statistics.median(samples["teacher_forcing"])
    t_dlb = statistics.median(samples["dlb"])
    ratio = t_dlb / t_tf - 1.0
    paper_bytes_per_device = dlb_cache.cache_bytes_per_device(CacheConfig(dtype="bfloat16"), PAPER_DATASET, mesh)
    paper_total_gb = paper_bytes_per_device * dlb_cache.episode_shards(mesh) / 1e9
    rows = [
        {"metric": "teacher-forcing step ms", "value": t_tf * 1e3},
        {"metric": "DLB step ms", "value": t_dlb * 1e3},
        {"metric": "dlb_overhead_ratio", "value": ratio, "target": "<= 0.03"},
        {"metric": "latent_cache_gb_paper_dataset (bf16, total)", "value": paper_total_gb, "target": "<= 5"},
        {"metric": "latent cache GB per device (this mesh)", "value": paper_bytes_per_device / 1e9},
    ]
    print(f"config {cfg.name}, batch {cfg.data.batch_size}, mesh {dict(mesh.shape)}, device {common.device_name()}, "
          f"{rounds} rounds x {iters} steps")
    common.print_table(rows, ["metric", "value", "target"])
    if not args.no_write and (args.write or not args.tiny):
        path = common.merge_results({
            "dlb_overhead_ratio": common.record(
                "dlb_overhead_ratio", ratio, 0.03, config=cfg.name, batch=cfg.data.batch_size,
                tf_step_ms=t_tf * 1e3, dlb_step_ms=t_dlb * 1e3),
            "latent_cache_gb_paper_dataset": common.record(
                "latent_cache_gb_paper_dataset", paper_total_gb, 5.0, dtype="bfloat16",
                dataset=list(PAPER_DATASET), per_device_gb=paper_bytes_per_device / 1e9),
        })
        print(f"merged into {path}")


if __name__ == "__main__":
    main()
