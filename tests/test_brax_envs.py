"""The MJX env and the learned simulator's env are brax ``Env``s: brax's training wrappers take them.

brax's wrappers mix int and float arrays (``EpisodeWrapper`` compares float step counts with an int32
limit), so they run under standard dtype promotion here; the tests' default is strict.
"""

import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.base import Env, State
from brax.envs.wrappers import training

from sword_jax.rl.env import ImaginedEnv, ImaginedPoolEnv
from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import tokenize_instructions
from tests.conftest import REPO


def _learned_env(max_chunks=4):
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl", "open the drawer", "close it"], 16))
    pool = toy_start_states(tokens, key=jax.random.key(0), frame_size=8)
    simulator = toy_simulator(frame_size=8, chunk_len=2, step_size=0.2, noise=0.01)
    return ImaginedPoolEnv(ImaginedEnv(simulator, toy_reward_model(), max_chunks=max_chunks), pool)


def test_learned_simulator_env_steps_a_vmapped_batch_with_autoreset_under_brax_wrappers():
    env = _learned_env(max_chunks=4)
    assert isinstance(env, Env) and env.backend == "learned_simulator"
    assert env.action_size == 2 * 7 and env.action_shape == (2, 7)
    assert env.observation_size == {"pixels/frame": (8, 8, 3), "proprio": (4,), "proprio_valid": (1,),
                                    "instruction_tokens": (16,)}
    wrapped = training.wrap(env, episode_length=2)  # brax's time limit comes before the env's 4 chunks
    assert (wrapped.action_size, wrapped.observation_size, wrapped.backend) == (14, env.observation_size,
                                                                                "learned_simulator")
    assert wrapped.unwrapped is env
    with jax.numpy_dtype_promotion("standard"):
        reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
        first = reset(jax.random.split(jax.random.PRNGKey(0), 3))  # brax's wrappers take raw keys
        actions = jnp.tile(jnp.asarray([1.0, 0.5] + [0.0] * 12, jnp.float32), (3, 1))  # flat chunks, as PPO's
        states = [first]
        for _ in range(3):
            states.append(step(states[-1], actions))
    assert all(type(s) is State for s in states)
    one, two, three = states[1:]
    np.testing.assert_array_equal(np.asarray(one.done), 0.0)
    np.testing.assert_array_equal(np.asarray(two.done), 1.0)  # the 2-step limit ...
    np.testing.assert_array_equal(np.asarray(two.info["truncation"]), 1.0)  # ... marked a truncation
    # auto-reset: the episode restarts whole, from its first observation and its first progress
    np.testing.assert_array_equal(np.asarray(two.obs["pixels/frame"]), np.asarray(first.obs["pixels/frame"]))
    np.testing.assert_array_equal(np.asarray(two.pipeline_state.chunk), 0)
    np.testing.assert_allclose(np.asarray(two.pipeline_state.score), np.asarray(first.pipeline_state.score))
    np.testing.assert_array_equal(np.asarray(three.pipeline_state.chunk), 1)
    np.testing.assert_array_equal(np.asarray(three.info["steps"]), 1.0)
    # the restarted episode's first reward is measured from its start score, not the finished one's last
    np.testing.assert_allclose(np.asarray(three.reward), np.asarray(three.info["score"] - first.info["score"]),
                               atol=1e-6)
    assert float(jnp.abs(three.reward - one.reward).max()) > 0  # the simulator's noise key ran on
    with pytest.raises(ValueError, match="14"):  # a flat chunk or a [2, 7] one (tests/test_api.py), nothing else
        env.step(first, jnp.zeros((13,), jnp.float32))


def test_mjx_env_conforms_to_brax_and_its_wrappers_take_its_states():
    """Types, sizes and brax's wrappers traced over the MJX env's states, its physics stubbed out (MJX's
    physics compiles for minutes on a CPU; its forward pass is traced once, nothing runs)."""
    import sim
    from sim.env import camera_renderer
    from sim.mjx_env import MjxEnv, MjxState

    env = sim.load("libero_spatial", task_id=0, backend="mjx")
    assert isinstance(env, MjxEnv) and isinstance(env, Env)
    assert (env.backend, env.action_size, env.observation_size) == ("mjx", 7, {"proprio": (8,)})
    renderer = camera_renderer(env.mj_model, resolution=16, pixels=True, tile=None, static_split=False)
    seen = sim.load("libero_spatial", task_id=0, backend="mjx", renderer=renderer)
    assert seen.observation_size == {"proprio": (8,), "pixels/agentview_rgb": (16, 16, 3)}  # brax's vision keys
    with pytest.raises(ValueError, match="pixels"):
        camera_renderer(env.mj_model, pixels=True, depth_and_seg=True)

    env._physics = lambda data, action: data  # this instance only: no MJX physics in the traced programs
    wrapped = training.wrap(env, episode_length=5)
    assert (wrapped.observation_size, wrapped.action_size, wrapped.backend) == ({"proprio": (8,)}, 7, "mjx")
    assert wrapped.unwrapped is env
    with jax.numpy_dtype_promotion("standard"):
        state = jax.eval_shape(wrapped.reset, jax.random.split(jax.random.PRNGKey(0), 2))
        stepped = jax.eval_shape(wrapped.step, state, jax.ShapeDtypeStruct((2, 7), jnp.float32))
    for s in (state, stepped):
        assert type(s) is MjxState and isinstance(s, State) and s.data is s.pipeline_state
        assert s.obs["proprio"].shape == (2, 8) and s.done.shape == (2,) and s.pipeline_state.qpos.shape[0] == 2
        assert {"steps", "truncation", "first_pipeline_state", "first_obs"} <= set(s.info)
    assert jax.tree.structure(state) == jax.tree.structure(stepped)  # what brax's scans carry


REMOVED = ("VmapWrapper", "EpisodeWrapper", "AutoResetWrapper", "wrap_for_training", "Wrapper")


def test_removed_wrappers_leave_no_caller_behind():
    """Every ``wrappers.<name>`` and ``from sim.wrappers import <name>`` in the repository names what
    ``sim/wrappers.py`` still defines; brax's training wrappers replaced the JAX ones."""
    from sim import wrappers

    for name in REMOVED:
        assert not hasattr(wrappers, name), name
    used = {}
    for folder in ("sim", "sword_jax", "train", "benchmarks", "tests", "examples"):
        for root, _, files in os.walk(os.path.join(REPO, folder)):
            for file in (f for f in files if f.endswith(".py")):
                path = os.path.join(root, file)
                with open(path) as f:
                    source = f.read()
                if not re.search(r"from sim import[^\n]*\bwrappers\b|import sim\.wrappers|from sim\.wrappers import",
                                 source):
                    continue
                names = re.findall(r"\bwrappers\.(?!py\b)(\w+)", source)
                names += [n.strip() for group in re.findall(r"from sim\.wrappers import ([\w, ]+)", source)
                          for n in group.split(",")]
                used[os.path.relpath(path, REPO)] = set(names)
    assert "tests/test_sim_gym.py" in used  # the scan finds the callers there are
    missing = {path: sorted(n for n in names if not hasattr(wrappers, n)) for path, names in used.items()}
    assert not any(missing.values()), f"callers of removed sim.wrappers names: {missing}"
