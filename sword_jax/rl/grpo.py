"""GRPO: group-normalised advantages, the clipped surrogate, and the pure jitted update step.

For a group of G trajectories from one start state with returns ``R_1..R_G``::

    A_i = (R_i - mean(R)) / (std(R) + eps)        (population std; 0 for a group with no signal)

or, with ``rl.grpo.scale_by_std=false``, ``A_i = R_i - mean(R)`` (Dr. GRPO): a group's advantages keep the size of
its returns' spread, so a group whose returns differ by a continuous estimate's noise (``rl.value``) weighs that
little beside one whose trajectories differ in success.

Every valid action token of trajectory i shares ``A_i`` (outcome supervision). The per-token
surrogate with DAPO's asymmetric ("clip-higher") range is::

    r = exp(logp_new - logp_old)
    l = -min(r A, clip(r, 1 - clip_low, 1 + clip_high) A) + kl_coef * k3(logp_ref, logp_new)
    k3 = exp(logp_ref - logp_new) - (logp_ref - logp_new) - 1

``loss_norm='trajectory'`` averages ``l`` over each trajectory's valid tokens (normalisation by
trajectory length) and then over the kept trajectories; ``'token'`` averages over all kept
valid tokens. Groups whose returns are all equal carry no signal and are filtered out.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx, struct
from jaxtyping import Array, Float, Int

from sword_jax import optim, tracing
from sword_jax import sharding as shd
from sword_jax.rl import imagined_check
from sword_jax.rl.config import RLConfig
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.policy import sampling_log_probs
from sword_jax.rl.rollout import Rollout, expand_groups, imagined_rollout, rollout_metrics, take_trajectories
from sword_jax.rl.sim_agreement import confirm_successes

SIGNAL_EPS = 1e-6
UPDATE_KEY_SALT = 0x5EED  # the update's shuffle key is fold_in(the step's key, UPDATE_KEY_SALT)
CONFIRM_KEY_SALT = 0xC0F1  # rl.imagined.confirm_success's second draw: fold_in(the step's key, CONFIRM_KEY_SALT)
SELECT_KEY_SALT = 0x5E1E  # rl.imagined.oversample's choice among mixed groups: fold_in(the step's key, SELECT_KEY_SALT)


def group_has_signal(returns: Float[Array, "b g"]) -> jax.Array:
    """``[b] bool``: the groups whose returns are not all equal (mixed outcomes: the only ones with a signal)."""
    return jnp.std(returns.astype(jnp.float32), axis=1) > jnp.float32(SIGNAL_EPS)


def select_groups(returns: Float[Array, "n g"], keep: int, *, key: jax.Array) -> Int[Array, " keep"]:
    """``keep`` of the ``n`` sampled groups, those with mixed outcomes first (``rl.imagined.oversample``).

    The groups are shuffled by ``key`` and then stably sorted mixed-before-unmixed, so which mixed groups are
    kept when more than ``keep`` are mixed is a uniform random choice (not biased toward low start indices),
    and when fewer are mixed every mixed group is kept and the rest are random groups without signal (which
    the update's keep mask then masks). Static shapes: jit-friendly.

    Args:
      returns: trajectory returns grouped by start state.
      keep: groups to return (``<= n``).
      key: the random order among equals.

    Returns:
      ``[keep]`` group indices into ``returns``' first axis, the mixed ones first.
    """
    n = returns.shape[0]
    if not 1 <= keep <= n:
        raise ValueError(f"select_groups: keep must be in [1, {n}] (the sampled groups), got {keep}")
    shuffled = jax.random.permutation(key, n)
    unmixed = jnp.logical_not(group_has_signal(returns))[shuffled]
    # stable: the shuffled order survives within the mixed and within the unmixed groups
    ranked = shuffled[jnp.argsort(unmixed, stable=True)]
    return ranked[:keep]


def group_trajectories(groups: Int[Array, " k"], group_size: int) -> Int[Array, " k_g"]:
    """Trajectory indices of ``groups`` in a group-major batch (:func:`~sword_jax.rl.rollout.expand_groups`):
    group ``b``'s trajectories are rows ``b * G .. b * G + G - 1``."""
    return (groups[:, None] * group_size + jnp.arange(group_size)[None, :]).reshape(-1)  # (K * G,)


def group_advantages(
    returns: Float[Array, "b g"], *, eps: float = 1e-6, filter_groups: bool = True, scale_by_std: bool = True
) -> tuple[Float[Array, "b g"], Float[Array, " b"]]:
    """Group-normalised advantages and a per-group "has signal" mask.

    Args:
      returns: trajectory returns grouped by start state.
      eps: added to the group std.
      filter_groups: zero the advantages (and the mask) of groups whose returns are all equal.
      scale_by_std: divide by the group's std (GRPO); False leaves the centred returns (Dr. GRPO).

    Returns:
      ``(advantages [b, g], keep [b])`` in float32.
    """
    returns = returns.astype(jnp.float32)
    mean = jnp.mean(returns, axis=1, keepdims=True)
    std = jnp.std(returns, axis=1, keepdims=True)
    has_signal = group_has_signal(returns)
    # a group with no signal has zero advantages (never 0/0), kept or not
    safe_std = jnp.where(has_signal[:, None], std, jnp.float32(1.0))
    scale = (safe_std + jnp.float32(eps)) if scale_by_std else jnp.float32(1.0)
    adv = jnp.where(has_signal[:, None], (returns - mean) / scale, jnp.float32(0.0))
    keep = has_signal.astype(jnp.float32) if filter_groups else jnp.ones(has_signal.shape, jnp.float32)
    return adv, keep


def clipped_token_loss(
    new_log_probs: Float[Array, "..."],
    old_log_probs: Float[Array, "..."],
    advantages: Float[Array, "..."],
    *,
    clip_low: float,
    clip_high: float,
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Per-token PPO clipped surrogate loss and a 0/1 "clipped" indicator (no gradient there)."""
    ratio = jnp.exp(new_log_probs - old_log_probs)
    clipped_ratio = jnp.clip(ratio, 1.0 - clip_low, 1.0 + clip_high)
    unclipped = ratio * advantages
    clipped = clipped_ratio * advantages
    loss = -jnp.minimum(unclipped, clipped)
    is_clipped = (clipped < unclipped).astype(jnp.float32)
    return loss, is_clipped


def loss_weights(valid: Float[Array, "n c"], keep: Float[Array, " n"], tokens_per_chunk: int,
                 cfg: RLConfig) -> Float[Array, "n c"]:
    """The weight of each valid token of chunk ``(i, c)`` in the GRPO objective (module docstring).

    They depend only on which chunks are valid and kept, not on the parameters, so the objective
    ``sum(loss * weight)`` is a plain sum over trajectories and its gradient can be accumulated
    over micro-batches of trajectories (``rl.grpo.update_microbatch``) exactly.
    """
    mask = valid.astype(jnp.float32) * keep[:, None]
    tokens_per_traj = jnp.sum(mask, axis=1) * jnp.float32(tokens_per_chunk)
    if cfg.grpo.loss_norm == "trajectory":
        kept = jnp.sum((tokens_per_traj > 0).astype(jnp.float32))
        return mask / jnp.maximum(tokens_per_traj, 1.0)[:, None] / jnp.maximum(kept, 1.0)
    return mask / jnp.maximum(jnp.sum(tokens_per_traj), 1.0)


def _token_terms(new_log_probs, old_log_probs, ref_log_probs, advantages, valid, keep, weights, cfg):
    """``(objective, sums)``: the weighted surrogate (+ KL) of a batch of trajectories and the
    masked sums of the per-token diagnostics (clipped, KL, ratio)."""
    shape = new_log_probs.shape
    adv = jnp.broadcast_to(advantages[:, None, None, None], shape)
    loss, is_clipped = clipped_token_loss(new_log_probs, old_log_probs, adv, clip_low=cfg.grpo.clip_low, clip_high=cfg.grpo.clip_high)
    kl = jnp.zeros_like(loss)
    if cfg.grpo.kl_coef > 0.0:
        if ref_log_probs is None:
            raise ValueError("rl.grpo.kl_coef > 0 needs reference log-probs")
        delta = ref_log_probs - new_log_probs
        kl = jnp.exp(delta) - delta - 1.0
        loss = loss + jnp.float32(cfg.grpo.kl_coef) * kl
    mask = jnp.broadcast_to((valid * keep[:, None])[:, :, None, None], shape)
    # masked tokens weigh 0; ``where`` keeps a non-finite value there (a token never trained on) out of the sum
    weight = jnp.broadcast_to(weights[:, :, None, None], shape)
    objective = jnp.sum(jnp.where(weight > 0, loss * weight, 0.0))
    sums = {"clipped": jnp.sum(is_clipped * mask), "kl": jnp.sum(kl * mask),
            "ratio": jnp.sum(jnp.exp(new_log_probs - old_log_probs) * mask)}
    return objective, sums


def _metrics_from_sums(sums, tokens, keep):
    denom = jnp.maximum(tokens, 1.0)
    return {"clip_fraction": sums["clipped"] / denom, "kl": sums["kl"] / denom, "ratio_mean": sums["ratio"] / denom,
            "kept_fraction": jnp.mean(keep)}


def grpo_loss(
    new_log_probs: Float[Array, "n c t a"],
    old_log_probs: Float[Array, "n c t a"],
    ref_log_probs: Float[Array, "n c t a"] | None,
    advantages: Float[Array, " n"],
    valid: Float[Array, "n c"],
    keep: Float[Array, " n"],
    cfg: RLConfig,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """The GRPO objective over a batch of trajectories (see module docstring).

    Args:
      new_log_probs / old_log_probs / ref_log_probs: per-token log-probs under the current,
        behaviour and reference policies (``ref_log_probs`` may be None when ``kl_coef == 0``).
      advantages: per-trajectory advantage.
      valid: chunk validity (0 after done).
      keep: 1 for trajectories of groups with signal.
      cfg: clip range, KL weight and normalisation.

    Returns:
      ``(loss, metrics)``.
    """
    t, a = new_log_probs.shape[2:]
    weights = loss_weights(valid, keep, t * a, cfg)
    total, sums = _token_terms(new_log_probs, old_log_probs, ref_log_probs, advantages, valid, keep, weights, cfg)
    return total, _metrics_from_sums(sums, jnp.sum(valid * keep[:, None]) * t * a, keep)


@struct.dataclass
class GRPOState:
    """Everything a GRPO step reads and writes."""

    params: Any
    opt_state: Any
    ref_params: Any
    step: jax.Array


def grpo_optimizer(cfg: RLConfig) -> optax.GradientTransformation:
    """Global-norm clipping at 1, then AdamW at ``cfg.grpo.learning_rate`` without weight decay."""
    return optim.make_optimizer(cfg.grpo.learning_rate, weight_decay=0.0, grad_clip=1.0)


def init_state(params: nnx.State, cfg: RLConfig) -> GRPOState:
    """Train state with the reference policy frozen at ``params`` (the SFT policy)."""
    ref = jax.tree.map(jnp.copy, params) if cfg.grpo.kl_coef > 0.0 else None
    return GRPOState(params=params, opt_state=grpo_optimizer(cfg).init(params), ref_params=ref, step=jnp.zeros((), jnp.int32))


def _rollout_log_probs(graphdef, params, batch: Rollout, temperature: float = 1.0) -> Float[Array, "n c t a"]:
    """Log-probs of the rollout's tokens under the policy at the sampling ``temperature``
    (:func:`~sword_jax.rl.policy.sampling_log_probs`); a rollout that executed only the first ``k``
    actions of each chunk (re-planning, ``tokens [N, C, k, A]``) is scored on those ``k``."""
    policy = nnx.merge(graphdef, params)
    n, c = batch.valid.shape
    flat = lambda x: x.reshape((n * c,) + x.shape[2:])  # noqa: E731 - (N, C, ...) -> (N * C, ...)
    tokens = jnp.repeat(batch.instruction_tokens, c, axis=0)
    frames = flat(batch.obs_frames)
    if frames.dtype == jnp.uint8:  # ground-truth rollouts keep policy-size frames as uint8
        frames = frames.astype(jnp.float32) / jnp.float32(255.0)
    logits = policy(frames, tokens, flat(batch.proprio), flat(batch.proprio_valid))
    executed = batch.tokens.shape[2]
    return sampling_log_probs(logits[:, :executed], flat(batch.tokens), temperature).reshape(batch.tokens.shape)


def _split_micro(x: jax.Array, parts: int) -> jax.Array:
    return x.reshape((parts, x.shape[0] // parts) + x.shape[1:])


def _gradient_fn(graphdef: nnx.GraphDef, cfg: RLConfig, batch: Rollout, ref_params: Any = None, *,
                 advantages: jax.Array | None = None, keep: jax.Array | None = None):
    """``fn(params) -> (loss, metrics, grads)`` of the GRPO objective on ``batch``, micro-batched by
    ``cfg.grpo.update_microbatch`` (the reference log-probs, when ``kl_coef > 0``, computed once here).

    ``advantages`` / ``keep`` (per trajectory): given when ``batch`` is a minibatch of a larger batch whose
    groups they were normalised over; by default they are computed from ``batch.returns`` by group."""
    g = cfg.grpo.group_size
    n = batch.valid.shape[0]
    micro = min(cfg.grpo.update_microbatch or n, n)
    if n % micro:
        raise ValueError(f"rl.grpo.update_microbatch={cfg.grpo.update_microbatch} must divide the {n} trajectories of a "
                         f"GRPO (mini)batch")
    parts = n // micro
    if advantages is None:
        adv, keep_group = group_advantages(batch.returns.reshape(-1, g), filter_groups=cfg.grpo.filter_groups,
                                           scale_by_std=cfg.grpo.scale_by_std)
        advantages, keep = adv.reshape(-1), jnp.repeat(keep_group, g)
    t, a = batch.tokens.shape[2:]
    valid = batch.valid.astype(jnp.float32)
    weights = loss_weights(valid, keep, t * a, cfg)
    tokens = jnp.sum(valid * keep[:, None]) * t * a
    split = lambda x: _split_micro(x, parts)  # noqa: E731
    data = {"obs_frames": split(batch.obs_frames), "proprio": split(batch.proprio),
            "proprio_valid": split(batch.proprio_valid), "instruction_tokens": split(batch.instruction_tokens),
            "tokens": split(batch.tokens), "old_lp": split(jax.lax.stop_gradient(batch.log_probs)),
            "valid": split(valid), "keep": split(keep), "adv": split(advantages), "weights": split(weights)}

    def as_rollout(part):
        return batch._replace(obs_frames=part["obs_frames"], proprio=part["proprio"],
                              proprio_valid=part["proprio_valid"], instruction_tokens=part["instruction_tokens"],
                              tokens=part["tokens"], valid=part["valid"])

    if cfg.grpo.kl_coef > 0.0:  # the frozen reference, once for all epochs
        if ref_params is None:
            raise ValueError("rl.grpo.kl_coef > 0 needs the reference policy's parameters")
        data["ref_lp"] = jax.lax.stop_gradient(jax.lax.map(
            lambda part: _rollout_log_probs(graphdef, ref_params, as_rollout(part), cfg.grpo.temperature), data))

    def micro_objective(params, part):
        new_lp = _rollout_log_probs(graphdef, params, as_rollout(part), cfg.grpo.temperature)
        return _token_terms(new_lp, part["old_lp"], part.get("ref_lp"), part["adv"], part["valid"], part["keep"],
                            part["weights"], cfg)

    def loss_and_grads(params):
        zero_sums = {"clipped": jnp.float32(0.0), "kl": jnp.float32(0.0), "ratio": jnp.float32(0.0)}
        zero = (jnp.float32(0.0), zero_sums, jax.tree.map(jnp.zeros_like, params))

        def body(acc, part):
            (objective, sums), grads = jax.value_and_grad(micro_objective, has_aux=True)(params, part)
            return jax.tree.map(jnp.add, acc, (objective, sums, grads)), None

        (loss, sums, grads), _ = jax.lax.scan(body, zero, data)
        return loss, _metrics_from_sums(sums, tokens, keep), grads

    return loss_and_grads


def grpo_gradients(graphdef: nnx.GraphDef, cfg: RLConfig, params: Any, batch: Rollout, *,
                   ref_params: Any = None) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]], Any]:
    """``(loss, metrics, grads)`` of the GRPO objective at ``params`` (what one update step applies)."""
    return _gradient_fn(graphdef, cfg, batch, ref_params)(params)


def behaviour_nll(batch: Rollout) -> Float[Array, ""]:
    """Mean negative log-probability of the sampled tokens under the policy that sampled them, over
    every valid chunk of the batch (kept groups or not): a Monte Carlo estimate of the behaviour
    policy's per-token entropy at its sampling temperature. A policy that memorised its
    demonstrations samples near-deterministic tokens (low), one that is unsure samples wide ones."""
    mask = jnp.broadcast_to(batch.valid.astype(jnp.float32)[:, :, None, None], batch.log_probs.shape)
    return -jnp.sum(batch.log_probs * mask) / jnp.maximum(jnp.sum(mask), 1.0)


SHUFFLE_KEY_SALT = 0x5F1E  # the permutations of rl.grpo.shuffle_returns, apart from the minibatch order's keys


def shuffle_within_groups(returns: Float[Array, "b g"], key: jax.Array | None) -> Float[Array, "b g"]:
    """Each group's returns permuted among its trajectories (``rl.grpo.shuffle_returns``): the same values per group,
    assigned to trajectories independently of what they did."""
    if key is None:
        raise ValueError("rl.grpo.shuffle_returns needs the update's key (grpo_update(..., key=...))")
    keys = jax.random.split(jax.random.fold_in(key, SHUFFLE_KEY_SALT), returns.shape[0])
    return jax.vmap(lambda k, r: jax.random.permutation(k, r))(keys, returns)


def grpo_update(
    graphdef: nnx.GraphDef, cfg: RLConfig, state: GRPOState, batch: Rollout, key: jax.Array | None = None
) -> tuple[GRPOState, dict[str, Float[Array, ""]]]:
    """``cfg.grpo.ppo_epochs`` passes over one batch of rollouts, each ``cfg.grpo.minibatches`` gradient steps.

    Advantages are normalised over the whole batch's groups first; each pass then splits the trajectories
    into ``minibatches`` equal parts (shuffled per pass when ``key`` is given) and takes one optimizer step
    on each, its objective normalised within the minibatch. From the second step on, the policy that
    scores a minibatch is no longer the one that sampled it, so the ratio leaves 1 and the clip can bind
    (PPO / GRPO as SimpleVLA-RL and RLinf run it). The metrics are means over every step
    (``loss``/``grad_norm``/``clip_fraction`` ...), ``updates`` the number of steps.

    With ``cfg.grpo.update_microbatch = m`` the policy's forward and backward run on ``m`` trajectories
    at a time (a ``lax.scan``) and the gradients are summed: the objective's token weights are
    fixed by the (mini)batch (:func:`loss_weights`), so this is the same gradient up to float
    summation order, with the activations of ``m`` trajectories alive instead of all of them.

    ``mixed_groups`` counts the batch's groups with a signal. With fewer than ``cfg.grpo.min_mixed_groups``
    the step applies no update (``skipped_update`` 1): the parameters and optimizer state come back as they
    were, ``state.step`` still advances, and the other metrics are those of the update it did not apply
    (``update_norm`` 0). With ``min_mixed_groups = 0`` every batch updates, as before the option existed.
    """
    optimizer = grpo_optimizer(cfg)
    n, g, parts = batch.valid.shape[0], cfg.grpo.group_size, cfg.grpo.minibatches
    if n % parts:
        raise ValueError(f"rl.grpo.minibatches={parts} must divide the {n} trajectories of a GRPO batch")
    grouped_returns = batch.returns.reshape(-1, g)  # (B, G): trajectories are group-major
    if cfg.grpo.shuffle_returns:  # static: the control run (config docstring)
        grouped_returns = shuffle_within_groups(grouped_returns, key)
    mixed_groups = jnp.sum(group_has_signal(grouped_returns).astype(jnp.float32))
    adv, keep_group = group_advantages(grouped_returns, filter_groups=cfg.grpo.filter_groups,
                                       scale_by_std=cfg.grpo.scale_by_std)
    advantages, keep = adv.reshape(-1), jnp.repeat(keep_group, g)
    size = n // parts

    def order(epoch):
        if key is None or parts == 1:
            return jnp.arange(n)
        return jax.random.permutation(jax.random.fold_in(key, epoch), n)

    def one_update(carry, index):
        params, opt_state = carry
        if parts == 1:  # the whole batch every step: no gather
            sub, sub_adv, sub_keep = batch, advantages, keep
        else:
            epoch, part = index // parts, index % parts
            idx = jax.lax.dynamic_slice_in_dim(order(epoch), part * size, size)
            sub = take_trajectories(batch, idx)
            sub_adv, sub_keep = advantages[idx], keep[idx]
        loss, metrics, grads = _gradient_fn(graphdef, cfg, sub, state.ref_params, advantages=sub_adv,
                                            keep=sub_keep)(params)
        grad_norm = optax.global_norm(grads)
        # a non-finite loss or gradient skips the update: NaN never reaches the parameters or a checkpoint
        updates, opt_state, params, finite = optim.apply_finite_update(optimizer, loss, grads, opt_state, params)
        metrics = dict(metrics, loss=loss, grad_norm=grad_norm, update_norm=optax.global_norm(updates),
                       finite=finite.astype(jnp.float32))
        return (params, opt_state), metrics

    steps = cfg.grpo.ppo_epochs * parts
    (params, opt_state), metrics = jax.lax.scan(one_update, (state.params, state.opt_state), jnp.arange(steps))
    finite = jnp.min(metrics["finite"])
    metrics = jax.tree.map(lambda x: jnp.mean(x), metrics)
    skipped = jnp.zeros((), bool)
    if cfg.grpo.min_mixed_groups > 0:  # static: with the option off the program is the one before it existed
        # too few groups with a signal: Adam would still take a full-size step, in a direction set by noise
        skipped = mixed_groups < jnp.float32(cfg.grpo.min_mixed_groups)
        keep_old = lambda new, old: jax.tree.map(lambda a, b: jnp.where(skipped, b, a), new, old)  # noqa: E731
        params, opt_state = keep_old(params, state.params), keep_old(opt_state, state.opt_state)
        metrics["update_norm"] = jnp.where(skipped, jnp.float32(0.0), metrics["update_norm"])
    metrics["finite"] = finite
    metrics["mixed_groups"] = mixed_groups
    metrics["skipped_update"] = skipped.astype(jnp.float32)
    metrics["kept_fraction"] = jnp.mean(keep)
    metrics["updates"] = jnp.float32(steps)
    metrics["param_norm"] = optax.global_norm(params)
    metrics["behaviour_nll"] = behaviour_nll(batch)
    return state.replace(params=params, opt_state=opt_state, step=state.step + 1), metrics


def make_grpo_step(
    graphdef: nnx.GraphDef, cfg: RLConfig, *, donate: bool = True, max_traces: int = 1, mesh=None,
    rules=shd.DEFAULT_RULES, env: Any = None,
) -> Callable[[GRPOState, tuple[LearnedSimulator, RewardModel, StartState], jax.Array], tuple[GRPOState, dict]]:
    """The compiled GRPO step ``step(state, batch, key) -> (state, metrics)``.

    ``batch = (simulator, reward_model, start_states [B])``: the simulator and reward model are
    arguments (not constants) so their weights are not baked into the program. The step
    expands each start state to ``cfg.grpo.group_size`` trajectories, rolls them out with the
    current policy, then updates it. ``state`` is donated.

    With ``cfg.imagined.oversample = k > 1`` the step is given ``B = k x rl.grpo.rollout_batch`` start
    states (:attr:`~sword_jax.rl.config.RLConfig.imagined_starts_per_step`), rolls all of them out and
    updates on ``B / k`` groups of them, mixed ones first (:func:`select_groups`). The update's metrics
    (``kept_fraction``, ``mixed_groups``, ``success_rate``, ``mean_return``, ``mean_chunks``, the
    confirmation's) are then those of the updated groups; ``sampled_mixed_fraction`` and
    ``imagined_success_sampled`` (every step) and ``mean_chunks_sampled`` (with ``k > 1``: the chunks
    actually rendered) are over all sampled ones. ``rl.grpo.min_mixed_groups`` counts the updated groups.

    Compiled by :func:`sword_jax.sharding.compile_step` over ``mesh`` (default: one device) and
    traced inside it, so the rollout's activation constraints shard the trajectories: the start
    states split over their leading dim, the simulator's and reward model's weights and the state
    kept where they were placed on ``mesh`` (else replicated).

    With ``cfg.imagined.reward = "executed"`` the batch is ``(simulator, reward_model, start_states [B], env_starts
    [B, ...][, start_steps [B]])`` and ``env`` a pure JAX environment (:class:`~sword_jax.rl.scan_rollout.JaxEnv`,
    e.g. ``sim.mjx_batch.MjxEpisodes``) that ``env_starts`` (the start states' recorded simulator states) reset: the
    imagined trajectories run the whole horizon, their executed actions are executed open loop in ``env`` and the
    real outcome pays them (:func:`~sword_jax.rl.imagined_check.paid_by_execution`); the metrics add
    ``real_rollouts`` (the trajectories executed: the step's share of a run's real episodes), the detector's verdict
    on the same trajectories (:func:`~sword_jax.rl.imagined_check.detector_metrics`), how its scores rank their real
    outcomes and what a threshold bounded by ``rl.refresh.max_false_success`` on them would pay
    (:func:`~sword_jax.rl.imagined_check.detector_separation`), with ``start_steps`` (each start's step in its
    episode) the same outcomes counted by where the starts stand
    (:func:`~sword_jax.rl.imagined_check.outcomes_by_start`) and, for the first
    ``rl.imagined.fidelity_trajectories``, where the closed loop through the simulator leaves the real one
    (:func:`~sword_jax.rl.imagined_check.closed_loop_fidelity`), with the share of it the simulator's decoder alone
    causes where the simulator has a round trip of real frames (the world model decoding with its VAE:
    :meth:`~sword_jax.rl.learned_simulator.LearnedSimulator.round_trip`).
    """
    cfg.validate()
    if cfg.imagined.reward == "calibrated":
        raise ValueError("make_grpo_step: rl.imagined.reward=calibrated changes its reward during the run: build "
                         "its step with make_calibrated_step")
    g, oversample = cfg.grpo.group_size, cfg.imagined.oversample
    executed = cfg.imagined.reward == "executed"
    if executed and env is None:
        raise ValueError("make_grpo_step: rl.imagined.reward=executed needs env= (the real environment that pays "
                         "the imagined actions)")

    def step(state: GRPOState, batch, key):
        simulator, reward_model, start = batch[:3]
        key = jax.random.fold_in(key, state.step)
        # one simulator start-up per start state; when the real environment pays, the detector stops nothing (every
        # trajectory runs the whole horizon) and its verdict is kept by its own rule
        rollout = imagined_rollout(graphdef, state.params, simulator, reward_model, start, cfg, key=key,
                                   group_size=g, stop_on_success=not executed)
        extra = {}
        if executed:
            actions, lengths = imagined_check.executed_actions(rollout, cfg.action_bins)
            env_starts = jnp.repeat(batch[3], g, axis=0)
            observed = min(cfg.imagined.fidelity_trajectories, actions.shape[0])
            if observed:  # the real frames at each decision's end too: where the closed loop leaves reality
                real_first, real_frames = imagined_check.execute_observed(
                    env, env_starts, actions, lengths, every=rollout.tokens.shape[2], rows=observed)
                # with the simulator's decoder round trip (the world model's VAE), that decoder's share of it
                round_trip = simulator.round_trip if getattr(simulator, "round_trip_fn", None) else None
                extra.update(imagined_check.closed_loop_fidelity(graphdef, state.params, rollout, real_frames,
                                                                 image_size=cfg.image_size,
                                                                 action_bins=cfg.action_bins, round_trip=round_trip))
            else:
                real_first = imagined_check.execute_open_loop(env, env_starts, actions, lengths)
            extra.update(imagined_check.detector_metrics(rollout.success, real_first >= 0),
                         real_rollouts=jnp.float32(actions.shape[0]))  # what the step took of the real budget
            extra.update(imagined_check.detector_separation(rollout.peaks, real_first >= 0,
                                                            max_false_success=cfg.refresh.max_false_success))
            if len(batch) > 4:  # each start's step in its episode: the outcomes counted by where it stands
                extra.update(imagined_check.outcomes_by_start(jnp.repeat(batch[4], g, axis=0), rollout.success,
                                                              real_first >= 0))
            rollout = imagined_check.paid_by_execution(rollout, real_first, cfg)
        unconfirmed_success = rollout.success
        if cfg.imagined.confirm_success:
            rollout, _ = confirm_successes(rollout, simulator, reward_model, expand_groups(start, g), cfg,
                                           key=jax.random.fold_in(key, CONFIRM_KEY_SALT))
        sampled_returns = rollout.returns.reshape(-1, g)  # (B, G): trajectories are group-major
        sampled = {"sampled_mixed_fraction": jnp.mean(group_has_signal(sampled_returns).astype(jnp.float32)),
                   "imagined_success_sampled": jnp.mean(rollout.success.astype(jnp.float32))}
        if oversample > 1:
            groups = sampled_returns.shape[0]
            if groups % oversample:
                raise ValueError(f"rl.imagined.oversample={oversample} must divide the step's {groups} start states "
                                 f"(give it rl.imagined_starts_per_step = oversample x rl.grpo.rollout_batch)")
            sampled["mean_chunks_sampled"] = rollout_metrics(rollout)["mean_chunks"]
            chosen = group_trajectories(select_groups(sampled_returns, groups // oversample,
                                                      key=jax.random.fold_in(key, SELECT_KEY_SALT)), g)
            rollout = take_trajectories(rollout, chosen)
            unconfirmed_success = unconfirmed_success[chosen]
        if cfg.imagined.confirm_success:  # the updated trajectories' successes before and after the second draw
            extra["imagined_success_unconfirmed"] = jnp.mean(unconfirmed_success.astype(jnp.float32))
            extra["unconfirmed_fraction"] = jnp.mean((unconfirmed_success & ~rollout.success).astype(jnp.float32))
        state, metrics = grpo_update(graphdef, cfg, state, rollout, jax.random.fold_in(key, UPDATE_KEY_SALT))
        return state, dict(metrics, **rollout_metrics(rollout), **extra, **sampled)

    mesh = shd.default_mesh(mesh)

    def batch_shardings(batch):
        simulator, reward_model, start = batch[:3]
        return (shd.shardings_on(simulator, mesh), shd.shardings_on(reward_model, mesh),
                *(shd.leading_axis_shardings(x, mesh, rules) for x in (start, *batch[3:])))

    # A retrace (changed shapes / static config) is a bug in the caller; ``max_traces`` bounds it.
    return shd.compile_step(tracing.max_traces(step, n=max_traces), mesh, rules, batch_shardings=batch_shardings,
                            donate=donate)



def calibrated_threshold(cuts: Sequence[float]) -> float:
    """The detector's threshold that the executed steps of ``rl.imagined.reward=calibrated`` set: just above the
    median of their ``detector_threshold_bounded`` (each the real failure's score that leaves at most
    ``rl.refresh.max_false_success`` of that step's real failures above it;
    :func:`~sword_jax.rl.imagined_check.detector_separation`), as a float32 a detector's score reaches only by
    exceeding it. NaN cuts (a step whose trajectories all succeeded for real) are left out; refused where none is
    left."""
    known = [float(c) for c in cuts if not math.isnan(float(c))]
    if not known:
        raise ValueError(f"rl.imagined.reward=calibrated: none of the {len(cuts)} steps paid by execution had a real "
                         "failure, so no threshold bounds the detector's false successes; give more "
                         "rl.imagined.calibrate_steps or a larger rl.grpo.rollout_batch")
    cut = np.float32(statistics.median(known))
    # one float32 step above the cut, and never a subnormal (which a device may flush to zero)
    return float(max(np.nextafter(cut, np.float32(np.inf)), np.finfo(np.float32).tiny))


def make_calibrated_step(graphdef: nnx.GraphDef, cfg: RLConfig, *, env: Any,
                         history: Callable[[], Sequence[dict]] = lambda: (), **kwargs: Any
                         ) -> Callable[[GRPOState, tuple, jax.Array], tuple[GRPOState, dict]]:
    """The GRPO step of ``rl.imagined.reward=calibrated``: ``step(state, batch, key) -> (state, metrics)`` with
    ``batch = (simulator, reward_model, start_states [B], env_starts [B, ...])`` as for ``executed``.

    Steps ``0 .. rl.imagined.calibrate_steps - 1`` (by ``state.step``) are :func:`make_grpo_step`'s with
    ``reward=executed`` (the real environment ``env`` pays; each logs ``detector_threshold_bounded``). The first
    step after them sets the detector's threshold from those steps (:func:`calibrated_threshold`) and it and every
    later one is :func:`make_grpo_step`'s with ``reward=detector`` at that ``success_threshold`` (compiled once,
    then); their metrics add ``detector_threshold``. The executed steps' cuts are kept as they run; those of a run
    resumed after some of them are read from ``history()``, the run's per-step records (``step`` 1-based, as
    :func:`~sword_jax.rl.grpo_loop.read_history` gives them), so the resumed run pays at the same threshold.
    ``kwargs`` go to :func:`make_grpo_step` (``donate``, ``max_traces``, ``mesh``, ``rules``)."""
    cfg.validate()
    if cfg.imagined.reward != "calibrated":
        raise ValueError(f"make_calibrated_step: rl.imagined.reward must be calibrated, got {cfg.imagined.reward!r}")
    k = cfg.imagined.calibrate_steps
    as_reward = lambda reward, **more: dataclasses.replace(  # noqa: E731
        cfg, **more, imagined=dataclasses.replace(cfg.imagined, reward=reward, calibrate_steps=0))
    paid = make_grpo_step(graphdef, as_reward("executed"), env=env, **kwargs)
    # the executed steps' cuts by their 1-based step: those this process ran, as they ran
    host: dict[str, Any] = {"step": None, "cuts": {}, "detector": None}

    def detector_step() -> tuple[Callable, float]:
        cuts = {s: float(c) for s, c in jax.device_get(host["cuts"]).items()}
        missing = [s for s in range(1, k + 1) if s not in cuts]
        if missing:  # resumed after some of them: their records
            rows = {int(r["step"]): r for r in history() if int(r["step"]) in missing}
            if sorted(rows) != missing:
                raise ValueError(f"rl.imagined.reward=calibrated: the run resumed after steps {missing} paid by "
                                 f"execution, but its records hold only steps {sorted(rows)} of them: the detector's "
                                 "threshold cannot be set as the run set it")
            cuts.update({s: rows[s].get("detector_threshold_bounded", float("nan")) for s in missing})
        threshold = calibrated_threshold([cuts[s] for s in range(1, k + 1)])
        return make_grpo_step(graphdef, as_reward("detector", success_threshold=threshold), **kwargs), threshold

    def step(state: GRPOState, batch: tuple, key: jax.Array) -> tuple[GRPOState, dict]:
        if host["step"] is None:  # read once; then counted here (a roll-back restores parameters, not the step)
            host["step"] = int(jax.device_get(state.step))
        at, host["step"] = host["step"], host["step"] + 1
        if at < k:
            state, metrics = paid(state, batch, key)
            host["cuts"][at + 1] = metrics["detector_threshold_bounded"]
            return state, metrics
        if host["detector"] is None:
            host["detector"] = detector_step()
        fn, threshold = host["detector"]
        state, metrics = fn(state, batch, key)
        return state, dict(metrics, detector_threshold=jnp.float32(threshold))

    return step
