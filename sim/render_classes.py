"""Segmentation classes of a MuJoCo scene: background, table, robot, each object, each fixture.

Classes are assigned per geom from the body tree, so any scene gets a sensible map without
hand-written tables:
  * ``background`` (id 0): nothing hit, and world-body geoms (floor, walls) not named table;
  * ``table`` (id 1): geoms whose own name or whose root body's name contains "table";
  * ``robot`` (id 2): every geom under a root body whose subtree name mentions the robot
    (robot, panda, mount, link, hand, finger, gripper) or holds >= 3 hinge joints;
  * one class per free-jointed root body (the movable objects), named after the body;
  * one class per remaining root body (fixtures such as the cabinet or the stove).
``overrides`` (body name -> class name) wins over these rules for that body's subtree.
"""

from __future__ import annotations

import mujoco
import numpy as np

BACKGROUND, TABLE, ROBOT = 0, 1, 2
_ROBOT_WORDS = ("robot", "panda", "mount", "link", "hand", "finger", "gripper")


def _name(model: mujoco.MjModel, obj: mujoco.mjtObj, idx: int) -> str:
    return mujoco.mj_id2name(model, obj, idx) or ""


def _root_of(model: mujoco.MjModel, body: int) -> int:
    while body != 0 and int(model.body_parentid[body]) != 0:
        body = int(model.body_parentid[body])
    return body


def segmentation_classes(
    model: mujoco.MjModel, *, overrides: dict[str, str] | None = None
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Class id of every geom and the class names.

    Args:
      model: the compiled model.
      overrides: body name -> class name for that body and its subtree (e.g.
        ``{"plate": "plate"}``); ``"background"``, ``"table"``, ``"robot"`` map to the
        fixed ids, any other name gets its own class.

    Returns:
      (geom_class (ngeom,) int32, class_names) with class_names[0:3] = background, table,
      robot.

    Raises:
      KeyError: an override names a body that is not in the model.
    """
    overrides = dict(overrides or {})
    body_names = {_name(model, mujoco.mjtObj.mjOBJ_BODY, b): b for b in range(model.nbody)}
    for name in overrides:
        if name not in body_names:
            raise KeyError(f"class override for unknown body {name!r}")
    names: list[str] = ["background", "table", "robot"]

    def class_id(name: str) -> int:
        if name not in names:
            names.append(name)
        return names.index(name)

    subtree_words: dict[int, str] = {}
    hinges: dict[int, int] = {}
    free_roots: set[int] = set()
    for body in range(1, model.nbody):
        root = _root_of(model, body)
        subtree_words[root] = subtree_words.get(root, "") + " " + _name(model, mujoco.mjtObj.mjOBJ_BODY, body).lower()
        for j in range(int(model.body_jntadr[body]), int(model.body_jntadr[body] + model.body_jntnum[body])):
            jtype = int(model.jnt_type[j])
            if jtype == mujoco.mjtJoint.mjJNT_HINGE:
                hinges[root] = hinges.get(root, 0) + 1
            elif jtype == mujoco.mjtJoint.mjJNT_FREE and body == root:
                free_roots.add(root)

    def overridden(body: int) -> str | None:
        while True:
            name = _name(model, mujoco.mjtObj.mjOBJ_BODY, body)
            if name in overrides:
                return overrides[name]
            if body == 0:
                return None
            body = int(model.body_parentid[body])

    geom_class = np.zeros(model.ngeom, np.int32)
    for geom in range(model.ngeom):
        body = int(model.geom_bodyid[geom])
        forced = overridden(body)
        if forced is not None:
            geom_class[geom] = class_id(forced)
            continue
        geom_name = _name(model, mujoco.mjtObj.mjOBJ_GEOM, geom).lower()
        if body == 0:
            geom_class[geom] = TABLE if "table" in geom_name else BACKGROUND
            continue
        root = _root_of(model, body)
        root_name = _name(model, mujoco.mjtObj.mjOBJ_BODY, root)
        words = subtree_words.get(root, "")
        if "table" in geom_name or "table" in root_name.lower():
            geom_class[geom] = TABLE
        elif root in free_roots:
            geom_class[geom] = class_id(root_name or f"object{root}")
        elif any(w in words for w in _ROBOT_WORDS) or hinges.get(root, 0) >= 3:
            geom_class[geom] = ROBOT
        else:
            geom_class[geom] = class_id(root_name or f"fixture{root}")
    return geom_class, tuple(names)
