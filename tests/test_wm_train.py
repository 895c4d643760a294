"""World-model training: loss falls with the real DiT, non-finite guard, EMA, hot step compiles once."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax import sharding as shd
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import data, flow, train_state, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig
from tests.support.world_model import build, full_mesh, single_device_mesh


def _eval_loss_fn(graphdef, buffers, batch, *, key):
    """Flow-matching loss on a fixed batch with fixed noise levels and noise (deterministic)."""
    latents = batch["latents"]
    sigma = jnp.linspace(0.05, 0.95, latents.shape[0], dtype=jnp.float32)
    noise = jax.random.normal(key, latents[:, 2:].shape, jnp.float32)
    model_input, timesteps = flow.noisy_segment(latents, noise, sigma, 2, FlowConfig(shift=1.0))

    def loss(params):
        prediction = nnx.merge(graphdef, params, buffers)(model_input, timesteps, batch["actions"])
        return flow.flow_loss(prediction, latents, noise, 2, FlowConfig(shift=1.0))

    return jax.jit(loss)


@pytest.mark.slow
def test_loss_falls_on_action_dependent_latents_with_real_dit(key):
    cfg = configs.get("sword:tiny")
    model_cfg = dataclasses.replace(cfg.model, num_layers=1)
    trainer_cfg = TrainerConfig(learning_rate=1e-2, warmup_steps=3, grad_clip=1.0)
    cache_cfg = CacheConfig(enabled=False)
    dataset = data.synthetic_latent_dataset(8, 6, 2, 2, 48, seed=0)
    mesh = single_device_mesh()
    graphdef, state, shardings = train_state.create_train_state(
        lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0)), trainer_cfg, cache_cfg, dataset.shape, mesh)
    loader = data.SegmentLoader(dataset, data.SegmentSampler(8, 6, 1, 2, 8, seed=0), 1, 2, mesh)
    eval_batch = dataset.segment(*data.SegmentSampler(8, 6, 1, 2, 24, seed=1).next_indices(), 1, 2)
    eval_loss = _eval_loss_fn(graphdef, state.buffers, eval_batch, key=jax.random.key(7))
    before = float(eval_loss(state.params))
    fn = train_step.make_train_step(graphdef, flow_cfg=FlowConfig(shift=1.0), trainer_cfg=trainer_cfg,
                                    cache_cfg=cache_cfg, num_context=1)
    step = train_step.compile_train_step(chex.assert_max_traces(fn, n=1), shardings, loader.shardings, mesh)
    for _ in range(50):
        state, metrics = step(state, loader.next(), key)
    chex.clear_trace_counter()
    after = float(eval_loss(state.params))
    assert np.isfinite(after) and after < 0.85 * before, (before, after)
    assert int(state.step) == 50


def test_nonfinite_batch_skips_update_and_records_step(key):
    mesh = single_device_mesh()
    _, state, _, step, loader = build(mesh=mesh, cache_cfg=CacheConfig(dtype="float32"))
    state, _ = step(state, loader.next(), key)
    before = jax.device_get((state.params, state.opt_state, state.cache))
    batch = loader.next()
    batch = {**batch, "latents": batch["latents"].at[0, 2].set(jnp.nan)}
    state, metrics = step(state, batch, key)
    assert int(metrics["nonfinite"]) == 1 and int(state.first_nonfinite_step) == 1
    for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(jax.device_get((state.params, state.opt_state, state.cache)))):
        np.testing.assert_array_equal(a, b)
    state, metrics = step(state, loader.next(), key)
    assert int(metrics["nonfinite"]) == 0 and int(state.first_nonfinite_step) == 1


def test_ema_params_follow_the_decay(key):
    trainer_cfg = TrainerConfig(learning_rate=1e-2, warmup_steps=0, ema_decay=0.9)
    _, state, _, step, loader = build(mesh=single_device_mesh(), cache_cfg=CacheConfig(enabled=False),
                                      trainer_cfg=trainer_cfg)
    ema0 = jax.device_get(state.ema_params)
    state, _ = step(state, loader.next(), key)
    params1, ema1 = jax.device_get((state.params, state.ema_params))
    chex.assert_trees_all_close(ema1, jax.tree.map(lambda e, p: 0.9 * e + 0.1 * p, ema0, params1), rtol=1e-6)
    assert not np.allclose(params1["frame_mix"], ema0["frame_mix"])


def test_action_dropout_trains_the_null_action_branch_and_keeps_its_predictions_out_of_the_cache(key):
    """flow.action_dropout: the dropped segments are trained on the null (all-zero) actions that guidance
    contrasts against, and write nothing into the DLB cache. A step that drops every segment is the step of
    a batch whose actions are zeros, with the same keys; one that drops some writes only the others' slots."""
    mesh = single_device_mesh()
    cache_cfg = CacheConfig(dtype="float32", scope="single")
    _, state0, _, plain, loader = build(mesh=mesh, cache_cfg=cache_cfg)
    batch = loader.next()
    zeroed = {**batch, "actions": jnp.zeros_like(batch["actions"])}
    ref_state, ref = plain(jax.tree.map(jnp.copy, state0), zeroed, key)
    _, state1, _, nearly_all, _ = build(mesh=mesh, cache_cfg=cache_cfg, flow_cfg=FlowConfig(action_dropout=0.999))
    out_state, out = nearly_all(state1, batch, key)
    assert float(out["action_dropped"]) == 1.0
    assert float(out["loss"]) == float(ref["loss"])  # the same keys draw the same noise: only the actions differ
    assert not np.any(np.asarray(out_state.cache.filled)) and np.any(np.asarray(ref_state.cache.filled))
    _, state2, _, half, _ = build(mesh=mesh, cache_cfg=cache_cfg, flow_cfg=FlowConfig(action_dropout=0.5))
    half_state, half_out = half(state2, batch, key)
    dropped = float(half_out["action_dropped"])
    assert 0.0 < dropped < 1.0
    filled = int(np.sum(np.asarray(half_state.cache.filled)))
    assert 0 < filled < int(np.sum(np.asarray(ref_state.cache.filled)))
    assert "action_dropped" not in ref
    with pytest.raises(ValueError, match="action_dropout"):
        FlowConfig(action_dropout=1.0).validate()


@pytest.mark.slow
def test_teacher_forcing_step_sharded_equals_single_device(key):
    cfg = CacheConfig(enabled=False)
    out = []
    for mesh in (single_device_mesh(), full_mesh()):
        _, state, _, step, loader = build(mesh=mesh, cache_cfg=cfg, flow_cfg=FlowConfig(context_noise=0.1))
        for _ in range(3):
            state, metrics = step(state, loader.next(), key)
        out.append(jax.device_get((state.params, metrics["loss"])))
    chex.assert_trees_all_close(out[0], out[1], rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_mesh_with_fsdp_shards_params_and_cache(key):
    mesh = shd.make_mesh(shd.MeshConfig(data=4, fsdp=2))
    _, state, _, step, loader = build(mesh=mesh, cache_cfg=CacheConfig())
    assert state.params["frame_mix"].sharding.spec == jax.sharding.PartitionSpec(None, "fsdp")
    assert state.cache.latents.sharding.spec[0] == ("data", "fsdp")
    state, metrics = step(state, loader.next(), key)
    assert np.isfinite(float(metrics["loss"]))
