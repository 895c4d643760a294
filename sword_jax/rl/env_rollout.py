"""Policy rollouts in a real (ground-truth) environment: evaluation and GRPO without a world model.

The environment is any object with the lockstep protocol of ``sim.lockstep.LockstepEnvs``
(the library does not import ``sim``)::

    envs.n, envs.language                      # episodes, their instructions
    envs.reset() -> {"frames" [N,H,W,3] uint8, "proprio" [N,P]}
    envs.step(actions [N,k,7]) -> {"frames", "proprio", "success" [N], "executed" [N], "done" [N]}

Every ``cfg.env.execute_steps`` actions the policy re-plans from the current frame: it predicts a
chunk of ``chunk_len`` actions and the first ``execute_steps`` are executed (``chunk_len`` =
open-loop chunks, as OpenVLA-OFT; 1 = closed loop every step). With ``cfg.env.action_ensemble``
each step of a greedy (evaluation) rollout executes the exponentially weighted mean of all chunk
predictions covering it (ACT's temporal ensembling); sampled (GRPO) rollouts execute each
decision's own sampled actions, whose log-probabilities the update needs.

:func:`run_policy` returns a :class:`~sword_jax.rl.rollout.Rollout` whose "chunks" are the
policy's decisions (``[N, C, execute_steps, A]`` tokens), so :func:`~sword_jax.rl.grpo.grpo_update`
trains on ground-truth rollouts exactly as on imagined ones. The reward is true success.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.rl.config import RLConfig
from sword_jax.rl.policy import greedy_chunk, resize_frames, sample_chunk, token_log_probs, tokenize_instructions
from sword_jax.rl.policy import tokens_to_actions
from sword_jax.rl.proprio_reckoning import ReckoningConfig, reckon
from sword_jax.rl.rollout import Rollout

PROPRIO_MODES = ("true", "reckoned", "missing")


def make_act_fns(graphdef: nnx.GraphDef, cfg: RLConfig):
    """Jitted policy calls on uint8 frames: ``act(params, frames, tokens, proprio, key, greedy, proprio_valid)``.

    ``proprio_valid [n]``: 1 = the policy reads ``proprio``, 0 = its learned "missing proprio"
    embedding (the input mode of a learned simulator that reports none); default all 1.
    :func:`run_policy` sets it from its ``proprio`` mode.

    Returns ``(frames at policy size uint8, tokens [n,T,A], log_probs [n,T,A], actions [n,T,A])``.
    """

    def act(params, frames, tokens, proprio, key, greedy: bool, proprio_valid=None):
        small = resize_frames(frames, cfg.image_size)
        valid = (jnp.ones((proprio.shape[0],), jnp.float32) if proprio_valid is None
                 else jnp.asarray(proprio_valid, jnp.float32))
        logits = nnx.merge(graphdef, params)(small, tokens, proprio, valid)
        if greedy:
            chunk = greedy_chunk(logits)
            logp = token_log_probs(logits, chunk)
        else:
            chunk, logp = sample_chunk(logits, key=key, temperature=cfg.grpo.temperature)
        obs = jnp.clip(jnp.round(small * 255.0), 0, 255).astype(jnp.uint8)
        return obs, chunk, logp, tokens_to_actions(chunk, cfg.action_bins)

    return jax.jit(act, static_argnames=("greedy",))


@functools.partial(jax.jit, static_argnames=("cfg",))
def _reckon_chunk(proprio: jax.Array, actions: jax.Array, cfg: ReckoningConfig) -> jax.Array:
    """Proprio after the executed ``actions [n, k, 7]`` (one compile per config and ``k``)."""
    return reckon(proprio, actions, cfg)[:, -1]


def max_decisions(cfg: RLConfig, max_steps: int) -> int:
    """Policy calls an episode of ``max_steps`` actions can need."""
    return math.ceil(max_steps / cfg.env.execute_steps)


def _ensemble(history: list[np.ndarray], decay: float) -> np.ndarray:
    """Mean of the chunk predictions for the current step (newest first), weights exp(-decay * age)."""
    preds, weights = [], []
    for age, chunk in enumerate(history):
        if age < chunk.shape[1]:
            preds.append(chunk[:, age])
            weights.append(math.exp(-decay * age))
    w = np.asarray(weights, np.float32)
    return np.tensordot(w / w.sum(), np.stack(preds), axes=1)


def run_policy(
    act: Any,
    params: nnx.State,
    envs: Any,
    cfg: RLConfig,
    *,
    key: jax.Array,
    greedy: bool,
    max_steps: int,
    record: bool = True,
    episodes: Any = None,
    proprio: str = "true",
    reckoning: ReckoningConfig | None = None,
    trace: Any = None,
) -> Rollout:
    """Runs the policy in ``envs`` until every episode succeeds or reaches ``max_steps``.

    Args:
      act: from :func:`make_act_fns`.
      params: policy parameters.
      envs: a lockstep environment (module docstring); it is reset here.
      cfg: chunking, re-planning and ensembling settings.
      key: sampling randomness (decision ``c`` uses ``fold_in(key, c)``).
      greedy: argmax actions (evaluation) instead of sampling.
      max_steps: the episodes' step limit (the decision count is padded to it).
      record: keep observations, tokens and log-probs for GRPO (else only outcomes).
      episodes: new ``(task, qpos)`` start states for ``envs.reset`` (default: its own).
      proprio: what the policy reads as proprio (``rl.env.proprio``): ``true``, the environment's;
        ``reckoned``, integrated from the episode's first proprio and the actions executed since
        (``reckoning``, the action convention), which is what the learned simulator gives the policy;
        ``missing``, the policy's "missing proprio" input. The rollout records what was read, so GRPO
        trains that input mode; the environment itself is the same in all three.
      reckoning: the action convention for ``proprio="reckoned"``.
      trace: a :class:`sword_jax.rl.sim_agreement.EpisodeTrace` to record every executed action and
        the head's frames in (its first ``head_steps`` actions are then executed one environment
        step at a time; the episodes are the same).

    Returns:
      A :class:`Rollout` with ``C = max_decisions(cfg, max_steps)``; ``success``/``returns`` are the
      true outcomes (return = ``1 + success_bonus`` on success, else 0).
    """
    if proprio not in PROPRIO_MODES:
        raise ValueError(f"run_policy: proprio must be one of {'|'.join(PROPRIO_MODES)}, got {proprio!r}")
    if proprio == "reckoned" and (reckoning is None or cfg.proprio_dim != 8):
        raise ValueError(f"run_policy: proprio='reckoned' needs a ReckoningConfig and the 8-D proprio "
                         f"(got reckoning={reckoning!r}, rl.proprio_dim={cfg.proprio_dim})")
    n, k = envs.n, cfg.env.execute_steps
    ensemble = cfg.env.action_ensemble and greedy  # sampled rollouts (GRPO) act on each decision's own chunk
    obs = envs.reset() if episodes is None else envs.reset(episodes)
    if trace is not None:
        trace.start(obs, envs.language)
    read = np.asarray(obs["proprio"][:, : cfg.proprio_dim], np.float32)  # what the policy reads as proprio
    valid_in = jnp.full((n,), 0.0 if proprio == "missing" else 1.0, jnp.float32)
    tokens_text = jnp.asarray(tokenize_instructions(envs.language, cfg.policy.max_instruction_bytes))
    c_max = max_decisions(cfg, max_steps)
    done = np.zeros(n, bool)
    success = np.zeros(n, bool)
    rec: dict[str, list[np.ndarray]] = {"obs": [], "proprio": [], "tokens": [], "log_probs": [], "valid": []}
    history: list[np.ndarray] = []
    for c in range(c_max):
        if done.all():
            break
        small, chunk, logp, actions = act(params, jnp.asarray(obs["frames"]), tokens_text, jnp.asarray(read),
                                          jax.random.fold_in(key, c), greedy, proprio_valid=valid_in)
        actions = np.asarray(actions)
        if ensemble:
            history = [actions] + history[: cfg.chunk_len - 1]
            step_actions = _ensemble(history, cfg.env.ensemble_decay)[:, None]
        else:
            step_actions = actions[:, :k]
        if record:
            rec["obs"].append(np.asarray(small))
            rec["proprio"].append(read)
            rec["tokens"].append(np.asarray(chunk)[:, :k])
            rec["log_probs"].append(np.asarray(logp)[:, :k])
            rec["valid"].append((~done).astype(np.float32))
        obs = _step(envs, step_actions, trace)
        success |= obs["success"]
        done = obs["done"]
        if proprio == "reckoned":  # an episode that ended mid-chunk is done: its proprio is never read again
            read = np.asarray(_reckon_chunk(jnp.asarray(read), jnp.asarray(step_actions, jnp.float32), reckoning))
        else:
            read = np.asarray(obs["proprio"][:, : cfg.proprio_dim], np.float32)
    returns = success.astype(np.float32) * (1.0 + cfg.grpo.success_bonus)
    if not record:
        empty = np.zeros((n, 0), np.float32)
        return Rollout(empty, empty, empty, np.asarray(tokens_text), empty, empty, empty, empty, empty,
                       success, returns, np.zeros((0,), np.float32))
    taken = len(rec["valid"])

    def stack(name: str) -> np.ndarray:
        x = np.stack(rec[name], axis=1)  # (N, taken, ...)
        pad = np.zeros((n, c_max - taken) + x.shape[2:], x.dtype)
        return np.concatenate([x, pad], axis=1)

    valid = stack("valid")
    # an episode stops being valid once done, so a success belongs to its last valid decision
    last_decision = valid.sum(1).astype(np.int64) - 1
    rewards = np.zeros((n, c_max), np.float32)
    rewards[np.flatnonzero(success), last_decision[success]] = 1.0
    return Rollout(
        obs_frames=stack("obs"), proprio=stack("proprio"),
        proprio_valid=np.full((n, c_max), 0.0 if proprio == "missing" else 1.0, np.float32),
        instruction_tokens=np.asarray(tokens_text), tokens=stack("tokens"), log_probs=stack("log_probs"),
        valid=valid, rewards=rewards, scores=np.cumsum(rewards, 1), success=success, returns=returns,
        frames=np.zeros((0,), np.float32))


def _step(envs: Any, actions: np.ndarray, trace: Any) -> dict[str, np.ndarray]:
    """``envs.step(actions)``, recorded in ``trace``; inside its head one action at a time (the
    outcomes are merged, so the caller sees one step)."""
    if trace is None:
        return envs.step(actions)
    success = np.zeros(envs.n, bool)
    executed = np.zeros(envs.n, np.int64)
    j = 0
    while j < actions.shape[1]:
        block = actions[:, j: j + 1] if trace.in_head else actions[:, j:]  # the rest of the block in one step
        obs = envs.step(block)
        trace.record(block, obs)
        success |= np.asarray(obs["success"], bool)
        executed += np.asarray(obs["executed"], np.int64)
        j += block.shape[1]
        if np.all(obs["done"]):
            break
    return dict(obs, success=success, executed=executed)


def wilson_interval(successes: int, trials: int, z: float = 1.96) -> tuple[float, float]:
    """95% Wilson score interval of a success rate."""
    if trials <= 0:
        return (0.0, 1.0)
    p = successes / trials
    denom = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denom
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


def difference_interval(a: int, n: int, b: int, m: int) -> tuple[float, float]:
    """95% Newcombe (Wilson-based) interval of the difference of two independent success rates ``b/m - a/n``
    (a gain between two evaluations of one run that kept their outcomes is paired instead: :func:`gain_interval`)."""
    p1, p2 = a / n, b / m
    l1, u1 = wilson_interval(a, n)
    l2, u2 = wilson_interval(b, m)
    d = p2 - p1
    return (d - math.sqrt((p2 - l2) ** 2 + (u1 - p1) ** 2), d + math.sqrt((u2 - p2) ** 2 + (p1 - l1) ** 2))


def paired_difference_interval(before: Any, after: Any, z: float = 1.96) -> tuple[float, float]:
    """95% interval of ``mean(after) - mean(before)`` for two outcomes of each of the same episodes (``before[i]`` and
    ``after[i]``: episode ``i`` from the same start, e.g. one policy evaluated before and after training): Newcombe's
    paired square-and-add interval (Stat. Med. 17:2635, 1998, method 10). Each rate's Wilson interval is combined
    with the correlation ``phi`` of the outcome pairs, so episodes that succeed or fail under both policies narrow
    it; with ``phi = 0`` it is :func:`difference_interval`."""
    x, y = np.asarray(before, bool).ravel(), np.asarray(after, bool).ravel()
    if x.shape != y.shape or x.size == 0:
        raise ValueError(f"paired_difference_interval: needs two outcomes of each of the same episodes, got "
                         f"{x.size} and {y.size}")
    n = x.size
    both, only_after = int(np.sum(x & y)), int(np.sum(~x & y))
    only_before, neither = int(np.sum(x & ~y)), int(np.sum(~x & ~y))
    p1, p2 = (both + only_after) / n, (both + only_before) / n  # after, before
    l1, u1 = wilson_interval(both + only_after, n, z)
    l2, u2 = wilson_interval(both + only_before, n, z)
    margins = (both + only_after) * (only_before + neither) * (both + only_before) * (only_after + neither)
    phi = (both * neither - only_after * only_before) / math.sqrt(margins) if margins else 0.0
    d = p1 - p2
    low = (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2
    high = (u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2
    return (d - math.sqrt(max(low, 0.0)), d + math.sqrt(max(high, 0.0)))


def mean_interval(values: Any, intervals: Any, z: float = 1.959964) -> tuple[float, tuple[float, float]]:
    """The mean of independent estimates (``values``, e.g. one gain difference per seed) and its 95% interval by the
    normal approximation: the variances read from the 95% ``intervals`` (``(low, high)`` pairs; as many as the
    estimates' independent parts, e.g. both gains of each difference) are summed, so the mean's half-width is
    ``z * sqrt(sum of variances) / len(values)``."""
    values = [float(v) for v in values]
    if not values:
        raise ValueError("mean_interval: needs at least one value")
    variance = sum(((high - low) / (2 * z)) ** 2 for low, high in intervals)
    mean = sum(values) / len(values)
    half = z * math.sqrt(variance) / len(values)
    return mean, (mean - half, mean + half)


def outcomes_text(success: Any) -> str:
    """Episode outcomes as a string of ``0`` and ``1`` in the episodes' order: how an evaluation point keeps them
    (``outcomes``), so gains between two points of one run pair them episode by episode."""
    return "".join("1" if s else "0" for s in np.asarray(success, bool).ravel())


def point_outcomes(point: dict) -> np.ndarray | None:
    """An evaluation point's per-episode outcomes (:func:`outcomes_text`), None where it did not keep them."""
    text = point.get("outcomes")
    if text is None:
        return None
    if set(text) - {"0", "1"} or len(text) != point.get("episodes", len(text)):
        raise ValueError(f"an evaluation point's outcomes must be {point.get('episodes')} characters 0 or 1, got "
                         f"{text[:40]!r}{'...' if len(text) > 40 else ''} ({len(text)} characters)")
    return np.frombuffer(text.encode(), np.uint8) == ord("1")


def outcome_changes(first: dict, last: dict) -> dict | None:
    """How the episodes' outcomes moved between two evaluation points of one run that both kept them:
    ``{"gained": failed then succeeded, "lost": succeeded then failed, "episodes"}``; None where they cannot be
    paired (as :func:`gain_interval` decides)."""
    a, b = point_outcomes(first), point_outcomes(last)
    if a is None or b is None or a.size != b.size:
        return None
    return {"gained": int(np.sum(~a & b)), "lost": int(np.sum(a & ~b)), "episodes": int(a.size)}


def gain_interval(first: dict, last: dict) -> tuple[float, float]:
    """95% interval of the gain ``last - first`` between two evaluation points of one run (dicts with
    ``successes`` and ``episodes``): paired episode by episode (:func:`paired_difference_interval`) where both kept
    their outcomes of the same number of episodes (a run evaluates the same starts at every point), else Newcombe's
    interval for two independent rates (:func:`difference_interval`)."""
    a, b = point_outcomes(first), point_outcomes(last)
    if a is not None and b is not None and a.size == b.size:
        return paired_difference_interval(a, b)
    return difference_interval(first["successes"], first["episodes"], last["successes"], last["episodes"])
