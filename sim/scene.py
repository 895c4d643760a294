"""LIBERO-Spatial-like kitchen-table scene as MJCF generated in Python.

Geometry is MJX-friendly: boxes and capsules collide (no meshes, no box-cylinder pairs);
cylinders are visual only. Every geom has a ``<material>`` (``mjx.ray`` needs one).

Segmentation (see ``sim/render_classes.py``): the floor is a world geom (background); the
table is the root body ``table``; the robot is ``panda_mount`` + ``panda_link0`` subtree;
each movable object is a free-jointed root body named as in LIBERO
(``akita_black_bowl_1`` = the bowl to pick up, ``akita_black_bowl_2``, ``plate_1``,
``glazed_rim_porcelain_ramekin_1``, ``cookies_1``); fixtures are static root bodies
``wooden_cabinet_1`` and ``flat_stove_1``. Geom names are prefixed with their body's name.
Geom groups: 0 scene, 1 robot, 2 objects and fixtures; group 3 holds collision-only geoms
that are never drawn (mujoco.Renderer's default shows groups 0-2).

Contacts are filtered with bits (contact iff ``ct_a & ca_b or ct_b & ca_a``), so a world
has 31 candidate pairs (all box-box) and typically < 20 active contacts:
  16 the table top;
   1 fixture supports (stove top, cabinet top, top-drawer floor);
   2 movable supports (plate, ramekin, cookie box; they rest on the table only);
   4 the target bowl: its base rests on 16|1|2, its walls and base touch the finger pads;
  32 the distractor bowl's base (rests on the table only);
   8 finger pads (touch bits 4 and 16: the target bowl and the table).
Pairs that no LIBERO-Spatial task can produce (the distractor on the plate, the plate on the
stove, fingers on fixtures) are filtered out.

Object body origins are at the centre of their bottom face (so ``pos.z`` = resting height).
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from sim import panda

TABLE_TOP_Z = 0.90
TABLE_HALF = (0.5, 0.6, 0.025)
ROBOT_BASE = (-0.66, 0.0, 0.912)
OBJECTS = (
    "akita_black_bowl_1",
    "akita_black_bowl_2",
    "plate_1",
    "glazed_rim_porcelain_ramekin_1",
    "cookies_1",
)
FIXTURES = ("wooden_cabinet_1", "flat_stove_1")
TARGET_BOWL = OBJECTS[0]
# Objects start this far above their support and drop during the settle steps.
DROP_CLEARANCE = 0.002

BOWL_RADIUS = 0.0535
BOWL_HEIGHT = 0.05
BOWL_WALL = 0.008  # wall thickness
BOWL_BASE_HALF = 0.033
PLATE_RADIUS = 0.069
PLATE_TOP = 0.010  # top of the plate's flat centre above its bottom
RAMEKIN_RADIUS = 0.0445
RAMEKIN_HEIGHT = 0.042
COOKIES_HALF = (0.031, 0.0415, 0.0095)
STOVE_POS = (-0.05, -0.36, TABLE_TOP_Z)
STOVE_HALF = (0.1, 0.11, 0.012)
STOVE_TOP = 2 * STOVE_HALF[2]
CABINET_POS = (-0.1, 0.4, TABLE_TOP_Z)  # drawers open toward -x (the robot)
CABINET_HALF = (0.1, 0.14)  # x depth, y width (half)
CABINET_HEIGHT = 0.26
DRAWER_OUT = 0.14  # how far the top drawer is pulled out
DRAWER_FLOOR_Z = 0.176  # top of the top drawer's floor above the cabinet bottom
DRAWER_CENTER_XY = (CABINET_POS[0] - CABINET_HALF[0] - DRAWER_OUT / 2 + 0.005, CABINET_POS[1])

# MJX-only culling (the C engine ignores these): per collision group (geom types x condim),
# only the nearest ``MJX_MAX_GEOM_PAIRS`` candidate pairs (bounding-sphere distance) run the
# box-box test, and at most ``MJX_MAX_CONTACT_POINTS`` contacts per condim reach the solver.
# The condim-3 group (supports) has 11 candidates of which <= 7 touch at once; the condim-4
# group (finger pads) has 20, of which the pads touch <= 4 at once.
MJX_MAX_GEOM_PAIRS = 8
MJX_MAX_CONTACT_POINTS = 32

COLORS = {
    "floor": (0.55, 0.5, 0.45, 1.0),
    "table": (0.78, 0.62, 0.43, 1.0),
    "table_leg": (0.45, 0.33, 0.22, 1.0),
    "mount": (0.25, 0.25, 0.27, 1.0),
    "panda_white": (0.95, 0.95, 0.95, 1.0),
    "panda_black": (0.12, 0.12, 0.12, 1.0),
    "bowl": (0.06, 0.06, 0.06, 1.0),
    "plate": (0.96, 0.96, 0.93, 1.0),
    "plate_rim": (0.85, 0.85, 0.82, 1.0),
    "ramekin": (0.95, 0.93, 0.86, 1.0),
    "cookies": (0.85, 0.25, 0.15, 1.0),
    "cookies_label": (0.2, 0.35, 0.75, 1.0),
    "cabinet": (0.6, 0.4, 0.22, 1.0),
    "cabinet_dark": (0.45, 0.28, 0.15, 1.0),
    "handle": (0.75, 0.75, 0.72, 1.0),
    "stove": (0.18, 0.18, 0.2, 1.0),
    "burner": (0.55, 0.12, 0.08, 1.0),
    "collision": (0.5, 0.5, 0.5, 0.0),
}


def _materials() -> str:
    rows = []
    for name, rgba in COLORS.items():
        spec = " ".join(f"{c:g}" for c in rgba)
        extra = ' specular="0.6" shininess="0.6"' if name in ("bowl", "plate", "ramekin") else ""
        rows.append(f'<material name="{name}" rgba="{spec}"{extra}/>')
    return "\n".join(rows)


def _box(name, pos, size, material, ct=0, ca=0, group=2, euler=None, **extra) -> str:
    fmt = lambda v: " ".join(f"{x:.5g}" for x in v)  # noqa: E731
    rot = f' euler="0 0 {euler:.6g}"' if euler is not None else ""
    attrs = "".join(f' {k}="{v}"' for k, v in extra.items())
    return (
        f'<geom name="{name}" type="box" pos="{fmt(pos)}" size="{fmt(size)}"{rot} material="{material}" '
        f'contype="{ct}" conaffinity="{ca}" group="{group}"{attrs}/>'
    )


def _ring(prefix, apothem, half_width, half_thick, z, half_h, material, ct, ca, mass=None, n=8) -> list[str]:
    """``n`` boxes around the z axis whose inner faces form a regular polygon."""
    rows = []
    for k in range(n):
        angle = 2 * np.pi * k / n
        pos = (apothem * np.cos(angle), apothem * np.sin(angle), z)
        extra = {"mass": f"{mass:.4g}"} if mass is not None else {}
        rows.append(_box(f"{prefix}_wall{k}", pos, (half_thick, half_width, half_h), material, ct, ca, euler=angle, **extra))
    return rows


def _free_body(name: str, geoms: list[str]) -> str:
    return f'<body name="{name}"><freejoint name="{name}_joint"/>' + "\n".join(geoms) + "</body>"


def _bowl(name: str, graspable: bool) -> str:
    apothem = BOWL_RADIUS - BOWL_WALL / 2
    half_width = apothem * np.tan(np.pi / 8) + 0.002
    base_ct, base_ca = (4, 16 | 1 | 2) if graspable else (32, 16)
    geoms = [
        _box(f"{name}_base", (0, 0, 0.004), (BOWL_BASE_HALF, BOWL_BASE_HALF, 0.004), "bowl", base_ct, base_ca, mass=0.06,
             friction="1.0 0.01 0.001"),
        _box(f"{name}_base_vis", (0, 0, 0.004), (BOWL_BASE_HALF, BOWL_BASE_HALF, 0.0039), "bowl", euler=np.pi / 4,
             mass=0.0),
    ]
    geoms += _ring(name, apothem, half_width, BOWL_WALL / 2, BOWL_HEIGHT / 2, BOWL_HEIGHT / 2, "bowl", 4 if graspable else 0,
                   0, mass=0.012)
    return _free_body(name, geoms)


def _plate() -> str:
    name = "plate_1"
    geoms = [
        _box(f"{name}_collision", (0, 0, PLATE_TOP / 2), (0.056, 0.056, PLATE_TOP / 2), "collision", 2, 16, group=3,
             mass=0.25, friction="1.0 0.01 0.001"),
        f'<geom name="{name}_dish" type="cylinder" pos="0 0 {PLATE_TOP / 2 - 0.0005}" size="{PLATE_RADIUS - 0.008} '
        f'{PLATE_TOP / 2 - 0.0005}" material="plate" contype="0" conaffinity="0" group="2" mass="0"/>',
    ]
    geoms += _ring(f"{name}_rim", PLATE_RADIUS - 0.008, PLATE_RADIUS * np.tan(np.pi / 8) * 0.95, 0.007, 0.012, 0.0045,
                   "plate_rim", 0, 0, mass=0.0)
    return _free_body(name, geoms)


def _ramekin() -> str:
    name = "glazed_rim_porcelain_ramekin_1"
    inner = RAMEKIN_RADIUS * np.cos(np.pi / 8) / np.sqrt(2) * 1.3
    geoms = [
        _box(f"{name}_collision", (0, 0, RAMEKIN_HEIGHT / 2), (inner, inner, RAMEKIN_HEIGHT / 2), "collision", 2, 16,
             group=3, mass=0.2),
        f'<geom name="{name}_base" type="cylinder" pos="0 0 0.003" size="{RAMEKIN_RADIUS - 0.004} 0.003" '
        f'material="ramekin" contype="0" conaffinity="0" group="2" mass="0"/>',
    ]
    apothem = RAMEKIN_RADIUS - 0.003
    geoms += _ring(name, apothem, apothem * np.tan(np.pi / 8) + 0.0015, 0.003, RAMEKIN_HEIGHT / 2, RAMEKIN_HEIGHT / 2,
                   "ramekin", 0, 0, mass=0.0)
    return _free_body(name, geoms)


def _cookies() -> str:
    name = "cookies_1"
    hx, hy, hz = COOKIES_HALF
    geoms = [
        _box(f"{name}_box", (0, 0, hz), COOKIES_HALF, "cookies", 2, 16, mass=0.1),
        _box(f"{name}_label", (0, 0, 2 * hz + 0.0004), (hx * 0.7, hy * 0.6, 0.0005), "cookies_label", mass=0.0),
    ]
    return _free_body(name, geoms)


def _stove() -> str:
    name = "flat_stove_1"
    hx, hy, hz = STOVE_HALF
    rows = [f'<body name="{name}" pos="{STOVE_POS[0]} {STOVE_POS[1]} {STOVE_POS[2]}">',
            _box(f"{name}_top", (0, 0, hz), STOVE_HALF, "stove", 1, 0)]
    for k, (bx, by) in enumerate(((-0.045, -0.05), (0.045, 0.05), (-0.045, 0.05), (0.045, -0.05))):
        rows.append(f'<geom name="{name}_burner{k}" type="cylinder" pos="{bx} {by} {2 * hz + 0.0005}" size="0.035 0.0006" '
                    f'material="burner" contype="0" conaffinity="0" group="2"/>')
    rows.append("</body>")
    return "\n".join(rows)


def _cabinet() -> str:
    name = "wooden_cabinet_1"
    hx, hy = CABINET_HALF
    h = CABINET_HEIGHT
    rows = [f'<body name="{name}" pos="{CABINET_POS[0]} {CABINET_POS[1]} {CABINET_POS[2]}">',
            _box(f"{name}_top", (0, 0, h - 0.01), (hx, hy, 0.01), "cabinet", 1, 0),
            _box(f"{name}_bottom", (0, 0, 0.005), (hx, hy - 0.01, 0.005), "cabinet"),
            _box(f"{name}_back", (hx - 0.005, 0, h / 2), (0.005, hy - 0.01, h / 2 - 0.01), "cabinet"),
            _box(f"{name}_side0", (0, hy - 0.005, h / 2), (hx, 0.005, h / 2 - 0.01), "cabinet"),
            _box(f"{name}_side1", (0, -hy + 0.005, h / 2), (hx, 0.005, h / 2 - 0.01), "cabinet")]
    front_half = (0.008, hy - 0.012, 0.036)
    for k, zc in enumerate((0.047, 0.127)):  # bottom and middle drawers, closed
        rows.append(_box(f"{name}_drawer{k}_front", (-hx + 0.008, 0, zc), front_half, "cabinet_dark"))
        rows.append(_box(f"{name}_drawer{k}_handle", (-hx - 0.006, 0, zc), (0.006, 0.04, 0.006), "handle"))
    # Top drawer, pulled out toward the robot: floor (collides), sides, front, handle.
    x0 = -hx - DRAWER_OUT  # outer face of the front
    depth_half = (hx * 2 - 0.02) / 2
    xc = x0 + 0.016 + depth_half
    rows += [
        _box(f"{name}_drawer2_floor", (xc, 0, DRAWER_FLOOR_Z - 0.004), (depth_half, hy - 0.02, 0.004), "cabinet_dark", 1, 0),
        _box(f"{name}_drawer2_side0", (xc, hy - 0.024, DRAWER_FLOOR_Z + 0.024), (depth_half, 0.004, 0.028), "cabinet"),
        _box(f"{name}_drawer2_side1", (xc, -hy + 0.024, DRAWER_FLOOR_Z + 0.024), (depth_half, 0.004, 0.028), "cabinet"),
        _box(f"{name}_drawer2_front", (x0 + 0.008, 0, 0.207), front_half, "cabinet_dark"),
        _box(f"{name}_drawer2_handle", (x0 - 0.006, 0, 0.207), (0.006, 0.04, 0.006), "handle"),
        "</body>",
    ]
    return "\n".join(rows)


def _table() -> str:
    hx, hy, hz = TABLE_HALF
    rows = ['<body name="table" pos="0 0 0">',
            _box("table_top", (0, 0, TABLE_TOP_Z - hz), TABLE_HALF, "table", 16, 0, group=0,
                 friction="1.0 0.01 0.001")]
    for k, (sx, sy) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
        rows.append(_box(f"table_leg{k}", (sx * (hx - 0.05), sy * (hy - 0.05), (TABLE_TOP_Z - 2 * hz) / 2),
                         (0.025, 0.025, (TABLE_TOP_Z - 2 * hz) / 2), "table_leg", group=0))
    rows.append("</body>")
    return "\n".join(rows)


def scene_xml(*, timestep: float = 0.005, iterations: int = 6, ls_iterations: int = 8) -> str:
    """The whole scene as an MJCF string."""
    bx, by, bz = ROBOT_BASE
    return f"""<mujoco model="libero_spatial">
<compiler angle="radian" autolimits="true" inertiafromgeom="true"/>
<option timestep="{timestep}" integrator="implicitfast" cone="pyramidal" iterations="{iterations}"
        ls_iterations="{ls_iterations}" gravity="0 0 -9.81"/>
<custom>
<numeric name="max_geom_pairs" data="{MJX_MAX_GEOM_PAIRS}"/>
<numeric name="max_contact_points" data="{MJX_MAX_CONTACT_POINTS}"/>
</custom>
<visual><global offwidth="512" offheight="512"/><quality shadowsize="0"/></visual>
<asset>
{_materials()}
</asset>
<worldbody>
<light name="top" pos="0 0 3" dir="0 0 -1" directional="true" diffuse="0.7 0.7 0.7" castshadow="false"/>
<light name="front" pos="1.5 0 2.2" dir="-0.6 0 -0.8" directional="true" diffuse="0.3 0.3 0.3" castshadow="false"/>
<geom name="floor" type="plane" size="3 3 0.05" material="floor" contype="0" conaffinity="0" group="0"/>
<camera name="agentview" pos="0.6586 0 1.6103" quat="0.6380 0.3048 0.3048 0.6380" fovy="45"/>
<camera name="frontview" pos="1.0 0 1.45" quat="0.56 0.43 0.43 0.56" fovy="45"/>
{_table()}
<body name="panda_mount" pos="{bx} {by} 0">
{_box("panda_mount_column", (0, 0, (bz - 0.01) / 2), (0.11, 0.11, (bz - 0.01) / 2), "mount", group=1)}
</body>
{panda.panda_xml(f"{bx} {by} {bz}")}
{_cabinet()}
{_stove()}
{_bowl(OBJECTS[0], graspable=True)}
{_bowl(OBJECTS[1], graspable=False)}
{_plate()}
{_ramekin()}
{_cookies()}
</worldbody>
<actuator>
{panda.actuators_xml()}
</actuator>
</mujoco>
"""


@functools.lru_cache(maxsize=8)
def _build_cached(timestep: float, iterations: int, ls_iterations: int) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(scene_xml(timestep=timestep, iterations=iterations, ls_iterations=ls_iterations))


def build_model(*, timestep: float = 0.005, iterations: int = 6, ls_iterations: int = 8) -> mujoco.MjModel:
    """Compile the scene. Returns a fresh copy (callers may edit it)."""
    if not 0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01], got {timestep}")
    return _build_cached(float(timestep), int(iterations), int(ls_iterations)).__copy__()


def geom_segment_labels(model: mujoco.MjModel) -> tuple[np.ndarray, tuple[str, ...]]:
    """Per-geom segmentation class for this scene (delegates to ``sim.render_classes``)."""
    from sim.render_classes import segmentation_classes

    return segmentation_classes(model)
