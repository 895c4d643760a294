"""LIBERO-Spatial-like MuJoCo / MJX environments.

Importing ``sim`` registers the gymnasium id ``sword/LiberoSpatial-v0`` (lazily; nothing
heavy is imported). ``sim.load(name, **overrides)`` builds a pure env::

    env = sim.load("libero_spatial", task_id=3, backend="mjx")   # MjxEnv
    env = sim.load("libero_spatial_3")                            # CpuEnv, task 3

Overrides are ``SimConfig`` fields (``backend``, ``physics_dt``, ``init`` ...) plus
``task_id``, ``config`` (a base ``SimConfig``), ``renderer`` (a ``data -> dict of images`` callable) and ``controller``
(a ``ControllerConfig``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium

GYM_ID = "sword/LiberoSpatial-v0"
ENV_NAMES = ("libero_spatial",) + tuple(f"libero_spatial_{k}" for k in range(10))

if GYM_ID not in gymnasium.registry:
    gymnasium.register(id=GYM_ID, entry_point="sim.gym_env:LiberoSpatialGymEnv")


def registry() -> tuple[str, ...]:
    """Names ``load`` accepts."""
    return ENV_NAMES


def load(name: str, **overrides: Any):
    """Builds the pure environment ``name`` with config overrides.

    Raises:
      KeyError: unknown name. TypeError: unknown override. ValueError: invalid values.
    """
    from sim.config import SimConfig
    from sim.env import make_env

    if name not in ENV_NAMES:
        raise KeyError(f"unknown sim env {name!r}; known: {', '.join(ENV_NAMES)}")
    task_id = overrides.pop("task_id", None)
    if name != "libero_spatial":
        implied = int(name.rsplit("_", 1)[1])
        if task_id is not None and int(task_id) != implied:
            raise ValueError(f"{name} is task {implied}, but task_id={task_id} was given")
        task_id = implied
    env_kwargs = {k: overrides.pop(k) for k in ("renderer", "controller") if k in overrides}
    config = overrides.pop("config", None) or SimConfig()
    fields = {f.name for f in dataclasses.fields(SimConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise TypeError(f"unknown sim overrides {unknown}; SimConfig fields: {sorted(fields)}")
    config = dataclasses.replace(config, **overrides)
    return make_env(config, 0 if task_id is None else int(task_id), **env_kwargs)
