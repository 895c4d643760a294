"""Episodes for behaviour cloning, the success detector and keyframe-initialised rollouts.

:class:`EpisodeSet` holds equal-length (padded) episodes on the host. It is built from the
simulator engineer's ``sim.dataset.Episode`` list (:func:`from_sim_episodes`) or directly from
arrays. Samplers are pure functions of a numpy ``Generator`` so a run is reproducible.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from sword_jax.rl.policy import tokenize_instructions


@dataclasses.dataclass(frozen=True)
class EpisodeSet:
    """Padded episodes (padding repeats the last step; ``lengths`` says where they end).

    Attributes:
      frames: ``[E, T, H, W, 3]`` uint8 agentview frames (frame t is seen before action t).
      actions: ``[E, T, 7]`` float32 in [-1, 1].
      proprio: ``[E, T, P]`` float32.
      lengths: ``[E]`` int true episode lengths.
      success: ``[E]`` bool, whether the episode ended in success.
      instructions: E language instructions.
    """

    frames: np.ndarray
    actions: np.ndarray
    proprio: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    instructions: tuple[str, ...]

    def __post_init__(self):
        e = self.frames.shape[0]
        if self.frames.ndim != 5 or self.frames.shape[-1] != 3 or self.frames.dtype != np.uint8:
            raise ValueError(f"episodes: frames must be [E, T, H, W, 3] uint8, got {self.frames.shape} {self.frames.dtype}")
        t = self.frames.shape[1]
        if self.actions.shape[:2] != (e, t) or self.proprio.shape[:2] != (e, t):
            raise ValueError(f"episodes: actions {self.actions.shape} / proprio {self.proprio.shape} must start with {(e, t)}")
        if self.lengths.shape != (e,) or self.success.shape != (e,) or len(self.instructions) != e:
            raise ValueError("episodes: lengths, success and instructions need one entry per episode")
        if np.any(self.lengths < 1) or np.any(self.lengths > t):
            raise ValueError(f"episodes: lengths must be in [1, {t}], got {self.lengths}")
        if not (np.all(np.isfinite(self.actions)) and np.all(np.isfinite(self.proprio))):
            raise ValueError("episodes: actions or proprio contain NaN/inf")

    @property
    def num_episodes(self) -> int:
        return int(self.frames.shape[0])

    def subset(self, index: np.ndarray) -> "EpisodeSet":
        index = np.asarray(index)
        return EpisodeSet(self.frames[index], self.actions[index], self.proprio[index], self.lengths[index],
                          self.success[index], tuple(self.instructions[i] for i in index))


def from_sim_episodes(episodes: Sequence[Any], *, success: Sequence[bool] | None = None) -> EpisodeSet:
    """Pads a list of ``sim.dataset.Episode`` to one :class:`EpisodeSet`.

    Proprio is ``[ee_states (6), gripper_states (2)]`` (8-D), the sim's layout. Success defaults
    to "the last ``dones`` flag is set".
    """
    if not episodes:
        raise ValueError("from_sim_episodes: no episodes")
    t = max(ep.num_samples for ep in episodes)
    pad = lambda x: np.concatenate([x, np.repeat(x[-1:], t - len(x), axis=0)], axis=0)  # noqa: E731
    frames = np.stack([pad(ep.agentview_rgb) for ep in episodes])
    actions = np.stack([pad(np.asarray(ep.actions, np.float32)) for ep in episodes])
    proprio = np.stack([pad(np.concatenate([ep.ee_states, ep.gripper_states], -1).astype(np.float32)) for ep in episodes])
    lengths = np.asarray([ep.num_samples for ep in episodes], np.int32)
    if success is None:
        success = [bool(np.asarray(ep.dones)[-1]) for ep in episodes]
    instructions = tuple(ep.language_instruction for ep in episodes)
    if any(not text for text in instructions):
        raise ValueError("from_sim_episodes: every episode needs a language_instruction")
    return EpisodeSet(frames, actions, proprio, lengths, np.asarray(success, bool), instructions)


def sample_bc_batch(
    episodes: EpisodeSet, batch_size: int, chunk_len: int, max_bytes: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """A behaviour-cloning batch: frame, instruction, proprio at step t and actions t..t+chunk_len-1.

    Actions past the end of an episode repeat its last action (the robot holds still).
    """
    ep = rng.integers(0, episodes.num_episodes, batch_size)
    t = (rng.random(batch_size) * episodes.lengths[ep]).astype(np.int64)
    idx = np.minimum(t[:, None] + np.arange(chunk_len)[None], episodes.lengths[ep][:, None] - 1)
    return {
        "frames": episodes.frames[ep, t],
        "instruction_tokens": tokenize_instructions([episodes.instructions[i] for i in ep], max_bytes),
        "proprio": episodes.proprio[ep, t],
        "actions": episodes.actions[ep[:, None], idx],
    }


def success_labels(episodes: EpisodeSet, positive_tail: int) -> np.ndarray:
    """``[E, T]`` 1 for the last ``positive_tail`` frames of successful episodes, else 0; -1 = padding."""
    e, t = episodes.frames.shape[:2]
    step = np.arange(t)[None]
    end = episodes.lengths[:, None]
    labels = ((step >= end - positive_tail) & (step < end) & episodes.success[:, None]).astype(np.int32)
    return np.where(step < end, labels, -1)


def sample_reward_batch(
    episodes: EpisodeSet, labels: np.ndarray, batch_size: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Class-balanced frames and labels for the success detector (half positives where any exist)."""
    pos = np.argwhere(labels == 1)
    neg = np.argwhere(labels == 0)
    if len(neg) == 0:
        raise ValueError("reward model data: no negative frames")
    n_pos = batch_size // 2 if len(pos) else 0
    pick = np.concatenate([pos[rng.integers(0, len(pos), n_pos)] if n_pos else np.zeros((0, 2), np.int64),
                           neg[rng.integers(0, len(neg), batch_size - n_pos)]])
    return {"frames": episodes.frames[pick[:, 0], pick[:, 1]], "labels": labels[pick[:, 0], pick[:, 1]].astype(np.float32)}


def keyframe_starts(episodes: EpisodeSet, count: int, rng: np.random.Generator, *, max_fraction: float = 0.5) -> dict[str, Any]:
    """Start states for imagined rollouts: frames from the first ``max_fraction`` of episodes (WoVR keyframes)."""
    ep = rng.integers(0, episodes.num_episodes, count)
    t = (rng.random(count) * np.maximum(episodes.lengths[ep] * max_fraction, 1)).astype(np.int64)
    return {"episode": ep, "t": t, "frame": episodes.frames[ep, t], "proprio": episodes.proprio[ep, t],
            "instructions": [episodes.instructions[i] for i in ep]}


def load_episodes(paths: Sequence[str]) -> EpisodeSet:
    """Reads LIBERO-layout HDF5 files (``sim.dataset``) into one :class:`EpisodeSet`."""
    from sim.dataset import read_dataset

    episodes = []
    for path in paths:
        _, eps = read_dataset(path)
        episodes.extend(eps)
    return from_sim_episodes(episodes)


def per_task_subset(episodes: EpisodeSet, per_instruction: int, rng: np.random.Generator) -> EpisodeSet:
    """At most ``per_instruction`` episodes of each instruction (the SFT data-amount knob; 0 = all)."""
    if per_instruction <= 0:
        return episodes
    keep = []
    for text in sorted(set(episodes.instructions)):
        idx = np.flatnonzero(np.asarray(episodes.instructions) == text)
        keep.extend(rng.permutation(idx)[:per_instruction])
    return episodes.subset(np.sort(np.asarray(keep)))
