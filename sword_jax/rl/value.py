"""A success-probability value that closes short GRPO rollouts (``rl.value``; MBPO closes its branched rollouts
the same way).

A rollout short enough for a learned simulator to stay honest seldom reaches success from most of its start
states, so a success-only return leaves most GRPO groups without a learning signal (on `small`, 3-8 of 32 groups
mixed at 2-4 decisions from every phase, against 26-30 at 12 decisions). :class:`ValueNet` reads a frame and the
instruction and predicts whether the episode goes on to succeed; :func:`terminal_returns` pays a rollout that
reached its horizon without an outcome that probability (times the success return).

The value is fitted (:func:`fit_value`) to the decisions of real episodes of the policy, each frame labelled with
its episode's outcome (:func:`decision_samples`): the Monte Carlo value of the policy that ran them. Its batches
are drawn uniformly over decisions, not class-balanced, so the sigmoid stays a calibrated probability;
:func:`calibration` reports it on held-out episodes against the constant predictor.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jaxtyping import Array, Float, Int

from sword_jax import optim
from sword_jax.rl.config import RLConfig
from sword_jax.rl.reward_model import conv_tower, pooled_features

VOCAB = 257  # instruction byte tokens 1..256, 0 padding (sword_jax.rl.policy.tokenize_instructions)


class ValueNet(nnx.Module):
    """Four stride-2 conv blocks -> global average pool, joined with the mean of the instruction's byte
    embeddings -> MLP -> one logit: whether the episode showing this frame goes on to succeed."""

    def __init__(self, cfg: RLConfig, *, rngs: nnx.Rngs):
        self.image_size = cfg.image_size
        w = cfg.value.width
        self.convs = conv_tower(w, rngs)
        self.text = nnx.Embed(VOCAB, 4 * w, rngs=rngs)
        self.hidden = nnx.Linear(8 * w, 4 * w, rngs=rngs)
        self.out = nnx.Linear(4 * w, 1, rngs=rngs)

    def __call__(self, frames: Float[Array, "n h w 3"], tokens: Int[Array, "n l"]) -> Float[Array, " n"]:
        """Logits for frames in [0, 1] (any size; resized to ``rl.image_size``) and instruction tokens."""
        x = pooled_features(self.convs, frames, self.image_size)
        present = (tokens > 0).astype(jnp.float32)[..., None]
        text = jnp.sum(self.text(tokens) * present, axis=1) / jnp.maximum(jnp.sum(present, axis=1), 1.0)
        h = jax.nn.gelu(self.hidden(jnp.concatenate([x, text.astype(x.dtype)], axis=-1)))
        return self.out(h)[:, 0].astype(jnp.float32)


def build_value(cfg: RLConfig, *, seed: int = 0) -> tuple[nnx.GraphDef, nnx.State]:
    with nnx.use_eager_sharding(False):
        return nnx.split(ValueNet(cfg, rngs=nnx.Rngs(seed)))


class Value(NamedTuple):
    """A fitted value as :func:`sword_jax.rl.scan_rollout.scan_rollout` takes it: ``fn(params, frames [n,h,w,3] in
    [0, 1], tokens [n, l]) -> success probability [n]`` and its params (an argument of the compiled rollout, so
    another fit does not recompile it)."""

    fn: Callable[[Any, Array, Array], Array]
    params: Any


def as_value(graphdef: nnx.GraphDef, params: Any) -> Value:
    def fn(params, frames, tokens):
        return jax.nn.sigmoid(nnx.merge(graphdef, params)(frames, tokens))

    return Value(fn=fn, params=params)


def terminal_returns(success: Array, truncated: Array, value: Array, success_return: float) -> Array:
    """``[n]`` returns: ``success_return`` on success, ``success_return x value`` for a rollout that reached its
    horizon with no outcome (``truncated``), 0 otherwise (a failure, e.g. its physics broke)."""
    success = jnp.asarray(success, bool)
    paid = jnp.where(jnp.asarray(truncated, bool) & ~success, jnp.clip(value, 0.0, 1.0), 0.0)
    return jnp.float32(success_return) * (success.astype(jnp.float32) + paid.astype(jnp.float32))


@dataclasses.dataclass
class ValueData:
    """Decisions of real episodes as value-training samples: ``frames [N, h, w, 3] uint8``, ``tokens [N, l]``,
    ``labels [N]`` (1.0: the episode succeeded), ``episode [N]`` (which episode each came from), ``states [N, f]``
    (the environment's snapshot at each decision, start states of branched rollouts; ``f = 0`` without one) and,
    once a value is fitted, ``predicted [N]`` (its success probability there)."""

    frames: np.ndarray
    tokens: np.ndarray
    labels: np.ndarray
    episode: np.ndarray
    states: np.ndarray
    predicted: np.ndarray | None = None  # the fitted value's success probability at each decision, once known

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def take(self, mask: np.ndarray) -> ValueData:
        return ValueData(*(None if getattr(self, f.name) is None else getattr(self, f.name)[mask]
                           for f in dataclasses.fields(self)))

    @staticmethod
    def concatenate(parts: list[ValueData]) -> ValueData:
        """The samples of ``parts`` in order, episode indices renumbered so that they stay distinct (``predicted``
        is kept only where every part has it)."""
        out, offset = [], 0
        for p in parts:
            out.append(dataclasses.replace(p, episode=p.episode + offset))
            offset += int(p.episode.max()) + 1 if len(p) else 0
        return ValueData(*(None if any(getattr(p, f.name) is None for p in out)
                           else np.concatenate([getattr(p, f.name) for p in out]) for f in dataclasses.fields(ValueData)))


def decision_samples(frames: np.ndarray, valid: np.ndarray, tokens: np.ndarray, success: np.ndarray,
                     states: np.ndarray | None = None) -> ValueData:
    """Every valid decision of ``E`` episodes (``frames [E, C, h, w, 3]`` uint8 seen at each decision, ``valid
    [E, C]``, ``tokens [E, l]``, ``success [E]``, optionally ``states [E, C, f]``), labelled with its episode's
    outcome.

    Raises:
      ValueError: shapes that do not agree, or no valid decision."""
    frames, valid = np.asarray(frames), np.asarray(valid) > 0
    tokens, success = np.asarray(tokens), np.asarray(success).astype(bool)
    e = success.shape[0]
    states = np.zeros(valid.shape + (0,), np.float32) if states is None else np.asarray(states, np.float32)
    if (frames.ndim != 5 or frames.shape[:2] != valid.shape or valid.shape[0] != e or tokens.shape[0] != e
            or states.shape[:2] != valid.shape):
        raise ValueError(f"decision_samples: frames [E, C, h, w, 3], valid [E, C], tokens [E, l], success [E] and "
                         f"states [E, C, f] must agree, got {frames.shape}, {valid.shape}, {tokens.shape}, "
                         f"{success.shape}, {states.shape}")
    rows, cols = np.nonzero(valid)
    if rows.size == 0:
        raise ValueError("decision_samples: the episodes hold no valid decision")
    return ValueData(frames[rows, cols], tokens[rows], success[rows].astype(np.float32), rows.astype(np.int32),
                     states[rows, cols])


def split_episodes(data: ValueData, holdout: float, rng: np.random.Generator) -> tuple[ValueData, ValueData]:
    """``(fit, held out)``: ``holdout`` of the episodes (whole) kept out of the fit."""
    episodes = np.unique(data.episode)
    held = rng.permutation(episodes)[: int(len(episodes) * holdout)]
    out = np.isin(data.episode, held)
    return data.take(~out), data.take(out)


def calibration(probs: np.ndarray, labels: np.ndarray, bins: int = 5) -> dict[str, Any]:
    """How well ``probs`` predict ``labels`` (0/1): Brier score against the constant predictor's (the labels'
    mean), log loss, ROC AUC, and the mean prediction against the observed rate in ``bins`` equal-width bins."""
    p = np.clip(np.asarray(probs, np.float64), 1e-6, 1 - 1e-6)
    y = np.asarray(labels, np.float64)
    if p.shape != y.shape or p.size == 0:
        raise ValueError(f"calibration: probs and labels must be equal, non-empty shapes, got {p.shape}, {y.shape}")
    pos, neg = p[y > 0.5], p[y <= 0.5]
    auc = None
    if pos.size and neg.size:
        order = np.argsort(np.concatenate([neg, pos]), kind="stable")
        ranks = np.empty(order.size)
        ranks[order] = np.arange(1, order.size + 1)
        values = np.concatenate([neg, pos])
        for v in np.unique(values):  # ties share their mean rank
            tie = values == v
            ranks[tie] = ranks[tie].mean()
        auc = float((ranks[neg.size:].sum() - pos.size * (pos.size + 1) / 2) / (pos.size * neg.size))
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(p, edges[1:-1]), 0, bins - 1)
    table = [{"bin": [round(float(edges[b]), 3), round(float(edges[b + 1]), 3)], "count": int(np.sum(which == b)),
              "predicted": float(p[which == b].mean()), "observed": float(y[which == b].mean())}
             for b in range(bins) if np.any(which == b)]
    return {"samples": int(y.size), "positive_rate": float(y.mean()), "brier": float(np.mean((p - y) ** 2)),
            "brier_constant": float(np.mean((y.mean() - y) ** 2)),
            "log_loss": float(-np.mean(y * np.log(p) + (1 - y) * np.log(1 - p))), "auc": auc, "bins": table}


def fit_value(graphdef: nnx.GraphDef, params: Any, cfg: RLConfig, data: ValueData, *, seed: int,
              log: Callable[[str], Any] = print) -> tuple[Any, dict[str, Any]]:
    """``rl.value.steps`` AdamW steps of binary cross-entropy on ``rl.value.batch_size`` decisions drawn uniformly
    from ``data`` (a pure function of ``seed``): ``(params, {"loss": last 10 steps' mean})``."""
    conf = cfg.value
    if len(data) == 0:
        raise ValueError("fit_value: no samples to fit")
    opt = optim.make_optimizer(conf.learning_rate, weight_decay=1e-4)
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, frames, tokens, labels):
        def loss_fn(p):
            logits = nnx.merge(graphdef, p)(frames.astype(jnp.float32) / 255.0, tokens)
            return jnp.mean(optax.sigmoid_binary_cross_entropy(logits, labels))

        loss, grads = jax.value_and_grad(loss_fn)(params)
        _, opt_state, params = optim.apply_optimizer(opt, grads, opt_state, params)
        return params, opt_state, loss

    rng = np.random.default_rng(seed)
    every, last = max(conf.steps // 5, 1), []
    for s in range(conf.steps):
        pick = rng.integers(0, len(data), conf.batch_size)
        params, opt_state, loss = step(params, opt_state, jnp.asarray(data.frames[pick]),
                                       jnp.asarray(data.tokens[pick]), jnp.asarray(data.labels[pick]))
        if s >= conf.steps - 10:
            last.append(float(loss))
        if (s + 1) % every == 0:
            log(f"value step {s + 1}/{conf.steps} loss {float(loss):.4f}")
    if not np.all(np.isfinite(last)):
        raise FloatingPointError(f"fit_value: the loss became non-finite ({last})")
    return params, {"loss": float(np.mean(last))}


def predict(value: Value, data: ValueData, chunk: int = 512) -> np.ndarray:
    """The value's success probability on every sample of ``data``, in chunks."""
    fn = jax.jit(value.fn)
    out = [np.asarray(fn(value.params, jnp.asarray(data.frames[i:i + chunk], jnp.float32) / 255.0,
                         jnp.asarray(data.tokens[i:i + chunk])))
           for i in range(0, len(data), chunk)]
    return np.concatenate(out) if out else np.zeros((0,), np.float32)
