"""The ten LIBERO-Spatial tasks: language, object placements, initial states, success.

All tasks share one scene (``sim/scene.py``); only the two black bowls' placements differ
(as in LIBERO-Spatial). ``akita_black_bowl_1`` is always the bowl to pick up, the other bowl
is a distractor. Initial states are full ``qpos`` vectors: the arm at its home posture,
fingers open, each free object at a sampled pose. Sampling maps uniform draws in [0, 1) to
poses with plain arithmetic (``xp`` = numpy or jax.numpy), so the same function gives the
50 fixed, seeded initial states per task (numpy) and fresh samples inside a jitted reset
(jax.numpy).

Initial-state splits (as LIBERO, whose demonstrations start elsewhere than its evaluation):
``eval`` is the 50 fixed states per task (policy evaluation); ``train`` (demonstrations,
world-model training) and ``heldout`` (world-model evaluation episodes) are two further seeded
streams of any length. A draw that coincides with an evaluation state (or, for ``heldout``, with
one of the first ``TRAIN_RESERVE`` training states) is rejected and redrawn, so the splits are
disjoint by check, not by luck.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import numpy as np

from sim import scene as sc

LANGUAGE: tuple[str, ...] = (
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "pick up the black bowl next to the ramekin and place it on the plate",
    "pick up the black bowl from table center and place it on the plate",
    "pick up the black bowl on the cookie box and place it on the plate",
    "pick up the black bowl in the top drawer of the wooden cabinet and place it on the plate",
    "pick up the black bowl on the ramekin and place it on the plate",
    "pick up the black bowl next to the cookie box and place it on the plate",
    "pick up the black bowl on the stove and place it on the plate",
    "pick up the black bowl next to the plate and place it on the plate",
    "pick up the black bowl on the wooden cabinet and place it on the plate",
)
NUM_TASKS = len(LANGUAGE)
NUM_INIT_STATES = 50
INIT_SPLITS = ("train", "eval", "heldout")
TRAIN_RESERVE = 2000  # training states per task that held-out states are checked against
SAME_STATE_TOL = 1e-3  # max |qpos difference| of the free objects under which two states coincide
_SPLIT_STREAM = {"train": 1, "heldout": 2}

# Nominal (x, y) of the objects that do not move between tasks (world frame, table at 0).
PLATE_XY = (-0.06, 0.16)
RAMEKIN_XY = (-0.06, -0.15)
COOKIES_XY = (-0.26, 0.0)


@dataclasses.dataclass(frozen=True)
class Placement:
    """Where a bowl starts: on the table at ``xy`` or on a support (then ``xy`` is an offset)."""

    xy: tuple[float, float]
    support: str = "table"  # table | cookies | ramekin | stove | cabinet_top | drawer
    jitter: float = 0.02  # half-width of the uniform xy region (m)


# (target bowl, distractor bowl) per task, in suite order.
BOWLS: tuple[tuple[Placement, Placement], ...] = (
    (Placement((-0.06, 0.0), jitter=0.01), Placement((0.08, -0.02))),
    (Placement((0.08, -0.12), jitter=0.01), Placement((0.1, 0.06))),
    (Placement((0.04, 0.02)), Placement((-0.22, -0.2))),
    (Placement((0.0, 0.0), "cookies", 0.005), Placement((0.05, -0.03))),
    (Placement((0.0, 0.0), "drawer", 0.008), Placement((0.05, 0.0))),
    (Placement((0.0, 0.0), "ramekin", 0.005), Placement((0.06, 0.04))),
    (Placement((-0.25, -0.15), jitter=0.015), Placement((0.07, 0.02))),
    (Placement((0.0, 0.0), "stove", 0.01), Placement((0.06, 0.01))),
    (Placement((0.1, 0.19), jitter=0.01), Placement((0.06, -0.04))),
    (Placement((0.0, 0.0), "cabinet_top", 0.01), Placement((0.05, -0.04))),
)

# Per free object: the uniform draws it uses (x, y, yaw).
_DRAWS_PER_OBJECT = 3
NUM_DRAWS = _DRAWS_PER_OBJECT * len(sc.OBJECTS)


def _support_top(support: str, xp: Any, cookies_xy: Any, ramekin_xy: Any) -> tuple[Any, Any]:
    """(xy centre, z of the top surface) of a support."""
    if support == "table":
        return xp.zeros(2), sc.TABLE_TOP_Z
    if support == "cookies":
        return cookies_xy, sc.TABLE_TOP_Z + 2 * sc.COOKIES_HALF[2]
    if support == "ramekin":
        return ramekin_xy, sc.TABLE_TOP_Z + sc.RAMEKIN_HEIGHT
    if support == "stove":
        return xp.asarray(sc.STOVE_POS[:2]), sc.TABLE_TOP_Z + sc.STOVE_TOP
    if support == "cabinet_top":
        return xp.asarray(sc.CABINET_POS[:2]), sc.TABLE_TOP_Z + sc.CABINET_HEIGHT
    if support == "drawer":
        return xp.asarray(sc.DRAWER_CENTER_XY), sc.TABLE_TOP_Z + sc.DRAWER_FLOOR_Z
    raise ValueError(f"unknown support {support!r}")


def _yaw_quat(yaw: Any, xp: Any) -> Any:
    return xp.stack([xp.cos(yaw / 2), xp.zeros_like(yaw), xp.zeros_like(yaw), xp.sin(yaw / 2)])


def init_qpos(task_id: int, draws: Any, *, xp: Any = np) -> Any:
    """Initial ``qpos`` of ``task_id`` from uniform draws.

    Args:
      task_id: 0-9 (Python int: placements are static).
      draws: (NUM_DRAWS,) uniforms in [0, 1).
      xp: ``numpy`` or ``jax.numpy``.

    Returns:
      (nq,) qpos: arm home, fingers open, objects in order ``scene.OBJECTS``.
    """
    if not 0 <= task_id < NUM_TASKS:
        raise ValueError(f"task_id must be in 0..{NUM_TASKS - 1}, got {task_id}")
    if draws.shape != (NUM_DRAWS,):
        raise ValueError(f"draws must have shape ({NUM_DRAWS},), got {draws.shape}")
    u = (draws.reshape(len(sc.OBJECTS), _DRAWS_PER_OBJECT) - 0.5) * 2.0  # in [-1, 1)
    from sim import panda

    arm = xp.asarray(np.concatenate([panda.HOME_QPOS, [panda.FINGER_OPEN, panda.FINGER_OPEN]]))

    def jittered(xy, jitter, row):
        return xp.asarray(xy) + jitter * u[row, :2]

    plate_xy = jittered(PLATE_XY, 0.015, 2)
    ramekin_xy = jittered(RAMEKIN_XY, 0.015, 3)
    cookies_xy = jittered(COOKIES_XY, 0.015, 4)
    poses = [None] * len(sc.OBJECTS)
    for row, placement in enumerate(BOWLS[task_id]):
        centre, top = _support_top(placement.support, xp, cookies_xy, ramekin_xy)
        xy = centre + xp.asarray(placement.xy) + placement.jitter * u[row, :2]
        yaw = u[row, 2] * (np.pi / 8)  # octagonal bowl: +-22.5 deg covers every look
        poses[row] = (xy, top, yaw)
    poses[2] = (plate_xy, sc.TABLE_TOP_Z, u[2, 2] * np.pi / 8)
    poses[3] = (ramekin_xy, sc.TABLE_TOP_Z, u[3, 2] * np.pi / 8)
    poses[4] = (cookies_xy, sc.TABLE_TOP_Z, u[4, 2] * 0.3)
    parts = [arm]
    for xy, z, yaw in poses:
        parts += [xy, xp.reshape(xp.asarray(z + sc.DROP_CLEARANCE), (1,)), _yaw_quat(yaw, xp)]
    return xp.concatenate([xp.asarray(p, dtype=xp.float32) for p in parts])


def fixed_init_states(task_id: int, *, seed: int = 0, count: int = NUM_INIT_STATES) -> np.ndarray:
    """The task's fixed initial states: (count, nq) float32, deterministic in (task_id, seed)."""
    rng = np.random.default_rng([seed, task_id, 20240])
    return np.stack([init_qpos(task_id, rng.random(NUM_DRAWS)) for _ in range(count)])


def _object_qpos(states: np.ndarray) -> np.ndarray:
    from sim import panda

    return np.asarray(states, np.float64)[..., len(panda.HOME_QPOS) + 2:]  # the arm starts at home in all


def coinciding(states: np.ndarray, others: np.ndarray, *, tol: float = SAME_STATE_TOL) -> np.ndarray:
    """(N,) bool: which of ``states`` (N, nq) lie within ``tol`` (max abs, object qpos) of any of ``others``."""
    a, b = _object_qpos(states), _object_qpos(others)
    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros(a.shape[0], bool)
    return np.array([np.any(np.max(np.abs(b - row), axis=-1) < tol) for row in a])


def assert_disjoint(states: np.ndarray, others: np.ndarray, what: str, *, tol: float = SAME_STATE_TOL) -> None:
    """Raises ``ValueError`` if any of ``states`` coincides with one of ``others`` (object qpos)."""
    hits = np.flatnonzero(coinciding(states, others, tol=tol))
    if hits.size:
        raise ValueError(f"{what}: {hits.size} initial states coincide with the other split (first at {hits[:5].tolist()})")


@functools.lru_cache(maxsize=64)
def _split_stream(task_id: int, split: str, count: int, seed: int) -> np.ndarray:
    """The first ``count`` states of a non-evaluation split's stream, rejections redrawn."""
    rng = np.random.default_rng([seed, task_id, 20240, _SPLIT_STREAM[split]])
    excluded = [fixed_init_states(task_id, seed=seed)]
    if split == "heldout":
        excluded.append(_split_stream(task_id, "train", TRAIN_RESERVE, seed))
    excluded = np.concatenate(excluded)
    states = []
    while len(states) < count:
        state = init_qpos(task_id, rng.random(NUM_DRAWS))
        if not coinciding(state[None], excluded)[0]:
            states.append(state)
    out = np.stack(states)
    out.setflags(write=False)
    return out


def split_init_states(task_id: int, split: str, count: int, *, start: int = 0, seed: int = 0) -> np.ndarray:
    """Initial states ``start .. start + count - 1`` of a split: (count, nq) float32.

    Args:
      task_id: 0-9.
      split: ``eval`` (the 50 fixed states, ``fixed_init_states``), ``train`` or ``heldout``.
      count, start: which states of the split's stream.
      seed: the seed of all three splits (``SimConfig.init_seed``).

    Raises:
      ValueError: unknown split, ``eval`` past its 50 states, ``heldout`` past ``TRAIN_RESERVE``
        or ``train`` states past ``TRAIN_RESERVE`` (held-out ones are only checked against those).
    """
    if split not in INIT_SPLITS:
        raise ValueError(f"init split must be one of {INIT_SPLITS}, got {split!r}")
    if start < 0 or count < 0:
        raise ValueError(f"init states: start and count must be >= 0, got {start}, {count}")
    if split == "eval":
        if start + count > NUM_INIT_STATES:
            raise ValueError(f"the eval split has {NUM_INIT_STATES} states per task; asked for {start}..{start + count - 1}")
        return fixed_init_states(task_id, seed=seed)[start:start + count]
    if start + count > TRAIN_RESERVE:
        raise ValueError(f"the {split} split is checked for {TRAIN_RESERVE} states per task; asked for "
                         f"{start}..{start + count - 1}")
    return np.array(_split_stream(task_id, split, start + count, seed)[start:])


def evaluation_episodes(tasks: Sequence[int], episodes_per_task: int) -> list[tuple[int, np.ndarray]]:
    """``(task, qpos)`` of each task's first ``episodes_per_task`` fixed evaluation initial states
    (the ``episodes`` of ``sword_jax.rl.policy_success.evaluate_in_sim`` and ``sim.lockstep.LockstepEnvs``)."""
    if not 1 <= episodes_per_task <= NUM_INIT_STATES:
        raise ValueError(f"episodes_per_task must be in 1..{NUM_INIT_STATES}, got {episodes_per_task}")
    return [(int(t), q) for t in tasks for q in split_init_states(int(t), "eval", episodes_per_task)]


def success(bowl_pos: Any, bowl_zaxis_z: Any, plate_pos: Any, *, xp: Any = np) -> Any:
    """LIBERO's ``On(bowl, plate)``: the bowl rests on the plate.

    Args:
      bowl_pos: (..., 3) origin of the target bowl (centre of its bottom face).
      bowl_zaxis_z: (...,) z component of the bowl's up axis (1 = upright).
      plate_pos: (..., 3) origin of the plate (centre of its bottom face).

    Returns:
      (...,) bool: plate below the bowl, bottom-to-top gap within 5 mm (or in contact),
      centres within 3 cm in xy, bowl upright (within ~35 deg).
    """
    gap = bowl_pos[..., 2] - (plate_pos[..., 2] + sc.PLATE_TOP)
    dxy = bowl_pos[..., :2] - plate_pos[..., :2]
    centred = xp.sum(dxy * dxy, axis=-1) < 0.03**2
    return (gap > -0.005) & (gap < 0.005) & centred & (bowl_zaxis_z > 0.8)
