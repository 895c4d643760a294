"""The world model trained on its own closed loop: its imagined latents as context, reality as the target.

GRPO reads the world model in a closed loop: the policy acts on the frames it predicts, and from the second
decision on it predicts from its own earlier predictions under those actions. Its training segments (and a refresh
on the policy's real episodes) give it real context and recorded actions, or DLB's one-step predictions of
recorded episodes. Measured on `small`, the closed loop drifts from reality decision by decision, and a refresh on
replays of real episodes does not move that drift. This module builds the training signal that targets it
directly:

1. :func:`trace_closed_loop` rolls the policy out in the world-model simulator as GRPO does (its imagined rollout,
   every decision run, no stop at a success) and keeps the actions it executed and the simulator's context latents
   after each decision: what the world model would predict the next chunk from.
2. Those actions are executed in the real environment from the same start states
   (:func:`~sword_jax.rl.imagined_check.execute_observed`) and the frames they reach are encoded as the world
   model's training latents (:func:`real_latents`), after the keyframe's real history as a training episode's are
   (with ``rl.imagined.start_encoding=prefix``, after its episode from frame 0, as the start's own latents).
3. :func:`closed_loop_segments` lays out one training segment per decision: the episode's first-frame latent, the
   world model's own context latents at that decision, and the real latents that the executed actions reached next,
   with the actions laid out as the simulator lays them out at inference.

A fine-tune that mixes these segments into its batches (``given_context`` rows of the world model's train step,
:func:`~sword_jax.rl.refresh.finetune_world_model`) is asked to predict reality from where its own closed loop
stands, for the policy's own actions. The first decision's segment has the real context (teacher forcing on the
policy's actions).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import numpy as np
from flax import nnx

from sword_jax.rl.imagined_check import executed_actions
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.rollout import imagined_rollout


class ClosedLoopTrace(NamedTuple):
    """What :func:`trace_closed_loop` keeps of ``N`` trajectories of ``D`` decisions.

    Attributes:
      actions: ``[N, D e, A]`` the executed actions (``e`` = the simulator's ``execute_len`` a decision).
      contexts: ``[N, D, k, h, w, c]`` the simulator's context latents after each decision (what it predicts the
        next decision's chunk from).
    """

    actions: jax.Array
    contexts: jax.Array


class ClosedLoopSegments(NamedTuple):
    """World-model training segments with given context (host arrays, ``M`` segments).

    Attributes:
      latents: ``[M, 1 + k + p, h, w, c]``: first-frame latent, the closed loop's context, the real future.
      actions: ``[M, 1 + 4 (k + p), A]`` laid out as a training segment's.
      decision: ``[M]`` the decision each segment starts at (0: the real start context).
      trajectory: ``[M]`` the trajectory each segment comes from (start-major, as traced).
    """

    latents: np.ndarray
    actions: np.ndarray
    decision: np.ndarray
    trajectory: np.ndarray

    def subset(self, mask: np.ndarray) -> "ClosedLoopSegments":
        return ClosedLoopSegments(self.latents[mask], self.actions[mask], self.decision[mask], self.trajectory[mask])

    @classmethod
    def concatenate(cls, parts: list["ClosedLoopSegments"]) -> "ClosedLoopSegments":
        """The parts' segments in order, each part's trajectories numbered after the previous part's."""
        offset, moved = 0, []
        for part in parts:
            moved.append(part._replace(trajectory=part.trajectory + offset))
            offset += int(part.trajectory.max()) + 1 if part.num else 0
        return cls(*(np.concatenate(x) for x in zip(*moved)))

    @property
    def num(self) -> int:
        return int(self.latents.shape[0])


def trace_closed_loop(graphdef: nnx.GraphDef, policy_params: Any, simulator: LearnedSimulator,
                      reward_model: RewardModel, start: StartState, rl: Any, *, key: jax.Array, group_size: int,
                      decisions: int) -> ClosedLoopTrace:
    """The policy's closed loop in a world-model simulator (:func:`~sword_jax.rl.world_model_sim.world_model_simulator`,
    whose state carries ``context``): GRPO's own imagined rollout (:func:`~sword_jax.rl.rollout.imagined_rollout`)
    of ``decisions`` decisions from each of ``start``'s states, ``group_size`` times each (start-major), none stopped
    at a success, with the simulator's context recorded after each decision. Jit it as a whole."""
    if group_size < 1 or decisions < 1:
        raise ValueError(f"trace_closed_loop: group_size and decisions must be >= 1, got {group_size}, {decisions}")

    def context_of(state):
        if not hasattr(state, "context"):
            raise ValueError("trace_closed_loop: the simulator's state has no context latents (a world-model "
                             f"simulator is needed, got {type(state).__name__})")
        return state.context

    run_rl = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, max_chunks=decisions))
    rollout = imagined_rollout(graphdef, policy_params, simulator, reward_model, start, run_rl, key=key,
                               group_size=group_size, stop_on_success=False, record_state=context_of)
    actions, _ = executed_actions(rollout, rl.action_bins)
    return ClosedLoopTrace(actions, rollout.recorded[:, :, 0])  # per trajectory the state holds [1, k, ...]


def real_latents(encode_frames: Any, first_frames: np.ndarray, history: np.ndarray, frames: np.ndarray, *,
                 frames_per_latent: int, batch: int = 16, latent_index: np.ndarray | None = None) -> np.ndarray:
    """``[n, T / f, h, w, c]`` the training latents of the real frames ``frames [n, T, H, W, 3]`` reached after each
    of ``T`` executed actions from a keyframe; latent ``j`` covers the frames after actions ``f j .. f j + f - 1``,
    the ones the simulator's ``j``-th executed latent stands for. Frames are uint8 or in [0, 1].

    ``encode_frames`` (``[n, F, H, W, 3]`` in [0, 1] -> latents) is the causal encoder the run's latents were made
    with. The video it encodes is laid out as the start's own latents were (:func:`~sword_jax.rl.world_model_sim.
    encode_history`): each episode's first frame, the keyframe's real ``history [n, f (k + 1), H, W, 3]`` (the
    frames up to and including the keyframe), then the executed frames, so that the first executed latent follows
    the real motion that led to the keyframe, as a training episode's latents do; the latents of the first frame
    and of the history are dropped.

    With ``latent_index [n]`` (``rl.imagined.start_encoding=prefix``), ``history`` is instead the keyframes' episodes
    after their first frame (:func:`~sword_jax.rl.data.keyframe_window`'s ``prefix[:, 1:]``, ``f S`` frames) and
    row ``i``'s executed frames follow its first ``f latent_index[i]`` of them, as the start's own latents were
    encoded (:func:`~sword_jax.rl.world_model_sim.encode_prefix`): the real latents are then the ones a whole
    episode's encoding would give. The rows are padded at their end to one length (the encoder is causal: the
    padding changes none of the latents kept)."""
    n, t = frames.shape[:2]
    f = frames_per_latent
    if t % f or history.shape[1] % f or first_frames.shape[0] != n or history.shape[0] != n:
        raise ValueError(f"real_latents: {t} frames and a history of {history.shape[1]} must be whole latents of "
                         f"{f}, with one first frame and history per sequence (got {first_frames.shape[0]} and "
                         f"{history.shape[0]} for {n})")
    unit = lambda x: (x.astype(np.float32) / np.float32(255.0) if x.dtype == np.uint8  # noqa: E731
                      else np.asarray(x, np.float32))
    lead = 1 + history.shape[1] // f
    if latent_index is not None:
        return _real_latents_after(encode_frames, unit(first_frames), unit(history), unit(frames),
                                   np.asarray(latent_index, np.int64), frames_per_latent=f, batch=batch)
    out = []
    for i in range(0, n, batch):
        video = np.concatenate([unit(first_frames[i:i + batch])[:, None], unit(history[i:i + batch]),
                                unit(frames[i:i + batch])], axis=1)
        out.append(np.asarray(encode_frames(video), np.float32)[:, lead:])
    return np.concatenate(out)


def _real_latents_after(encode_frames: Any, first_frames: np.ndarray, prefix: np.ndarray, frames: np.ndarray,
                        latent_index: np.ndarray, *, frames_per_latent: int, batch: int) -> np.ndarray:
    """:func:`real_latents` with ``latent_index``: row ``i`` encodes ``first, prefix[i, :f index_i], frames[i]``, then
    its last executed frame repeated up to one length for all rows, and keeps latents ``1 + index_i ..``."""
    f, (n, t) = frames_per_latent, frames.shape[:2]
    if latent_index.shape != (n,) or np.any(latent_index < 0) or np.any(f * latent_index > prefix.shape[1]):
        raise ValueError(f"real_latents: latent_index {latent_index.tolist()} must hold one index per sequence "
                         f"within the {prefix.shape[1] // f} latents of its prefix")
    total = prefix.shape[1] + t
    out = []
    for i in range(0, n, batch):
        rows = []
        for j in range(i, min(i + batch, n)):
            lead = f * int(latent_index[j])
            row = np.concatenate([prefix[j, :lead], frames[j]])
            rows.append(np.concatenate([row, np.repeat(row[-1:], total - len(row), axis=0)]))
        video = np.concatenate([first_frames[i:i + batch, None], np.stack(rows)], axis=1)
        latents = np.asarray(encode_frames(video), np.float32)
        out.extend(latents[r, 1 + latent_index[i + r]: 1 + latent_index[i + r] + t // f] for r in range(len(rows)))
    return np.stack(out)


def closed_loop_segments(start_latents: np.ndarray, start_actions: np.ndarray, contexts: np.ndarray,
                         real: np.ndarray, actions: np.ndarray, *, num_future: int, execute_latents: int,
                         frames_per_latent: int = 4) -> ClosedLoopSegments:
    """One training segment per decision whose real future is known.

    Args:
      start_latents: ``[n, 1 + k, h, w, c]`` the start states' first-frame and context latents
        (:func:`~sword_jax.rl.world_model_sim.encode_history`, or ``encode_prefix`` with
        ``rl.imagined.start_encoding=prefix``).
      start_actions: ``[n, 1 + f k, A]`` the actions the first frame and the context frames carried.
      contexts: ``[n, D, k, h, w, c]`` the simulator's context after each decision (:func:`trace_closed_loop`).
      real: ``[n, L, h, w, c]`` the real latents of the executed actions (:func:`real_latents`), ``L = D x``.
      actions: ``[n, f L, A]`` the executed actions.
      num_future: latents ``p`` a training segment predicts; execute_latents: latents ``x`` executed a decision.

    Decision ``d`` starts at latent ``j = d x`` (action ``f j``): its segment's context is the start's real one for
    ``d = 0``, else the simulator's after decision ``d - 1``; its future the real latents ``j + 1 .. j + p``, kept
    where ``j + p <= L``. Actions are laid out as a training segment's (:meth:`~sword_jax.world_model.data.
    LatentDataset.segment`: frame ``i`` carries the action executed at it, so the context's last frame carries the
    decision's first action), with the executed actions in place of the policy's plan; the last segment's last
    frame, whose action was never executed, repeats the one before it (as the simulator does at inference)."""
    n, d_count, k = contexts.shape[:3]
    f, p, x = frames_per_latent, num_future, execute_latents
    length = real.shape[1]
    if length != d_count * x or actions.shape[1] != f * length:
        raise ValueError(f"closed_loop_segments: {d_count} decisions of {x} latents need {d_count * x} real latents "
                         f"and {f * d_count * x} actions, got {real.shape[1]} and {actions.shape[1]}")
    if start_latents.shape[1] != 1 + k or start_actions.shape[1] != 1 + f * k:
        raise ValueError(f"closed_loop_segments: start latents [n, {1 + k}, ...] and actions [n, {1 + f * k}, A] for "
                         f"{k} context latents, got {start_latents.shape} and {start_actions.shape}")
    # every frame's action from the context's first frame on: the start's context frames (the last one carries the
    # first executed action), then the executed ones (frame i >= 1 carries action i)
    lead = start_actions[:, 1:].copy()
    lead[:, -1] = actions[:, 0]
    # index i: frame i - f k + 1; the frame after the last executed action repeats it (it was never executed)
    per_frame = np.concatenate([lead, actions[:, 1:], actions[:, -1:]], axis=1)
    offset = f * k - 1
    latents, acts, which, rows = [], [], [], []
    for d in range(d_count):
        j = d * x
        if j + p > length:
            break
        context = start_latents[:, 1:] if d == 0 else contexts[:, d - 1]
        latents.append(np.concatenate([start_latents[:, :1], context, real[:, j:j + p]], axis=1))
        ctx_actions = per_frame[:, offset + f * j - f * k + 1: offset + f * j + 1]
        future = per_frame[:, offset + f * j + 1: offset + f * (j + p) + 1]
        acts.append(np.concatenate([start_actions[:, :1], ctx_actions, future], axis=1))
        which.append(np.full(n, d, np.int32))
        rows.append(np.arange(n, dtype=np.int32))
    if not latents:
        raise ValueError(f"closed_loop_segments: {d_count} decisions of {x} latents leave no segment of {p} future "
                         "latents")
    return ClosedLoopSegments(np.concatenate(latents).astype(np.float32), np.concatenate(acts).astype(np.float32),
                              np.concatenate(which), np.concatenate(rows))


def drift_by_decision(contexts: np.ndarray, real: np.ndarray, *, execute_latents: int) -> list[float]:
    """Per decision ``d``, the mean squared difference between the simulator's newest context latent after decision
    ``d`` and the real latent the same actions reached there: how far the closed loop has drifted in the world
    model's own latent space (the figure the fine-tune on :func:`closed_loop_segments` is meant to lower)."""
    d_count = contexts.shape[1]
    idx = (np.arange(d_count) + 1) * execute_latents - 1
    return [float(np.mean((contexts[:, d, -1] - real[:, i]) ** 2)) for d, i in enumerate(idx)]
