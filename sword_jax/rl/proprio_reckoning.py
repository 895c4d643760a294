"""Proprio for imagined rollouts, dead-reckoned from the actions the policy takes.

A video world model predicts frames, not the robot's joint state, yet the policy reads proprio
(end-effector position, orientation, fingers). Marking it missing in imagination (the policy's
learned "missing proprio" embedding) makes GRPO in the world model optimise a different input
mode from the one the policy is evaluated with in the real environment, where proprio is valid.
Here proprio is integrated from the actions instead (``rl.imagined.proprio=reckoned``; measured on
``small``, the SFT policy reading it in the real environments succeeds less often than with proprio
missing, 0.160 vs 0.200 of 200 episodes, so ``missing`` is the default; README), by the action
convention the simulator's controller implements (``sim/controller.py``): position ``+= a[:3] * pos_scale`` (metres), a
world-frame rotation ``exp(a[3:6] * rot_scale)`` applied on the left, and each finger moving a
fraction ``finger_rate`` of the way to its servo target ``open + (closed - open) (a[6] + 1) / 2``
per step, clipped to ``[0, open]``. The arm does not realise every command in full (the IK is
damped, joints saturate): :func:`fit_gains` measures the realised fraction per axis from
demonstrations (least squares of one-step increments on the commands), which the caller passes
in; measured on the expert's episodes the yaw gain is about 0.4. The error against the true proprio grows with the horizon
(``python -m benchmarks.bench_proprio_reckoning`` measures it on the C engine); the
values here carry no dependency on ``sim`` -- callers pass the controller's constants.

Proprio layout (LIBERO's, 8-D): ee xyz, ee axis-angle, fingers (left +, right -).
"""

from __future__ import annotations

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from sword_jax.atomic_write import write_json_atomic
from sword_jax.rl.policy import axis_angle_to_matrix


@dataclasses.dataclass(frozen=True)
class ReckoningConfig:
    """The action convention (the simulator's controller) that turns actions into proprio changes."""

    pos_scale: float = 0.05  # m per unit action
    rot_scale: float = 0.5  # rad per unit action
    finger_open: float = 0.04  # finger joint position when open (m)
    finger_closed_target: float = -0.03  # servo target at a[6] = +1 (past closed)
    finger_rate: float = 0.5  # fraction of the gap to the target closed per control step
    # realised / commanded motion per axis (world frame), e.g. fitted by :func:`fit_gains`
    pos_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    rot_gain: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def validate(self) -> None:
        for name in ("pos_scale", "rot_scale", "finger_open"):
            if not getattr(self, name) > 0:
                raise ValueError(f"proprio reckoning: {name} must be > 0, got {getattr(self, name)}")
        if len(self.pos_gain) != 3 or len(self.rot_gain) != 3:
            raise ValueError(f"proprio reckoning: pos_gain/rot_gain need 3 values, got {self.pos_gain}/{self.rot_gain}")
        if not 0 < self.finger_rate <= 1:
            raise ValueError(f"proprio reckoning: finger_rate must be in (0, 1], got {self.finger_rate}")


def matrix_to_axis_angle(mat: Float[Array, "... 3 3"]) -> Float[Array, "... 3"]:
    """Rotation matrix -> axis-angle with angle in [0, pi] (the simulator's convention, w >= 0)."""
    m = mat.astype(jnp.float32)
    # quaternion (Shepperd): pick the largest of w, x, y, z for stability
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    t = jnp.stack([1 + tr, 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
                   1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2], 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]], -1)
    s = jnp.sqrt(jnp.maximum(t, 1e-12)) * 2
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    cands = jnp.stack([
        jnp.stack([s[..., 0] / 4, d21 / s[..., 0], d02 / s[..., 0], d10 / s[..., 0]], -1),
        jnp.stack([d21 / s[..., 1], s[..., 1] / 4, s01 / s[..., 1], s02 / s[..., 1]], -1),
        jnp.stack([d02 / s[..., 2], s01 / s[..., 2], s[..., 2] / 4, s12 / s[..., 2]], -1),
        jnp.stack([d10 / s[..., 3], s02 / s[..., 3], s12 / s[..., 3], s[..., 3] / 4], -1),
    ], -2)
    quat = jnp.take_along_axis(cands, jnp.argmax(t, -1)[..., None, None], axis=-2)[..., 0, :]
    quat = quat * jnp.where(quat[..., :1] < 0, -1.0, 1.0)
    vec = quat[..., 1:]
    norm = jnp.sqrt(jnp.sum(vec * vec, -1, keepdims=True))
    angle = 2 * jnp.arctan2(norm, quat[..., :1])
    return vec * (angle / jnp.maximum(norm, 1e-9))


def reckon_step(proprio: Float[Array, "... 8"], action: Float[Array, "... 7"],
                cfg: ReckoningConfig = ReckoningConfig()) -> Float[Array, "... 8"]:
    """Proprio after one action, from the proprio before it."""
    p = proprio.astype(jnp.float32)
    a = jnp.clip(action.astype(jnp.float32), -1.0, 1.0)
    pos_gain, rot_gain = jnp.asarray(cfg.pos_gain, jnp.float32), jnp.asarray(cfg.rot_gain, jnp.float32)
    pos = p[..., :3] + a[..., :3] * jnp.float32(cfg.pos_scale) * pos_gain
    rot = axis_angle_to_matrix(a[..., 3:6] * jnp.float32(cfg.rot_scale) * rot_gain) @ axis_angle_to_matrix(p[..., 3:6])
    target = cfg.finger_open + (cfg.finger_closed_target - cfg.finger_open) * (a[..., 6:7] + 1.0) * 0.5
    left = p[..., 6:7] + jnp.float32(cfg.finger_rate) * (target - p[..., 6:7])
    left = jnp.clip(left, 0.0, cfg.finger_open)
    return jnp.concatenate([pos, matrix_to_axis_angle(rot), left, -left], -1)


def reckon(proprio: Float[Array, "... 8"], actions: Float[Array, "... t 7"],
           cfg: ReckoningConfig = ReckoningConfig()) -> Float[Array, "... t 8"]:
    """Proprio after each of ``actions`` (``[..., t, 7]``), integrated from ``proprio``."""

    def body(p, a):
        p = reckon_step(p, a, cfg)
        return p, p

    _, out = jax.lax.scan(body, proprio.astype(jnp.float32), jnp.moveaxis(actions, -2, 0))
    return jnp.moveaxis(out, 0, -2)


def fit_gains(proprio: np.ndarray, actions: np.ndarray, cfg: ReckoningConfig = ReckoningConfig(),
              lengths: np.ndarray | None = None) -> ReckoningConfig:
    """``cfg`` with ``pos_gain``/``rot_gain`` fitted to recorded episodes.

    Args:
      proprio: ``[E, T, 8]`` proprio observed before each action.
      actions: ``[E, T, 7]`` the actions taken (proprio ``t + 1`` follows action ``t``).
      lengths: valid steps per episode (default all ``T``).

    Per axis, the least-squares gain ``g`` of ``realised = g * commanded`` over every one-step
    increment (position in metres; rotation as the world-frame axis-angle of ``R_t+1 R_t^T``),
    clipped to [0.05, 2] so a degenerate fit cannot stop or explode the reckoning.
    """
    proprio, actions = np.asarray(proprio, np.float32), np.asarray(actions, np.float32)
    if proprio.ndim != 3 or proprio.shape[-1] != 8 or actions.shape[:2] != proprio.shape[:2] or actions.shape[-1] != 7:
        raise ValueError(f"fit_gains: proprio [E, T, 8] and actions [E, T, 7], got {proprio.shape} / {actions.shape}")
    e, t = proprio.shape[:2]
    lengths = np.full((e,), t) if lengths is None else np.asarray(lengths)
    mask = (np.arange(t - 1)[None] < (lengths[:, None] - 1)).reshape(-1)
    cmd = np.clip(actions[:, :-1], -1.0, 1.0).reshape(-1, 7)[mask]
    cur, nxt = proprio[:, :-1].reshape(-1, 8)[mask], proprio[:, 1:].reshape(-1, 8)[mask]
    if cmd.shape[0] < 2:
        raise ValueError("fit_gains: needs at least two recorded steps")
    d_pos = nxt[:, :3] - cur[:, :3]
    r_cur, r_nxt = axis_angle_to_matrix(jnp.asarray(cur[:, 3:6])), axis_angle_to_matrix(jnp.asarray(nxt[:, 3:6]))
    d_rot = np.asarray(matrix_to_axis_angle(r_nxt @ jnp.swapaxes(r_cur, -1, -2)))

    def gain(x, y):
        den = float(np.sum(x * x))
        return float(np.clip(np.sum(x * y) / den, 0.05, 2.0)) if den > 0 else 1.0

    pos_cmd, rot_cmd = cmd[:, :3] * cfg.pos_scale, cmd[:, 3:6] * cfg.rot_scale
    return dataclasses.replace(cfg, pos_gain=tuple(gain(pos_cmd[:, i], d_pos[:, i]) for i in range(3)),
                               rot_gain=tuple(gain(rot_cmd[:, i], d_rot[:, i]) for i in range(3)))


def save_reckoning(path: str, cfg: ReckoningConfig) -> None:
    """Writes ``cfg`` as JSON (e.g. beside the policy whose demonstrations it was fitted to)."""
    write_json_atomic(path, dataclasses.asdict(cfg))


def load_reckoning(path: str) -> ReckoningConfig:
    """Reads a :func:`save_reckoning` file; a missing file or unknown field is an error naming it."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"proprio reckoning file not found: {path}")
    with open(path) as f:
        raw = json.load(f)
    names = {f.name for f in dataclasses.fields(ReckoningConfig)}
    unknown = sorted(set(raw) - names)
    if unknown:
        raise ValueError(f"{path}: unknown proprio reckoning fields {unknown}")
    cfg = ReckoningConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in raw.items()})
    cfg.validate()
    return cfg
