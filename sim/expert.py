"""Scripted expert: LIBERO-format actions that pick the target bowl and place it on the plate.

A phase machine (approach, descend, grasp, lift, carry, place, release, retreat) driven by
privileged state (tool-centre pose, bowl and plate poses). With ``ExpertConfig.cycle`` the
expert keeps going after it succeeds (fixed-length world-model episodes with motion over the
whole horizon): after the retreat it grasps the bowl again, carries it to a free spot on the
table, places and releases it, retreats, brings it back to the plate, and so on, alternating
between ``AWAY_SPOTS``. Cycling also keeps the picture moving while the gripper acts (world-model
data should have few near-identical consecutive frames): the fingers start to close over the last
centimetre of the descent and the hand rises while they grip or open; a bowl that hangs on the
opened fingers is gripped again rather than chased out of reach. Without ``cycle`` (the
stop-at-success demonstrations) none of this applies. The gripper takes the bowl by its
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
# Free table spots (world xy) clear of the plate, ramekin, cookie box, cabinet, stove and every
# task's distractor bowl, within the arm's reach; cycling visits them in turn.
AWAY_SPOTS = ((-0.20, 0.13), (-0.12, -0.03))
_CREEP = 0.006  # cycling: m per step the hand rises while the gripper finishes closing / opening
_CREEP_RAMP = ((0, 0, 0.5, 0.5, 2), (0, 1, 2, 2, 2))  # cycling: creeps per step at gripper step 0..4+ (grasp; release)
_CLOSE_ABOVE = 0.015  # cycling: the fingers start to close this far (m) above the grasp point (aligned in xy)
_MIN_DESCENT_SPEED = 0.12  # cycling: |position action| floor while descending
_STALL_STEPS = 100  # cycling: a phase that lasts this long gives up (retreat, then start over)


@dataclasses.dataclass(frozen=True)
class ExpertConfig:
    """Gains, tolerances and noise of the scripted expert."""

    gain: float = 1.0  # action per (error / action scale)
    max_speed: float = 0.7  # |position action| cap
    noise: float = 0.0  # std of Gaussian noise added to the motion part of the action
    # the noise's step-to-step correlation (an AR(1) process of unit variance: 0 = independent draws, the DART
    # default; towards 1 the perturbation holds its direction over many steps. Measured on the C engine, tasks 0, 4, 8
    # x 3 initial states: the tool centre's largest departure from the clean expert's path in the first 40 steps,
    # median 21 cm at noise 0.3 and correlation 0.9, against 12 cm at DART's independent 0.1)
    noise_correlation: float = 0.0
    grip_steps: int = 8  # control steps to close / open the gripper
    cycle: bool = False  # after the retreat, start over: bowl to a table spot, back to the plate, ...

    def validate(self) -> None:
        if not 0 <= self.noise <= 1:
            raise ValueError(f"expert noise must be in [0, 1], got {self.noise}")
        if not 0 <= self.noise_correlation < 1:  # also rejects NaN
            raise ValueError(f"expert noise_correlation must be in [0, 1), got {self.noise_correlation}")
        if self.gain <= 0 or not 0 < self.max_speed <= 1 or self.grip_steps < 1:
            raise ValueError(f"bad expert gains: {self}")


@struct.dataclass
class ExpertState:
    """Per-episode memory: phase, steps spent in it, the grasp yaw, the lift height, where the
    bowl goes (0 = the plate, k = ``AWAY_SPOTS[k - 1]``) and how many away trips were made."""

    phase: Any
    count: Any
    yaw: Any
    lift_z: Any
    goal: Any
    trips: Any


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
    zero = xp.asarray(0, xp.int32)
    return ExpertState(phase=xp.asarray(APPROACH, xp.int32), count=zero, yaw=xp.asarray(_grasp_yaw(priv, xp), dtype),
                       lift_z=xp.asarray(lift_z, dtype), goal=zero, trips=zero)


def act(priv: dict[str, Any], est: ExpertState, noise: Any, cfg: ExpertConfig = ExpertConfig(),
        *, xp: Any = np) -> tuple[Any, ExpertState]:
    """One expert action to execute (noised by ``noise``); see ``act_labelled``.

    Returns:
      (action (7,) in [-1, 1], next memory).
    """
    executed, _, est = act_labelled(priv, est, noise, cfg, xp=xp)
    return executed, est


def act_labelled(priv: dict[str, Any], est: ExpertState, noise: Any, cfg: ExpertConfig = ExpertConfig(),
                 *, xp: Any = np) -> tuple[Any, Any, ExpertState]:
    """One expert step, DART style: the noisy action is executed, the clean one is the label.

    Args:
      priv: from ``privileged``.
      est: expert memory.
      noise: (6,) standard-normal draws (scaled by ``cfg.noise``; zeros for none).
      cfg: gains.
      xp: numpy or jax.numpy.

    Returns:
      (executed action (7,), clean action (7,), next memory); both in [-1, 1], equal without noise.
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
    plate_top = plate[2] + scene.PLATE_TOP
    # Where the bowl goes: the plate (measured) or a table spot (fixed).
    goal_xy = xp.concatenate([plate[None, :2], xp.asarray(AWAY_SPOTS, dtype)])[est.goal]
    goal_top = xp.where(est.goal == 0, plate_top, scene.TABLE_TOP_Z).astype(dtype)
    bowl_on_goal_xy = tcp[:2] + (goal_xy - bowl[:2])  # moves the bowl centre over the goal
    carry_z = xp.clip(tcp[2] + (goal_top + _CARRY_CLEARANCE - bowl[2]), est.lift_z, est.lift_z + 0.1)
    place_z = xp.maximum(tcp[2] + (goal_top + 0.002 - bowl[2]), scene.TABLE_TOP_Z + 0.02)

    def point(xy, z):
        return xp.concatenate([xy, xp.reshape(z, (1,))]).astype(dtype)

    # Cycling keeps the picture moving while the gripper acts: the descent finishes during the
    # first two closing steps (the fingers reach the wall on the third), then the hand creeps
    # upward; on release it rises once the fingers have opened clear of the wall.
    ramp = xp.asarray(_CREEP_RAMP, dtype)[xp.where(est.phase == GRASP, 0, 1), xp.minimum(est.count, 4)]
    creep = xp.where(xp.asarray(cfg.cycle), ramp * _CREEP, 0.0).astype(dtype)
    hold = point(tcp[:2], tcp[2] + creep)
    grasp_point = point(grasp_xy, bowl[2] + _GRASP_HEIGHT)
    closing_descent = xp.asarray(cfg.cycle) & (est.count < 2)

    targets = xp.stack([
        point(grasp_xy, bowl[2] + _GRASP_HEIGHT + _HOVER),  # approach
        grasp_point,  # descend
        xp.where(closing_descent, grasp_point, hold),  # grasp: hold still (or finish the descent, creep up)
        point(tcp[:2], est.lift_z),  # lift
        point(bowl_on_goal_xy, carry_z),  # carry
        point(bowl_on_goal_xy, place_z),  # place
        hold,  # release
        point(tcp[:2], plate_top + 0.2),  # retreat
    ])
    grip = xp.asarray([-1, -1, 1, 1, 1, 1, -1, -1], dtype)
    pos_err = targets[est.phase] - tcp
    bowl_xy_err = xp.sqrt(xp.sum((goal_xy - bowl[:2]) ** 2))
    dist = xp.sqrt(xp.sum(pos_err * pos_err))
    rot_err = ctl.rotation_error(priv["tcp_mat"], _yaw_rot(est.yaw, xp) @ xp.asarray(_HOME_MAT, dtype), xp=xp)
    rot_ok = xp.sqrt(xp.sum(rot_err * rot_err)) < 0.05
    done = xp.stack([
        (dist < 0.01) & rot_ok,
        xp.where(xp.asarray(cfg.cycle), (xp.sqrt(xp.sum(pos_err[:2] ** 2)) < 0.006) & (xp.abs(pos_err[2]) < _CLOSE_ABOVE),
                 dist < 0.006),
        est.count >= cfg.grip_steps,
        dist < 0.015,
        (bowl_xy_err < 0.008) & (xp.abs(pos_err[2]) < 0.02),
        (bowl[2] - goal_top < 0.006) | (est.count >= 40),
        est.count >= cfg.grip_steps,
        xp.asarray(cfg.cycle) & (dist < 0.015),  # retreat: terminal unless cycling
    ])[est.phase]
    move = xp.clip(pos_err / 0.05 * cfg.gain, -cfg.max_speed, cfg.max_speed)
    # Cycling: the descent ends at a minimum speed instead of creeping in exponentially.
    floor = xp.where(xp.asarray(cfg.cycle) & (est.phase == DESCEND), _MIN_DESCENT_SPEED, 0.0)
    move = move * xp.maximum(1.0, floor / xp.maximum(xp.sqrt(xp.sum(move * move)), 1e-6))
    turn = xp.clip(rot_err / 0.5 * cfg.gain, -1.0, 1.0)
    # Noise is for diverse demonstrations: full in the gross phases, damped where precision
    # matters (descend, place) and off while the gripper acts; rotation noise is smaller.
    phase_noise = xp.asarray(_NOISE_BY_PHASE, dtype)[est.phase]
    noise_scale = xp.asarray([1.0, 1.0, 1.0, 0.3, 0.3, 0.3], dtype) * (cfg.noise * phase_noise)
    clean_motion = xp.concatenate([move, turn])
    noisy_motion = clean_motion + noise_scale * xp.asarray(noise, dtype)
    grip_action = xp.reshape(grip[est.phase], (1,))
    clean = xp.concatenate([xp.clip(clean_motion, -1.0, 1.0), grip_action]).astype(dtype)
    executed = xp.concatenate([xp.clip(noisy_motion, -1.0, 1.0), grip_action]).astype(dtype)
    phase = xp.where(done, xp.where(est.phase == RETREAT, APPROACH, xp.minimum(est.phase + 1, RETREAT)), est.phase)
    # Lost the bowl while carrying or placing (it is no longer between the fingers): start over.
    held_offset = tcp - bowl
    near_hand = (xp.sqrt(xp.sum(held_offset[:2] ** 2)) <= 0.08) & (held_offset[2] <= 0.07)
    lost = ((est.phase == CARRY) | (est.phase == PLACE)) & ~near_hand
    phase = xp.where(lost, APPROACH, phase)
    # Cycling: a bowl that rises with the opened hand while it retreats hangs on the fingers (else
    # the approach chases it out of reach): close them again, which grips it or lets it drop.
    hanging = xp.asarray(cfg.cycle) & (est.phase == RETREAT) & near_hand & (bowl[2] - goal_top > 0.02)
    phase = xp.where(hanging, GRASP, phase)
    # Cycling never stands still: a phase that makes no progress gives up and retreats.
    stalled = xp.asarray(cfg.cycle) & (est.count >= _STALL_STEPS) & ~done & ~lost & ~hanging
    phase = xp.where(stalled, RETREAT, phase).astype(xp.int32)
    count = xp.where(done | lost | hanging | stalled, 0, est.count + 1).astype(xp.int32)
    # A finished trip (retreat done) sends the bowl elsewhere: plate -> a table spot -> plate -> the next spot.
    trip_done = done & (est.phase == RETREAT)
    next_goal = xp.where(est.goal == 0, 1 + est.trips % len(AWAY_SPOTS), 0)
    goal = xp.where(trip_done, next_goal, est.goal).astype(xp.int32)
    trips = xp.where(trip_done & (est.goal == 0), est.trips + 1, est.trips).astype(xp.int32)
    return executed, clean, est.replace(phase=phase, count=count, goal=goal, trips=trips)


def correlated(previous: Any, draw: Any, correlation: float, *, xp: Any = np) -> Any:
    """The next value of a unit-variance AR(1) noise process: ``rho * previous + sqrt(1 - rho^2) * draw`` for a
    standard-normal ``draw``; exactly ``draw`` for ``rho = 0`` (independent draws)."""
    if correlation == 0:
        return draw
    rho = float(correlation)
    return rho * previous + float(np.sqrt(1.0 - rho * rho)) * xp.asarray(draw)


def rollout_cpu(env: Any, qpos: np.ndarray, *, cfg: ExpertConfig = ExpertConfig(), rng: np.random.Generator | None = None,
                max_steps: int | None = None, record: bool = False, stop_at_success: bool = True) -> dict[str, Any]:
    """Runs the expert on the C backend from an initial qpos.

    Args:
      stop_at_success: stop at the first success (else run exactly ``max_steps`` steps).

    Returns:
      dict with ``success`` (solved at some step), ``first_success`` (index of the first action
      after which the task was solved, -1 if never), ``steps`` (int), ``phase`` (final phase
      name) and, with ``record``, ``actions`` (T, 7) the clean expert labels, ``executed`` (T, 7)
      the actions actually executed (noised, DART style) and ``states`` (``State`` list, T + 1).
    """
    cfg.validate()
    rng = rng if rng is not None else np.random.default_rng(0)
    max_steps = env.config.max_steps if max_steps is None else max_steps
    state = env.reset_to(qpos)
    est = init(privileged(env, state.data), xp=np)
    actions, executed, states = [], [], [state]
    solved_at_reset, first_success = bool(state.done), -1
    steps = 0
    noise = np.zeros(6)
    while steps < max_steps and not (stop_at_success and (solved_at_reset or first_success >= 0)):
        noise = correlated(noise, rng.standard_normal(6), cfg.noise_correlation) if cfg.noise > 0 else np.zeros(6)
        action, label, est = act_labelled(privileged(env, state.data), est, noise, cfg, xp=np)
        state = env.step(state, action) if record else env.step_inplace(state, action)
        if first_success < 0 and state.done:
            first_success = steps
        steps += 1
        if record:
            actions.append(label)
            executed.append(action)
            states.append(state)
    out = {"success": solved_at_reset or first_success >= 0, "first_success": first_success, "steps": steps,
           "phase": PHASE_NAMES[int(est.phase)]}
    if record:
        empty = np.zeros((0, ctl.ACTION_DIM))
        out["actions"] = np.stack(actions) if actions else empty
        out["executed"] = np.stack(executed) if executed else empty
        out["states"] = states
    return out


def jax_policy(env: Any, cfg: ExpertConfig = ExpertConfig()):
    """(init_fn(state) -> ExpertState, act_fn(state, est, key, noise_gain=1) -> (executed, clean, est)) for MJX.

    Both are pure and vmappable (one env each); ``key`` drives the action noise (times
    ``noise_gain``, 0 for a clean episode), or ``noise=`` gives the step's (6,) draws already scaled by the gain
    (:func:`episode_mjx` passes its correlated ones). ``executed`` is the noisy action to step with,
    ``clean`` the expert's label (DART).
    """
    cfg.validate()

    def init_fn(state):
        return init(privileged(env, state.data), xp=jnp)

    def act_fn(state, est, key=None, noise_gain=1.0, *, noise=None):
        if noise is None:  # one independent draw of the step's key (a caller with correlated noise passes it)
            noise = jax.random.normal(key, (6,), jnp.float32) * noise_gain
        return act_labelled(privileged(env, state.data), est, noise, cfg, xp=jnp)

    return init_fn, act_fn


def episode_mjx(env: Any, qpos: Any, keys: jax.Array, cfg: ExpertConfig = ExpertConfig(), *,
                noise_gain: Any = 1.0, observe: Any = None) -> tuple[Any, dict[str, Any]]:
    """One expert episode on MJX from one initial qpos, one step per key (pure, vmappable; jit it).

    Args:
      keys: ``[T]`` PRNG keys, the action noise of each step (times ``noise_gain``; 0 = clean), correlated from
        step to step by ``cfg.noise_correlation`` (:func:`correlated`).
      observe: ``observe(state) -> dict`` of arrays to record from the state each action is taken in.

    Returns:
      ``(initial state, records)``, records stacked over the ``T`` steps: ``observe``'s entries,
      ``actions`` (the clean labels), ``executed`` (the noisy actions stepped with), ``phase`` (the
      expert's phase after the step) and ``done`` (solved after the step).
    """
    init_fn, act_fn = jax_policy(env, cfg)
    state = env.reset_to(qpos)

    def body(carry, step_key):
        state, est, noise = carry
        noise = correlated(noise, jax.random.normal(step_key, (6,), jnp.float32), cfg.noise_correlation, xp=jnp)
        executed, clean, est = act_fn(state, est, noise=noise * noise_gain)
        record = {**(observe(state) if observe is not None else {}), "actions": clean, "executed": executed,
                  "phase": est.phase}
        state = env.step(state, executed)
        record["done"] = state.done
        return (state, est, noise), record

    _, records = jax.lax.scan(body, (state, init_fn(state), jnp.zeros((6,), jnp.float32)), keys)
    return state, records


def rollout_mjx(env: Any, qpos: Any, key: jax.Array, horizon: int, cfg: ExpertConfig = ExpertConfig()):
    """The expert on MJX from a batch of initial qpos for ``horizon`` steps (pure; jit it).

    Step ``t`` of episode ``i`` draws its noise from ``split(split(key, horizon)[t], n)[i]``.

    Returns:
      ``(solved [n], phases [horizon, n])``: whether each episode succeeded at any step, and the
      expert's phase after every step.
    """
    n = qpos.shape[0]
    step_keys = jax.vmap(lambda k: jax.random.split(k, n))(jax.random.split(key, horizon))  # (horizon, n)
    start, records = jax.vmap(lambda q, k: episode_mjx(env, q, k, cfg))(qpos, jnp.swapaxes(step_keys, 0, 1))
    solved = jnp.maximum(start.done, jnp.max(records["done"], axis=1))
    return solved, jnp.swapaxes(records["phase"], 0, 1)
