"""Scripted expert: LIBERO-format actions that pick the target bowl and place it on the plate.

A phase machine (approach, descend, grasp, lift, carry, place, release, retreat) driven by
privileged state (tool-centre pose, bowl and plate poses). The gripper takes the bowl by its
rim: fingers straddle the wall facing -y, the hand yawed to that wall's normal (the bowls
are octagons of boxes). Position and rotation errors become actions by proportional control,
clipped to [-1, 1]; the carry and place phases servo the *bowl's* measured centre onto the
plate, so grasp offsets do not matter.

Written once for ``xp`` = numpy (C backend) or jax.numpy (MJX backend, vmappable: the phase
is data, selection is by indexing, no Python branching on values).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim import controller as ctl
from sim import scene

APPROACH, DESCEND, GRASP, LIFT, CARRY, PLACE, RELEASE, RETREAT = range(8)
PHASE_NAMES = ("approach", "descend", "grasp", "lift", "carry", "place", "release", "retreat")
_GRASP_RADIUS = scene.BOWL_RADIUS - scene.BOWL_WALL / 2  # wall centre line
_GRASP_HEIGHT = 0.028  # tool centre above the bowl's bottom while grasping
_HOVER = 0.10  # pre-grasp height above the rim
_CARRY_CLEARANCE = 0.10  # bowl bottom above the plate top while carrying
_NOISE_BY_PHASE = (1.0, 0.2, 0.0, 1.0, 1.0, 0.2, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class ExpertConfig:
    """Gains, tolerances and noise of the scripted expert."""

    gain: float = 1.0  # action per (error / action scale)
    max_speed: float = 0.7  # |position action| cap
    noise: float = 0.0  # std of Gaussian noise added to the motion part of the action
    grip_steps: int = 8  # control steps to close / open the gripper

    def validate(self) -> None:
        if not 0 <= self.noise <= 1:
            raise ValueError(f"expert noise must be in [0, 1], got {self.noise}")
        if self.gain <= 0 or not 0 < self.max_speed <= 1 or self.grip_steps < 1:
            raise ValueError(f"bad expert gains: {self}")


@struct.dataclass
class ExpertState:
    """Per-episode memory: phase, steps spent in it, the grasp yaw, the lift height."""

    phase: Any
    count: Any
    yaw: Any
    lift_z: Any


def privileged(env: Any, data: Any) -> dict[str, Any]:
    """The state the expert reads, from an ``mjx.Data`` or ``mujoco.MjData``."""
    return {
        "tcp_pos": data.site_xpos[env.site_id],
        "tcp_mat": data.site_xmat[env.site_id].reshape(3, 3),
        "bowl_pos": data.xpos[env.bowl_body],
        "bowl_mat": data.xmat[env.bowl_body].reshape(3, 3),
        "plate_pos": data.xpos[env.plate_body],
    }


def _yaw_rot(yaw: Any, xp: Any) -> Any:
    c, s = xp.cos(yaw), xp.sin(yaw)
    zero, one = xp.zeros_like(c), xp.ones_like(c)
    return xp.stack([xp.stack([c, -s, zero]), xp.stack([s, c, zero]), xp.stack([zero, zero, one])])


# Tool orientation at home: pointing down, fingers closing along world y.
_HOME_MAT = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def _grasp_yaw(priv: dict[str, Any], xp: Any) -> Any:
    """Yaw (from the home orientation) that faces the bowl wall whose normal is nearest -y."""
    bowl_yaw = xp.arctan2(priv["bowl_mat"][1, 0], priv["bowl_mat"][0, 0])
    return xp.mod(bowl_yaw + np.pi / 2 + np.pi / 8, np.pi / 4) - np.pi / 8


def init(priv: dict[str, Any], *, xp: Any = np) -> ExpertState:
    """Expert memory for a fresh episode."""
    dtype = priv["tcp_pos"].dtype
    lift_z = priv["bowl_pos"][2] + _GRASP_HEIGHT + _HOVER
    return ExpertState(phase=xp.asarray(APPROACH, xp.int32), count=xp.asarray(0, xp.int32),
                       yaw=xp.asarray(_grasp_yaw(priv, xp), dtype), lift_z=xp.asarray(lift_z, dtype))


def act(priv: dict[str, Any], est: ExpertState, noise: Any, cfg: ExpertConfig = ExpertConfig(),
        *, xp: Any = np) -> tuple[Any, ExpertState]:
    """One expert action.

    Args:
      priv: from ``privileged``.
      est: expert memory.
      noise: (6,) standard-normal draws (scaled by ``cfg.noise``; zeros for none).
      cfg: gains.
      xp: numpy or jax.numpy.

    Returns:
      (action (7,) in [-1, 1], next memory).
    """
    dtype = priv["tcp_pos"].dtype
    tcp, bowl, plate = priv["tcp_pos"], priv["bowl_pos"], priv["plate_pos"]
    # Until the descent starts, track the bowl (it may have been nudged or dropped).
    approaching = est.phase == APPROACH
    est = est.replace(
        yaw=xp.where(approaching, _grasp_yaw(priv, xp), est.yaw).astype(dtype),
        lift_z=xp.where(approaching, bowl[2] + _GRASP_HEIGHT + _HOVER, est.lift_z).astype(dtype),
    )
    normal_angle = est.yaw - np.pi / 2
    radial = xp.stack([xp.cos(normal_angle), xp.sin(normal_angle), xp.zeros_like(normal_angle)])
    grasp_xy = (bowl + _GRASP_RADIUS * radial)[:2]
    bowl_on_plate_xy = tcp[:2] + (plate[:2] - bowl[:2])  # moves the bowl centre over the plate
    plate_top = plate[2] + scene.PLATE_TOP
    carry_z = xp.clip(tcp[2] + (plate_top + _CARRY_CLEARANCE - bowl[2]), est.lift_z, est.lift_z + 0.1)
    place_z = xp.maximum(tcp[2] + (plate_top + 0.002 - bowl[2]), scene.TABLE_TOP_Z + 0.02)

    def point(xy, z):
        return xp.concatenate([xy, xp.reshape(z, (1,))]).astype(dtype)

    targets = xp.stack([
        point(grasp_xy, bowl[2] + _GRASP_HEIGHT + _HOVER),  # approach
        point(grasp_xy, bowl[2] + _GRASP_HEIGHT),  # descend
        tcp,  # grasp: hold still
        point(tcp[:2], est.lift_z),  # lift
        point(bowl_on_plate_xy, carry_z),  # carry
        point(bowl_on_plate_xy, place_z),  # place
        tcp,  # release
        point(tcp[:2], plate_top + 0.2),  # retreat
    ])
    grip = xp.asarray([-1, -1, 1, 1, 1, 1, -1, -1], dtype)
    pos_err = targets[est.phase] - tcp
    bowl_xy_err = xp.sqrt(xp.sum((plate[:2] - bowl[:2]) ** 2))
    dist = xp.sqrt(xp.sum(pos_err * pos_err))
    rot_err = ctl.rotation_error(priv["tcp_mat"], _yaw_rot(est.yaw, xp) @ xp.asarray(_HOME_MAT, dtype), xp=xp)
    rot_ok = xp.sqrt(xp.sum(rot_err * rot_err)) < 0.05
    done = xp.stack([
        (dist < 0.01) & rot_ok,
        dist < 0.006,
        est.count >= cfg.grip_steps,
        dist < 0.015,
        (bowl_xy_err < 0.008) & (xp.abs(pos_err[2]) < 0.02),
        (bowl[2] - plate_top < 0.006) | (est.count >= 40),
        est.count >= cfg.grip_steps,
        xp.asarray(False),
    ])[est.phase]
    move = xp.clip(pos_err / 0.05 * cfg.gain, -cfg.max_speed, cfg.max_speed)
    turn = xp.clip(rot_err / 0.5 * cfg.gain, -1.0, 1.0)
    # Noise is for diverse demonstrations: full in the gross phases, damped where precision
    # matters (descend, place) and off while the gripper acts; rotation noise is smaller.
    phase_noise = xp.asarray(_NOISE_BY_PHASE, dtype)[est.phase]
    noise_scale = xp.asarray([1.0, 1.0, 1.0, 0.3, 0.3, 0.3], dtype) * (cfg.noise * phase_noise)
    motion = xp.concatenate([move, turn]) + noise_scale * xp.asarray(noise, dtype)
    action = xp.concatenate([xp.clip(motion, -1.0, 1.0), xp.reshape(grip[est.phase], (1,))]).astype(dtype)
    phase = xp.where(done, xp.minimum(est.phase + 1, RETREAT), est.phase)
    # Lost the bowl while carrying or placing (it is no longer between the fingers): start over.
    held_offset = tcp - bowl
    lost = ((est.phase == CARRY) | (est.phase == PLACE)) & (
        (xp.sqrt(xp.sum(held_offset[:2] ** 2)) > 0.08) | (held_offset[2] > 0.07))
    phase = xp.where(lost, APPROACH, phase).astype(xp.int32)
    count = xp.where(done | lost, 0, est.count + 1).astype(xp.int32)
    return action, est.replace(phase=phase, count=count)


def rollout_cpu(env: Any, qpos: np.ndarray, *, cfg: ExpertConfig = ExpertConfig(), rng: np.random.Generator | None = None,
                max_steps: int | None = None, record: bool = False) -> dict[str, Any]:
    """Runs the expert on the C backend from an initial qpos until success or the step limit.

    Returns:
      dict with ``success`` (bool), ``steps`` (int), ``phase`` (final phase name) and, with
      ``record``, ``actions`` (T, 7) and ``states`` (list of ``State``, T + 1 long).
    """
    cfg.validate()
    rng = rng if rng is not None else np.random.default_rng(0)
    max_steps = env.config.max_steps if max_steps is None else max_steps
    state = env.reset_to(qpos)
    est = init(privileged(env, state.data), xp=np)
    actions, states = [], [state]
    success = bool(state.done)
    steps = 0
    while not success and steps < max_steps:
        noise = rng.standard_normal(6) if cfg.noise > 0 else np.zeros(6)
        action, est = act(privileged(env, state.data), est, noise, cfg, xp=np)
        state = env.step(state, action) if record else env.step_inplace(state, action)
        steps += 1
        success = bool(state.done)
        if record:
            actions.append(action)
            states.append(state)
    out = {"success": success, "steps": steps, "phase": PHASE_NAMES[int(est.phase)]}
    if record:
        out["actions"] = np.stack(actions) if actions else np.zeros((0, ctl.ACTION_DIM))
        out["states"] = states
    return out


def jax_policy(env: Any, cfg: ExpertConfig = ExpertConfig()):
    """(init_fn(state) -> ExpertState, act_fn(state, est, key) -> (action, est)) for MJX.

    Both are pure and vmappable (one env each); ``key`` drives the action noise.
    """
    cfg.validate()

    def init_fn(state):
        return init(privileged(env, state.data), xp=jnp)

    def act_fn(state, est, key):
        noise = jax.random.normal(key, (6,), jnp.float32)
        return act(privileged(env, state.data), est, noise, cfg, xp=jnp)

    return init_fn, act_fn


def rollout_mjx(env: Any, qpos: Any, key: jax.Array, horizon: int, cfg: ExpertConfig = ExpertConfig()):
    """The expert on MJX from a batch of initial qpos for ``horizon`` steps (pure; jit it).

    Returns:
      ``(solved [n], phases [horizon, n])``: whether each episode succeeded at any step, and the
      expert's phase after every step.
    """
    init_fn, act_fn = jax_policy(env, cfg)
    state = jax.vmap(env.reset_to)(qpos)
    est = jax.vmap(init_fn)(state)

    def body(carry, step_key):
        state, est, solved = carry
        action, est = jax.vmap(act_fn)(state, est, jax.random.split(step_key, qpos.shape[0]))
        state = jax.vmap(env.step)(state, action)
        return (state, est, jnp.maximum(solved, state.done)), est.phase

    (_, _, solved), phases = jax.lax.scan(body, (state, est, state.done), jax.random.split(key, horizon))
    return solved, phases
