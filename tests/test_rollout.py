"""Latent rollouts: finite, deterministic, equal to repeated one-chunk sampling; action slicing; round trip."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax.dit.action_dit import WorldModel
from sword_jax.world_model import rollout, sampler
from sword_jax.world_model.config import FlowConfig
from tests.support.world_model import MixerWorldModel


def _setup(keys, chunks=3, batch=2):
    first = jax.random.normal(keys[0], (batch, 2, 2, 8))
    context = jax.random.normal(keys[1], (batch, 2, 2, 8))
    actions = jax.random.uniform(keys[2], (batch, 1 + 4 + 8 * chunks, 7), minval=-1.0, maxval=1.0)
    return first, context, actions


def test_chunk_actions_slices_each_chunks_frames():
    actions = jnp.arange(1 + 4 + 8 * 3, dtype=jnp.float32)[None, :, None]  # value = frame index
    assert rollout.num_chunks_for(actions.shape[1], 1, 2) == 3
    for chunk in range(3):
        got = np.asarray(rollout.chunk_actions(actions, chunk, 1, 2))[0, :, 0]
        context_start = 1 + 8 * chunk
        np.testing.assert_array_equal(got, [0] + list(range(context_start, context_start + 12)))
    with pytest.raises(ValueError, match="actions"):
        rollout.num_chunks_for(1 + 4 + 7, 1, 2)


def test_rollout_equals_repeated_chunks_and_is_deterministic(keys):
    graphdef, state = nnx.split(MixerWorldModel(rngs=nnx.Rngs(0)))
    first, context, actions = _setup(keys)
    cfg = FlowConfig(sample_steps=3)
    run = jax.jit(lambda s, f, c, a, k: rollout.rollout(graphdef, s, f, c, a, key=k, cfg=cfg))
    out = run(state, first, context, actions, keys[3])
    assert out.shape == (2, 6, 2, 2, 8) and np.all(np.isfinite(out))
    np.testing.assert_array_equal(out, run(state, first, context, actions, keys[3]))
    assert not np.allclose(out, run(state, first, context, actions, keys[4]))

    model_fn = sampler.model_fn_from_state(graphdef, state)
    one_chunk = jax.jit(lambda c, a, k: rollout.predict_chunk(model_fn, first[:, None], c, a, key=k, num_future=2,
                                                              cfg=cfg))
    chunk_keys = jax.random.split(keys[3], 3)
    ctx, expected = context[:, None], []
    for i in range(3):
        future = one_chunk(ctx, rollout.chunk_actions(actions, i, 1, 2), chunk_keys[i])
        expected.append(future)
        ctx = future[:, -1:]
    np.testing.assert_allclose(out, jnp.concatenate(expected, axis=1), rtol=1e-5, atol=1e-5)


def test_round_trip_option_routes_context_through_given_function(keys):
    graphdef, state = nnx.split(MixerWorldModel(rngs=nnx.Rngs(0)))
    first, context, actions = _setup(keys, chunks=2)
    plain = rollout.rollout(graphdef, state, first, context, actions, key=keys[3], cfg=FlowConfig(sample_steps=1))
    with pytest.raises(ValueError, match="round_trip"):
        rollout.rollout(graphdef, state, first, context, actions, key=keys[3],
                        cfg=FlowConfig(sample_steps=1, pixel_round_trip=True))
    identity = rollout.rollout(graphdef, state, first, context, actions, key=keys[3],
                               cfg=FlowConfig(sample_steps=1, pixel_round_trip=True),
                               round_trip=lambda f, fut: fut[:, -1:])
    np.testing.assert_allclose(identity, plain, rtol=1e-6)
    shifted = rollout.rollout(graphdef, state, first, context, actions, key=keys[3],
                              cfg=FlowConfig(sample_steps=1, pixel_round_trip=True),
                              round_trip=lambda f, fut: fut[:, -1:] + 1.0)
    np.testing.assert_allclose(shifted[:, :2], plain[:, :2], rtol=1e-6)  # first chunk uses the given context
    assert not np.allclose(shifted[:, 2:], plain[:, 2:])


@pytest.mark.slow
def test_rollout_with_real_world_model_is_finite_and_action_dependent(keys):
    """The real DiT (1 layer): finite output, and other actions give another future."""
    cfg = configs.get("sword:tiny")
    model_cfg = cfg.model.__class__(**{**cfg.model.__dict__, "num_layers": 1})
    graphdef, state = nnx.split(WorldModel(model_cfg, rngs=nnx.Rngs(0)))
    # zero-initialised output/action layers would hide the inputs; perturb every weight a little
    leaves, treedef = jax.tree.flatten(state)
    noise_keys = jax.random.split(keys[5], len(leaves))
    state = jax.tree.unflatten(treedef, [x + 0.05 * jax.random.normal(k, x.shape, x.dtype) if jnp.issubdtype(x.dtype, jnp.floating)
                                         else x for x, k in zip(leaves, noise_keys)])
    first = jax.random.normal(keys[0], (1, 2, 2, 48))
    context = jax.random.normal(keys[1], (1, 2, 2, 48))
    actions = jax.random.uniform(keys[2], (1, 1 + 4 + 16, 7), minval=-1.0, maxval=1.0)
    run = jax.jit(lambda a: rollout.rollout(graphdef, state, first, context, a, key=keys[3],
                                            cfg=FlowConfig(sample_steps=2)))
    out = run(actions)
    assert out.shape == (1, 4, 2, 2, 48) and np.all(np.isfinite(out))
    assert not np.allclose(out, run(-actions), atol=1e-4)
