"""The learned simulator as an environment: the functional brax-state env and the gymnasium wrappers."""

import jax
import jax.numpy as jnp
import numpy as np
from gymnasium.utils.env_checker import check_env

from sword_jax.rl.env import ImaginedEnv, ImaginedGymEnv, ImaginedVectorEnv
from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import tokenize_instructions


def _env(max_chunks=3):
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl", "open the drawer", "close it"], 24))
    pool = toy_start_states(tokens, key=jax.random.key(0), frame_size=8)
    env = ImaginedEnv(toy_simulator(frame_size=8, step_size=0.1, noise=0.01), toy_reward_model(), max_chunks=max_chunks)
    return env, pool


def test_functional_env_vmaps_and_truncates():
    env, pool = _env()
    reset = jax.jit(jax.vmap(lambda s, k: env.reset(s, key=k)))
    step = jax.jit(jax.vmap(env.step))
    state = reset(pool, jax.random.split(jax.random.key(1), 3))
    zeros = jnp.zeros((3, 8, 7))
    for _ in range(3):
        state = step(state, zeros)
    assert state.info["frames"].shape == (3, 8, 8, 8, 3)
    np.testing.assert_array_equal(np.asarray(state.done), 1.0)  # chunk limit (zero actions never succeed here)
    np.testing.assert_array_equal(np.asarray(state.info["truncation"]), 1.0)
    after = step(state, jnp.ones((3, 8, 7)))  # done envs are frozen: no reward, same obs
    np.testing.assert_array_equal(np.asarray(after.reward), 0.0)
    np.testing.assert_array_equal(np.asarray(after.obs["pixels/frame"]), np.asarray(state.obs["pixels/frame"]))


def test_gym_env_passes_env_checker():
    env, pool = _env()
    check_env(ImaginedGymEnv(env, pool), skip_render_check=True)


def test_vector_env_autoreset_and_seeding():
    env, pool = _env(max_chunks=2)
    vec = ImaginedVectorEnv(env, pool, num_envs=4)
    obs, _ = vec.reset(seed=3)
    assert vec.observation_space.contains(obs)
    obs2, _ = vec.reset(seed=3)
    np.testing.assert_array_equal(obs["frame"], obs2["frame"])
    action = np.full(vec.action_space.shape, 0.5, np.float32)
    _, r1, term, trunc, info = vec.step(action)
    assert r1.shape == (4,) and info["frames"].shape == (4, 8, 8, 8, 3)
    _, _, term, trunc, _ = vec.step(action)
    assert np.all(term | trunc)  # chunk limit 2
    obs3, r3, term3, trunc3, _ = vec.step(action)  # next-step auto-reset
    np.testing.assert_array_equal(r3, 0.0)
    assert not np.any(term3 | trunc3)
    assert vec.observation_space.contains(obs3)
    try:
        vec.step(np.zeros((4, 8, 6), np.float32))
    except ValueError as err:
        assert "shape" in str(err)
    else:
        raise AssertionError("a wrong action shape must be rejected")
