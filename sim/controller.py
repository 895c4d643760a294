"""LIBERO-format action -> Panda servo targets, written once for numpy and jax.numpy.

Action (7,) in [-1, 1]: delta end-effector position (x 0.05 m), delta rotation as a
world-frame axis-angle (x 0.5 rad), gripper (-1 open, +1 close). A damped-least-squares IK
step turns the 6-D pose delta into a joint-position target for the arm's position servos,
with a null-space pull toward the home posture; the gripper maps linearly to finger targets.

Every function takes ``xp`` (``numpy`` or ``jax.numpy``): the C backend calls them with
numpy on ``mujoco.MjData`` fields, the MJX backend with jax.numpy inside ``jit``; the math is
the same code.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from sim import panda

ACTION_DIM = 7
PROPRIO_DIM = 8


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """Gains and scales of the action -> servo-target map."""

    pos_scale: float = 0.05  # m per unit action
    rot_scale: float = 0.5  # rad per unit action
    damping: float = 0.05  # DLS lambda
    nullspace_gain: float = 0.05  # fraction of the home-posture error removed per step
    max_joint_delta: float = 0.3  # rad per control step, per joint

    def validate(self) -> None:
        for name in ("pos_scale", "rot_scale", "damping", "max_joint_delta"):
            if not getattr(self, name) > 0:
                raise ValueError(f"controller.{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.nullspace_gain <= 1:
            raise ValueError(f"controller.nullspace_gain must be in [0, 1], got {self.nullspace_gain}")


def servo_targets(
    action: Any,
    q_arm: Any,
    jacp: Any,
    jacr: Any,
    cfg: ControllerConfig = ControllerConfig(),
    *,
    xp: Any = np,
) -> Any:
    """Position-servo targets for one control step.

    Args:
      action: (7,) LIBERO action, clipped to [-1, 1].
      q_arm: (7,) current arm joint positions.
      jacp: (3, 7) translational Jacobian of the tool-centre site w.r.t. the arm joints.
      jacr: (3, 7) rotational Jacobian.
      cfg: gains.
      xp: numpy or jax.numpy.

    Returns:
      (9,) ctrl: seven arm joint targets then the two finger targets.
    """
    action = xp.clip(action, -1.0, 1.0)
    twist = xp.concatenate([action[:3] * cfg.pos_scale, action[3:6] * cfg.rot_scale])  # (6,)
    jac = xp.concatenate([jacp, jacr], axis=0)  # (6, 7)
    gram = jac @ jac.T + (cfg.damping**2) * xp.eye(6, dtype=jac.dtype)
    jac_pinv = jac.T @ xp.linalg.inv(gram)  # (7, 6) damped pseudo-inverse
    dq = jac_pinv @ twist
    home = xp.asarray(panda.HOME_QPOS, dtype=q_arm.dtype)
    nullspace = xp.eye(7, dtype=jac.dtype) - jac_pinv @ jac
    dq = dq + nullspace @ (cfg.nullspace_gain * (home - q_arm))
    dq = xp.clip(dq, -cfg.max_joint_delta, cfg.max_joint_delta)
    lower = xp.asarray(panda.JOINT_LOWER, dtype=q_arm.dtype)
    upper = xp.asarray(panda.JOINT_UPPER, dtype=q_arm.dtype)
    q_target = xp.clip(q_arm + dq, lower, upper)
    # -1 -> open (0.04), +1 -> a target past closed so the fingers squeeze what they hold.
    finger = panda.FINGER_OPEN + (panda.FINGER_CLOSED_TARGET - panda.FINGER_OPEN) * (action[6] + 1.0) * 0.5
    return xp.concatenate([q_target, xp.stack([finger, finger]).astype(q_target.dtype)])


def mat_to_quat(mat: Any, *, xp: Any = np) -> Any:
    """(3, 3) rotation matrix -> (4,) quaternion (w, x, y, z), w >= 0 (Shepperd's method)."""
    r = mat
    t = xp.stack([
        1 + r[0, 0] + r[1, 1] + r[2, 2],
        1 + r[0, 0] - r[1, 1] - r[2, 2],
        1 - r[0, 0] + r[1, 1] - r[2, 2],
        1 - r[0, 0] - r[1, 1] + r[2, 2],
    ])
    s = xp.sqrt(xp.maximum(t, 1e-12)) * 2  # 4 * (the largest component) for the chosen row
    cands = xp.stack([
        xp.stack([s[0] / 4, (r[2, 1] - r[1, 2]) / s[0], (r[0, 2] - r[2, 0]) / s[0], (r[1, 0] - r[0, 1]) / s[0]]),
        xp.stack([(r[2, 1] - r[1, 2]) / s[1], s[1] / 4, (r[0, 1] + r[1, 0]) / s[1], (r[0, 2] + r[2, 0]) / s[1]]),
        xp.stack([(r[0, 2] - r[2, 0]) / s[2], (r[0, 1] + r[1, 0]) / s[2], s[2] / 4, (r[1, 2] + r[2, 1]) / s[2]]),
        xp.stack([(r[1, 0] - r[0, 1]) / s[3], (r[0, 2] + r[2, 0]) / s[3], (r[1, 2] + r[2, 1]) / s[3], s[3] / 4]),
    ])
    quat = cands[xp.argmax(t)]
    return quat * xp.where(quat[0] < 0, -1.0, 1.0).astype(quat.dtype)


def quat_to_axis_angle(quat: Any, *, xp: Any = np) -> Any:
    """(4,) unit quaternion (w >= 0) -> (3,) axis-angle, as robosuite's ``quat2axisangle``."""
    vec = quat[1:]
    norm = xp.sqrt(xp.sum(vec * vec))
    angle = 2 * xp.arctan2(norm, quat[0])
    return vec * (angle / xp.maximum(norm, 1e-9))


def rotation_error(current: Any, target: Any, *, xp: Any = np) -> Any:
    """World-frame axis-angle that rotates ``current`` (3, 3) onto ``target`` (3, 3)."""
    return quat_to_axis_angle(mat_to_quat(target @ current.T, xp=xp), xp=xp)


def proprio(ee_pos: Any, ee_mat: Any, finger_q: Any, *, xp: Any = np) -> Any:
    """8-D proprio as LIBERO stores it: ee position, ee axis-angle, finger positions.

    Finger positions follow robosuite's sign convention (left +, right -).
    """
    axis_angle = quat_to_axis_angle(mat_to_quat(ee_mat, xp=xp), xp=xp)
    fingers = xp.stack([finger_q[0], -finger_q[1]]).astype(ee_pos.dtype)
    return xp.concatenate([ee_pos, axis_angle.astype(ee_pos.dtype), fingers])
