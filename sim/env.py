"""Pure LIBERO-Spatial environments: ``reset(key) -> State``, ``step(state, action) -> State``.

Two backends over ONE model (``sim/scene.py``) and ONE controller (``sim/controller.py``):

* ``MjxEnv`` (``sim/mjx_env.py``): MJX (JAX), jit/vmap-able, for accelerators; a brax ``Env`` whose
  states are brax's ``envs.State`` with an ``mjx.Data`` as ``pipeline_state`` (also read as ``data``).
* ``CpuEnv``: MuJoCo's C engine, numpy in and out, for CPU work (tests, data generation).
  ``State.data`` is a ``mujoco.MjData`` that ``step`` copies, never mutates, so the API stays
  pure. MJX's JAX implementation is far too slow on a CPU for an arm (~0.4 s per physics step
  here), the C engine runs ~1e5 steps/s.

Both share the observation, reward and success code (``_Common``, written for ``xp`` =
numpy or jax.numpy). One control step (20 Hz) = controller once + ``substeps`` physics steps.
``reset`` places the objects (one of the task's 50 fixed initial states, or a fresh sample)
and runs the 10 settle steps (zero motion, gripper open) as LIBERO does. Batching, episode limits and
auto-reset are wrappers, not here: brax's training wrappers for ``MjxEnv``, the host-side ones of
``sim/wrappers.py`` for ``CpuEnv``.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from sim import controller as ctl
from sim import panda, scene, tasks
from sim.config import SimConfig

Renderer = Callable[[Any], dict[str, Any]]
SETTLE_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], np.float32)


@struct.dataclass
class State:
    """The C engine's environment state (brax's ``envs.State`` fields, with ``data`` for
    ``pipeline_state``; the MJX backend's is brax's own, ``sim.mjx_env.MjxState``).

    Attributes:
      data: ``mujoco.MjData``.
      obs: dict with ``proprio`` (8,) and any images the renderer adds.
      reward: () 1.0 when the task is solved in this state.
      done: () 1.0 when the task is solved (time limits are a wrapper's business).
      metrics: dict of () floats (``success``).
      info: dict of per-env bookkeeping (wrappers add ``steps``, ``truncation`` ...).
    """

    data: Any
    obs: dict[str, Any]
    reward: Any
    done: Any
    metrics: dict[str, Any]
    info: dict[str, Any]


class _Common:
    """Model ids, config and the backend-independent observation / success math."""

    def __init__(self, config: SimConfig, task_id: int, renderer: Renderer | None = None,
                 controller: ctl.ControllerConfig = ctl.ControllerConfig()):
        config.validate()
        controller.validate()
        if not 0 <= task_id < tasks.NUM_TASKS:
            raise ValueError(f"task_id must be in 0..{tasks.NUM_TASKS - 1}, got {task_id}")
        self.config = config
        self.task_id = int(task_id)
        self.language = tasks.LANGUAGE[self.task_id]
        self.controller = controller
        self.renderer = renderer
        self.mj_model = scene.build_model(timestep=config.physics_dt, iterations=config.solver_iterations,
                                          ls_iterations=config.ls_iterations)
        steps = 1.0 / (config.control_hz * config.physics_dt)
        if abs(steps - round(steps)) > 1e-6:
            raise ValueError(f"1/(control_hz*physics_dt) must be an integer, got {steps}")
        self.substeps = int(round(steps))
        m = self.mj_model
        self.site_id = m.site("grip_site").id
        self.hand_body = m.body("panda_hand").id
        self.bowl_body = m.body(scene.TARGET_BOWL).id
        self.plate_body = m.body("plate_1").id
        self.init_states = tasks.fixed_init_states(self.task_id, seed=config.init_seed)
        self.nq, self.nv = m.nq, m.nv

    @property
    def action_size(self) -> int:
        return ctl.ACTION_DIM

    @property
    def observation_size(self) -> dict[str, tuple[int, ...]]:
        return {"proprio": (ctl.PROPRIO_DIM,)}

    def _draws_to_qpos(self, draws: Any, xp: Any) -> Any:
        """draws (NUM_DRAWS + 1,) -> qpos: a fixed init state or a fresh sample."""
        if self.config.init == "fixed":
            idx = xp.minimum((draws[-1] * tasks.NUM_INIT_STATES).astype(xp.int32), tasks.NUM_INIT_STATES - 1)
            return xp.asarray(self.init_states)[idx]
        return tasks.init_qpos(self.task_id, draws[:-1], xp=xp)

    def _obs(self, data: Any, xp: Any) -> dict[str, Any]:
        ee_mat = data.site_xmat[self.site_id].reshape(3, 3)
        obs = {"proprio": ctl.proprio(data.site_xpos[self.site_id], ee_mat, data.qpos[7:9], xp=xp)}
        if self.renderer is not None:
            obs.update(self.renderer(data))
        return obs

    def _success(self, data: Any, xp: Any) -> Any:
        return tasks.success(data.xpos[self.bowl_body], data.xmat[self.bowl_body].reshape(3, 3)[2, 2],
                             data.xpos[self.plate_body], xp=xp)

    @staticmethod
    def _check_action(action: Any) -> None:
        shape = np.shape(action)
        if shape != (ctl.ACTION_DIM,):
            raise ValueError(f"action must have shape ({ctl.ACTION_DIM},), got {shape}")


class CpuEnv(_Common):
    """C-engine backend (numpy state). Same ``reset``/``step`` API as ``MjxEnv``."""

    def __init__(self, config: SimConfig = SimConfig(), task_id: int = 0, **kwargs):
        super().__init__(config, task_id, **kwargs)
        self._jacp = np.zeros((3, self.nv))
        self._jacr = np.zeros((3, self.nv))

    def _draws(self, key: Any) -> np.ndarray:
        if isinstance(key, np.random.Generator):
            return key.random(tasks.NUM_DRAWS + 1)
        return np.asarray(jax.random.uniform(key, (tasks.NUM_DRAWS + 1,)), np.float64)

    def initial_qpos(self, key: Any) -> np.ndarray:
        """The ``(nq,)`` qpos a reset from ``key`` (jax PRNG key or ``numpy.random.Generator``) starts
        from, before the settle steps."""
        return self._draws_to_qpos(self._draws(key), np)

    def reset(self, key: Any) -> State:
        """New episode from a jax PRNG key (or a ``numpy.random.Generator``)."""
        return self.reset_to(self.initial_qpos(key))

    def reset_to(self, qpos: np.ndarray) -> State:
        """New episode from a given initial ``qpos`` (e.g. ``init_states[i]``), then settle."""
        qpos = np.asarray(qpos, np.float64)
        if qpos.shape != (self.nq,) or not np.all(np.isfinite(qpos)):
            raise ValueError(f"qpos must be finite with shape ({self.nq},), got {qpos.shape}")
        data = self._data_at(qpos)
        for _ in range(self.config.settle_steps):
            self._physics(data, SETTLE_ACTION)
        return self._state(data, info={})

    def restore(self, flat_state: np.ndarray) -> State:
        """An episode continued from a recorded state: a dataset's flattened ``states[t]`` (``[time, qpos,
        qvel]``, LIBERO's layout), with no settling. The controller keeps no state of its own, so the
        next ``step`` acts exactly as it did in the recorded episode, up to the solver's warm start."""
        flat = np.asarray(flat_state, np.float64)
        if flat.shape != (1 + self.nq + self.nv,) or not np.all(np.isfinite(flat)):
            raise ValueError(f"flat state must be finite with shape ({1 + self.nq + self.nv},) = [time, "
                             f"qpos ({self.nq}), qvel ({self.nv})], got {flat.shape}")
        return self._state(self._data_at(flat[1: 1 + self.nq], flat[1 + self.nq:], flat[0]), info={})

    def _data_at(self, qpos: np.ndarray, qvel: np.ndarray | None = None, time: float = 0.0) -> mujoco.MjData:
        """Fresh ``MjData`` at ``qpos`` (and ``qvel``, ``time``), the arm's servos holding it, the gripper
        open (the controller rewrites the controls at every step), kinematics computed."""
        data = mujoco.MjData(self.mj_model)
        data.time = time
        data.qpos[:] = qpos
        if qvel is not None:
            data.qvel[:] = qvel
        data.ctrl[:7] = qpos[:7]
        data.ctrl[7:] = panda.FINGER_OPEN
        mujoco.mj_forward(self.mj_model, data)
        return data

    def _physics(self, data: mujoco.MjData, action: np.ndarray) -> None:
        mujoco.mj_jacSite(self.mj_model, data, self._jacp, self._jacr, self.site_id)
        data.ctrl[:] = ctl.servo_targets(np.asarray(action, np.float64), data.qpos[:7].copy(),
                                         self._jacp[:, :7], self._jacr[:, :7], self.controller, xp=np)
        for _ in range(self.substeps):
            mujoco.mj_step(self.mj_model, data)

    def _state(self, data: mujoco.MjData, info: dict[str, Any]) -> State:
        solved = np.float32(self._success(data, np))
        return State(data=data, obs=self._obs(data, np), reward=solved, done=solved,
                     metrics={"success": solved}, info=info)

    def step(self, state: State, action: np.ndarray) -> State:
        """One 20 Hz control step; ``state`` is not modified (its MjData is copied)."""
        return self.step_inplace(state.replace(data=copy.copy(state.data)), action)

    def step_inplace(self, state: State, action: np.ndarray) -> State:
        """``step`` that advances ``state.data`` in place (no MjData copy, which costs
        more than the physics here). The old ``state`` must not be used afterwards."""
        self._check_action(action)
        action = np.asarray(action, np.float64)
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action}")
        data = state.data
        self._physics(data, action)
        if not np.all(np.isfinite(data.qpos)):
            raise FloatingPointError("simulation diverged (non-finite qpos)")
        return self._state(data, info=dict(state.info))


def _mjx_promotion():
    # MJX's internals mix Python floats and bools; keep them working under strict promotion.
    return jax.numpy_dtype_promotion("standard")


def _mjx():
    from mujoco import mjx  # imported lazily: it costs seconds and the C backend does not need it

    return mjx


def mjx_step(model: Any, data: Any) -> Any:
    """One MJX physics step that integrates and places box-box contacts like MuJoCo's C engine.

    Two departures of MJX's JAX backend (mujoco-mjx 3.17) from the C engine are undone here:

    * MuJoCo's implicit integrators leave an actuator whose force sits at its ``forcerange`` bound
      out of the velocity derivative (``mjd_actuator_vel``: its force no longer depends on velocity).
      MJX's ``implicit`` keeps every actuator's ``kv``, so a saturated arm servo is damped in MJX and
      not in the C engine: from the same state and controls one 5 ms step left the arm's joint
      velocities up to 0.31 rad/s apart, and the scripted expert, 100% on the C engine, solved
      64-84% of tasks 0, 6, 7 and 9 on MJX. The implicit update here removes the clamped actuators'
      terms, as the C engine does.
    * MJX's box-box collider puts each contact on the reference face, the C engine halfway between
      the two surfaces (:func:`_midpoint_box_contacts`). The friction rows' Jacobian is taken at the
      contact point, so in a pinch grasp the two engines gave the held bowl's friction a lever arm
      half a penetration depth apart (2.9 mm at 5.8 mm depth; the bowl's net constraint force 4%
      apart, in float32 and float64 alike), and on task 7 the bowl slipped from the fingers in MJX
      where it held in the C engine.

    Args:
      model: an ``mjx.Model`` whose integrator is implicitfast (the scene's).
      data: an ``mjx.Data`` of it (vmap over a batch).

    Returns:
      The ``mjx.Data`` one physics step (``model.opt.timestep``) later.

    Raises:
      ValueError: another integrator.
    """
    with _mjx_promotion():  # MJX's internals mix Python floats and bools
        return _mjx_step(model, data)


def _mjx_step(model: Any, data: Any) -> Any:
    from mujoco.mjx._src import derivative, support
    from mujoco.mjx._src import forward as mjx_forward

    if int(model.opt.integrator) != int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST):
        raise ValueError(f"mjx_step integrates implicitfast models only, got integrator {model.opt.integrator}")
    data = _mjx_forward(model, data)
    qderiv = derivative.deriv_smooth_vel(model, data)
    if qderiv is not None and model.nu:
        force, forcerange = data.actuator_force, jnp.asarray(model.actuator_forcerange)
        clamped = jnp.asarray(model.actuator_forcelimited, bool) & (
            (force <= forcerange[:, 0]) | (force >= forcerange[:, 1]))
        affine_bias = jnp.asarray(model.actuator_biastype) == int(mujoco.mjtBias.mjBIAS_AFFINE)
        affine_gain = jnp.asarray(model.actuator_gaintype) == int(mujoco.mjtGain.mjGAIN_AFFINE)
        vel = (jnp.where(affine_bias, jnp.asarray(model.actuator_biasprm)[:, 2], 0.0)
               + jnp.where(affine_gain, jnp.asarray(model.actuator_gainprm)[:, 2], 0.0) * data.ctrl)
        moment = data._impl.actuator_moment  # (nu, nv)
        qderiv = qderiv - moment.T @ (moment * jnp.where(clamped, vel, 0.0)[:, None])
    qacc = data.qacc
    if qderiv is not None:
        qm = support.full_m(model, data) if support.is_sparse(model) else data._impl.M
        factor = jax.scipy.linalg.cho_factor(qm - model.opt.timestep * qderiv)
        qacc = jax.scipy.linalg.cho_solve(factor, data.qfrc_smooth + data.qfrc_constraint)
    return mjx_forward._advance(model, data, data.act_dot, qacc)


def _mjx_forward(model: Any, data: Any) -> Any:
    """``mjx.forward`` (the stages of mujoco-mjx 3.17's JAX backend, in its order) with box-box contacts
    moved to the C engine's midpoint between collision and constraint assembly."""
    from mujoco.mjx._src import collision_driver, constraint, sensor, smooth, solver
    from mujoco.mjx._src import forward as mjx_forward

    d = data
    for stage in (smooth.kinematics, smooth.com_pos, smooth.camlight, smooth.tendon, smooth.crb,
                  smooth.tendon_armature, smooth.factor_m, collision_driver.collision):
        d = stage(model, d)
    d = _midpoint_box_contacts(model, d)
    for stage in (constraint.make_constraint, smooth.transmission, sensor.sensor_pos, mjx_forward.fwd_velocity,
                  sensor.sensor_vel, mjx_forward.fwd_actuation, mjx_forward.fwd_acceleration):
        d = stage(model, d)
    if d._impl.efc_J.size == 0:
        return d.replace(qacc=d.qacc_smooth)
    return sensor.sensor_acc(model, solver.solve(model, d))


def _midpoint_box_contacts(model: Any, data: Any) -> Any:
    """Moves every box-box contact from the face MJX's collider put it on to halfway between the two
    boxes' surfaces along the contact normal, where MuJoCo's C engine puts it (``mjc_BoxBox``).

    The point lies on the reference face of one box, and that box is found by which surface it is on
    (its signed distance to that box is ~0, to the other about the depth). Along the normal (from
    geom 1 towards geom 2) the midpoint is then ``dist / 2`` further on from geom 1's surface, and
    ``dist / 2`` back from geom 2's. Depth, normal and frame are unchanged."""
    contact = data._impl.contact
    if contact.pos.shape[0] == 0:
        return data
    geom_type = jnp.asarray(model.geom_type)
    box = int(mujoco.mjtGeom.mjGEOM_BOX)
    g1, g2 = contact.geom[:, 0], contact.geom[:, 1]
    box_box = (geom_type[g1] == box) & (geom_type[g2] == box)

    def surface_distance(g):
        local = jnp.einsum("ci,cij->cj", contact.pos - data.geom_xpos[g], data.geom_xmat[g])
        return jnp.max(jnp.abs(local) - jnp.asarray(model.geom_size)[g], axis=-1)

    on_first = jnp.abs(surface_distance(g1)) <= jnp.abs(surface_distance(g2))
    shift = jnp.where(on_first, 0.5, -0.5) * contact.dist
    pos = contact.pos + jnp.where(box_box, shift, 0.0)[:, None] * contact.frame[:, 0, :]
    return data.tree_replace({"_impl.contact.pos": pos})


def make_env(config: SimConfig, task_id: int, **kwargs) -> Any:
    """The backend ``config.backend`` names: a ``CpuEnv`` or an ``MjxEnv`` (``sim/mjx_env.py``)."""
    if config.backend == "mjx":
        from sim.mjx_env import MjxEnv  # imports brax and MJX: seconds the C backend does not spend

        return MjxEnv(config, task_id, **kwargs)
    return CpuEnv(config, task_id, **kwargs)


def camera_renderer(mj_model: mujoco.MjModel, *, resolution: int = 128, wrist_camera: bool = False,
                    depth_and_seg: bool = False, static_split: bool = True, unroll: int | bool | None = None,
                    tile: int | None = 8, chunk: int = 16, pixels: bool = False) -> Renderer:
    """An observation renderer (``data -> dict``) built on ``sim/render.py``'s JAX ray caster.

    Works on ``mjx.Data`` under jit/vmap (the MJX backend) and on ``mujoco.MjData``. Keys:
    ``agentview_rgb`` (and ``eye_in_hand_rgb``), plus ``*_depth`` / ``*_seg`` on request.
    ``pixels=True``: the RGB frames alone, as brax's vision PPO reads them: float32 in [0, 1] under
    ``pixels/agentview_rgb`` (and ``pixels/eye_in_hand_rgb``), the keys its CNN runs on.
    ``static_split=False`` tests every geom in every frame (the same frames up to float rounding;
    for benchmarks that time the split). ``unroll``: geoms per step of the renderer's scans
    (``sim.render.render``; the same frames); ``None``: 4 on a GPU, 1 elsewhere, as measured (128 px,
    render-only: H100 1.32-1.34x at batch 1024-4096 and 1.00x at 8192; on a 2-core CPU 0.94x).
    ``tile``/``chunk``: tile culling (``sim/render_cull.py``: each ray tests only the geoms whose projected
    bound covers its ``tile`` x ``tile`` pixel tile; the same frames); ``tile=None`` tests every geom.
    """
    from sim import render

    if pixels and depth_and_seg:
        raise ValueError("pixels=True gives the RGB frames alone (brax's CNN input); depth_and_seg needs pixels=False")
    if unroll is None:
        unroll = 4 if jax.default_backend() == "gpu" else 1

    scene_ = render.build_scene(mj_model)
    cameras = ("agentview", "eye_in_hand") if wrist_camera else ("agentview",)
    # a fixed camera's static geoms are intersected once, here, not in every frame (sim/render.py)
    draws = {cam: render.make_renderer(scene_, cam, height=resolution, width=resolution,
                                       model=mj_model if static_split else None, unroll=unroll, tile=tile,
                                       chunk=chunk)
             for cam in cameras}

    def renderer(data: Any) -> dict[str, Any]:
        out = {}
        for cam, draw in draws.items():
            frame = draw(data)
            if pixels:
                out[f"pixels/{cam}_rgb"] = frame.rgb.astype(jnp.float32) / 255.0
                continue
            out[f"{cam}_rgb"] = frame.rgb
            if depth_and_seg:
                out[f"{cam}_depth"] = frame.depth
                out[f"{cam}_seg"] = frame.seg
        return out

    return renderer
