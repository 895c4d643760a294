"""Brax-style wrappers around the pure envs: vmap, episode limit, auto-reset.

The single env's ``step`` never batches, counts time or resets; these do, in brax's order::

    env = wrap_for_training(sim.load("libero_spatial", backend="mjx"), episode_length=220)
    state = jax.jit(env.reset)(jax.random.split(key, 128))
    state = jax.jit(env.step)(state, actions)         # (128, 7)

``EpisodeWrapper`` and ``AutoResetWrapper`` work on both backends (jax.numpy on MJX states,
plain Python on C-backend states); ``VmapWrapper`` is for the MJX backend.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from sim.env import State


class Wrapper:
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


def _is_cpu(state: State) -> bool:
    return isinstance(state.data, mujoco.MjData)


class VmapWrapper(Wrapper):
    """Batches ``reset(keys (B,))`` and ``step(states, actions (B, 7))`` with ``jax.vmap``."""

    def reset(self, key: jax.Array) -> State:
        if key.ndim != 1 or not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            raise ValueError(f"VmapWrapper.reset wants a (B,) array of typed PRNG keys, got {key.shape} {key.dtype}")
        return jax.vmap(self.env.reset)(key)

    def step(self, state: State, action: jax.Array) -> State:
        if action.ndim != 2:
            raise ValueError(f"VmapWrapper.step wants actions of shape (B, 7), got {action.shape}")
        return jax.vmap(self.env.step)(state, action)


class EpisodeWrapper(Wrapper):
    """Counts steps; ``done`` at the limit, ``info['truncation']`` = 1 when the limit (not success) ended it."""

    def __init__(self, env: Any, episode_length: int):
        super().__init__(env)
        if episode_length <= 0:
            raise ValueError(f"episode_length must be > 0, got {episode_length}")
        self.episode_length = int(episode_length)

    def reset(self, key: Any) -> State:
        state = self.env.reset(key)
        cpu = _is_cpu(state)
        info = dict(state.info, steps=np.int32(0) if cpu else jnp.zeros((), jnp.int32),
                    truncation=np.float32(0) if cpu else jnp.zeros((), jnp.float32))
        return state.replace(info=info)

    def step(self, state: State, action: Any) -> State:
        state = self.env.step(state, action)
        xp = np if _is_cpu(state) else jnp
        steps = state.info["steps"] + 1
        at_limit = steps >= self.episode_length
        truncation = xp.where(at_limit & (state.done == 0), 1.0, 0.0).astype(xp.float32)
        done = xp.where(at_limit, 1.0, state.done).astype(xp.float32)
        return state.replace(done=done, info=dict(state.info, steps=xp.asarray(steps, xp.int32), truncation=truncation))


class AutoResetWrapper(Wrapper):
    """When an episode ends, the next state is the episode's first state (brax semantics).

    ``reset`` stores the first data and obs in ``info``; ``step`` swaps them in where
    ``done``. The returned state keeps ``done``/``reward`` of the finished step, so learners
    still see the terminal transition; step counters from ``EpisodeWrapper`` restart at 0.
    """

    def reset(self, key: Any) -> State:
        state = self.env.reset(key)
        first = (_copy_data(state.data) if _is_cpu(state) else state.data)
        return state.replace(info=dict(state.info, first_data=first, first_obs=state.obs))

    def step(self, state: State, action: Any) -> State:
        if _is_cpu(state):
            # A finished episode must not be stepped further: start from the stored first state.
            state = self.env.step(state, action)
            if bool(state.done):
                info = dict(state.info, first_data=state.info["first_data"], first_obs=state.info["first_obs"])
                if "steps" in info:
                    info["steps"] = np.int32(0)
                return state.replace(data=_copy_data(state.info["first_data"]), obs=state.info["first_obs"], info=info)
            return state
        state = state.replace(done=jnp.zeros_like(state.done))
        state = self.env.step(state, action)

        def where_done(first, now):
            done = state.done
            if done.ndim > 0:
                done = jnp.reshape(done, [done.shape[0]] + [1] * (now.ndim - 1))
            return jnp.where(done > 0, first, now)

        data = jax.tree.map(where_done, state.info["first_data"], state.data)
        obs = jax.tree.map(where_done, state.info["first_obs"], state.obs)
        info = dict(state.info)
        if "steps" in info:
            info["steps"] = jnp.where(state.done > 0, 0, info["steps"]).astype(jnp.int32)
        return state.replace(data=data, obs=obs, info=info)


def _copy_data(data: mujoco.MjData) -> mujoco.MjData:
    import copy

    return copy.copy(data)


def wrap_for_training(env: Any, episode_length: int = 220) -> Wrapper:
    """Episode limit, then vmap, then auto-reset (brax's ``wrap_for_training`` order)."""
    return AutoResetWrapper(VmapWrapper(EpisodeWrapper(env, episode_length)))
