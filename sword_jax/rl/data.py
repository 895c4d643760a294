"""Episodes for behaviour cloning, the success detector and keyframe-initialised rollouts.

:class:`EpisodeSet` holds equal-length (padded) episodes on the host. It is built from the
simulator engineer's ``sim.dataset.Episode`` list (:func:`from_sim_episodes`) or directly from
arrays. Samplers are pure functions of a numpy ``Generator`` so a run is reproducible.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
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
      frame_success: ``[E, T]`` bool, the task's success predicate on the state frame t shows (the
        state after action ``t - 1``; False at t = 0), or None where unknown.
      states: ``[E, T, S]`` the simulator's flattened state at frame t (``[time, qpos, qvel]``: an
        environment can continue the episode from it), or None where unknown.
      tasks: ``[E]`` int task ids, or None where unknown.
    """

    frames: np.ndarray
    actions: np.ndarray
    proprio: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    instructions: tuple[str, ...]
    frame_success: np.ndarray | None = None
    states: np.ndarray | None = None
    tasks: np.ndarray | None = None

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
        if self.frame_success is not None and (self.frame_success.shape != (e, t) or self.frame_success.dtype != bool):
            raise ValueError(f"episodes: frame_success must be [E, T] = {(e, t)} bool, got "
                             f"{self.frame_success.shape} {self.frame_success.dtype}")
        if self.states is not None and (self.states.ndim != 3 or self.states.shape[:2] != (e, t)):
            raise ValueError(f"episodes: states must be [E, T, S] with (E, T) = {(e, t)}, got {self.states.shape}")
        if self.tasks is not None and np.shape(self.tasks) != (e,):
            raise ValueError(f"episodes: tasks must hold one id per episode ({e}), got shape {np.shape(self.tasks)}")

    @property
    def num_episodes(self) -> int:
        return int(self.frames.shape[0])

    def subset(self, index: np.ndarray) -> "EpisodeSet":
        index = np.asarray(index)
        take = lambda x: None if x is None else x[index]  # noqa: E731
        return EpisodeSet(self.frames[index], self.actions[index], self.proprio[index], self.lengths[index],
                          self.success[index], tuple(self.instructions[i] for i in index), take(self.frame_success),
                          take(self.states), take(self.tasks))


def success_length(episode: Any) -> int:
    """Steps up to and including the first success (``rewards[t]`` = success after action t), or all."""
    rewards = np.asarray(episode.rewards)
    hits = np.flatnonzero(rewards > 0)
    return int(hits[0]) + 1 if hits.size else int(episode.num_samples)


def from_sim_episodes(episodes: Sequence[Any], *, success: Sequence[bool] | None = None,
                      stop_at_success: bool = True) -> EpisodeSet:
    """Pads a list of ``sim.dataset.Episode`` to one :class:`EpisodeSet`.

    Proprio is ``[ee_states (6), gripper_states (2)]`` (8-D), the sim's layout. With
    ``stop_at_success`` an episode ends at its first success (data that keeps moving afterwards,
    as the world model's, would otherwise teach the policy to leave the solved state). Success
    defaults to "some step succeeded". ``frame_success`` comes from the episodes' ``rewards``
    (``rewards[t]`` = solved after action t, so frame ``t + 1`` shows a solved state).
    """
    if not episodes:
        raise ValueError("from_sim_episodes: no episodes")
    lengths = np.asarray([success_length(ep) if stop_at_success else ep.num_samples for ep in episodes], np.int32)
    t = int(lengths.max())
    pad = lambda x, n: np.concatenate([x[:n], np.repeat(x[n - 1:n], t - n, axis=0)], axis=0)  # noqa: E731
    frames = np.stack([pad(ep.agentview_rgb, n) for ep, n in zip(episodes, lengths)])
    actions = np.stack([pad(np.asarray(ep.actions, np.float32), n) for ep, n in zip(episodes, lengths)])
    proprio = np.stack([pad(np.concatenate([ep.ee_states, ep.gripper_states], -1).astype(np.float32), n)
                        for ep, n in zip(episodes, lengths)])
    if success is None:
        success = [bool(np.any(np.asarray(ep.rewards) > 0)) for ep in episodes]
    instructions = tuple(ep.language_instruction for ep in episodes)
    if any(not text for text in instructions):
        raise ValueError("from_sim_episodes: every episode needs a language_instruction")
    solved = np.stack([pad(np.concatenate([[False], np.asarray(ep.rewards)[:-1] > 0]), n)
                       for ep, n in zip(episodes, lengths)])
    states = None
    if all(getattr(ep, "states", None) is not None and len(ep.states) for ep in episodes):
        states = np.stack([pad(np.asarray(ep.states, np.float64), n) for ep, n in zip(episodes, lengths)])
    tasks = None
    if all(getattr(ep, "task_id", None) is not None for ep in episodes):
        tasks = np.asarray([int(ep.task_id) for ep in episodes])
    return EpisodeSet(frames, actions, proprio, lengths, np.asarray(success, bool), instructions, solved, states, tasks)


def sample_bc_batch(
    episodes: EpisodeSet, batch_size: int, chunk_len: int, max_bytes: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """A behaviour-cloning batch: frame, instruction, proprio at step t and actions t..t+chunk_len-1.

    Actions past the end of an episode repeat its last action (the robot holds still).
    """
    return bc_batch_at(episodes, *bc_batch_index(episodes, batch_size, rng), chunk_len, max_bytes)


def bc_batch_index(episodes: EpisodeSet, batch_size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(episode [b], step t [b])`` of the samples :func:`sample_bc_batch` draws with the same ``rng`` state."""
    ep = rng.integers(0, episodes.num_episodes, batch_size)
    t = (rng.random(batch_size) * episodes.lengths[ep]).astype(np.int64)
    return ep, t


def bc_batch_at(episodes: EpisodeSet, ep: np.ndarray, t: np.ndarray, chunk_len: int, max_bytes: int
                ) -> dict[str, np.ndarray]:
    """:func:`sample_bc_batch`'s batch of the samples ``(ep, t)`` (from :func:`bc_batch_index`)."""
    idx = np.minimum(t[:, None] + np.arange(chunk_len)[None], episodes.lengths[ep][:, None] - 1)
    return {
        "frames": episodes.frames[ep, t],
        "instruction_tokens": tokenize_instructions([episodes.instructions[i] for i in ep], max_bytes),
        "proprio": episodes.proprio[ep, t],
        "actions": episodes.actions[ep[:, None], idx],
    }


REWARD_LABELS = ("state", "tail")


def success_labels(episodes: EpisodeSet, positive_tail: int, source: str = "tail") -> np.ndarray:
    """``[E, T]`` per-frame success-detector labels: 1 positive, 0 negative, -1 padding.

    ``source="state"``: the task's success predicate on the state each frame shows
    (``episodes.frame_success``), the event an imagined rollout's reward stands for.
    ``source="tail"``: the last ``positive_tail`` frames of successful episodes (for episodes that
    end at their first success these are the frames *before* it: the bowl still in the air).
    """
    if source not in REWARD_LABELS:
        raise ValueError(f"success labels: source must be one of {REWARD_LABELS}, got {source!r}")
    e, t = episodes.frames.shape[:2]
    step = np.arange(t)[None]
    end = episodes.lengths[:, None]
    if source == "state":
        if episodes.frame_success is None:
            raise ValueError("success labels: source='state' needs episodes.frame_success (per-frame success of "
                             "the simulator's rewards); these episodes have none")
        labels = episodes.frame_success.astype(np.int32)
    else:
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


def sample_mixed_reward_batch(sources: Sequence[tuple[EpisodeSet, np.ndarray, float]], batch_size: int,
                              rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A detector batch drawn from several labelled frame sources ``(episodes, labels, share)`` (e.g. real
    frames and the learned simulator's replays of real episodes, :func:`sword_jax.rl.sim_agreement.replay_labels`):
    each source gives ``round(share * batch_size)`` frames (the last source the rest), class-balanced
    within it (:func:`sample_reward_batch`)."""
    shares = np.asarray([share for _, _, share in sources], np.float64)
    if not len(sources) or np.any(shares < 0) or not np.isclose(shares.sum(), 1.0):
        raise ValueError(f"sample_mixed_reward_batch: shares must be >= 0 and sum to 1, got {shares.tolist()}")
    counts = np.round(shares * batch_size).astype(int)
    counts[-1] = batch_size - counts[:-1].sum()
    parts = [sample_reward_batch(eps, labels, int(n), rng) for (eps, labels, _), n in zip(sources, counts) if n > 0]
    return {k: np.concatenate([p[k] for p in parts]) for k in ("frames", "labels")}


def keyframe_starts(episodes: EpisodeSet, count: int, rng: np.random.Generator, *, max_fraction: float = 0.5,
                    min_fraction: float = 0.0, num_context: int = 1, frames_per_latent: int = 4,
                    rows: np.ndarray | None = None, prefix_latents: int | None = None) -> dict[str, Any]:
    """Start states for imagined rollouts at latent-aligned keyframes between fractions ``min_fraction`` and
    ``max_fraction`` of episodes (WoVR keyframes), with the real history a world model conditions on.

    A keyframe is frame ``t = 4 s`` (``s >= num_context``), the last frame of latent ``s``. Returns
    :func:`keyframe_window` at those frames plus ``instructions``. ``rows``: cut only these of the ``count``
    windows (a process's share of a global batch); the keyframes are drawn for all ``count`` first, so each
    row is the same whichever rows are asked for.
    """
    ep, t = keyframe_indices(episodes, count, rng, max_fraction=max_fraction, min_fraction=min_fraction,
                             num_context=num_context, frames_per_latent=frames_per_latent, rows=rows)
    window = keyframe_window(episodes.frames, episodes.actions, episodes.proprio, ep, t, num_context=num_context,
                             frames_per_latent=frames_per_latent, prefix_latents=prefix_latents)
    return dict(window, instructions=[episodes.instructions[i] for i in ep])


def prefix_latents_for(episodes: EpisodeSet, *, max_fraction: float, num_context: int = 1,
                       frames_per_latent: int = 4) -> int:
    """The latents after the first that :func:`keyframe_window`'s ``prefix`` must hold so that every keyframe
    :func:`keyframe_indices` can draw from ``episodes`` (up to fraction ``max_fraction``) lies in it: one fixed
    length per run, so the encoder compiles once."""
    return int(np.max(_last_keyframe_latent(episodes.lengths, max_fraction, num_context, frames_per_latent)))


def prefix_encoder(start_encoding: str, encode_prefix: Callable[..., Any] | None, user: str
                   ) -> Callable[..., Any] | None:
    """The start encoder ``encode_prefix(prefix, latent_index)`` a path that encodes a world model's starts from
    real frames (``user``, named in the error) uses with ``rl.imagined.start_encoding=prefix``; None with
    ``window``, whose paths encode :func:`keyframe_window`'s first frame and history. A path asked for the prefix
    without its encoder refuses rather than falling back to the window (a run never mixes the two)."""
    if start_encoding != "prefix":
        return None
    if encode_prefix is None:
        raise ValueError(f"rl.imagined.start_encoding=prefix: {user} encodes its starts from real frames and needs "
                         "the prefix encoder (encode_prefix=, e.g. the GRPO setup's); pass it or use "
                         "--rl.imagined.start_encoding=window")
    return encode_prefix


def _last_keyframe_latent(lengths: np.ndarray, max_fraction: float, num_context: int,
                          frames_per_latent: int) -> np.ndarray:
    """Per episode of ``lengths`` the latest keyframe latent :func:`keyframe_indices` may draw: the last at or before
    fraction ``max_fraction`` of the episode, at least ``num_context``."""
    return np.maximum((np.asarray(lengths) - 1) * max_fraction // frames_per_latent, num_context).astype(np.int64)


def keyframe_indices(episodes: EpisodeSet, count: int, rng: np.random.Generator, *, max_fraction: float = 0.5,
                     min_fraction: float = 0.0, num_context: int = 1, frames_per_latent: int = 4,
                     rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(episode [n], frame t [n])`` of the keyframes :func:`keyframe_starts` draws with the same arguments and
    ``rng`` state, without cutting their windows (e.g. to read the recorded ``states[episode, t]``).

    Latent ``s`` is uniform over ``[first, last]``: ``last`` the latest keyframe at or before fraction
    ``max_fraction`` of the episode (``(length - 1) * max_fraction``), ``first`` the earliest at or after
    fraction ``min_fraction``; both at least ``num_context``, and ``first`` at most ``last`` (an episode too
    short to hold a keyframe in the window starts at ``last``).
    """
    if not 0.0 <= min_fraction <= max_fraction:
        raise ValueError(f"keyframe_indices: need 0 <= min_fraction <= max_fraction, got {min_fraction} and "
                         f"{max_fraction}")
    k, f = num_context, frames_per_latent
    ep = rng.integers(0, episodes.num_episodes, count)
    last = _last_keyframe_latent(episodes.lengths[ep], max_fraction, k, f)
    # ceil, so no keyframe precedes the window; min_fraction 0 gives first = k
    first = np.minimum(np.maximum(-(-(episodes.lengths[ep] - 1) * min_fraction // f), k), last).astype(np.int64)
    s = first + (rng.random(count) * (last - first + 1)).astype(np.int64)
    t = np.minimum(f * s, episodes.lengths[ep] - 1)
    if rows is not None:
        ep, t = ep[rows], t[rows]
    return ep, t


def keyframe_window(frames: np.ndarray, actions: np.ndarray, proprio: np.ndarray, ep: np.ndarray, t: np.ndarray, *,
                    num_context: int = 1, frames_per_latent: int = 4,
                    prefix_latents: int | None = None) -> dict[str, np.ndarray]:
    """What a world model starting at frame ``t`` of episode ``ep`` conditions on, laid out as a training
    segment: ``frame``/``proprio`` at ``t``, the episode's ``first_frame``, ``history`` (the ``4 (k + 1)``
    frames up to ``t``, the oldest clamped at frame 0) and ``actions`` (``[1 + 4k, A]``: the first frame's
    action then the context frames').

    With ``prefix_latents = S`` also ``prefix`` (``[n, 1 + 4 S, ...]``: the episode from frame 0, the frames after
    ``t`` repeating frame ``t``) and ``latent_index`` (``[n]``: the latent that ends at ``t``, ``ceil(t / 4)``, at
    least ``k``): a causal encoder's latents of the prefix up to that index are those of the whole episode
    (:func:`~sword_jax.rl.world_model_sim.encode_prefix`). ``S`` must hold every ``latent_index``
    (:func:`prefix_latents_for`).

    Args:
      frames / actions / proprio: ``[E, T, ...]`` episodes (frame t is seen before action t).
      ep / t: ``[n]`` episode indices and keyframes.
    """
    k, f = num_context, frames_per_latent
    hist_idx = np.maximum(t[:, None] - f * (k + 1) + 1 + np.arange(f * (k + 1))[None], 0)
    act_idx = np.concatenate([np.zeros((len(ep), 1), np.int64),
                              np.maximum(t[:, None] - f * k + 1 + np.arange(f * k)[None], 0)], axis=1)
    out = {"episode": ep, "t": t, "frame": frames[ep, t], "proprio": proprio[ep, t], "first_frame": frames[ep, 0],
           "history": frames[ep[:, None], hist_idx], "actions": actions[ep[:, None], act_idx]}
    if prefix_latents is not None:
        index = np.maximum(-(-np.asarray(t) // f), k).astype(np.int64)
        if np.any(index > prefix_latents):
            raise ValueError(f"keyframe_window: prefix_latents={prefix_latents} does not hold keyframes up to latent "
                             f"{int(index.max())}")
        prefix_idx = np.minimum(np.arange(1 + f * prefix_latents)[None], np.asarray(t)[:, None])
        out.update(prefix=frames[ep[:, None], prefix_idx], latent_index=index)
    return out


def load_episodes(paths: Sequence[str], *, read: Callable[[str], tuple[Any, Sequence[Any]]] | None = None,
                  stop_at_success: bool = True) -> EpisodeSet:
    """Reads episode files into one :class:`EpisodeSet`.

    Args:
      paths: episode files, read in order.
      read: ``path -> (info, episodes)`` with ``sim.dataset.Episode``-like episodes, e.g.
        ``sim.dataset.read_dataset`` for LIBERO-layout HDF5 files (the library does not import ``sim``).
      stop_at_success: end each episode at its first success (:func:`from_sim_episodes`).

    Raises:
      ValueError: no ``read`` given.
    """
    if read is None:
        raise ValueError("load_episodes needs read=(path) -> (info, episodes), e.g. read=sim.dataset.read_dataset")
    episodes = []
    for path in paths:
        _, eps = read(path)
        episodes.extend(eps)
    return from_sim_episodes(episodes, stop_at_success=stop_at_success)


def successful(episodes: EpisodeSet) -> EpisodeSet:
    """Only the episodes that reached success (behaviour cloning imitates solutions, not failures)."""
    keep = np.flatnonzero(episodes.success)
    if keep.size == 0:
        raise ValueError("no successful episode among the demonstrations")
    return episodes.subset(keep)


def split_holdout(episodes: EpisodeSet, fraction: float, rng: np.random.Generator) -> tuple[EpisodeSet, EpisodeSet | None]:
    """``(train, held_out)``: about ``fraction`` of each instruction's episodes held out (at least one
    where an instruction has two or more; None when nothing is held out)."""
    if fraction <= 0.0:
        return episodes, None
    train, held = [], []
    for text in sorted(set(episodes.instructions)):
        idx = rng.permutation(np.flatnonzero(np.asarray(episodes.instructions) == text))
        n_held = min(max(int(round(fraction * len(idx))), 1), len(idx) - 1) if len(idx) > 1 else 0
        held.extend(idx[:n_held])
        train.extend(idx[n_held:])
    if not held:
        return episodes, None
    return episodes.subset(np.sort(np.asarray(train))), episodes.subset(np.sort(np.asarray(held)))


def per_task_subset(episodes: EpisodeSet, per_instruction: int, rng: np.random.Generator) -> EpisodeSet:
    """At most ``per_instruction`` episodes of each instruction (the SFT data-amount knob; 0 = all)."""
    if per_instruction <= 0:
        return episodes
    keep = []
    for text in sorted(set(episodes.instructions)):
        idx = np.flatnonzero(np.asarray(episodes.instructions) == text)
        keep.extend(rng.permutation(idx)[:per_instruction])
    return episodes.subset(np.sort(np.asarray(keep)))
