"""Franka Emika Panda as MJCF text: real kinematics, capsule geometry, parallel gripper.

Link offsets, joint axes and limits follow the official Franka description (as used by
robosuite's ``robot.xml`` and mujoco_menagerie's ``panda.xml``): seven revolute joints with
modified-DH offsets d1 = 0.333, d3 = 0.316, a3 = 0.0825, a4 = -0.0825, d5 = 0.384,
a6 = 0.088, flange 0.107, hand rotated -45 deg about the flange axis, two slide fingers
(0-0.04 m each). Link masses are the published ones; inertias come from the capsule
geometry (``inertiafromgeom``). Arm links carry no collision (``contype=conaffinity=0``)
so a world has few contacts; only the finger pads collide (with the grasped object).

Every body and geom name starts with ``panda_`` (segmentation: robot).
"""

from __future__ import annotations

import numpy as np

ARM_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
JOINT_LOWER = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])
JOINT_UPPER = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])
FINGER_OPEN = 0.04
# Closed-gripper servo target: below the joint limit so a grasp squeezes with ~30 N per finger.
FINGER_CLOSED_TARGET = -0.03
# LIBERO's mounted Panda home posture (gripper down, fingers along world y).
HOME_QPOS = np.array([0.0, -0.161, 0.0, -2.44, 0.0, 2.227, np.pi / 4])
# Tool centre point: between the finger pads, 0.1034 m below the hand origin.
TCP_OFFSET = 0.1034
# Collision bits (see sim/scene.py): finger pads are bit 8; they touch the target bowl (4) and the table (16).
FINGER_CONTYPE, FINGER_CONAFFINITY = 8, 20

_LINK_MASS = (4.970684, 0.646926, 3.228604, 3.587895, 1.225946, 1.666555, 0.735522)

# (body, parent pos, quat, joint range, capsules [(fromto, radius)])
_LINKS = (
    ("panda_link1", "0 0 0.333", "1 0 0 0", 0, [("0 0 -0.19 0 0 -0.06", 0.06), ("0 0 -0.06 0 0 0.06", 0.06)]),
    ("panda_link2", "0 0 0", "1 -1 0 0", 1, [("0 0 -0.06 0 0 0.06", 0.06), ("0 0 0 0 -0.19 0", 0.06)]),
    ("panda_link3", "0 -0.316 0", "1 1 0 0", 2, [("0 0 -0.15 0 0 -0.02", 0.06), ("0.0825 0 -0.06 0.0825 0 0.05", 0.055)]),
    ("panda_link4", "0.0825 0 0", "1 1 0 0", 3, [("0 0 -0.05 0 0 0.05", 0.055), ("-0.0825 0.02 0 -0.0825 0.12 0", 0.055)]),
    ("panda_link5", "-0.0825 0.384 0", "1 -1 0 0", 4, [("0 0 -0.26 0 0 -0.02", 0.05), ("0 0.08 -0.12 0 0.08 -0.02", 0.03)]),
    ("panda_link6", "0 0 0", "1 1 0 0", 5, [("0 0 -0.05 0 0 0.02", 0.05), ("0 0 0 0.088 0 0", 0.045)]),
    ("panda_link7", "0.088 0 0", "1 1 0 0", 6, [("0 0 -0.03 0 0 0.08", 0.045)]),
)


def _arm_geom(name: str, fromto: str, radius: float, mass: float, material: str) -> str:
    return (
        f'<geom name="{name}" type="capsule" fromto="{fromto}" size="{radius}" mass="{mass:.6f}" '
        f'material="{material}" contype="0" conaffinity="0" group="1"/>'
    )


def _finger(side: str, quat: str) -> str:
    joint = "panda_finger_joint1" if side == "left" else "panda_finger_joint2"
    # Inner pad face lies at y = joint position, so the gap between pads is q1 + q2.
    return (
        f'<body name="panda_{side}_finger" pos="0 0 0.0584" quat="{quat}">'
        f'<joint name="{joint}" type="slide" axis="0 1 0" range="0 {FINGER_OPEN}" damping="150" armature="0.05"/>'
        f'<geom name="panda_{side}_finger_body" type="box" pos="0 0.012 0.012" size="0.01 0.012 0.014" mass="0.008" '
        f'material="panda_white" contype="0" conaffinity="0" group="1"/>'
        f'<geom name="panda_{side}_finger_pad" type="box" pos="0 0.006 0.042" size="0.011 0.006 0.016" mass="0.007" '
        f'material="panda_black" contype="{FINGER_CONTYPE}" conaffinity="{FINGER_CONAFFINITY}" friction="2.0 0.05 0.001" '
        f'condim="4" group="1" solref="0.005 1"/>'
        "</body>"
    )


def panda_xml(base_pos: str = "-0.66 0 0.912") -> str:
    """MJCF ``<body>`` fragment of the Panda rooted at ``panda_link0`` placed at ``base_pos``.

    Contains the ``grip_site`` tool-centre site and the ``eye_in_hand`` camera on the hand.
    """
    out = [
        f'<body name="panda_link0" pos="{base_pos}">',
        '<geom name="panda_link0_geom" type="capsule" fromto="-0.04 0 0.03 -0.04 0 0.2" size="0.08" '
        'mass="0.629769" material="panda_white" contype="0" conaffinity="0" group="1"/>',
    ]
    closers = ["</body>"]
    for idx, (body, pos, quat, jidx, capsules) in enumerate(_LINKS):
        out.append(f'<body name="{body}" pos="{pos}" quat="{quat}" gravcomp="1">')
        lo, hi = JOINT_LOWER[jidx], JOINT_UPPER[jidx]
        out.append(
            f'<joint name="{ARM_JOINTS[jidx]}" axis="0 0 1" range="{lo} {hi}" damping="5" armature="0.1"/>'
        )
        share = _LINK_MASS[idx] / len(capsules)
        for k, (fromto, radius) in enumerate(capsules):
            material = "panda_black" if (idx == 6 or k == 1 and idx == 4) else "panda_white"
            out.append(_arm_geom(f"{body}_geom{k}", fromto, radius, share, material))
        closers.append("</body>")
    out.append('<body name="panda_hand" pos="0 0 0.107" quat="0.9238795 0 0 -0.3826834" gravcomp="1">')
    out.append(
        '<geom name="panda_hand_geom" type="box" pos="0 0 0.03" size="0.025 0.095 0.028" mass="0.73" '
        'material="panda_white" contype="0" conaffinity="0" group="1"/>'
    )
    out.append(f'<site name="grip_site" pos="0 0 {TCP_OFFSET}" size="0.005" rgba="1 0 0 0" group="5"/>')
    # Camera looks along the hand's +z (toward the fingers); MuJoCo cameras look down -z.
    out.append('<camera name="eye_in_hand" pos="0.06 0 0.0" quat="0 0.7071068 0.7071068 0" fovy="75"/>')
    for side, quat in (("left", "1 0 0 0"), ("right", "0 0 0 1")):
        out.append(_finger(side, quat).replace('<body name', '<body gravcomp="1" name', 1))
    out.append("</body>")
    out.extend(reversed(closers))
    return "\n".join(out)


def actuators_xml() -> str:
    """Joint-position servos for the arm and the two fingers (force limited)."""
    kp = (2000, 2000, 1500, 1500, 800, 800, 400)
    kv = (40, 40, 30, 30, 10, 10, 5)
    frc = (87, 87, 87, 87, 12, 12, 12)
    rows = [
        f'<position name="act_{j}" joint="{j}" kp="{p}" kv="{v}" forcerange="{-f} {f}" ctrlrange="{lo} {hi}"/>'
        for j, p, v, f, lo, hi in zip(ARM_JOINTS, kp, kv, frc, JOINT_LOWER, JOINT_UPPER)
    ]
    rows += [
        f'<position name="act_{j}" joint="{j}" kp="2000" kv="20" forcerange="-40 40" ctrlrange="{FINGER_CLOSED_TARGET} {FINGER_OPEN}"/>'
        for j in FINGER_JOINTS
    ]
    return "\n".join(rows)
