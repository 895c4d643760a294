"""Gymnasium interface: ``gymnasium.make("sword/LiberoSpatial-v0", task_id=k)`` (C backend).

Observations are a dict: ``proprio`` (8,) float32 and, with ``image_obs=True``,
``agentview_rgb`` (and ``eye_in_hand_rgb`` with ``wrist_camera=True``) as (H, W, 3) uint8.
``terminated`` = success, ``truncated`` = the 220-step limit. ``render_mode="rgb_array"``
returns the agentview frame. ``gymnasium.make_vec(..., num_envs=n)`` vectorises it
(synchronously; numpy in and out). ``reset(options={"init_state_id": i})`` starts from the
task's fixed initial state ``i``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from sim import controller as ctl
from sim import tasks
from sim.config import SimConfig
from sim.env import CpuEnv


class _Frames:
    """Renders ``mujoco.MjData`` frames: MuJoCo's OpenGL renderer where a GL context can be
    made (fast on CPU; EGL or OSMesa on a headless machine), else the JAX ray-cast renderer of
    ``sim/render.py``."""

    def __init__(self, model: Any, resolution: int, renderer: str = "auto"):
        if renderer not in ("auto", "gl", "jax"):
            raise ValueError(f"renderer must be auto|gl|jax, got {renderer!r}")
        self.model = model
        self.resolution = resolution
        self._jax_scene = None
        self._gl = None
        if renderer != "jax":
            from sim.render_gl import GLUnavailableError, make_renderer

            try:  # picks EGL/OSMesa on a headless machine (see sim/render_gl.py)
                self._gl = make_renderer(model, resolution, resolution)
            except GLUnavailableError:  # no OpenGL here: fall back to the JAX renderer
                if renderer == "gl":
                    raise
        if self._gl is None:
            from sim import render as jax_render

            self._jax_render = jax_render
            self._jax_scene = jax_render.build_scene(model)

    def __call__(self, data: Any, camera: str) -> np.ndarray:
        if self._gl is not None:
            self._gl.update_scene(data, camera=camera)
            return self._gl.render().copy()
        frame = self._jax_render.render_mjdata(self._jax_scene, [data], camera, height=self.resolution,
                                               width=self.resolution)
        return np.asarray(frame.rgb[0], dtype=np.uint8)

    def close(self) -> None:
        if self._gl is not None:
            self._gl.close()
            self._gl = None


class LiberoSpatialGymEnv(gymnasium.Env):
    """One LIBERO-Spatial task on MuJoCo's C engine."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, task_id: int = 0, render_mode: str | None = None, resolution: int = 128,
                 image_obs: bool = False, wrist_camera: bool = False, max_steps: int = 220,
                 init: str = "fixed", init_seed: int = 0, renderer: str = "auto"):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.config = SimConfig(backend="cpu", resolution=resolution, max_steps=max_steps, init=init,
                                init_seed=init_seed, wrist_camera=wrist_camera)
        self.env = CpuEnv(self.config, task_id)
        self.task_id = int(task_id)
        self.language = tasks.LANGUAGE[self.task_id]
        self.render_mode = render_mode
        self.image_obs = image_obs
        self.action_space = spaces.Box(-1.0, 1.0, (ctl.ACTION_DIM,), np.float32)
        obs_spaces: dict[str, spaces.Space] = {
            "proprio": spaces.Box(-10.0, 10.0, (ctl.PROPRIO_DIM,), np.float32)}
        image = spaces.Box(0, 255, (resolution, resolution, 3), np.uint8)
        if image_obs:
            obs_spaces["agentview_rgb"] = image
            if wrist_camera:
                obs_spaces["eye_in_hand_rgb"] = image
        self.observation_space = spaces.Dict(obs_spaces)
        # renderer: "jax" gives the look of data generated with sim/render.py (the pipeline's data).
        self._frames = _Frames(self.env.mj_model, resolution, renderer) if (render_mode or image_obs) else None
        self._state = None
        self._steps = 0

    def _obs(self) -> dict[str, np.ndarray]:
        obs = {"proprio": np.asarray(self._state.obs["proprio"], np.float32)}
        if self.image_obs:
            obs["agentview_rgb"] = self._frames(self._state.data, "agentview")
            if self.config.wrist_camera:
                obs["eye_in_hand_rgb"] = self._frames(self._state.data, "eye_in_hand")
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        if "init_state_id" in options:
            idx = int(options["init_state_id"])
            if not 0 <= idx < len(self.env.init_states):
                raise ValueError(f"init_state_id must be in 0..{len(self.env.init_states) - 1}, got {idx}")
            self._state = self.env.reset_to(self.env.init_states[idx])
        else:
            self._state = self.env.reset(self.np_random)
        self._steps = 0
        return self._obs(), {"success": False, "language": self.language}

    def step(self, action: np.ndarray):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, np.float32)
        if action.shape != (ctl.ACTION_DIM,):
            raise ValueError(f"action must have shape ({ctl.ACTION_DIM},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError("action contains NaN or inf")
        if np.any(np.abs(action) > 1.0 + 1e-5):
            raise ValueError(f"action outside [-1, 1] (LIBERO's normalised actions): {action.tolist()}")
        self._state = self.env.step_inplace(self._state, np.clip(action, -1.0, 1.0))
        self._steps += 1
        success = bool(self._state.done)
        truncated = (not success) and self._steps >= self.config.max_steps
        info = {"success": success, "is_success": success, "language": self.language}
        return self._obs(), float(self._state.reward), success, truncated, info

    def render(self):
        if self.render_mode != "rgb_array" or self._state is None:
            return None
        return self._frames(self._state.data, "agentview")

    @property
    def sim_state(self):
        """The underlying pure-env ``State`` (C backend)."""
        return self._state

    def close(self) -> None:
        if self._frames is not None:
            self._frames.close()
