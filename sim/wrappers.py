"""Host-side episode limit and auto-reset for the C-engine backend (``CpuEnv``).

The MJX env is a brax ``Env``: brax's own training wrappers batch it, limit its episodes and reset
them (``brax.envs.wrappers.training.wrap``: ``VmapWrapper``, ``EpisodeWrapper``, ``AutoResetWrapper``).
Those compute with ``jax.numpy`` on every state leaf. A C-engine state holds a mutable
``mujoco.MjData`` and is stepped one env at a time on the host, so the two wrappers here do brax's
episode-limit and auto-reset jobs there, in numpy, copying the stored first ``MjData`` on a reset::

    env = HostAutoResetWrapper(HostEpisodeWrapper(sim.load("libero_spatial"), episode_length=220))
    state = env.reset(np.random.default_rng(0))
    state = env.step(state, action)                  # (7,)
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np

from sim.env import State


class _HostWrapper:
    """Forwards everything to the wrapped env."""

    def __init__(self, env: Any):
        self.env = env

    def reset(self, key: Any) -> State:
        return self.env.reset(key)

    def step(self, state: State, action: Any) -> State:
        return self.env.step(state, action)

    @property
    def unwrapped(self) -> Any:
        return getattr(self.env, "unwrapped", self.env)

    def __getattr__(self, name: str) -> Any:
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)


class HostEpisodeWrapper(_HostWrapper):
    """Counts steps; ``done`` at the limit, ``info['truncation']`` = 1 when the limit (not success) ended it
    (brax's ``EpisodeWrapper`` on a C-engine state)."""

    def __init__(self, env: Any, episode_length: int):
        super().__init__(env)
        if episode_length <= 0:
            raise ValueError(f"episode_length must be > 0, got {episode_length}")
        self.episode_length = int(episode_length)

    def reset(self, key: Any) -> State:
        state = self.env.reset(key)
        return state.replace(info=dict(state.info, steps=np.int32(0), truncation=np.float32(0)))

    def step(self, state: State, action: Any) -> State:
        state = self.env.step(state, action)
        steps = np.int32(state.info["steps"] + 1)
        at_limit = steps >= self.episode_length
        truncation = np.float32(at_limit and state.done == 0)
        done = np.float32(1.0 if at_limit else state.done)
        return state.replace(done=done, info=dict(state.info, steps=steps, truncation=truncation))


class HostAutoResetWrapper(_HostWrapper):
    """When an episode ends, the next state is the episode's first state (brax's ``AutoResetWrapper`` on a
    C-engine state).

    ``reset`` stores a copy of the first ``MjData`` and obs in ``info``; a ``step`` that ends the episode
    returns a fresh copy of them, keeping ``done``/``reward`` of the finished step so learners still see
    the terminal transition; ``HostEpisodeWrapper``'s step counter restarts at 0.
    """

    def reset(self, key: Any) -> State:
        state = self.env.reset(key)
        return state.replace(info=dict(state.info, first_data=copy.copy(state.data), first_obs=state.obs))

    def step(self, state: State, action: Any) -> State:
        state = self.env.step(state, action)
        if not bool(state.done):
            return state
        info = dict(state.info)
        if "steps" in info:
            info["steps"] = np.int32(0)
        # a copy: the C engine steps MjData in place, and the stored first state must outlive the episode
        return state.replace(data=copy.copy(info["first_data"]), obs=info["first_obs"], info=info)
