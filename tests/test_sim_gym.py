"""Gymnasium registration, check_env, the vector env, and the host-side wrappers of the C backend."""

import os
import subprocess
import sys

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import sim
from sim import expert, tasks, wrappers
from sim.config import SimConfig
from sim.env import CpuEnv


def test_gymnasium_make_passes_check_env():
    env = gymnasium.make(sim.GYM_ID, task_id=3, render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=False)
    obs, info = env.reset(seed=0)
    assert obs["proprio"].dtype == np.float32 and obs["proprio"].shape == (8,)
    assert info["language"] == tasks.LANGUAGE[3]
    frame = env.render()
    assert frame.shape == (128, 128, 3) and frame.dtype == np.uint8 and frame.std() > 5
    env.close()


HEADLESS_SCRIPT = """
import gymnasium, sim
from gymnasium.utils.env_checker import check_env
from sim import render_gl
env = gymnasium.make(sim.GYM_ID, task_id=4, render_mode="rgb_array")
check_env(env.unwrapped, skip_render_check=False)
env.reset(seed=0)
frame = env.render()
assert frame.shape == (128, 128, 3) and frame.std() > 5, frame.std()
print("renderer", "gl" if env.unwrapped._frames._gl is not None else "jax", render_gl.gl_backend())
"""


@pytest.mark.parametrize("mujoco_gl", [None, "glfw"])
def test_gym_env_on_a_headless_machine(mujoco_gl):
    """No display: MUJOCO_GL unset picks EGL/OSMesa; a failing user choice falls back to JAX, never aborts."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY", "PYOPENGL_PLATFORM")}
    if mujoco_gl:
        env["MUJOCO_GL"] = mujoco_gl
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run([sys.executable, "-c", HEADLESS_SCRIPT], env=env, cwd=root, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    if mujoco_gl == "glfw":  # GLFW cannot work without a display: the JAX renderer took over
        assert "renderer jax glfw" in proc.stdout, proc.stdout


def test_gym_episode_terminates_on_success_and_seeds_reproduce():
    env = gymnasium.make(sim.GYM_ID, task_id=2)
    a, _ = env.reset(seed=3)
    b, _ = env.reset(seed=3)
    np.testing.assert_array_equal(a["proprio"], b["proprio"])
    env.reset(options={"init_state_id": 4})
    inner = env.unwrapped
    est = expert.init(expert.privileged(inner.env, inner.sim_state.data))
    for _ in range(150):
        action, est = expert.act(expert.privileged(inner.env, inner.sim_state.data), est, np.zeros(6))
        _, reward, terminated, truncated, info = env.step(action.astype(np.float32))
        if terminated:
            break
    assert terminated and reward == 1.0 and info["is_success"] and not truncated
    with pytest.raises(ValueError, match="init_state_id"):
        env.reset(options={"init_state_id": 50})
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3, np.float32))


def test_gym_truncates_at_the_step_limit():
    env = gymnasium.make(sim.GYM_ID, task_id=0, max_steps=3)
    env.reset(seed=0)
    flags = [env.step(np.zeros(7, np.float32))[3] for _ in range(3)]
    assert flags == [False, False, True]


def test_make_vec_gives_a_numpy_vector_env():
    venv = gymnasium.make_vec(sim.GYM_ID, num_envs=2, task_id=1)
    obs, _ = venv.reset(seed=0)
    assert obs["proprio"].shape == (2, 8)
    obs, reward, terminated, truncated, _ = venv.step(np.zeros((2, 7), np.float32))
    assert reward.shape == (2,) and terminated.dtype == bool
    venv.close()


def test_host_episode_and_autoreset_wrappers_on_the_cpu_backend():
    env = wrappers.HostAutoResetWrapper(wrappers.HostEpisodeWrapper(CpuEnv(SimConfig(), 0), episode_length=2))
    state = env.reset(np.random.default_rng(0))
    first_qpos = state.data.qpos.copy()
    action = np.array([0.5, 0, 0, 0, 0, 0, -1.0])
    state = env.step(state, action)
    assert state.info["steps"] == 1 and state.done == 0
    assert not np.allclose(state.data.qpos, first_qpos)
    state = env.step(state, action)
    assert state.done == 1 and state.info["truncation"] == 1
    np.testing.assert_array_equal(state.data.qpos, first_qpos)  # auto-reset to the first state
    assert state.info["steps"] == 0
    state = env.step(state, action)  # the next episode steps a copy: the stored first state stays as it was
    assert state.info["steps"] == 1 and not np.allclose(state.data.qpos, first_qpos)
    np.testing.assert_array_equal(state.info["first_data"].qpos, first_qpos)
    with pytest.raises(ValueError, match="episode_length"):
        wrappers.HostEpisodeWrapper(CpuEnv(SimConfig(), 0), episode_length=0)

