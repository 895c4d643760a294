"""Imagined rollouts: a group of G trajectories per start state, inside the learned simulator.

One jitted computation: ``lax.scan`` over action chunks; per chunk the policy reads the current
(decoded) frame, samples an 8-step action chunk, the simulator (vmapped over trajectories)
predicts the next 8 frames, and the reward model scores them. A trajectory is *done* once the
score passes the success threshold or the chunk limit is reached; after that its simulator
state is frozen and it contributes no reward and no policy-gradient tokens (``valid = 0``).
:func:`chunk_outcome` is that rule, the one place it is written: the functional env
(:class:`sword_jax.rl.env.ImaginedEnv`) steps by it too.

Trajectory arrays are laid out ``[B * G, ...]`` (start-major), sharded over the ``batch``
logical axis; :func:`group_view` reshapes to ``[B, G, ...]``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Bool, Float, Int

from sword_jax.rl.config import RLConfig
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.policy import resize_frames, sample_chunk, tokens_to_actions
from sword_jax.sharding import constrain


class Rollout(NamedTuple):
    """What GRPO needs from a batch of imagined trajectories (N = B * G, C = max_chunks).

    Attributes:
      obs_frames: the frame the policy acted on, at policy resolution ``[N, C, s, s, 3]``.
      proprio / proprio_valid: policy proprio inputs ``[N, C, P]`` / ``[N, C]``.
      instruction_tokens: ``[N, L]``.
      tokens: the executed actions' sampled tokens ``[N, C, T, A]`` (``T`` = the simulator's
        ``frames_per_step``: the policy's whole chunk, or its first actions where the simulator
        re-plans sooner; GRPO scores only these).
      log_probs: their log-probs under the behaviour policy ``[N, C, T, A]``.
      valid: 1 where the chunk was taken before the trajectory was done ``[N, C]``.
      rewards: per-chunk reward (change of success score), 0 after done ``[N, C]``.
      scores: success score of the chunk's last frame ``[N, C]``.
      success: the score passed the threshold at some frame ``[N]``.
      returns: trajectory return used for advantages ``[N]``.
      frames: all predicted frames ``[N, C, T, H, W, 3]`` when recorded, else an empty array.
      peaks: the reward model's highest frame score within each chunk ``[N, C]`` (0 after the trajectory was
        done), where the rollout came from :func:`imagined_rollout`; None otherwise. With
        ``rl.imagined.success_frames = 1`` a trajectory's detector verdict at any threshold is its highest peak
        reaching it (:func:`~sword_jax.rl.imagined_check.detector_separation` reads them so).
      recorded: what :func:`imagined_rollout`'s ``record_state`` took of the simulator's state after each chunk,
        ``[N, C, ...]`` leaves; None when nothing was recorded.
    """

    obs_frames: Float[Array, "n c s s 3"]
    proprio: Float[Array, "n c p"]
    proprio_valid: Float[Array, "n c"]
    instruction_tokens: Int[Array, "n l"]
    tokens: Int[Array, "n c t a"]
    log_probs: Float[Array, "n c t a"]
    valid: Float[Array, "n c"]
    rewards: Float[Array, "n c"]
    scores: Float[Array, "n c"]
    success: Bool[Array, " n"]
    returns: Float[Array, " n"]
    frames: Float[Array, "..."]
    peaks: Float[Array, "n c"] | None = None
    recorded: Any = None


class ChunkOutcome(NamedTuple):
    """What one action chunk earns under the task's rule (leading axes ``...``: trajectories, or none).

    Attributes:
      reward: change of the success score over the chunk; 0 where the trajectory was already done.
      score: success score of the chunk's last frame; the previous score where already done.
      success: a frame of the chunk scored >= the threshold, and the trajectory was not done before.
      truncated: the chunk was the last one allowed and did not succeed.
      done: done after the chunk (done before, succeeded, or truncated).
      run: consecutive frames at or above the threshold ending at the chunk's last frame (carried
        into the next chunk for ``rl.imagined.success_frames``); the previous run where already done.
    """

    reward: Float[Array, "..."]
    score: Float[Array, "..."]
    success: Bool[Array, "..."]
    truncated: Bool[Array, "..."]
    done: Bool[Array, "..."]
    run: Int[Array, "..."]


def success_runs(hit: Bool[Array, "... t"], start: Int[Array, "..."] | None = None) -> Int[Array, "... t"]:
    """Consecutive True values ending at each position of the last axis of ``hit``, continuing a run
    of ``start`` (default 0) that ended just before it: the count ``rl.imagined.success_frames``
    compares with."""
    run = jnp.zeros(hit.shape[:-1], jnp.int32) if start is None else jnp.asarray(start, jnp.int32)

    def count(run, h):
        run = jnp.where(h, run + 1, 0)
        return run, run

    _, runs = jax.lax.scan(count, run, jnp.moveaxis(hit, -1, 0))
    return jnp.moveaxis(runs, 0, -1)


def chunk_outcome(scores: Float[Array, "... t"], prev_score: Float[Array, "..."], done: Bool[Array, "..."],
                  chunk_index: Int[Array, "..."], *, success_threshold: float, max_chunks: int,
                  prev_run: Int[Array, "..."] | None = None, success_frames: int = 1,
                  stop_on_success: bool = True) -> ChunkOutcome:
    """The reward and termination rule of an imagined trajectory, for one action chunk.

    Args:
      scores: the reward model's success score of each frame the chunk produced.
      prev_score: the score before the chunk (the start frame's, then the last chunk's).
      done: the trajectory was done before this chunk (its state is frozen; it earns nothing).
      chunk_index: 0-based index of this chunk; the chunk ``max_chunks - 1`` is the last.
      success_threshold: a frame scoring at least this counts as a success frame.
      max_chunks: the step limit, in chunks.
      prev_run: consecutive success frames ending at the previous chunk's last frame (0 at the start).
      success_frames: success needs this many consecutive success frames, counted across chunks
        (``rl.imagined.success_frames``; 1 = any frame), so a one-frame flicker of the detector on a
        hallucinated scene does not end an episode as a success.
      stop_on_success: a success ends the trajectory (the detector's reward). With False the success is
        recorded and the trajectory runs on to ``max_chunks`` (a reward paid elsewhere, e.g. by executing the
        actions, with the detector's verdict kept by the same rule).

    Returns:
      A :class:`ChunkOutcome`. The trajectory return adds ``rl.grpo.success_bonus`` once on success
      (:func:`imagined_rollout`).
    """
    if success_frames < 1:
        raise ValueError(f"chunk_outcome: success_frames must be >= 1, got {success_frames}")
    valid = ~done
    prev_run = jnp.zeros(scores.shape[:-1], jnp.int32) if prev_run is None else jnp.asarray(prev_run, jnp.int32)
    runs = success_runs(scores >= jnp.float32(success_threshold), prev_run)
    success_now = jnp.any(runs >= success_frames, axis=-1)
    score = jnp.where(valid, scores[..., -1], prev_score)
    reward = jnp.where(valid, score - prev_score, jnp.float32(0.0))
    success = valid & success_now
    last = chunk_index + 1 >= max_chunks
    truncated = valid & (~success_now & last if stop_on_success else last)
    ended = success | truncated if stop_on_success else truncated
    return ChunkOutcome(reward=reward, score=score, success=success, truncated=truncated,
                        done=done | ended, run=jnp.where(valid, runs[..., -1], prev_run))


def trajectory_returns(rewards: Float[Array, "n c"], success: Bool[Array, " n"], cfg: RLConfig) -> Float[Array, " n"]:
    """The GRPO return of imagined trajectories by ``cfg.imagined.return_rule``: ``success``, ``1 +
    success_bonus`` on success and 0 otherwise (as in the ground-truth environments); ``score``, the
    summed per-chunk score changes plus ``success_bonus`` on success."""
    bonus = jnp.float32(cfg.grpo.success_bonus) * success.astype(jnp.float32)
    if cfg.imagined.return_rule == "success":
        return success.astype(jnp.float32) + bonus
    if cfg.imagined.return_rule == "score":
        return jnp.sum(rewards, axis=1) + bonus
    raise ValueError(f"rl.imagined.return_rule must be success|score, got {cfg.imagined.return_rule!r}")


def simulator_keys(key: jax.Array, n: int, cfg: RLConfig) -> jax.Array:
    """The simulator's noise key of each of ``n`` trajectories for one chunk: one per trajectory, or with
    ``rl.imagined.shared_group_noise`` one per group of ``rl.grpo.group_size`` consecutive trajectories (the
    layout :func:`expand_groups` makes), so the members of a group differ only by their actions and a
    group's advantages do not reward the noise draw that happened to favour one member."""
    if not cfg.imagined.shared_group_noise:
        return jax.random.split(key, n)
    g = cfg.grpo.group_size
    if n % g:
        raise ValueError(f"rl.imagined.shared_group_noise needs whole groups: {n} trajectories are not groups of {g}")
    return jnp.repeat(jax.random.split(key, n // g), g, axis=0)


def take_trajectories(rollout: Rollout, idx: Int[Array, " m"]) -> Rollout:
    """The trajectories ``idx`` of ``rollout`` (every per-trajectory field; the empty ``frames`` stays)."""
    n = rollout.valid.shape[0]
    return jax.tree.map(lambda x: x if x.ndim == 0 or x.shape[0] != n else jnp.take(x, idx, axis=0), rollout)


def expand_groups(start: StartState, group_size: int) -> StartState:
    """Repeats each start state ``group_size`` times: leading ``[B]`` -> ``[B * G]`` (start-major)."""
    return jax.tree.map(lambda x: jnp.repeat(x, group_size, axis=0), start)


def group_view(x: Array, group_size: int) -> Array:
    """``[B * G, ...]`` -> ``[B, G, ...]``."""
    return x.reshape((x.shape[0] // group_size, group_size) + x.shape[1:])


def microbatches_for(trajectories: int, requested: int, max_slice: int | None) -> int:
    """``rl.imagined.sim_microbatches`` resolved: ``requested`` if >= 1, else (0, auto) the fewest slices that
    divide ``trajectories`` into at most ``max_slice`` each (one slice without a limit)."""
    if requested >= 1:
        return requested
    if max_slice is None:
        return 1
    return next(s for s in range(1, trajectories + 1) if trajectories % s == 0 and trajectories // s <= max_slice)


def to_slices(tree: Any, slices: int) -> Any:
    """Leading axis ``n`` -> ``[slices, n / slices]``; slice ``j`` holds rows ``j, j + slices, ...``.

    Interleaved, so a leading axis sharded in contiguous blocks stays spread over the devices
    within every slice.
    """
    n = jax.tree.leaves(tree)[0].shape[0]
    if n % slices:
        raise ValueError(f"rl.imagined.sim_microbatches={slices} does not divide the {n} trajectories")
    if slices == 1:
        return jax.tree.map(lambda x: x[None], tree)
    return jax.tree.map(lambda x: jnp.swapaxes(x.reshape((n // slices, slices) + x.shape[1:]), 0, 1), tree)


def from_slices(tree: Any) -> Any:
    """Inverse of :func:`to_slices`."""
    def merge(y):
        if y.shape[0] == 1:
            return y[0]
        return jnp.swapaxes(y, 0, 1).reshape((y.shape[0] * y.shape[1],) + y.shape[2:])
    return jax.tree.map(merge, tree)


def map_over_slices(fn: Callable, sliced_args: Any) -> Any:
    """``fn`` vmapped over each slice of :func:`to_slices`-laid-out arguments, one slice at a time."""
    if jax.tree.leaves(sliced_args)[0].shape[0] == 1:
        return jax.tree.map(lambda y: y[None], jax.vmap(fn)(*jax.tree.map(lambda x: x[0], sliced_args)))
    return jax.lax.map(lambda args: jax.vmap(fn)(*args), sliced_args)


def imagined_rollout(
    graphdef: nnx.GraphDef,
    policy_params: nnx.State,
    simulator: LearnedSimulator,
    reward_model: RewardModel,
    start: StartState,
    cfg: RLConfig,
    *,
    key: jax.Array,
    record_frames: bool = False,
    greedy: bool = False,
    group_size: int = 1,
    stop_on_success: bool = True,
    record_state: Callable[[Any], Any] | None = None,
) -> Rollout:
    """Rolls the policy out in the learned simulator for ``cfg.imagined.max_chunks`` chunks.

    Args:
      graphdef / policy_params: the split :class:`~sword_jax.rl.policy.VLAPolicy`.
      simulator: the learned simulator (protocol in :mod:`sword_jax.rl.learned_simulator`).
      reward_model: per-frame success scorer.
      start: start states with leading axis N (already expanded to groups), or with ``group_size`` G > 1
        the N / G distinct start states of the groups: the simulator is then initialised once per start
        state (a world model's start-up decode of the start latents) and its state broadcast to the G
        members, the same rollout as from :func:`expand_groups` of them for G times less start-up work.
      cfg: RL config (threshold, chunk limit, temperature, success bonus).
      key: rollout randomness (policy sampling and simulator noise); same key, same rollout.
      record_frames: also return every predicted frame (for videos; memory heavy).
      greedy: take the argmax action instead of sampling (evaluation).
      group_size: see ``start``.
      stop_on_success: a trajectory ends at the detector's success (its reward). With False every trajectory
        runs ``max_chunks`` chunks and ``success`` is still the detector's verdict by the same rule (a run of
        ``rl.imagined.success_frames`` frames at or above ``cfg.success_threshold``, any frame of a chunk): what
        the detector would have paid a trajectory whose reward comes from elsewhere.
      record_state: a function of the simulator's state (a pytree of its leaves, as the state holds them: in the
        microbatch layout of :func:`to_slices`) taken after each chunk, returned as ``Rollout.recorded`` with the
        trajectories merged (e.g. a world model's context latents, :mod:`~sword_jax.rl.closed_loop`).

    Returns:
      A :class:`Rollout` of N trajectories (start-major).
    """
    policy = nnx.merge(graphdef, policy_params)
    if group_size < 1:
        raise ValueError(f"imagined_rollout: group_size must be >= 1, got {group_size}")
    n = start.frame.shape[0] * group_size
    if start.frame.ndim != 4 or start.frame.shape[-1] != 3:
        raise ValueError(f"start.frame must be [N, H, W, 3], got {start.frame.shape}")
    slices = microbatches_for(n, cfg.imagined.sim_microbatches, simulator.max_slice)
    # The simulator's state stays in the sliced layout for the whole rollout (no per-step relayout of its
    # decoder cache); only the per-step inputs and outputs are sliced and merged.
    if group_size == 1:
        sim_state = map_over_slices(simulator.init, to_slices((start,), slices))
        init_score = reward_model.score(start.frame)
    else:  # one start-up per start state, broadcast to its group
        sim_state = to_slices(expand_groups(jax.vmap(simulator.init)(start), group_size), slices)
        init_score = jnp.repeat(reward_model.score(start.frame), group_size, axis=0)
        start = expand_groups(start, group_size)
    # The policy's view of the latest frame is carried (the start frame and the simulator's frames may differ
    # in size, e.g. with a light decoder at the policy's resolution).
    carry = (sim_state, resize_frames(start.frame, cfg.image_size), init_score, jnp.zeros((n,), jnp.bool_),
             jnp.zeros((n,), jnp.int32))

    def chunk_step(carry, chunk_index):
        sim_state, frame, prev_score, done, prev_run = carry
        chunk_key = jax.random.fold_in(key, chunk_index)
        policy_key, sim_key = jax.random.split(chunk_key)
        obs = constrain(frame, ("batch", "height", "width", "channels"))
        proprio, proprio_valid = from_slices(map_over_slices(simulator.observe, (sim_state,)))
        logits = policy(obs, start.instruction_tokens, proprio, proprio_valid)
        if greedy:
            tokens = jnp.argmax(logits, axis=-1).astype(jnp.int32)
            log_probs = jnp.take_along_axis(jax.nn.log_softmax(logits, -1), tokens[..., None], -1)[..., 0]
        else:
            tokens, log_probs = sample_chunk(logits, key=policy_key, temperature=cfg.grpo.temperature)
        actions = tokens_to_actions(tokens, cfg.action_bins)  # (N, T, A)
        new_state, frames = map_over_slices(lambda s, a, k: simulator.step(s, a, key=k),
                                            (sim_state,) + to_slices((actions, simulator_keys(sim_key, n, cfg)), slices))
        frames = from_slices(frames)
        frames = constrain(frames, ("batch", "time", "height", "width", "channels"))
        t = frames.shape[1]  # actions executed (= frames predicted) this step; the policy re-plans after them
        tokens, log_probs = tokens[:, :t], log_probs[:, :t]
        scores = reward_model.score(frames.reshape((n * t,) + frames.shape[2:])).reshape(n, t)
        outcome = chunk_outcome(scores, prev_score, done, chunk_index, success_threshold=cfg.success_threshold,
                                max_chunks=cfg.imagined.max_chunks, prev_run=prev_run,
                                success_frames=cfg.imagined.success_frames, stop_on_success=stop_on_success)
        valid = ~done
        # done trajectories keep their state and frame (the rule keeps their score); they earn nothing more
        keep = lambda mask: lambda new, old: jnp.where(mask.reshape(mask.shape + (1,) * (new.ndim - mask.ndim)),  # noqa: E731
                                                       new, old)
        sim_state = jax.tree.map(keep(to_slices(valid, slices)), new_state, sim_state)
        next_frame = keep(valid)(resize_frames(frames[:, -1], cfg.image_size), frame)
        out = dict(obs=obs, proprio=proprio, proprio_valid=proprio_valid.astype(jnp.float32), tokens=tokens,
                   log_probs=log_probs, valid=valid.astype(jnp.float32), reward=outcome.reward, score=outcome.score,
                   success=outcome.success, peak=jnp.where(valid, jnp.max(scores, axis=-1), jnp.float32(0.0)))
        if record_frames:
            out["frames"] = frames
        if record_state is not None:
            out["recorded"] = from_slices(record_state(sim_state))
        return (sim_state, next_frame, outcome.score, outcome.done, outcome.run), out

    _, traj = jax.lax.scan(chunk_step, carry, jnp.arange(cfg.imagined.max_chunks))
    swap = lambda x: jnp.swapaxes(x, 0, 1)  # noqa: E731 - (C, N, ...) -> (N, C, ...)
    success = jnp.any(traj["success"], axis=0)
    rewards = swap(traj["reward"])
    returns = trajectory_returns(rewards, success, cfg)
    return Rollout(
        obs_frames=swap(traj["obs"]),
        proprio=swap(traj["proprio"]),
        proprio_valid=swap(traj["proprio_valid"]),
        instruction_tokens=start.instruction_tokens,
        tokens=swap(traj["tokens"]),
        log_probs=swap(traj["log_probs"]),
        valid=swap(traj["valid"]),
        rewards=rewards,
        scores=swap(traj["score"]),
        success=success,
        returns=returns,
        frames=swap(traj["frames"]) if record_frames else jnp.zeros((0,), jnp.float32),
        peaks=swap(traj["peak"]),
        recorded=jax.tree.map(swap, traj["recorded"]) if record_state is not None else None,
    )


def rollout_metrics(rollout: Rollout) -> dict[str, Float[Array, ""]]:
    """Scalar summaries: success rate, mean return, mean trajectory length in chunks."""
    return {
        "success_rate": jnp.mean(rollout.success.astype(jnp.float32)),
        "mean_return": jnp.mean(rollout.returns),
        "mean_chunks": jnp.mean(jnp.sum(rollout.valid, axis=1)),
    }
