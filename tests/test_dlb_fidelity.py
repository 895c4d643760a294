"""DLB faithful to inference: the write source, the cache-vs-inference distance, the read end value."""

import json

import jax
import numpy as np
import pytest

import configs
from sword_jax import checkpoint
from sword_jax.dlb import schedule
from sword_jax.world_model import cache_fidelity as fidelity
from sword_jax.dlb.config import CacheConfig
from sword_jax.rng import stream_key
from sword_jax.world_model import sampler, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig
from tests.support.world_model import build, single_device_mesh

# Teacher-forced context (read 0) and no context noise: the conditioning is the batch's latents.
PLAIN = dict(read_prob_start=0.0, read_prob_end=0.0, dtype="float32")
FLOW = FlowConfig(sample_steps=3)


def _slots(batch, values, scope_len):
    """{(episode, frame): value} of a batch's writes, the last sample in batch order winning."""
    out = {}
    for i, (episode, start) in enumerate(zip(np.asarray(batch["episode"]), np.asarray(batch["start"]))):
        for j in range(scope_len):
            out[(int(episode), int(start) + 1 + j)] = values[i, j]
    return out


def test_latent_distance_values():
    reference = jax.random.normal(jax.random.key(1), (3, 2, 2, 2, 4))
    same = fidelity.latent_distance(reference, reference)
    np.testing.assert_allclose([same["rel_mse"], same["cosine"], same["norm_ratio"]], [0.0, 1.0, 1.0], atol=1e-6)
    half = fidelity.latent_distance(0.5 * reference, reference)
    np.testing.assert_allclose([half["rel_mse"], half["cosine"], half["norm_ratio"]], [0.25, 1.0, 0.5], rtol=1e-5)
    opposite = fidelity.latent_distance(-reference, reference)
    np.testing.assert_allclose([opposite["rel_mse"], opposite["cosine"]], [4.0, -1.0], rtol=1e-5)


def test_sampler_write_source_writes_what_the_sampler_returns(key):
    cfg = CacheConfig(write_source="sampler", write_sample_steps=2, log_inference_distance=False, **PLAIN)
    graphdef, state, _, step, loader = build(mesh=single_device_mesh(), cache_cfg=cfg, flow_cfg=FLOW)
    params, buffers = jax.device_get((state.params, state.buffers))  # the state is donated
    batch = loader.next()
    state, _ = step(state, batch, key)
    direct = sampler.sample(sampler.model_fn_from_state(graphdef, (params, buffers)), batch["latents"][:, :2],
                            batch["actions"], key=train_step.step_keys(key, 0)["write"], num_future=2, cfg=FLOW,
                            num_steps=2)
    cache = jax.device_get(state.cache)
    expected = _slots(batch, np.asarray(direct), 2)
    for (episode, frame), value in expected.items():
        assert cache.filled[episode, frame]
        np.testing.assert_allclose(cache.latents[episode, frame], value, rtol=1e-5, atol=1e-5)
    assert int(cache.filled.sum()) == len(expected)


def test_cache_vs_inference_distance_computed_on_log_steps_and_logged(key, tmp_path):
    # The sampler source at 2 steps makes the written latents reproducible outside the step.
    cfg = CacheConfig(write_source="sampler", write_sample_steps=2, **PLAIN)
    trainer_cfg = TrainerConfig(learning_rate=1e-2, warmup_steps=0, steps=3, log_every=2)
    graphdef, state, _, step, loader = build(mesh=single_device_mesh(), cache_cfg=cfg, flow_cfg=FLOW,
                                             trainer_cfg=trainer_cfg)
    with open(tmp_path / "log.txt", "w") as stream:
        logger = checkpoint.MetricLogger(3, 2, jsonl_path=str(tmp_path / "metrics.jsonl"), stream=stream)
        names = [f"cache_vs_inference_{n}" for n in fidelity.DISTANCE_METRICS]
        for done in (1, 2, 3):
            model_fn = sampler.model_fn_from_state(graphdef, jax.device_get((state.params, state.buffers)))
            batch = loader.next()
            state, metrics = step(state, batch, key)
            logger.push(done, metrics)
            if done == 1:  # not a log step: not measured
                assert all(np.isnan(metrics[n]) for n in names)
                continue
            # The metric is the distance between what was written and the inference sampler's output.
            cond, actions, write_key = batch["latents"][:, :2], batch["actions"], train_step.step_keys(key, done - 1)["write"]
            written = sampler.sample(model_fn, cond, actions, key=write_key, num_future=2, cfg=FLOW, num_steps=2)
            reference = fidelity.inference_context(FLOW, model_fn, cond, actions, key=stream_key(write_key, train_step.INFERENCE_STREAM),
                                                   num_future=2)
            expected = fidelity.latent_distance(written, reference)
            for name in fidelity.DISTANCE_METRICS:
                np.testing.assert_allclose(metrics[f"cache_vs_inference_{name}"], expected[name], rtol=1e-4)
            assert float(expected["rel_mse"]) > 1e-3  # a 2-step write is not the 3-step inference sample
        logger.close()
    rows = [json.loads(line) for line in open(tmp_path / "metrics.jsonl")]
    assert [r["step"] for r in rows] == [2, 3]
    assert all(np.isfinite(r[n]) for r in rows for n in names)


def test_read_prob_end_is_honoured(key):
    assert CacheConfig().read_prob_end == 1.0  # the paper: a transition to prediction-based conditioning
    for sched in ("linear", "warmup_cosine"):
        cfg = CacheConfig(schedule=sched, read_prob_end=0.3, schedule_steps=4, warmup_steps=1)
        np.testing.assert_allclose(schedule.read_prob(cfg, 100), 0.3, rtol=1e-6)
        np.testing.assert_allclose(schedule.read_prob(CacheConfig(schedule=sched, schedule_steps=4), 100), 1.0)
    cfg = CacheConfig(read_prob_end=0.3, schedule_steps=2, log_inference_distance=False, dtype="float32")
    _, state, _, step, loader = build(mesh=single_device_mesh(), cache_cfg=cfg)
    for _ in range(4):
        state, metrics = step(state, loader.next(), key)
    np.testing.assert_allclose(metrics["read_prob"], 0.3, rtol=1e-6)
    # Every cache_ablation design carries the paper's end value and takes an override.
    cfg, _ = configs.from_argv(["--config", "cache_ablation:warmup_cosine-ema-single", "--cache.read_prob_end=0.5",
                                "--cache.write_source=sampler", "--cache.write_sample_steps=3"])
    assert (cfg.cache.schedule, cfg.cache.read_prob_end, cfg.cache.write_source, cfg.cache.write_sample_steps) == (
        "warmup_cosine", 0.5, "sampler", 3)
    assert configs.get("cache_ablation:small-linear-direct-all").cache.read_prob_end == 1.0
    with pytest.raises(ValueError, match="write_source"):
        CacheConfig(write_source="sample").validate()
