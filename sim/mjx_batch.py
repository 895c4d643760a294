"""A batch of LIBERO-Spatial episodes of any tasks on MJX: the pure ``reset``/``step`` that the library's
scan rollouts drive (:class:`sword_jax.rl.scan_rollout.JaxEnv`).

Every task shares one scene and one success predicate (the target bowl on the plate); a task is its
initial states and its instruction. So one :class:`~sim.mjx_env.MjxEnv` serves every episode of a batch, each
reset from its own initial ``qpos``, and a batch may mix tasks freely.

What the policy sees is what :class:`sim.lockstep.LockstepEnvs` (the C engine) gives it: the agentview
frame rendered by ``sim/render.py``'s JAX ray caster (uint8), the 8-D proprio, success checked after
every action, actions clipped to [-1, 1]. Episode limits live in the rollout (``max_steps``), not here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sim import tasks as sim_tasks
from sim.config import SimConfig


class MjxEpisodes:
    """Batched MJX episodes (see the module docstring).

    Args:
      config: the simulator config (physics rates and MJX solver settings are read from it).
      resolution: agentview frame size (default ``config.resolution``).
    """

    def __init__(self, config: SimConfig = SimConfig(backend="mjx"), *, resolution: int | None = None):
        from sim import scene
        from sim.env import camera_renderer
        from sim.mjx_env import MjxEnv

        resolution = config.resolution if resolution is None else resolution
        config = dataclasses.replace(config, backend="mjx", resolution=resolution)
        config.validate()
        self.config, self.resolution = config, resolution
        renderer = camera_renderer(scene.build_model(), resolution=resolution)
        self.env = MjxEnv(config, 0, renderer=renderer)
        self.nq = self.env.nq
        self.flat_size = 1 + self.env.mjx_model.nq + self.env.mjx_model.nv  # a recorded [time, qpos, qvel]

    def _observation(self, state: Any) -> dict[str, jax.Array]:
        return {"frames": state.obs["agentview_rgb"], "proprio": state.obs["proprio"].astype(jnp.float32)}

    def reset(self, starts: jax.Array) -> tuple[Any, dict[str, jax.Array]]:
        """Start states (any tasks) -> ``(data, obs)`` (pure): ``[N, nq]`` initial qpos, each settled
        into a new episode, or ``[N, 1 + nq + nv]`` recorded flat states (``[time, qpos, qvel]``, a
        dataset's ``states[t]``), each continued without settling, as the C engine's lockstep episodes
        tell the two apart.

        ``obs``: ``frames [N, H, W, 3]`` uint8, ``proprio [N, 8]`` float32.
        """
        if starts.ndim != 2 or starts.shape[1] not in (self.nq, self.flat_size):
            raise ValueError(f"MjxEpisodes.reset: starts must be [N, {self.nq}] initial qpos or [N, {self.flat_size}] "
                             f"flat states [time, qpos, qvel], got {starts.shape}")
        state = jax.vmap(self.env.reset_to if starts.shape[1] == self.nq else self.env.restore)(starts)
        return state.data, self._observation(state)

    def snapshot(self, data: Any) -> jax.Array:
        """``[N, 1 + nq + nv]`` flat states ``[time, qpos, qvel]`` of the episodes (pure): what :meth:`reset`
        continues, as it continues a dataset's recorded ``states[t]``."""
        return jnp.concatenate([jnp.asarray(data.time, jnp.float32)[:, None], data.qpos.astype(jnp.float32),
                                data.qvel.astype(jnp.float32)], axis=1)

    def step(self, data: Any, actions: jax.Array) -> tuple[Any, dict[str, jax.Array], jax.Array]:
        """One 20 Hz control step of every episode (pure): ``actions [N, 7]`` clipped to [-1, 1].

        Returns ``(data, obs, success [N] bool)``: success of the state reached by this action.
        """
        if actions.ndim != 2 or actions.shape[1] != self.env.action_size:
            raise ValueError(f"MjxEpisodes.step: actions must be [N, {self.env.action_size}], got {actions.shape}")
        clipped = jnp.clip(actions.astype(jnp.float32), -1.0, 1.0)

        def one(d, a):
            return self.env._state(self.env._physics(d, a), info={})

        state = jax.vmap(one)(data, clipped)
        return state.data, self._observation(state), state.done > 0.5

    def observe(self, data: Any) -> dict[str, jax.Array]:
        """The observation of batched ``mjx.Data`` (no physics): what :meth:`reset` and :meth:`step` return."""
        return self._observation(jax.vmap(lambda d: self.env._state(d, info={}))(data))


def episode_starts(episodes: Sequence[tuple[int, np.ndarray]]) -> tuple[np.ndarray, list[str]]:
    """``(qpos [N, nq] float32, instructions)`` of ``(task, initial qpos)`` episodes."""
    if not episodes:
        raise ValueError("episode_starts: no episodes")
    qpos = np.stack([np.asarray(q, np.float32) for _, q in episodes])
    return qpos, [sim_tasks.LANGUAGE[int(t)] for t, _ in episodes]


def stratified_train_starts(tasks: Sequence[int], groups: int, rng: np.random.Generator, *, init_seed: int = 0,
                            pool: dict[int, np.ndarray] | None = None) -> list[tuple[int, np.ndarray]]:
    """``groups`` training-split start states, stratified over ``tasks``: group ``j`` is task
    ``tasks[(offset + j) % len(tasks)]`` (``offset`` drawn from ``rng``), so every task gets
    ``groups // len(tasks)`` or one more, and which tasks get the extra ones rotates between draws.
    The state within a task is drawn uniformly from its training reserve (never an evaluation state)."""
    tasks = [int(t) for t in tasks]
    if not tasks or groups < 1:
        raise ValueError(f"stratified_train_starts needs tasks and groups >= 1, got {tasks}, {groups}")
    if pool is None:
        pool = {t: sim_tasks.split_init_states(t, "train", sim_tasks.TRAIN_RESERVE, seed=init_seed) for t in tasks}
    offset = int(rng.integers(0, len(tasks)))
    picks = rng.integers(0, [len(pool[tasks[(offset + j) % len(tasks)]]) for j in range(groups)])
    return [(tasks[(offset + j) % len(tasks)], pool[tasks[(offset + j) % len(tasks)]][int(b)])
            for j, b in enumerate(picks)]
