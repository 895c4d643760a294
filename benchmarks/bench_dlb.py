"""DLB overhead: the DLB train step vs the teacher-forcing step, and the latent cache's size.

Both steps use the same model, batch and mesh; they are compiled in this process and timed in
alternating rounds (side by side), so ``dlb_overhead_ratio = t_DLB / t_TF - 1`` (target <= 0.03).
``latent_cache_gb_paper_dataset`` is the cache for the paper's dataset (1500 episodes x 128 latent
frames x 16x16x48, bfloat16 storage), computed by the same function the trainer prints
(:func:`sword_jax.dlb.cache.cache_bytes_per_device`), summed over devices (target <= 5 GB).

  python -m benchmarks.bench_dlb                 # GPU: sword:small model, batch from the config
  python -m benchmarks.bench_dlb --tiny          # CPU check: tiny model, a few iterations

``--write-sources`` compares the cache's write sources (``cache.write_source``): it trains the
config's model for ``--train-steps`` DLB steps (``one_step`` writes) on the config's latents
(``--data.path`` style ``--latents``, else synthetic), then, on ``--eval-batches`` fresh batches
and the same params, measures the distance (:func:`sword_jax.world_model.cache_fidelity.latent_distance`)
between what each source would write and what the inference sampler (``flow.sample_steps``,
fresh noise) produces for the same conditioning: ``one_step`` at the training noise levels,
``sampler`` at each of ``--sampler-steps``, and ``floor`` (a second inference sample: the
sampler's own spread). It also times the train step per source (distance metric off) against
teacher forcing, and the extra cost of one log step's distance metric. Results go under
``dlb_write_sources`` (overheads) and ``dlb_cache_vs_inference`` (distances).

  python -m benchmarks.bench_dlb --write-sources                      # GPU: sword:small
  python -m benchmarks.bench_dlb --write-sources --tiny --train-steps 200
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

import configs
from benchmarks import common
from sword_jax import cli
from sword_jax import sharding as shd
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dlb import cache as dlb_cache
from sword_jax.world_model import cache_fidelity as fidelity
from sword_jax.dlb.config import CacheConfig
from sword_jax.rng import stream_key, stream_seed
from sword_jax.world_model import data, flow, sampler, train_state, train_step

PAPER_DATASET = (1500, 128, 16, 16, 48)


def build_step(cfg, cache_cfg: CacheConfig, dataset: data.LatentDataset, mesh, *, trainer_cfg=None, seed=None,
               with_graphdef=False):
    trainer_cfg = trainer_cfg or cfg.trainer
    graphdef, state, shardings = train_state.create_train_state(
        lambda: WorldModel(cfg.model, rngs=nnx.Rngs(cfg.seed)), trainer_cfg, cache_cfg, dataset.shape, mesh)
    segments = data.SegmentSampler(dataset.shape[0], dataset.shape[1], 1, 2, cfg.data.batch_size,
                                   seed=cfg.seed if seed is None else seed)
    loader = data.SegmentLoader(dataset, segments, 1, 2, mesh)
    fn = train_step.make_train_step(graphdef, flow_cfg=cfg.flow, trainer_cfg=trainer_cfg, cache_cfg=cache_cfg,
                                    num_context=1, num_episodes=dataset.shape[0])
    step = train_step.compile_train_step(fn, shardings, loader.shardings, mesh)
    return (step, state, loader, graphdef) if with_graphdef else (step, state, loader)


def time_alternating(variants: dict, rounds: int, iters: int) -> dict[str, float]:
    """Median seconds per step of each ``name -> (step, state, loader)``, timed in alternating rounds."""
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
    return {name: statistics.median(v) for name, v in samples.items()}


def make_fidelity_eval(cfg, graphdef, sampler_steps: tuple[int, ...]):
    """Jitted ``(params, buffers, batch, key) -> {source: distances}`` on one batch, same params for all."""
    flow_cfg, num_cond = cfg.flow, 2
    sources = {"one_step": dataclasses.replace(cfg.cache, write_source="one_step")}
    sources.update({f"sampler_{k}": dataclasses.replace(cfg.cache, write_source="sampler", write_sample_steps=k)
                    for k in sampler_steps})

    @jax.jit
    def evaluate(params, buffers, batch, key):
        keys = train_step.step_keys(key, 0)
        model_fn = sampler.model_fn_from_state(graphdef, (params, buffers))
        latents, actions = batch["latents"].astype(jnp.float32), batch["actions"].astype(jnp.float32)
        cond, future = latents[:, :num_cond], latents[:, num_cond:]
        # The training forward pass at training noise levels, as the step makes it.
        sigma = flow.sample_sigmas(latents.shape[0], flow_cfg, key=keys["sigma"])
        noise = jax.random.normal(keys["noise"], future.shape, jnp.float32)
        model_input, timesteps = flow.noisy_segment(latents, noise, sigma, num_cond, flow_cfg)
        prediction = model_fn(model_input, timesteps, actions)
        reference = fidelity.inference_context(flow_cfg, model_fn, cond, actions, key=stream_key(keys["write"], train_step.INFERENCE_STREAM),
                                               num_future=future.shape[1])
        out = {}
        for name, cache_cfg in sources.items():
            written = fidelity.write_latents(cache_cfg, flow_cfg, model_fn, cond, actions, key=keys["write"],
                                             prediction_future=prediction[:, num_cond:],
                                             noisy_future=model_input[:, num_cond:], sigma=sigma)
            out[name] = fidelity.latent_distance(fidelity.stored(written, cache_cfg), reference)
        floor = fidelity.inference_context(flow_cfg, model_fn, cond, actions, key=stream_key(keys["write"], "dlb/inference_floor"),
                                           num_future=future.shape[1])
        out["floor"] = fidelity.latent_distance(floor, reference)
        out["sigma_median"] = {"value": jnp.median(sigma)}
        return out

    return evaluate


def write_sources(args, cfg, mesh) -> None:
    """``--write-sources``: cache-vs-inference distance and step time of each write source."""
    side = cfg.data.image_size // 16
    num_latents = 1 + (cfg.data.episode_frames - 1) // 4
    if args.latents:
        dataset = data.load_latent_dataset(args.latents)
    else:
        dataset = data.synthetic_latent_dataset(cfg.data.num_episodes, num_latents, side, side, cfg.vae.z_dim,
                                                seed=cfg.seed, action_dim=cfg.model.action_dim)
    sampler_steps = tuple(int(k) for k in args.sampler_steps.split(","))
    train_steps = args.train_steps or (200 if args.tiny else 1000)
    # 1. Train with the default (one_step) source, the schedule completing within the run.
    train_cache = dataclasses.replace(cfg.cache, enabled=True, write_source="one_step", schedule_steps=train_steps,
                                      log_inference_distance=True)
    trainer_cfg = dataclasses.replace(cfg.trainer, steps=train_steps, log_every=max(train_steps // 4, 1))
    step, state, loader, graphdef = build_step(cfg, train_cache, dataset, mesh, trainer_cfg=trainer_cfg,
                                               with_graphdef=True)
    root = jax.random.key(cfg.seed)
    start = time.perf_counter()
    curve = []
    for done in range(1, train_steps + 1):
        state, metrics = step(state, loader.next(), root)
        if done % trainer_cfg.log_every == 0:
            row = {k: float(np.asarray(v)) for k, v in jax.device_get(metrics).items()}
            curve.append({"step": done, "loss": row["loss"], "read_prob": row["read_prob"],
                          "rel_mse": row["cache_vs_inference_rel_mse"], "norm_ratio": row["cache_vs_inference_norm_ratio"]})
            print(f"  train {done}/{train_steps}: " + " ".join(f"{k}={v:.4g}" for k, v in curve[-1].items() if k != "step"))
    train_s = time.perf_counter() - start
    # 2. Distances on fresh batches, same params for every source.
    evaluate = make_fidelity_eval(cfg, graphdef, sampler_steps)
    eval_loader = data.SegmentLoader(dataset, data.SegmentSampler(dataset.shape[0], dataset.shape[1], 1, 2,
                                                                  cfg.data.batch_size,
                                                                  seed=stream_seed(cfg.seed, "bench_dlb/eval_segments")),
                                        1, 2, mesh)
    params, buffers = (state.ema_params if state.ema_params is not None else state.params), state.buffers
    totals: dict[str, dict[str, list[float]]] = {}
    eval_key = stream_key(jax.random.key(cfg.seed), "bench_dlb/eval_noise")
    for i in range(args.eval_batches):
        out = jax.device_get(evaluate(params, buffers, eval_loader.next(), jax.random.fold_in(eval_key, i)))
        for name, values in out.items():
            for metric, value in values.items():
                totals.setdefault(name, {}).setdefault(metric, []).append(float(value))
    distances = {name: {m: float(np.mean(v)) for m, v in values.items()} for name, values in totals.items()}
    # 3. Step time per source (distance metric off), and one log step's distance metric.
    off = dataclasses.replace(cfg.cache, enabled=True, read_prob_start=0.5, read_prob_end=0.5,
                              log_inference_distance=False)
    every = dataclasses.replace(cfg.trainer, log_every=1)
    variants = {"teacher_forcing": build_step(cfg, CacheConfig(enabled=False), dataset, mesh),
                "one_step": build_step(cfg, off, dataset, mesh),
                "one_step_distance_every_step": build_step(cfg, dataclasses.replace(off, log_inference_distance=True),
                                                           dataset, mesh, trainer_cfg=every)}
    for k in sampler_steps:
        variants[f"sampler_{k}"] = build_step(cfg, dataclasses.replace(off, write_source="sampler", write_sample_steps=k),
                                              dataset, mesh)
    rounds, iters = args.rounds or (3 if args.tiny else 10), args.iters or (3 if args.tiny else 20)
    times = time_alternating(variants, rounds, iters)
    t_tf, t_one = times["teacher_forcing"], times["one_step"]
    rows = [{"source": name, "step_ms": t * 1e3, "vs_teacher_forcing": t / t_tf - 1.0, "vs_one_step": t / t_one - 1.0,
             **{m: distances.get(name, {}).get(m) for m in fidelity.DISTANCE_METRICS}}
            for name, t in times.items()]
    rows.append({"source": "floor", **distances["floor"]})
    print(f"config {cfg.name}, batch {cfg.data.batch_size}, mesh {dict(mesh.shape)}, device {common.device_name()}, "
          f"{train_steps} train steps ({train_s:.0f} s), {args.eval_batches} eval batches, inference "
          f"{cfg.flow.sample_steps} steps, median training sigma {distances['sigma_median']['value']:.3f}")
    common.print_table(rows, ["source", "step_ms", "vs_teacher_forcing", "vs_one_step", *fidelity.DISTANCE_METRICS])
    if not args.no_write and (args.write or not args.tiny):
        inference_k = f"sampler_{cfg.flow.sample_steps}"
        path = common.merge_results({
            "dlb_write_sources": common.record(
                "dlb_write_sources", times[inference_k] / t_one - 1.0 if inference_k in times else None, None,
                config=cfg.name, batch=cfg.data.batch_size, step_ms={n: t * 1e3 for n, t in times.items()},
                overhead_vs_one_step={n: t / t_one - 1.0 for n, t in times.items()},
                value_is=f"step-time overhead of write_source=sampler at {cfg.flow.sample_steps} steps vs one_step"),
            "dlb_cache_vs_inference": common.record(
                "dlb_cache_vs_inference", distances["one_step"]["rel_mse"], None, config=cfg.name,
                train_steps=train_steps, eval_batches=args.eval_batches, latents=args.latents or "synthetic",
                distances=distances, training_curve=curve,
                value_is="rel_mse of the one_step write vs an inference sample (see distances for all sources)"),
        })
        print(f"merged into {path}")


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="CPU check with the tiny config")
    parser.add_argument("--config", default=None, help="experiment config (default sword:small, tiny with --tiny); "
                        "dotted overrides such as --data.batch_size=8 apply to it")
    parser.add_argument("--rounds", type=int, default=None, help="alternating timing rounds")
    parser.add_argument("--iters", type=int, default=None, help="steps per round and variant")
    parser.add_argument("--no-write", action="store_true", help="do not merge into benchmarks/results/latest.json")
    parser.add_argument("--write", action="store_true", help="merge results even with --tiny")
    parser.add_argument("--write-sources", action="store_true",
                        help="compare cache write sources: cache-vs-inference distance and step time")
    parser.add_argument("--train-steps", type=int, default=None, help="--write-sources: DLB steps before measuring")
    parser.add_argument("--sampler-steps", default="1,2,5", help="--write-sources: sampler source step counts")
    parser.add_argument("--eval-batches", type=int, default=4, help="--write-sources: batches the distances average")
    parser.add_argument("--latents", default=None, help="--write-sources: latent dataset (.npz/.h5); default synthetic")
    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, rest = configs.from_argv(argv, default="sword:tiny" if "--tiny" in argv else "sword:small")
    args = parser.parse_args(rest)  # --config and dotted overrides (--model.dim=64) went to the config
    if args.write_sources:
        write_sources(args, cfg, shd.make_mesh(cfg.mesh))
        return
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
    times = time_alternating(variants, rounds, iters)
    t_tf, t_dlb = times["teacher_forcing"], times["dlb"]
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
    cli.run(main)
