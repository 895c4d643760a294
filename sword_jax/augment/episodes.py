"""The episode batch the augmentation pipeline, the evaluation splits and the ingest path share."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sword_jax.augment.transforms import to_unit_range


class Episodes(NamedTuple):
    """``N`` equal-length episodes (host numpy arrays).

    Attributes:
      frames: ``[N, T, H, W, 3]`` float32 in [0, 1].
      depth: ``[N, T, H, W]`` float32 metres (non-finite = far), or ``None`` (styled elsewhere).
      seg: ``[N, T, H, W]`` int class map, or ``None``.
      actions: ``[N, T, A]`` float32 (or ``[N, T-1, A]``: one action between frames).
      episode_ids: ``[N]`` int64, unique.
    """

    frames: np.ndarray
    depth: np.ndarray | None
    seg: np.ndarray | None
    actions: np.ndarray
    episode_ids: np.ndarray

    @property
    def num(self) -> int:
        return int(self.frames.shape[0])

    def take(self, index: np.ndarray) -> Episodes:
        """The episodes at positions ``index`` (in that order)."""
        index = np.asarray(index, np.int64)
        pick = lambda x: None if x is None else x[index]  # noqa: E731
        return Episodes(*(pick(x) for x in self))


def as_episodes(data: Episodes | dict, *, frames_range: str = "unit", require_geometry: bool = True) -> Episodes:
    """Validate and convert a dict (``frames``, ``depth``, ``seg``, ``actions``, ``episode_ids``) or
    :class:`Episodes`; ``frames_range`` is "unit" ([0, 1]), "signed" ([-1, 1]) or "uint8".

    Raises:
      ValueError / KeyError: naming the missing key, bad shape, duplicate id, NaN or out-of-range value.
    """
    if isinstance(data, Episodes):
        data = data._asdict()
    for name in ("frames", "actions"):
        if name not in data or data[name] is None:
            raise KeyError(f"episodes: missing {name!r}")
    frames = np.asarray(data["frames"])
    if frames.ndim != 5 or frames.shape[-1] != 3:
        raise ValueError(f"episodes: frames must be [N, T, H, W, 3], got {frames.shape}")
    frames = np.asarray(to_unit_range(frames, frames_range)) if frames_range != "unit" else frames.astype(np.float32)
    if not np.isfinite(frames).all():
        raise ValueError("episodes: frames contain NaN/inf")
    if frames.min() < -1e-3 or frames.max() > 1 + 1e-3:
        raise ValueError(
            f"episodes: frames outside [0, 1] (range [{frames.min():.3g}, {frames.max():.3g}]); "
            "pass frames_range='signed' or 'uint8' for other encodings"
        )
    n, t = frames.shape[:2]
    geometry = {}
    for name, dtype in (("depth", np.float32), ("seg", None)):
        value = data.get(name)
        if value is None:
            if require_geometry:
                raise KeyError(f"episodes: missing {name!r} (structure-guided augmentation needs it)")
            geometry[name] = None
            continue
        value = np.asarray(value)
        if value.shape != frames.shape[:-1]:
            raise ValueError(f"episodes: {name} must be [N, T, H, W] = {frames.shape[:-1]}, got {value.shape}")
        if name == "seg" and not np.issubdtype(value.dtype, np.integer):
            raise TypeError(f"episodes: seg must be integer class ids, got {value.dtype}")
        if name == "depth" and np.isnan(value).any():
            raise ValueError("episodes: depth contains NaN (use inf for 'no surface')")
        geometry[name] = value.astype(dtype) if dtype else value
    actions = np.asarray(data["actions"], np.float32)
    if actions.ndim != 3 or actions.shape[0] != n or actions.shape[1] not in (t, t - 1):
        raise ValueError(f"episodes: actions must be [N={n}, T={t} (or T-1), A], got {actions.shape}")
    if not np.isfinite(actions).all():
        raise ValueError("episodes: actions contain NaN/inf")
    ids = np.asarray(data.get("episode_ids", np.arange(n)), np.int64)
    if ids.shape != (n,):
        raise ValueError(f"episodes: episode_ids must be [N={n}], got {ids.shape}")
    if len(np.unique(ids)) != n:
        raise ValueError("episodes: duplicate episode_ids")
    return Episodes(frames, geometry["depth"], geometry["seg"], actions, ids)


def episodes_from_sim(
    sim_episodes, *, episode_ids=None, num_frames: int | None = None
) -> Episodes:
    """From ``sim.dataset.Episode`` objects (``read_dataset``'s output) with depth and segmentation.

    Args:
      sim_episodes: sequence of episodes with ``agentview_rgb`` (uint8), ``agentview_depth``,
        ``agentview_seg`` and ``actions``.
      episode_ids: ``[N]`` ids (default ``0..N-1``).
      num_frames: crop every episode to its first ``num_frames`` (needed when lengths differ).

    Raises:
      ValueError: an episode lacks depth / segmentation, or lengths differ without ``num_frames``.
    """
    sim_episodes = list(sim_episodes)
    if not sim_episodes:
        raise ValueError("episodes_from_sim: no episodes")
    lengths = [len(e.actions) for e in sim_episodes]
    if num_frames is None:
        if len(set(lengths)) != 1:
            raise ValueError(f"episodes_from_sim: episode lengths differ ({sorted(set(lengths))[:5]}...); pass num_frames")
        num_frames = lengths[0]
    if min(lengths) < num_frames:
        raise ValueError(f"episodes_from_sim: num_frames={num_frames} but the shortest episode has {min(lengths)}")
    for k, e in enumerate(sim_episodes):
        if e.agentview_depth is None or e.agentview_seg is None:
            raise ValueError(f"episodes_from_sim: episode {k} has no agentview depth/segmentation "
                             "(record them with the renderer's depth_and_seg=True)")
    crop = slice(0, num_frames)
    return as_episodes(
        {
            "frames": np.stack([e.agentview_rgb[crop] for e in sim_episodes]),
            "depth": np.stack([e.agentview_depth[crop] for e in sim_episodes]),
            "seg": np.stack([e.agentview_seg[crop].astype(np.int32) for e in sim_episodes]),
            "actions": np.stack([e.actions[crop] for e in sim_episodes]),
            "episode_ids": np.arange(len(sim_episodes)) if episode_ids is None else episode_ids,
        },
        frames_range="uint8",
    )
