"""The state probe's targets (``sword_jax.evaluation.probe.TARGET_NAMES``) read from a recorded episode's
simulator state: the end effector, the finger distance and the target bowl's position."""

from __future__ import annotations

import functools

import numpy as np

from sim import scene


@functools.lru_cache(maxsize=1)
def _bowl_qpos_slice() -> slice:
    model = scene.build_model()
    joint = model.body(scene.TARGET_BOWL).jntadr[0]
    adr = 1 + int(model.jnt_qposadr[joint])  # states = [time, qpos, qvel]
    return slice(adr, adr + 3)


def episode_targets(episode) -> np.ndarray:
    """``[T, 7]`` probe targets (``probe.TARGET_NAMES``, metres) of one :class:`sim.dataset.Episode`."""
    gripper = episode.gripper_states[:, 0] - episode.gripper_states[:, 1]
    return np.concatenate([episode.ee_states[:, :3], gripper[:, None], episode.states[:, _bowl_qpos_slice()]],
                          axis=1).astype(np.float32)
