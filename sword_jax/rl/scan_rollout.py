"""Policy episodes in a pure JAX environment (MJX) as one ``lax.scan``: GRPO's ground-truth rollouts and
its evaluations on the accelerator.

The environment is any object with two pure functions (``sim.mjx_batch.MjxEpisodes`` is the MJX one; the
library does not import ``sim``)::

    env.reset(starts)          -> (env_state, obs)            obs: frames [N,H,W,3] uint8, proprio [N,P]
    env.step(env_state, a[N,7]) -> (env_state, obs, success [N] bool)

:func:`scan_rollout` runs the policy from ``starts`` for ``max_steps`` actions: every
``rl.env.execute_steps`` actions it predicts a chunk from the current frame and proprio (greedy or
sampled at ``rl.grpo.temperature``) and executes its first ``execute_steps`` actions; with ``ensemble``
(``execute_steps = 1``) each action is the exponentially weighted mean of every chunk's prediction for
that step (ACT's temporal ensembling), exactly as :func:`sword_jax.rl.env_rollout.run_policy` does on the
C engine. An episode ends at success or at ``max_steps``; later decisions are recorded as invalid.
``greedy`` and ``ensemble`` are traced flags, so GRPO's sampled rollouts and the greedy, ensembled
evaluation run ONE compiled program (its compilation, with the physics inside, dominates start-up).

The result is the :class:`~sword_jax.rl.rollout.Rollout` that :func:`~sword_jax.rl.grpo.grpo_update` trains on
(frames kept at the policy's size as uint8), with :class:`EpisodeStats` (actions executed, physics broken).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Bool, Float, Int

from sword_jax.rl.config import RLConfig
from sword_jax.rl.policy import resize_frames, sampling_log_probs, tokens_to_actions
from sword_jax.rl.rollout import Rollout
from sword_jax.rl.value import Value, terminal_returns


class EpisodeStats(NamedTuple):
    """Per episode: ``steps`` the actions it executed; ``broken`` its physics state went non-finite (the
    episode then ended as a failure at that action); ``terminal_value`` with a ``value``, its success
    probability at the final frame (what a rollout that reached its horizon was paid, over the success return);
    ``states`` with ``record_states``, the environment's snapshot at each decision (what ``env.reset`` continues)."""

    steps: Int[Array, " n"]
    broken: Bool[Array, " n"]
    terminal_value: Float[Array, " n"] | None = None
    states: Float[Array, "n c f"] | None = None


class JaxEnv(Protocol):
    def reset(self, starts: Any) -> tuple[Any, dict[str, jax.Array]]: ...

    def step(self, state: Any, actions: jax.Array) -> tuple[Any, dict[str, jax.Array], jax.Array]: ...

    # optional: ``snapshot(state) -> [n, f]`` start states ``reset`` continues from that state (MJX: flat
    # ``[time, qpos, qvel]``), for rollouts branched from the decisions of recorded episodes (``record_states``)


def decisions(cfg: RLConfig, max_steps: int) -> int:
    """Policy decisions an episode of ``max_steps`` actions can need."""
    return math.ceil(max_steps / cfg.env.execute_steps)


def ensemble_weights(cfg: RLConfig) -> Float[Array, " L"]:
    """``exp(-decay * age)`` for the ages ``0 .. chunk_len - 1`` of the chunks that predict a step."""
    return jnp.exp(-jnp.float32(cfg.env.ensemble_decay) * jnp.arange(cfg.chunk_len, dtype=jnp.float32))


def ensembled_action(history: Float[Array, "n L L a"], made: Int[Array, ""], weights: Float[Array, " L"]
                     ) -> Float[Array, "n a"]:
    """The current step's action from the chunk ``history`` (``history[:, age]`` = the chunk predicted
    ``age`` decisions ago, so its entry ``age`` is its prediction for now); only the ``made`` chunks
    predicted so far count."""
    size = history.shape[1]
    ages = jnp.arange(size)
    w = jnp.where(ages < made, weights, 0.0)
    diagonal = history[:, ages, ages]  # (N, L, A): each chunk's prediction for the current step
    return jnp.einsum("l,nla->na", w / jnp.sum(w), diagonal)


def scan_rollout(
    graphdef: nnx.GraphDef,
    params: nnx.State,
    env: JaxEnv,
    starts: Any,
    instruction_tokens: Int[Array, "n l"],
    cfg: RLConfig,
    *,
    key: jax.Array,
    greedy: Bool[Array, ""] | bool,
    ensemble: Bool[Array, ""] | bool,
    max_steps: int,
    proprio_valid: Float[Array, " n"] | None = None,
    value: Value | None = None,
    record_states: bool = False,
) -> tuple[Rollout, EpisodeStats]:
    """Runs the policy in ``env`` (module docstring); pure, jit it.

    Args:
      graphdef / params: the split policy.
      env: the environment's pure functions (:class:`JaxEnv`).
      starts: what ``env.reset`` takes for the ``n`` episodes (MJX: initial ``qpos [n, nq]``).
      instruction_tokens: each episode's instruction (:func:`~sword_jax.rl.policy.tokenize_instructions`).
      cfg: chunk size, bins, image size, ``env.execute_steps``, ``env.ensemble_decay``, ``grpo.temperature``.
      key: sampling randomness (decision ``c`` uses ``fold_in(key, c)``).
      greedy: argmax tokens instead of samples (may be traced).
      ensemble: temporal ensembling of the executed action; needs ``execute_steps = 1`` (may be traced).
      max_steps: the episodes' action limit.
      proprio_valid: ``[n]``, 0 where the policy reads its "missing proprio" input (default all 1).
      value: a fitted success-probability value (:class:`~sword_jax.rl.value.Value`, ``rl.value``): an episode
        that reaches ``max_steps`` with no outcome is paid ``(1 + success_bonus) x`` its value at the final
        frame (:func:`~sword_jax.rl.value.terminal_returns`) instead of 0.
      record_states: keep ``env.snapshot(state)`` at each decision in the stats (``[n, C, f]``, zeros after the
        episode ended): start states of rollouts branched from these episodes.

    Returns:
      ``(rollout, stats)``: the rollout with ``C = decisions(cfg, max_steps)`` decisions of
      ``execute_steps`` tokens each, returns ``1 + success_bonus`` on success, and everything recorded
      after an episode ended zeroed (an ended episode also executes zero actions); and
      :class:`EpisodeStats`. An episode whose physics goes non-finite ends there as a failure.
    """
    k = cfg.env.execute_steps
    if isinstance(ensemble, bool) and ensemble and k != 1:
        raise ValueError(f"scan_rollout: ensembling needs rl.env.execute_steps=1, got {k}")
    if record_states and not hasattr(env, "snapshot"):
        raise ValueError(f"scan_rollout: record_states needs an environment with snapshot(state); "
                         f"{type(env).__name__} has none")
    n = instruction_tokens.shape[0]
    c_max = decisions(cfg, max_steps)
    policy = nnx.merge(graphdef, params)
    valid_in = jnp.ones((n,), jnp.float32) if proprio_valid is None else jnp.asarray(proprio_valid, jnp.float32)
    weights = ensemble_weights(cfg)
    greedy = jnp.asarray(greedy, jnp.bool_)
    ensemble = jnp.asarray(ensemble, jnp.bool_) & (k == 1)
    state, obs = env.reset(starts)
    size, a_dim = cfg.chunk_len, cfg.action_dim

    def decide(carry, c):
        state, obs, done, success, steps, broken, history = carry
        snap = env.snapshot(state).astype(jnp.float32) if record_states else None  # where this decision is made
        small = resize_frames(obs["frames"], cfg.image_size)
        proprio = obs["proprio"][:, : cfg.proprio_dim].astype(jnp.float32)
        logits = policy(small, instruction_tokens, proprio, valid_in)
        sampled = jax.random.categorical(jax.random.fold_in(key, c), logits / jnp.float32(cfg.grpo.temperature), axis=-1)
        chunk = jnp.where(greedy, jnp.argmax(logits, axis=-1), sampled).astype(jnp.int32)  # (N, L, A)
        log_probs = sampling_log_probs(logits, chunk, cfg.grpo.temperature)
        actions = tokens_to_actions(chunk, cfg.action_bins)
        history = jnp.concatenate([actions[:, None], history[:, :-1]], axis=1)
        smoothed = ensembled_action(history, jnp.minimum(c + 1, size), weights)[:, None]
        executed = jnp.where(ensemble, smoothed, actions[:, :k]) if k == 1 else actions[:, :k]
        valid = ~done
        executed = jnp.where(valid[:, None, None], executed, 0.0)  # an ended episode holds still

        def act(inner, j):
            state, obs, done, success, steps, broken = inner
            active = ~done
            state, obs, reached = env.step(state, executed[:, j])
            # a physics state gone non-finite ends its episode as a failure, counted in ``broken``
            bad = ~jnp.all(jnp.isfinite(obs["proprio"]), axis=-1) & active
            reached = reached & active & ~bad
            steps = steps + active.astype(jnp.int32)
            success = success | reached
            broken = broken | bad
            done = done | reached | bad | (steps >= max_steps)
            return (state, obs, done, success, steps, broken), None

        (state, obs, done, success, steps, broken), _ = jax.lax.scan(
            act, (state, obs, done, success, steps, broken), jnp.arange(k))
        keep = valid[:, None]
        # what an ended episode's decision saw is never trained on; zeros keep it finite for the masked update
        record = {"obs": jnp.where(keep[:, :, None, None], jnp.clip(jnp.round(small * 255.0), 0, 255), 0).astype(jnp.uint8),
                  "proprio": jnp.where(keep, proprio, 0.0), "tokens": jnp.where(keep[:, :, None], chunk[:, :k], 0),
                  "log_probs": jnp.where(keep[:, :, None], log_probs[:, :k], 0.0), "valid": valid.astype(jnp.float32)}
        if record_states:
            record["states"] = jnp.where(keep, snap, 0.0)
        return (state, obs, done, success, steps, broken, history), record

    init = (state, obs, jnp.zeros((n,), jnp.bool_), jnp.zeros((n,), jnp.bool_), jnp.zeros((n,), jnp.int32),
            jnp.zeros((n,), jnp.bool_), jnp.zeros((n, size, size, a_dim), jnp.float32))
    (_, final_obs, _, success, steps, broken, _), rec = jax.lax.scan(decide, init, jnp.arange(c_max))
    rec = jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), rec)  # (N, C, ...)
    valid = rec["valid"]
    last = jnp.maximum(jnp.sum(valid, axis=1).astype(jnp.int32) - 1, 0)
    unit = success.astype(jnp.float32)  # the return in units of the success return
    terminal = None
    if value is not None:
        # an episode ends at success, broken physics or max_steps: without the first two it reached its horizon
        terminal = value.fn(value.params, resize_frames(final_obs["frames"], cfg.image_size), instruction_tokens)
        unit = terminal_returns(success, ~success & ~broken, terminal, 1.0)
    returns = unit * jnp.float32(1.0 + cfg.grpo.success_bonus)
    rewards = jax.nn.one_hot(last, c_max, dtype=jnp.float32) * unit[:, None]
    rollout = Rollout(obs_frames=rec["obs"], proprio=rec["proprio"],
                      proprio_valid=jnp.broadcast_to(valid_in[:, None], valid.shape), instruction_tokens=instruction_tokens,
                      tokens=rec["tokens"], log_probs=rec["log_probs"], valid=valid, rewards=rewards,
                      scores=jnp.cumsum(rewards, axis=1), success=success, returns=returns,
                      frames=jnp.zeros((0,), jnp.float32))
    return rollout, EpisodeStats(steps=steps, broken=broken, terminal_value=terminal, states=rec.get("states"))


class RecordedEpisodes(NamedTuple):
    """Policy episodes recorded whole (:func:`record_episodes`): ``n`` episodes of ``T`` actions.

    Attributes:
      frames: ``[n, T + 1, H, W, 3]`` uint8 at the environment's resolution; frame ``t`` is seen before
        action ``t`` (the last one after the last action).
      proprio: ``[n, T + 1, P]`` at the same frames.
      actions: ``[n, T, A]`` the executed actions.
      success: ``[n, T]`` the task's success predicate on the state after action ``t``.
      broken: ``[n]`` the physics went non-finite (from then on the episode holds its last frame).
    """

    frames: jax.Array
    proprio: jax.Array
    actions: jax.Array
    success: jax.Array
    broken: jax.Array


def record_episodes(
    graphdef: nnx.GraphDef,
    params: nnx.State,
    env: JaxEnv,
    starts: Any,
    instruction_tokens: Int[Array, "n l"],
    cfg: RLConfig,
    *,
    key: jax.Array,
    steps: int,
) -> RecordedEpisodes:
    """The policy's own episodes as training data for the learned simulator and its success detector.

    The policy acts for exactly ``steps`` actions, sampled at ``rl.grpo.temperature`` (GRPO's behaviour
    distribution), re-planning every ``rl.env.execute_steps`` actions, and keeps acting after a success
    (a world model must see what follows it, a detector solved scenes that stay solved); every frame is
    kept at the environment's resolution. Decision ``c`` samples with ``fold_in(key, c)``. Pure; jit it.
    """
    k = cfg.env.execute_steps
    if steps < 1:
        raise ValueError(f"record_episodes: steps must be >= 1, got {steps}")
    policy = nnx.merge(graphdef, params)
    n = instruction_tokens.shape[0]
    state, obs = env.reset(starts)

    def decide(carry, c):
        state, obs, broken = carry
        small = resize_frames(obs["frames"], cfg.image_size)
        proprio = obs["proprio"][:, : cfg.proprio_dim].astype(jnp.float32)
        logits = policy(small, instruction_tokens, proprio, jnp.ones((n,), jnp.float32))
        chunk = jax.random.categorical(jax.random.fold_in(key, c), logits / jnp.float32(cfg.grpo.temperature), axis=-1)
        actions = tokens_to_actions(chunk.astype(jnp.int32), cfg.action_bins)[:, :k]

        def act(inner, j):
            state, obs, broken = inner
            new_state, new_obs, reached = env.step(state, actions[:, j])
            bad = broken | ~jnp.all(jnp.isfinite(new_obs["proprio"]), axis=-1)
            # a broken episode holds its last good observation (its later steps are not physics)
            keep = lambda new, old: jnp.where(bad.reshape((-1,) + (1,) * (new.ndim - 1)), old, new)  # noqa: E731
            new_obs = jax.tree.map(keep, new_obs, obs)
            record = {"frames": obs["frames"].astype(jnp.uint8), "proprio": obs["proprio"].astype(jnp.float32),
                      "actions": actions[:, j], "success": reached & ~bad}
            return (new_state, new_obs, bad), record

        (state, obs, broken), record = jax.lax.scan(act, (state, obs, broken), jnp.arange(k))
        return (state, obs, broken), record

    decisions_needed = math.ceil(steps / k)
    (_, last_obs, broken), rec = jax.lax.scan(decide, (state, obs, jnp.zeros((n,), jnp.bool_)),
                                              jnp.arange(decisions_needed))
    # (C, k, n, ...) -> (n, C k, ...); frame t of the whole scan is the one before action t, so the frame
    # after action ``steps - 1`` is frame ``steps`` (the final observation when the scan ends there)
    rec = jax.tree.map(lambda x: jnp.moveaxis(x.reshape((-1,) + x.shape[2:]), 0, 1), rec)
    frames = jnp.concatenate([rec["frames"], last_obs["frames"].astype(jnp.uint8)[:, None]], axis=1)[:, : steps + 1]
    proprio = jnp.concatenate([rec["proprio"], last_obs["proprio"].astype(jnp.float32)[:, None]], axis=1)[:, : steps + 1]
    return RecordedEpisodes(frames, proprio, rec["actions"][:, :steps], rec["success"][:, :steps], broken)
