"""The MJX backend as a brax ``Env``: ``reset(rng) -> State``, ``step(state, action) -> State``, pure JAX.

``MjxEnv`` shares the model, controller, observation and success code with the C engine's ``CpuEnv``
(``sim/env.py``) and steps with :func:`sim.env.mjx_step`. Its states are brax's ``envs.State``
(``pipeline_state`` an ``mjx.Data``), ``action_size`` / ``observation_size`` / ``backend`` are as brax
defines them, so brax's training wrappers batch it, limit its episodes and reset them, and its trainers
take it::

    from brax.envs.wrappers import training
    env = training.wrap(sim.load("libero_spatial", backend="mjx"), episode_length=220)
    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 128))
    state = jax.jit(env.step)(state, actions)         # (128, 7)

(brax's wrappers read the batch from a raw ``PRNGKey``'s shape, so they take raw keys, not typed ones.)
This module imports brax and MJX (seconds); the C backend never loads it.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from brax.envs.base import Env
from brax.envs.base import State as BraxState
from flax import struct

from sim import controller as ctl
from sim import panda, scene, tasks
from sim.config import SimConfig
from sim.env import SETTLE_ACTION, _Common, _mjx, _mjx_forward, _mjx_promotion, mjx_step


@struct.dataclass
class MjxState(BraxState):
    """brax's ``envs.State`` with an ``mjx.Data`` as ``pipeline_state``; ``data`` reads it too, as on the
    C engine's ``sim.env.State``, so code written for both backends reads ``state.data``."""

    @property
    def data(self) -> Any:
        return self.pipeline_state


class MjxEnv(_Common, Env):
    """MJX backend, a brax ``Env``: ``reset``/``step`` are pure JAX functions (jit them; batch, limit and
    auto-reset them with brax's training wrappers)."""

    def __init__(self, config: SimConfig = SimConfig(backend="mjx"), task_id: int = 0, **kwargs):
        super().__init__(config, task_id, **kwargs)
        mjx = _mjx()
        # MJX's solver settings are its own (sim.mjx_solver_iterations); mj_model keeps the C engine's.
        model = scene.build_model(timestep=config.physics_dt, iterations=config.mjx_solver_iterations,
                                  ls_iterations=config.mjx_ls_iterations)
        self.mjx_model = mjx.put_model(model)
        self._init_states_j = jnp.asarray(self.init_states, jnp.float32)

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def observation_size(self) -> dict[str, tuple[int, ...]]:
        """Shapes of one observation's entries, the renderer's images included (traced abstractly on a
        fresh ``mjx.Data``: no physics runs)."""
        mjx = _mjx()

        def obs():
            with _mjx_promotion():
                data = mjx.make_data(self.mjx_model)
            return self._obs(data, jnp)

        return {name: tuple(value.shape) for name, value in jax.eval_shape(obs).items()}

    def _draws_to_qpos(self, draws: Any, xp: Any) -> Any:
        if self.config.init == "fixed":
            idx = jnp.minimum((draws[-1] * tasks.NUM_INIT_STATES).astype(jnp.int32), tasks.NUM_INIT_STATES - 1)
            return self._init_states_j[idx]
        return tasks.init_qpos(self.task_id, draws[:-1], xp=jnp)

    def initial_qpos(self, key: jax.Array) -> jax.Array:
        """The ``(nq,)`` qpos a reset from ``key`` starts from, before the settle steps (pure)."""
        return self._draws_to_qpos(jax.random.uniform(key, (tasks.NUM_DRAWS + 1,)), jnp)

    def reset(self, rng: jax.Array) -> MjxState:
        """New episode (pure). ``rng``: a jax PRNG key (raw ``PRNGKey`` under brax's wrappers)."""
        return self.reset_to(self.initial_qpos(rng))

    def _data_at(self, qpos: jax.Array, **recorded: jax.Array) -> Any:
        """Fresh ``mjx.Data`` at ``qpos`` (and a recorded ``qvel``, ``time``), the arm's servos holding it, the
        gripper open (the controller rewrites the controls at every step), kinematics computed (pure)."""
        ctrl = jnp.concatenate([qpos[:7], jnp.full((2,), panda.FINGER_OPEN, jnp.float32)])
        mjx = _mjx()
        with _mjx_promotion():
            data = mjx.make_data(self.mjx_model).replace(qpos=qpos, ctrl=ctrl, **recorded)
            return _mjx_forward(self.mjx_model, data)  # as mjx_step's forward: the C engine's contact points

    def reset_to(self, qpos: jax.Array) -> MjxState:
        """New episode from a given initial qpos (nq,), then the settle steps (pure)."""
        data = self._data_at(jnp.asarray(qpos, jnp.float32))
        settle = jnp.asarray(SETTLE_ACTION)
        data = jax.lax.fori_loop(0, self.config.settle_steps, lambda _, d: self._physics(d, settle), data)
        return self._state(data, info={})

    def restore(self, flat_state: jax.Array) -> MjxState:
        """An episode continued from a recorded state (pure): a dataset's flattened ``states[t]`` (``[time,
        qpos, qvel]``, LIBERO's layout), with no settling, as :meth:`sim.env.CpuEnv.restore` continues it:
        the arm's servos hold the recorded pose and the gripper is open until the controller rewrites the
        controls at the next step."""
        flat = jnp.asarray(flat_state, jnp.float32)
        nq, nv = self.mjx_model.nq, self.mjx_model.nv
        if flat.shape != (1 + nq + nv,):
            raise ValueError(f"MjxEnv.restore: flat state must have shape ({1 + nq + nv},) = [time, qpos ({nq}), "
                             f"qvel ({nv})], got {flat.shape}")
        return self._state(self._data_at(flat[1: 1 + nq], qvel=flat[1 + nq:], time=flat[0]), info={})

    def _physics(self, data: Any, action: jax.Array) -> Any:
        from mujoco.mjx._src import support

        with _mjx_promotion():
            jacp, jacr = support.jac(self.mjx_model, data, data.site_xpos[self.site_id], self.hand_body)  # (nv, 3)
        ctrl = ctl.servo_targets(action.astype(jnp.float32), data.qpos[:7], jacp[:7].T, jacr[:7].T,
                                 self.controller, xp=jnp)
        data = data.replace(ctrl=ctrl)
        with _mjx_promotion():
            return jax.lax.fori_loop(0, self.substeps, lambda _, d: mjx_step(self.mjx_model, d), data)

    def _state(self, data: Any, info: dict[str, Any]) -> MjxState:
        solved = self._success(data, jnp).astype(jnp.float32)
        return MjxState(pipeline_state=data, obs=self._obs(data, jnp), reward=solved, done=solved,
                        metrics={"success": solved}, info=info)

    def step(self, state: MjxState, action: jax.Array) -> MjxState:
        """One 20 Hz control step (pure; jit it)."""
        self._check_action(action)
        data = self._physics(state.data, jnp.asarray(action, jnp.float32))
        return self._state(data, info=dict(state.info))
