"""Does the learned simulator agree with the real environment about the policy's own episodes?

GRPO inside a learned simulator can only lift real success where the simulator's verdict on a
trajectory (the success detector on imagined frames) follows the real outcome of the same
actions. A simulator that turns the policy's real failures into imagined successes is one GRPO
learns to fool. This module measures that directly:

1. :class:`EpisodeTrace` records real episodes as :func:`~sword_jax.rl.env_rollout.run_policy`
   runs them: every executed action, the outcome, and the frames and proprio of the first
   ``head_steps`` environment steps (stepped one action at a time so each frame is seen).
2. :func:`replay_starts` turns the traced heads into learned-simulator start states at frame
   ``t0 = 4 k`` (``k`` context latents), laid out exactly as GRPO's keyframe starts
   (:func:`sword_jax.rl.data.keyframe_window`), encoded as ``rl.imagined.start_encoding`` says (with ``prefix``
   the head from frame 0, the latents the world model was trained on).
3. :func:`replay_actions` feeds each episode's remaining executed actions, open loop, through the
   simulator and scores every imagined frame with the success detector (pure; jit it).
4. :func:`agreement` compares imagined and real outcomes: how often the simulator calls a real
   failure a success (``false_success``) and a real success a failure (``missed_success``), with
   95% Wilson intervals; replaying twice with other simulator noise tells how often the outcome
   follows the noise rather than the actions (``resample_disagreement``).

:func:`replay_report` runs 2-4 for a traced evaluation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from sword_jax.rl.data import EpisodeSet, keyframe_window
from sword_jax.rl.env_rollout import wilson_interval
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.policy import tokenize_instructions, tokens_to_actions
from sword_jax.rl.reward_model import score_episodes
from sword_jax.rl.config import CALIBRATIONS, RLConfig
from sword_jax.rl.rollout import Rollout, success_runs, trajectory_returns


class TracedEpisodes(NamedTuple):
    """Real episodes as executed (``n`` episodes, ``h = head_steps``).

    Attributes:
      frames: ``[n, 1 + h, H, W, 3]`` uint8, frame ``j`` seen before action ``j`` (an episode done
        inside the head repeats its last frame).
      proprio: ``[n, 1 + h, P]`` at the same frames.
      actions: ``[n, T, A]`` the executed actions, zero after ``lengths``.
      lengths: ``[n]`` actions executed.
      success: ``[n]`` the real outcome.
      language: the ``n`` instructions.
    """

    frames: np.ndarray
    proprio: np.ndarray
    actions: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    language: tuple[str, ...]


class EpisodeTrace:
    """Recorder :func:`~sword_jax.rl.env_rollout.run_policy` fills (its ``trace`` argument).

    ``run_policy`` calls :meth:`start` after the reset and :meth:`record` after every environment
    step, and steps the first ``head_steps`` actions one at a time so their frames are kept.
    """

    def __init__(self, head_steps: int):
        if head_steps < 1:
            raise ValueError(f"EpisodeTrace: head_steps must be >= 1, got {head_steps}")
        self.head_steps = int(head_steps)
        self._frames: list[np.ndarray] = []
        self._proprio: list[np.ndarray] = []
        self._actions: list[list[np.ndarray]] = []
        self._success = np.zeros(0, bool)
        self._language: tuple[str, ...] = ()
        self.steps = 0  # environment steps recorded so far (the longest episode's actions)

    def start(self, obs: dict[str, np.ndarray], language: Sequence[str]) -> None:
        n = len(obs["frames"])
        self._frames, self._proprio = [np.asarray(obs["frames"]).copy()], [np.asarray(obs["proprio"]).copy()]
        self._actions = [[] for _ in range(n)]
        self._success = np.zeros(n, bool)
        self._language = tuple(language)
        self.steps = 0

    @property
    def in_head(self) -> bool:
        """Whether the next environment step still falls in the head (one action at a time)."""
        return self.steps < self.head_steps

    def record(self, actions: np.ndarray, obs: dict[str, np.ndarray]) -> None:
        """One environment step: ``actions [n, b, A]`` were offered, ``obs["executed"]`` of them ran."""
        actions = np.asarray(actions, np.float32)
        executed = np.asarray(obs["executed"], np.int64)
        for i in np.flatnonzero(executed):
            self._actions[i].append(actions[i, : executed[i]])
        self._success |= np.asarray(obs["success"], bool)
        if self.in_head:
            if actions.shape[1] != 1:
                raise ValueError(f"EpisodeTrace: the head is recorded one action at a time, got {actions.shape[1]}")
            self._frames.append(np.asarray(obs["frames"]).copy())
            self._proprio.append(np.asarray(obs["proprio"]).copy())
        self.steps += actions.shape[1]

    def result(self) -> TracedEpisodes:
        if not self._frames:
            raise ValueError("EpisodeTrace: nothing recorded (run_policy(..., trace=...) fills it)")
        head = len(self._frames)
        frames = np.stack(self._frames + [self._frames[-1]] * (1 + self.head_steps - head), axis=1)
        proprio = np.stack(self._proprio + [self._proprio[-1]] * (1 + self.head_steps - head), axis=1)
        lengths = np.asarray([sum(len(a) for a in acts) for acts in self._actions], np.int64)
        dim = next((a.shape[-1] for acts in self._actions for a in acts), 7)
        actions = np.zeros((len(lengths), max(int(lengths.max(initial=0)), 1), dim), np.float32)
        for i, acts in enumerate(self._actions):
            if acts:
                actions[i, : lengths[i]] = np.concatenate(acts)
        return TracedEpisodes(frames, proprio, actions, lengths, self._success.copy(), self._language)


def select(traced: TracedEpisodes, idx: Sequence[int] | np.ndarray) -> TracedEpisodes:
    """The traced episodes at ``idx``."""
    idx = np.asarray(idx, np.int64)
    return TracedEpisodes(traced.frames[idx], traced.proprio[idx], traced.actions[idx], traced.lengths[idx],
                          traced.success[idx], tuple(traced.language[i] for i in idx))


def spread(total: int, count: int) -> np.ndarray:
    """``min(count, total)`` indices spread evenly over ``range(total)`` (every task of a task-major list)."""
    return np.unique(np.linspace(0, total - 1, min(count, total)).round().astype(np.int64)) if total else np.zeros(0, int)


def replay_starts(traced: TracedEpisodes, encode: Callable[[Any, Any], Any], *, num_context: int = 1,
                  frames_per_latent: int = 4, proprio_dim: int = 8, max_instruction_bytes: int = 96,
                  encode_prefix: Callable[[Any, Any], Any] | None = None
                  ) -> tuple[StartState, np.ndarray, np.ndarray]:
    """Learned-simulator starts at frame ``t0 = frames_per_latent * num_context`` of each traced episode.

    Args:
      traced: from :meth:`EpisodeTrace.result`, with ``head_steps >= t0``.
      encode: ``(first_frames [n,H,W,3], history [n,4(k+1),H,W,3]) -> latents``, both in [0, 1] (e.g.
        :func:`sword_jax.rl.world_model_sim.encode_history` with the VAE bound); its result becomes
        ``StartState.latents`` beside the start actions, as GRPO's keyframe starts lay them out.
      encode_prefix: with ``rl.imagined.start_encoding=prefix``, ``(prefix [n, 1 + 4k, H, W, 3] in [0, 1],
        latent_index [n]) -> latents`` (:func:`sword_jax.rl.world_model_sim.encode_prefix` with the VAE bound),
        used instead of ``encode``: the head from frame 0 to ``t0`` (:func:`~sword_jax.rl.data.keyframe_window`'s
        ``prefix``), so the start latents are the whole episode's there.

    Returns:
      ``(start, actions [n, T - t0, A], lengths [n])``: the actions still to replay from ``t0`` and
      how many of them each episode executed (<= 0 where it ended inside the head).
    """
    t0 = frames_per_latent * num_context
    head = traced.frames.shape[1] - 1
    if head < t0:
        raise ValueError(f"replay_starts: the traced head holds {head} steps; a start at frame {t0} needs {t0}")
    n = len(traced.lengths)
    padded = np.zeros((n, max(traced.actions.shape[1], t0 + 1), traced.actions.shape[2]), np.float32)
    padded[:, : traced.actions.shape[1]] = traced.actions
    # with the prefix: the head itself, frames 0 .. t0 (latent num_context ends at t0)
    window = keyframe_window(traced.frames, padded, traced.proprio, np.arange(n), np.full(n, t0, np.int64),
                             num_context=num_context, frames_per_latent=frames_per_latent,
                             prefix_latents=None if encode_prefix is None else num_context)
    unit = lambda x: jnp.asarray(x, jnp.float32) / jnp.float32(255.0)  # noqa: E731
    if encode_prefix is None:
        latents = encode(unit(window["first_frame"]), unit(window["history"]))
    else:
        latents = encode_prefix(unit(window["prefix"]), jnp.asarray(window["latent_index"], jnp.int32))
    start = StartState(unit(window["frame"]), jnp.asarray(window["proprio"][:, :proprio_dim], jnp.float32),
                       jnp.asarray(tokenize_instructions(list(traced.language), max_instruction_bytes)),
                       (latents, jnp.asarray(window["actions"], jnp.float32)))
    return start, padded[:, t0:], traced.lengths - t0


class ReplayOutcome(NamedTuple):
    """The success detector on replayed trajectories.

    Attributes:
      success: ``[n]`` some replayed frame scored at least the threshold.
      first_success: ``[n]`` index of the first such action (its frame is the one after it), -1 if none.
      scores: ``[n, T]`` the detector's score of the frame after each replayed action (0 past ``lengths``).
      frames: with ``record_frames``, ``[n, T, H, W, 3]`` uint8 those frames (else empty).
    """

    success: Bool[Array, " n"]
    first_success: Int[Array, " n"]
    scores: Float[Array, "n t"]
    frames: Any = ()  # with record_frames: [n, T, H, W, 3] uint8, the frame after each replayed action


GRIPPER = 6  # the gripper command's index in the 7-D action (LIBERO: 6 pose deltas, then the gripper)


def replay_actions(simulator: LearnedSimulator, reward_model: RewardModel, start: StartState,
                   actions: Float[Array, "n t a"], lengths: Int[Array, " n"], *, success_threshold: float,
                   key: jax.Array, settle_steps: int = 0, success_frames: int = 1,
                   record_frames: bool = False) -> ReplayOutcome:
    """Feeds fixed action sequences, open loop, through the learned simulator and scores each frame.

    Step ``c`` offers the simulator the window ``actions[c E : c E + chunk_len]`` (``E`` = its
    ``frames_per_step``; actions past the end repeat the last), so every action is executed once
    and conditions the frames it produced exactly as in an imagined rollout.

    A real episode that succeeded ended at the action that reached success, so its replay has no
    frame after that action in which the imagined scene could show it. ``settle_steps`` gives every
    episode that many more scored frames, driven by *hold* actions (zero pose deltas, the last
    gripper command: the arm stays still, as it would after success); frames past
    ``lengths + settle_steps`` are not scored. The window is the same for every episode, whatever
    its real outcome. ``actions`` must have room for it (``t >= max(lengths) + settle_steps``).
    ``success_frames``: the imagined episode succeeds once that many consecutive scored frames reach the
    threshold (``rl.imagined.success_frames``, the rule GRPO's imagined rollouts use). ``record_frames``
    also returns the frames (uint8), e.g. to train the detector on imagined frames (:func:`replayed_episodes`).
    """
    n, total, dim = actions.shape
    if dim != simulator.action_dim:
        raise ValueError(f"replay_actions: actions must have {simulator.action_dim} dims, got {actions.shape}")
    if settle_steps < 0:
        raise ValueError(f"replay_actions: settle_steps must be >= 0, got {settle_steps}")
    if success_frames < 1:
        raise ValueError(f"replay_actions: success_frames must be >= 1, got {success_frames}")
    e, window = simulator.frames_per_step, simulator.chunk_len
    chunks = -(-total // e)
    pad = chunks * e + window - e - total
    actions = jnp.asarray(actions, jnp.float32)
    lengths = jnp.asarray(lengths)
    if settle_steps:
        last = jnp.take_along_axis(actions, jnp.maximum(lengths - 1, 0)[:, None, None], axis=1)  # (n, 1, a)
        hold = jnp.zeros_like(last).at[..., GRIPPER].set(last[..., GRIPPER])
        actions = jnp.where(jnp.arange(total)[None, :, None] >= lengths[:, None, None], hold, actions)
    if pad > 0:
        actions = jnp.concatenate([actions, jnp.repeat(actions[:, -1:], pad, axis=1)], axis=1)
    keys = jax.random.split(key, chunks)

    def step(state, c):
        chunk = jax.lax.dynamic_slice_in_dim(actions, c * e, window, axis=1)
        state, frames = jax.vmap(lambda s, a, k: simulator.step(s, a, key=k))(state, chunk,
                                                                            jax.random.split(keys[c], n))
        scores = reward_model.score(frames.reshape((n * e,) + frames.shape[2:])).reshape(n, e)
        kept = jnp.clip(jnp.round(frames * 255.0), 0, 255).astype(jnp.uint8) if record_frames else ()
        return state, (scores, kept)

    _, (scores, frames) = jax.lax.scan(step, jax.vmap(simulator.init)(start), jnp.arange(chunks))
    if record_frames:  # (C, n, E, H, W, 3) -> (n, T, H, W, 3)
        frames = jnp.swapaxes(frames, 0, 1).reshape((n, chunks * e) + frames.shape[3:])[:, :total]
    scores = jnp.swapaxes(scores, 0, 1).reshape(n, chunks * e)[:, :total]
    valid = jnp.arange(total)[None] < lengths[:, None] + settle_steps
    scores = jnp.where(valid, scores, 0.0)
    reached = success_runs(valid & (scores >= jnp.float32(success_threshold))) >= success_frames
    success = jnp.any(reached, axis=1)
    return ReplayOutcome(success, jnp.where(success, jnp.argmax(reached, axis=1), -1).astype(jnp.int32), scores,
                         frames)


def _replay_batches(start: StartState, actions: np.ndarray, lengths: np.ndarray, keep: np.ndarray,
                    batch: int) -> list[tuple[tuple[Any, jax.Array, jax.Array], int]]:
    """The episodes ``keep`` as :func:`replay_actions` inputs ``(start, actions, lengths)`` in slices of
    ``batch``, each with the count of real episodes in it; the last slice is padded by repeating its last
    episode, so one compile serves every call."""
    out = []
    for lo in range(0, len(keep), batch):
        idx = keep[lo: lo + batch]
        count = len(idx)
        idx = np.concatenate([idx, np.repeat(idx[-1:], batch - count)])
        out.append(((jax.tree.map(lambda y: jnp.asarray(y)[idx], start), jnp.asarray(actions[idx]),
                     jnp.asarray(lengths[idx])), count))
    return out


def replayed_episodes(traced: TracedEpisodes, simulator: LearnedSimulator, reward_model: RewardModel,
                      encode: Callable[[Any, Any], Any], *, success_threshold: float, key: jax.Array,
                      batch: int = 64, num_context: int = 1, frames_per_latent: int = 4, proprio_dim: int = 8,
                      max_instruction_bytes: int = 96, settle_steps: int = 0,
                      encode_prefix: Callable[[Any, Any], Any] | None = None) -> tuple[EpisodeSet, np.ndarray]:
    """Real episodes as the learned simulator imagines them: each traced episode's actions replayed from
    its start frame (:func:`replay_starts`, with ``encode_prefix`` its prefix encoding; :func:`replay_actions` with
    ``settle_steps`` hold actions),
    its imagined frames kept, labelled with the REAL outcome: what a success detector that must be honest
    on imagined frames trains and is calibrated on (:func:`replay_labels`).

    Episodes that ended inside the head are left out. Returns ``(episodes, real_lengths)``: an
    :class:`~sword_jax.rl.data.EpisodeSet` whose frame ``t`` is the imagined frame after replayed action
    ``t``, ``lengths`` = actions replayed + ``settle_steps``, ``success`` = the real outcome (actions and
    proprio are zeros: only frames and labels are meant to be read), and each kept episode's real action
    count from the start frame.
    """
    start, actions, lengths = replay_starts(traced, encode, num_context=num_context, frames_per_latent=frames_per_latent,
                                            proprio_dim=proprio_dim, max_instruction_bytes=max_instruction_bytes,
                                            encode_prefix=encode_prefix)
    keep = np.flatnonzero(lengths > 0)
    if keep.size == 0:
        raise ValueError("replayed_episodes: every traced episode ended inside the head; nothing to replay")
    used = int(lengths[keep].max())
    actions = np.pad(actions[:, :used], ((0, 0), (0, settle_steps), (0, 0)))
    replay = jax.jit(lambda sim, rm, s, a, n, k: replay_actions(sim, rm, s, a, n, success_threshold=success_threshold,
                                                                 key=k, settle_steps=settle_steps, record_frames=True))
    frames = []
    for b, (inputs, count) in enumerate(_replay_batches(start, actions, lengths, keep, batch)):
        out = replay(simulator, reward_model, *inputs, jax.random.fold_in(key, b))
        frames.append(np.asarray(out.frames)[:count])
    frames = np.concatenate(frames)
    e, t = frames.shape[:2]
    episodes = EpisodeSet(frames=frames, actions=np.zeros((e, t, actions.shape[-1]), np.float32),
                          proprio=np.zeros((e, t, proprio_dim), np.float32),
                          lengths=(lengths[keep] + settle_steps).astype(np.int64),
                          success=np.asarray(traced.success, bool)[keep],
                          instructions=tuple(traced.language[i] for i in keep))
    return episodes, lengths[keep].astype(np.int64)


def replay_labels(episodes: EpisodeSet, real_lengths: np.ndarray, positive_tail: int) -> np.ndarray:
    """``[E, T]`` detector labels of :func:`replayed_episodes` from the real outcome: 1 on the last
    ``positive_tail`` replayed actions' frames and the settle frames of real successes (the scene the
    real episode ended on), 0 on every frame of real failures, -1 elsewhere (earlier frames of real
    successes, which may or may not show the task done, and padding)."""
    if positive_tail < 1:
        raise ValueError(f"replay_labels: positive_tail must be >= 1, got {positive_tail}")
    t = np.arange(episodes.frames.shape[1])[None]
    end, real_end = episodes.lengths[:, None], np.asarray(real_lengths)[:, None]
    success = episodes.success[:, None]
    labels = np.full(episodes.frames.shape[:2], -1, np.int32)
    labels[(t < end) & ~success] = 0
    labels[(t >= real_end - positive_tail) & (t < end) & success] = 1
    return labels


def confirm_successes(rollout: Rollout, simulator: LearnedSimulator, reward_model: RewardModel, start: StartState,
                      cfg: RLConfig, *, key: jax.Array) -> tuple[Rollout, Float[Array, ""]]:
    """``rl.imagined.confirm_success``: an imagined success counts only when a second, independent
    imagination of the same trajectory -- its executed actions fed open loop from the same start with
    other simulator noise (:func:`replay_actions`) -- succeeds too. A success the noise made rarely
    survives a second draw; one the actions made does (``replay_report``'s ``confirmed_by_second_replay``
    measures the rule on real episodes). Costs a second pass of the simulator over every trajectory.

    Args:
      rollout: an :func:`~sword_jax.rl.rollout.imagined_rollout` from ``start`` (``[N]``, expanded to groups).
      simulator / reward_model / cfg: as the rollout used them (threshold, ``success_frames``).
      key: the second draw's noise.

    Returns:
      ``(rollout, unconfirmed)``: the rollout with ``success`` and ``returns`` under the rule (the
      recorded decisions and rewards unchanged), and the fraction of trajectories whose success the
      second draw did not confirm.
    """
    n, c, t, a = rollout.tokens.shape
    actions = tokens_to_actions(rollout.tokens, cfg.action_bins).reshape(n, c * t, a)
    lengths = (jnp.sum(rollout.valid, axis=1) * t).astype(jnp.int32)
    again = replay_actions(simulator, reward_model, start, actions, lengths, success_threshold=cfg.success_threshold,
                           key=key, success_frames=cfg.imagined.success_frames)
    success = rollout.success & again.success
    unconfirmed = jnp.mean((rollout.success & ~again.success).astype(jnp.float32))
    return rollout._replace(success=success, returns=trajectory_returns(rollout.rewards, success, cfg)), unconfirmed


def decisive_scores(scores: np.ndarray, lengths: np.ndarray, success_frames: int = 1) -> np.ndarray:
    """``[E]`` each episode's decisive detector score under the imagined-success rule: the best, over its
    first ``lengths`` frames, of the lowest score in any ``success_frames`` consecutive frames. The episode
    is an imagined success at threshold ``c`` exactly when its decisive score is ``>= c`` (what
    :func:`calibrate_threshold` takes)."""
    scores, lengths = np.asarray(scores, np.float64), np.asarray(lengths)
    if scores.ndim != 2 or lengths.shape != scores.shape[:1] or success_frames < 1:
        raise ValueError(f"decisive_scores: scores [E, T] with lengths [E] and success_frames >= 1, got "
                         f"{scores.shape}, {lengths.shape}, {success_frames}")
    valid = np.arange(scores.shape[1])[None] < lengths[:, None]
    masked = np.where(valid, scores, -np.inf)
    k = success_frames
    if k > 1:  # lowest score of each window of k frames ending at t
        windows = np.lib.stride_tricks.sliding_window_view(masked, k, axis=1)
        masked = windows.min(axis=-1)
    return masked.max(axis=1)


def calibrated_detector_report(score: Callable[[Any], Any], replayed: EpisodeSet, real_lengths: np.ndarray, *,
                               positive_tail: int, calibrate: np.ndarray, max_false_success: float = 0.05,
                               success_frames: int = 1) -> dict[str, Any]:
    """The detector's success threshold set on held-out replays, and how it reads imagined frames.

    ``replayed`` (:func:`replayed_episodes`) is split by the boolean mask ``calibrate``: the threshold is
    the lowest whose imagined false-success rate on the calibration episodes is at most
    ``max_false_success`` (:func:`calibrate_threshold` on :func:`decisive_scores`); the other episodes
    report, at that threshold, the episode-level agreement (false and missed success) and the frame-level
    precision and recall against :func:`replay_labels`.
    """
    calibrate = np.asarray(calibrate, bool)
    if calibrate.shape != replayed.success.shape or calibrate.all() or not calibrate.any():
        raise ValueError("calibrated_detector_report: calibrate must mark some but not all replayed episodes")
    frame_scores = score_episodes(jax.jit(score), replayed.frames)
    decisive = decisive_scores(frame_scores, replayed.lengths, success_frames)
    chosen = calibrate_threshold(decisive[calibrate], replayed.success[calibrate], max_false_success=max_false_success)
    threshold, held = chosen["threshold"], ~calibrate
    labels = replay_labels(replayed, real_lengths, positive_tail)[held]
    fire, labelled = frame_scores[held] >= threshold, labels >= 0
    truth = labels == 1
    tp = float((fire & truth & labelled).sum())
    return {"threshold": threshold, "max_false_success": max_false_success, "calibration_episodes": int(calibrate.sum()),
            "calibration": {k: chosen[k] for k in ("false_success", "missed_success", "imagined_success")},
            "held_out_episodes": int(held.sum()),
            "held_out": _agreement_summary(replayed.success[held], decisive[held] >= threshold, "real_success"),
            "frame_precision": tp / max(float((fire & labelled).sum()), 1.0),
            "frame_recall": tp / max(float(truth.sum()), 1.0)}


SUSTAIN_SWEEP = (1, 2, 4, 8)  # consecutive frames at or above the threshold a stricter success rule would ask for
HORIZON_SWEEP = (24, 48, 96)  # actions from the start frame: imagined success that early, real successes vs failures


def _succeeded_by(first_success: np.ndarray, horizon: int | None) -> np.ndarray:
    """Imagined success within the first ``horizon`` actions (``None``: at all); -1 = never."""
    return (first_success >= 0) if horizon is None else (first_success >= 0) & (first_success < horizon)


def success_by_horizon(real: np.ndarray, first_success: np.ndarray,
                       horizons: tuple[int, ...] = HORIZON_SWEEP) -> dict[str, dict[str, Any]]:
    """Imagined success by action ``h`` of the replay, among real successes and among real failures.

    A real failure runs to the step limit while a real success ends soon after it succeeds, so the
    whole-episode ``false_success`` gives failures many more frames in which to hallucinate success.
    At a common horizon the two groups are compared on equal footing: a simulator whose outcomes
    follow the actions calls real successes successes more often than real failures at every ``h``.
    ``first_success`` is -1 where the imagined episode never succeeded. Keys: ``str(h)`` and ``"all"``.
    """
    real, first = np.asarray(real, bool), np.asarray(first_success)
    if real.shape != first.shape or real.ndim != 1:
        raise ValueError(f"success_by_horizon: real {real.shape} and first_success {first.shape} must be equal 1-D shapes")

    out = {}
    for label, h in [*((str(h), h) for h in horizons), ("all", None)]:
        hit = _succeeded_by(first, h)
        out[label] = {"real_success": wilson_rate(int(hit[real].sum()), int(real.sum())),
                      "real_failure": wilson_rate(int(hit[~real].sum()), int((~real).sum()))}
    return out


def _pair_auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """P(a score of ``pos`` > a score of ``neg``), ties counting half: 0.5 = no ranking."""
    diff = pos[:, None] - neg[None, :]
    return float(np.mean((diff > 0) + 0.5 * (diff == 0)))


def within_group_separation(real: np.ndarray, first_success: np.ndarray, group_size: int,
                            horizons: tuple[int, ...] = HORIZON_SWEEP,
                            scores: np.ndarray | None = None) -> dict[str, Any]:
    """Separation of real outcomes inside groups of episodes that share a start state: what GRPO's group
    advantages read, where :func:`success_by_horizon` compares episodes from different starts.

    Episodes ``[g k, (g + 1) k)`` form group ``g`` (``k = group_size``). Per horizon ``h`` (and ``"all"``):
    ``separation``, over the groups whose real outcomes are mixed, the mean of P(imagined success by ``h``
    | real success) - P(... | real failure) within the group (0 when the verdict follows the start and
    not the actions, 1 for a perfect simulator; None without a mixed group); ``imagined_mixed``, the share
    of all groups whose imagined verdicts by ``h`` differ (the groups that carry a learning signal in the
    simulator). ``first_success`` is -1 where the imagined episode never succeeded. With ``scores`` (``[n, T]``,
    the detector's score after each replayed action) also ``auc``: over the mixed groups, the mean chance that a
    real success's highest score within ``h`` actions beats a real failure's (0.5 = no ranking). It needs no
    threshold: it says whether any recalibration of the detector could give GRPO a signal from this simulator.
    """
    real, first = np.asarray(real, bool), np.asarray(first_success)
    if scores is not None:
        scores = np.asarray(scores, np.float64)
        if scores.ndim != 2 or scores.shape[0] != real.size:
            raise ValueError(f"within_group_separation: scores must be [{real.size}, T], got {scores.shape}")
    if real.shape != first.shape or real.ndim != 1:
        raise ValueError(f"within_group_separation: real {real.shape} and first_success {first.shape} must be equal "
                         f"1-D shapes")
    k = int(group_size)
    if k < 2 or real.size % k:
        raise ValueError(f"within_group_separation: {real.size} episodes are not whole groups of {k} (>= 2)")
    groups = real.reshape(-1, k)
    mixed = np.flatnonzero(groups.any(1) & ~groups.all(1))  # the groups whose real outcomes differ
    out: dict[str, Any] = {"group_size": k, "groups": int(groups.shape[0]), "mixed_real_groups": int(mixed.size)}
    for label, h in [*((str(h), h) for h in horizons), ("all", None)]:
        hit = _succeeded_by(first, h).reshape(-1, k).astype(np.float64)
        per_group = [hit[g][groups[g]].mean() - hit[g][~groups[g]].mean() for g in mixed]
        out[label] = {"separation": float(np.mean(per_group)) if per_group else None,
                      "imagined_mixed": float(np.mean(hit.min(1) != hit.max(1)))}
        if scores is not None:
            best = scores[:, : scores.shape[1] if h is None else h].max(1).reshape(-1, k)
            aucs = [_pair_auc(best[g][groups[g]], best[g][~groups[g]]) for g in mixed]
            out[label]["auc"] = float(np.mean(aucs)) if aucs else None
    return out


def separation(real: np.ndarray, first_success: Sequence[np.ndarray], horizon: int | None = 48, *,
               resamples: int = 2000, seed: int = 0) -> dict[str, Any]:
    """How well replays separate real outcomes by action ``horizon`` (``None``: the whole replay).

    Separation = P(imagined success by ``horizon`` | real success) - P(... | real failure): 0 for a
    simulator whose verdicts ignore the actions, 1 for a perfect one. ``first_success`` holds one or
    more simulators' first imagined successes (-1: never) on the **same** real episodes, so their
    difference is paired: the 95% intervals come from one bootstrap over episodes (resampled within
    real successes and within real failures, keeping both groups' sizes). Returns per simulator
    ``{"separation", "ci95"}`` in ``"per_simulator"`` and, for two, ``"difference"`` (second minus first)
    with its interval."""
    real = np.asarray(real, bool)
    firsts = [np.asarray(f) for f in first_success]
    if real.ndim != 1 or any(f.shape != real.shape for f in firsts):
        raise ValueError(f"separation: real {real.shape} and every first_success must be equal 1-D shapes")
    if real.all() or not real.any():
        raise ValueError("separation needs both real successes and real failures among the episodes")
    hits = np.stack([_succeeded_by(f, horizon) for f in firsts]).astype(np.float64)
    wins, losses = np.flatnonzero(real), np.flatnonzero(~real)

    def sep(win_idx, loss_idx):
        return hits[:, win_idx].mean(1) - hits[:, loss_idx].mean(1)

    rng = np.random.default_rng(seed)
    boot = np.stack([sep(rng.choice(wins, wins.size), rng.choice(losses, losses.size)) for _ in range(resamples)])
    point = sep(wins, losses)
    out: dict[str, Any] = {"horizon": horizon, "real_successes": int(wins.size), "real_failures": int(losses.size),
                           "per_simulator": [{"separation": float(p), "ci95": np.percentile(boot[:, i], [2.5, 97.5]).tolist()}
                                             for i, p in enumerate(point)]}
    if len(firsts) == 2:
        diff = boot[:, 1] - boot[:, 0]
        out["difference"] = {"separation": float(point[1] - point[0]), "ci95": np.percentile(diff, [2.5, 97.5]).tolist()}
    return out


def wilson_rate(hits: int, of: int) -> dict[str, Any]:
    """``hits / of`` with its 95% Wilson interval (``None`` rate where ``of`` is 0)."""
    return {"rate": hits / of if of else None, "ci95": list(wilson_interval(hits, of)), "of": of}


def calibrate_threshold(scores: np.ndarray, real: np.ndarray, *, max_false_success: float = 0.05) -> dict[str, Any]:
    """The lowest success threshold whose false-success rate on these episodes is at most ``max_false_success``.

    Args:
      scores: ``[n]`` each replayed episode's decisive detector score (e.g. its best score over the frames,
        or over runs of ``rl.imagined.success_frames`` frames): the episode is imagined a success when the
        score is at or above the threshold.
      real: ``[n]`` bool, the episodes' real outcomes.
      max_false_success: the bound on P(imagined success | real failure).

    Returns:
      ``{"threshold", "false_success", "missed_success", ...}`` (:func:`agreement` at that threshold): the
      threshold lets through at most ``floor(max_false_success * failures)`` real failures, the largest
      recall on real successes any threshold with that bound has. Calibrate on held-out replays and
      report it on others.

    Raises:
      ValueError: mismatched or empty inputs, no real failure, or a bound outside [0, 1).
    """
    scores, real = np.asarray(scores, np.float64), np.asarray(real, bool)
    if scores.shape != real.shape or scores.ndim != 1 or not np.all(np.isfinite(scores)):
        raise ValueError(f"calibrate_threshold: scores {scores.shape} must be finite and match real {real.shape} (1-D)")
    if not 0.0 <= max_false_success < 1.0:
        raise ValueError(f"calibrate_threshold: max_false_success must be in [0, 1), got {max_false_success}")
    failures = np.sort(scores[~real])[::-1]
    if failures.size == 0:
        raise ValueError("calibrate_threshold: no real failure among the episodes: the false-success rate is undefined")
    allowed = int(np.floor(max_false_success * failures.size + 1e-9))
    # just above the (allowed + 1)-th highest failure score: that one and every lower one stay failures
    threshold = float(np.nextafter(failures[allowed], np.inf))
    return {"threshold": threshold, "max_false_success": max_false_success, **agreement(real, scores >= threshold)}


def calibrate_separation(scores: np.ndarray, real: np.ndarray) -> dict[str, Any]:
    """The success threshold that separates these episodes' real outcomes best.

    Separation = P(imagined success | real success) - P(imagined success | real failure) (Youden's J). A
    GRPO group's expected imagined reward is ``false_success + separation * p`` for a policy that really
    succeeds with probability ``p`` (while the simulator's errors do not depend on the policy, which the
    refreshes check), so its learning signal is proportional to the separation; a bound on false success
    alone (:func:`calibrate_threshold`) can leave almost none of it.

    Args:
      scores: ``[n]`` each replayed episode's decisive detector score (:func:`decisive_scores`).
      real: ``[n]`` bool, the episodes' real outcomes; both outcomes present.

    Returns:
      ``{"threshold", "separation", ...}`` (:func:`agreement` at that threshold): the highest of the
      thresholds with the largest separation (ties go to fewer false successes).

    Raises:
      ValueError: mismatched, non-finite or empty inputs, or a real outcome missing.
    """
    scores, real = np.asarray(scores, np.float64), np.asarray(real, bool)
    if scores.shape != real.shape or scores.ndim != 1 or not np.all(np.isfinite(scores)):
        raise ValueError(f"calibrate_separation: scores {scores.shape} must be finite and match real {real.shape} (1-D)")
    if real.all() or not real.any():
        raise ValueError("calibrate_separation: needs real successes and real failures among the episodes, got "
                         f"{int(real.sum())} of {real.size} successes")
    cuts = np.r_[np.unique(scores), np.nextafter(scores.max(), np.inf)]  # the last: nothing fires
    fire = scores[None, :] >= cuts[:, None]
    seps = fire[:, real].mean(axis=1) - fire[:, ~real].mean(axis=1)
    best = int(np.flatnonzero(seps == seps.max())[-1])
    threshold = float(cuts[best])
    return {"threshold": threshold, "separation": float(seps[best]), **agreement(real, scores >= threshold)}


def roc_points(scores: np.ndarray, real: np.ndarray) -> list[list[float]]:
    """``[[threshold, false success, recall], ...]`` at every decisive score of these episodes (highest
    threshold first): the trade-off a calibration chose from (recall = P(imagined success | real success))."""
    scores, real = np.asarray(scores, np.float64), np.asarray(real, bool)
    out = []
    for cut in np.unique(scores)[::-1]:
        fire = scores >= cut
        out.append([round(float(cut), 6), round(float(fire[~real].mean()), 4) if (~real).any() else None,
                    round(float(fire[real].mean()), 4) if real.any() else None])
    return out


def calibrate_replays(scores: np.ndarray, lengths: np.ndarray, real: np.ndarray, *,
                      horizons: Sequence[int | None], calibration: str = "false_success",
                      max_false_success: float = 0.05, success_frames: int = 1) -> dict[str, dict[str, Any]]:
    """The detector's threshold set on replays of real episodes, over each of ``horizons``.

    Args:
      scores: ``[E, T]`` the detector's scores of the replayed frames, one frame per action.
      lengths: ``[E]`` frames of each replay that count.
      real: ``[E]`` bool, the real outcomes.
      horizons: actions of each replay the imagined outcome is read over (``None``: the whole replay). GRPO's
        imagined rollouts run a few dozen actions: calibrated over whole replays of 200-odd actions, the
        world model's late drift into a solved-looking scene sets the threshold for rollouts that never
        reach it.
      calibration: ``false_success`` (:func:`calibrate_threshold` at ``max_false_success``) or ``separation``
        (:func:`calibrate_separation`).
      success_frames: the imagined-success rule's consecutive frames (:func:`decisive_scores`).

    Returns:
      ``{str(h) or "all": {"threshold", "false_success", "missed_success", ..., "separation", "roc"}}``.
    """
    if calibration not in CALIBRATIONS:
        raise ValueError(f"calibrate_replays: calibration must be {'|'.join(CALIBRATIONS)}, got {calibration!r}")
    lengths = np.asarray(lengths)
    real = np.asarray(real, bool)
    out = {}
    for h in horizons:
        if h is not None and h < 1:
            raise ValueError(f"calibrate_replays: horizons must be >= 1 actions (or None), got {h}")
        decisive = decisive_scores(scores, lengths if h is None else np.minimum(lengths, h), success_frames)
        if calibration == "separation":
            chosen = calibrate_separation(decisive, real)
        else:
            chosen = calibrate_threshold(decisive, real, max_false_success=max_false_success)
            fire = decisive >= chosen["threshold"]
            chosen["separation"] = float(fire[real].mean() - fire[~real].mean()) if real.any() else None
        chosen["roc"] = roc_points(decisive, real)
        out["all" if h is None else str(h)] = chosen
    return out


def _agreement_summary(real: np.ndarray, imagined: np.ndarray, *more: str) -> dict[str, Any]:
    """:func:`agreement`'s imagined success, false and missed success and agreement (and ``more`` of its keys)."""
    keep = ("imagined_success", "false_success", "missed_success", "agreement", *more)
    return {name: sub for name, sub in agreement(real, imagined).items() if name in keep}


def agreement(real: np.ndarray, imagined: np.ndarray) -> dict[str, Any]:
    """Imagined vs real outcomes of the same episodes, with 95% Wilson intervals.

    ``false_success`` = P(imagined success | real failure): what GRPO can exploit.
    ``missed_success`` = P(imagined failure | real success): real successes GRPO cannot see.
    """
    real, imagined = np.asarray(real, bool), np.asarray(imagined, bool)
    if real.shape != imagined.shape or real.ndim != 1:
        raise ValueError(f"agreement: real {real.shape} and imagined {imagined.shape} must be equal 1-D shapes")
    tp, fp = int(np.sum(real & imagined)), int(np.sum(~real & imagined))
    fn, tn = int(np.sum(real & ~imagined)), int(np.sum(~real & ~imagined))

    n = real.size
    return {"episodes": n, "real_success": float(real.mean()) if n else None,
            "imagined_success": float(imagined.mean()) if n else None, "agreement": wilson_rate(tp + tn, n),
            "false_success": wilson_rate(fp, fp + tn), "missed_success": wilson_rate(fn, tp + fn),
            "counts": {"real_and_imagined": tp, "imagined_only": fp, "real_only": fn, "neither": tn}}


def replay_report(traced: TracedEpisodes, simulator: LearnedSimulator, reward_model: RewardModel,
                  encode: Callable[[Any, Any], Any], *, success_threshold: float, key: jax.Array, batch: int = 64,
                  num_context: int = 1, frames_per_latent: int = 4, proprio_dim: int = 8,
                  max_instruction_bytes: int = 96, max_steps: int | None = None, repeats: int = 2,
                  settle_steps: int = 0, replay_fn: Callable | None = None,
                  encode_prefix: Callable[[Any, Any], Any] | None = None) -> dict[str, Any]:
    """Replays traced real episodes in the learned simulator and reports :func:`agreement`.

    Episodes that ended inside the head (before the simulator's start frame) are left out. The
    replay runs ``batch`` episodes per call (the last batch padded), so one compile serves any
    count, and the actions are padded to ``max_steps`` (the episodes' step limit) so every evaluation
    has the same shapes; pass ``replay_fn`` (``jax.jit`` of :func:`replay_actions` with ``success_threshold``
    and the same ``settle_steps`` bound) to reuse one compile across reports. ``settle_steps``: hold
    actions scored after each episode's last action (:func:`replay_actions`), for the imagined scene to
    show a success the real episode ended on. ``encode_prefix``: the starts' prefix encoder with
    ``rl.imagined.start_encoding=prefix`` (:func:`replay_starts`).

    Each episode is replayed ``repeats`` times with other simulator noise (a flow-matching world
    model samples its futures): the agreement is the first replay's, and ``resample_disagreement``
    is how often two replays of the same actions end differently. Inside GRPO every trajectory of
    a group draws its own noise, so outcomes that follow the noise rather than the actions are a
    spread in the group's returns that no action explains.

    ``sustained_success_sweep[k]`` is the agreement a stricter success rule would have had, one that
    asks for ``k`` consecutive frames at or above the threshold (:data:`SUSTAIN_SWEEP`), computed
    from the first replay's scores: whether the simulator's false successes are one-frame flickers
    such a rule removes or sustained scenes it does not. ``imagined_success_by_horizon``
    (:func:`success_by_horizon`) compares real successes and failures at common horizons.

    ``confirmed_by_second_replay`` (with ``repeats >= 2``) is the agreement of the rule
    ``rl.imagined.confirm_success`` applies in GRPO: an episode counts as an imagined success only when
    both independent replays succeed.

    Returns :func:`agreement` plus ``left_out``, ``resample_disagreement`` (with ``repeats >= 2``),
    ``imagined_success_repeats`` and, per replayed episode counted from the start frame,
    ``imagined_first_success`` / ``imagined_longest_success_run`` / ``real_lengths`` / ``real_success_flags``.
    """
    if repeats < 1:
        raise ValueError(f"replay_report: repeats must be >= 1, got {repeats}")
    start, actions, lengths = replay_starts(traced, encode, num_context=num_context,
                                            frames_per_latent=frames_per_latent, proprio_dim=proprio_dim,
                                            max_instruction_bytes=max_instruction_bytes, encode_prefix=encode_prefix)
    keep = np.flatnonzero(lengths > 0)
    if max_steps is not None:
        t0 = frames_per_latent * num_context
        if max_steps - t0 < actions.shape[1]:
            raise ValueError(f"replay_report: episodes executed {actions.shape[1] + t0} actions, more than "
                             f"max_steps={max_steps}")
        actions = np.pad(actions, ((0, 0), (0, max_steps - t0 - actions.shape[1]), (0, 0)))
    actions = np.pad(actions, ((0, 0), (0, settle_steps), (0, 0)))  # room for the hold actions
    replay_fn = replay_fn or jax.jit(lambda sim, rm, s, a, l, k: replay_actions(
        sim, rm, s, a, l, success_threshold=success_threshold, key=k, settle_steps=settle_steps))
    batches = _replay_batches(start, actions, lengths, keep, batch)
    outcomes, first, runs = [], [], []
    for r in range(repeats):
        imagined = []
        for b, (inputs, count) in enumerate(batches):
            out = replay_fn(simulator, reward_model, *inputs, jax.random.fold_in(jax.random.fold_in(key, r), b))
            imagined.append(np.asarray(out.success)[:count])
            if r == 0:
                first.append(np.asarray(out.first_success)[:count])
                runs.append(np.asarray(success_runs(out.scores[:count] >= success_threshold)).max(axis=1, initial=0))
        outcomes.append(np.concatenate(imagined) if imagined else np.zeros(0, bool))
    report = agreement(traced.success[keep], outcomes[0])
    run = np.concatenate(runs) if runs else np.zeros(0, np.int64)
    # what a success rule asking for k consecutive frames would have said, from the same scores
    report["sustained_success_sweep"] = {
        str(k): _agreement_summary(traced.success[keep], run >= k)
        for k in SUSTAIN_SWEEP}
    report["imagined_longest_success_run"] = run.tolist()
    report["imagined_success_by_horizon"] = success_by_horizon(
        traced.success[keep], np.concatenate(first) if first else np.zeros(0, np.int32))
    flips = int(np.sum(outcomes[0] != outcomes[1])) if repeats >= 2 else 0
    report.update(left_out=int(len(lengths) - len(keep)), settle_steps=int(settle_steps),
                  imagined_success_repeats=[float(o.mean()) if o.size else None for o in outcomes],
                  imagined_first_success=np.concatenate(first).tolist() if first else [],
                  real_lengths=lengths[keep].tolist(), real_success_flags=traced.success[keep].astype(int).tolist())
    if repeats >= 2:  # what rl.imagined.confirm_success would say: both independent replays succeed
        report["confirmed_by_second_replay"] = _agreement_summary(traced.success[keep], outcomes[0] & outcomes[1])
        report["resample_disagreement"] = {"rate": flips / len(keep) if len(keep) else None,
                                           "ci95": list(wilson_interval(flips, len(keep))), "of": int(len(keep))}
    return report
