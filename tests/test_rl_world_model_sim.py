"""The WorldModel + streaming VAE learned simulator inside the imagined rollout (tiny shapes)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax.rl.config import RLConfig
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.rollout import expand_groups, imagined_rollout
from sword_jax.rl.simulator import StartState, toy_reward_model
from sword_jax.rl.world_model_sim import encode_keyframes, world_model_simulator


@pytest.mark.slow
def test_world_model_simulator_rollout_deterministic_and_streams_frames():
    from sword_jax.dit.world_model import WorldModel
    from sword_jax.vae import api as vae_api

    cfg = configs.get("sword:tiny")
    with nnx.use_eager_sharding(False):
        wm_graphdef, wm_state = nnx.split(WorldModel(cfg.model, rngs=nnx.Rngs(0)))
    vae_graphdef, vae_state = nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(1)))
    frames = jax.random.uniform(jax.random.key(2), (2, 32, 32, 3))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    assert latents.shape == (2, 2, 2, 2, cfg.vae.z_dim)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                                sample_steps=2)
    rl = RLConfig(image_size=8, policy_width=16, policy_heads=2, policy_layers=1, max_instruction_bytes=32,
                  action_bins=8, max_chunks=2, group_size=2, success_threshold=1.0)
    graphdef, params = build_policy(rl)
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl", "open the drawer"], 32))
    start = expand_groups(StartState(frames, jnp.zeros((2, 8)), tokens, latents), 2)
    run = jax.jit(lambda p, s, k: imagined_rollout(graphdef, p, s, toy_reward_model(), start, rl, key=k, record_frames=True))
    a, b = run(params, sim, jax.random.key(0)), run(params, sim, jax.random.key(0))
    np.testing.assert_array_equal(np.asarray(a.frames), np.asarray(b.frames))
    assert a.frames.shape == (4, 2, 8, 32, 32, 3)
    assert np.all(np.isfinite(np.asarray(a.frames))) and float(a.frames.min()) >= 0 and float(a.frames.max()) <= 1
    # different sampled actions / noise give different imagined futures
    c = run(params, sim, jax.random.key(1))
    assert not np.allclose(np.asarray(a.frames), np.asarray(c.frames))
    np.testing.assert_array_equal(np.asarray(a.proprio_valid), 0.0)  # the world model reports no proprio
