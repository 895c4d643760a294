"""How much of a GRPO batch gradient is signal, and where it points.

A GRPO step's gradient is the mean over its groups of each group's contribution ``h_i`` (the start states
are drawn independently, so the ``h_i`` are i.i.d. draws around the expected gradient ``G``). From the
``h_i`` of one batch, unbiasedly (McCandlish et al.'s gradient noise scale, estimated per group):

- ``signal`` = ``|G|^2``, from the off-diagonal sum of the groups' Gram matrix;
- ``power`` = ``E |h|^2``, its diagonal mean; ``noise`` = ``tr Cov(h)`` = ``power - signal``;
- ``cos_at(B)``: the expected cosine between the gradients of two independent batches of ``B`` groups,
  ``signal / (signal + noise / B)``: near 1, every batch points the same way; near 0, an optimiser that
  normalises its step (Adam) takes full-size steps in directions the next batch does not repeat;
- ``alignment(a, b)``: the cosine of two settings' expected gradients, ``G_a . G_b / (|G_a| |G_b|)``, e.g.
  whether short rollouts from mid-episode states pull the policy where full episodes from rest do;
- ``useful(a, b, B)``: the expected cosine of one ``B``-group batch gradient of ``a`` with ``G_b``, both effects
  together: ``G_a . G_b / (|G_b| sqrt(signal_a + noise_a / B))``.

Everything is a function of the Gram matrix of the ``h_i`` (all settings stacked), so bootstrap intervals over
groups cost no further gradients. Two settings measured on the same trajectories (one rollout scored two ways)
are paired: their cross terms leave out each group's product with itself, as the unbiased signal does.

:func:`group_gradients` computes the ``h_i`` with GRPO's own objective (:func:`sword_jax.rl.grpo._gradient_fn`)
at the behaviour policy (ratio 1, so the clipped surrogate's gradient is the policy gradient), scaled so that their
mean is the batch gradient GRPO would apply: a group without signal contributes zero.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.flatten_util import ravel_pytree

from sword_jax.rl import grpo
from sword_jax.rl.config import RLConfig
from sword_jax.rl.rollout import Rollout


def first_decisions(batch: Rollout, horizon: int, cfg: RLConfig) -> Rollout:
    """``batch`` cut to its first ``horizon`` decisions, paid success within them (``1 + success_bonus``, as
    :func:`sword_jax.rl.env_rollout.run_policy` pays) — GRPO's short rollout read off a longer one.

    A ground-truth episode ends at its success, so it succeeded within the horizon exactly when it succeeded
    having taken at most ``horizon`` decisions."""
    if horizon < 1:
        raise ValueError(f"first_decisions: horizon must be >= 1, got {horizon}")
    valid = np.asarray(batch.valid) > 0
    success = np.asarray(batch.success).astype(bool) & (valid.sum(axis=1) <= horizon)
    cut = lambda x: x[:, :horizon]  # noqa: E731
    return batch._replace(obs_frames=cut(batch.obs_frames), proprio=cut(batch.proprio),
                          proprio_valid=cut(batch.proprio_valid), tokens=cut(batch.tokens),
                          log_probs=cut(batch.log_probs), valid=cut(batch.valid), rewards=cut(batch.rewards),
                          scores=cut(batch.scores), success=success,
                          returns=(success * (1.0 + cfg.grpo.success_bonus)).astype(np.float32), frames=np.zeros((0,)))


def _group(batch: Rollout, index: int, size: int) -> Rollout:
    part = slice(index * size, (index + 1) * size)
    return jax.tree.map(lambda x: x[part] if np.ndim(x) and np.shape(x)[0] == np.shape(batch.valid)[0] else x, batch)


def _share(batch: Rollout, cfg: RLConfig) -> np.ndarray:
    """Each group's share of the batch objective (summing to 1, or all 0 when no group carries a signal): its chunks'
    weights (:func:`grpo.loss_weights`, over the groups :func:`grpo.group_advantages` keeps) over all of them."""
    g = cfg.grpo.group_size
    _, keep_group = grpo.group_advantages(jnp.asarray(batch.returns).reshape(-1, g), filter_groups=cfg.grpo.filter_groups,
                                          scale_by_std=cfg.grpo.scale_by_std)
    t, a = np.shape(batch.tokens)[2:]
    weights = grpo.loss_weights(jnp.asarray(batch.valid, jnp.float32), jnp.repeat(keep_group, g), t * a, cfg)
    per_group = np.asarray(weights, np.float64).reshape(-1, g * weights.shape[1]).sum(axis=1)
    total = per_group.sum()
    return per_group / total if total > 0 else per_group


def group_gradients(graphdef: nnx.GraphDef, cfg: RLConfig, params: Any, batch: Rollout) -> np.ndarray:
    """``h [groups, P]`` (float32): each group's contribution to GRPO's batch gradient at ``params``, flattened,
    scaled so that ``h.mean(0)`` is the gradient of the whole batch's objective (``batch``: ``groups x
    rl.grpo.group_size`` trajectories in group order, sampled by the policy at ``params``)."""
    g = cfg.grpo.group_size
    n = int(np.shape(batch.valid)[0])
    if n % g:
        raise ValueError(f"group_gradients: {n} trajectories are not whole groups of rl.grpo.group_size={g}")
    groups = n // g
    one = dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, update_microbatch=g))

    @jax.jit
    def gradient(p, part):
        _, _, grads = grpo._gradient_fn(graphdef, one, part)(p)
        return ravel_pytree(grads)[0]

    share = _share(batch, cfg)  # sums to 1 over the groups, or to 0 when none carries a signal
    out = np.zeros((groups, ravel_pytree(params)[0].size), np.float32)
    for i in range(groups):
        if share[i] == 0:
            continue
        part = jax.tree.map(jnp.asarray, _group(batch, i, g))
        out[i] = np.asarray(gradient(params, part)) * np.float32(groups * share[i])
    return out


@dataclasses.dataclass(frozen=True)
class Setting:
    """Rows ``rows`` of the Gram matrix, one per group. Settings with the same ``pairing`` label were scored on
    the same trajectories, row ``k`` of one with row ``k`` of the other. ``ids`` name the groups (default: their
    position); products of a group with itself (the same id, in one setting or two paired ones) are left out."""

    rows: np.ndarray
    pairing: str = ""
    ids: np.ndarray | None = None

    def group_ids(self) -> np.ndarray:
        return np.arange(len(self.rows)) if self.ids is None else np.asarray(self.ids)


def _mean_of_products(gram: np.ndarray, a: Setting, b: Setting, *, exclude_same: bool) -> float:
    block = gram[np.ix_(np.asarray(a.rows), np.asarray(b.rows))]
    if not exclude_same:
        return float(block.mean())
    distinct = a.group_ids()[:, None] != b.group_ids()[None, :]
    return float(block[distinct].mean()) if distinct.any() else float("nan")


def _signal(gram: np.ndarray, s: Setting) -> float:
    return _mean_of_products(gram, s, s, exclude_same=True)


def _cross(gram: np.ndarray, a: Setting, b: Setting) -> float:
    return _mean_of_products(gram, a, b, exclude_same=bool(a.pairing) and a.pairing == b.pairing)


def statistics(gram: np.ndarray, settings: Mapping[str, Setting], *, reference: str, batch_groups: int) -> dict:
    """Per setting: ``signal``, ``power``, ``noise``, ``signal_fraction`` (``signal / power``: one group's),
    ``cos_at_batch`` (two independent ``batch_groups``-group batches), ``alignment`` with ``reference``'s
    expected gradient and ``useful`` (one batch's expected cosine with it). A signal at or below zero (the noise
    hides it at this many groups) gives ``None`` for the ratios that need its root."""
    if reference not in settings:
        raise ValueError(f"statistics: reference {reference!r} is not one of the settings {sorted(settings)}")
    sizes: dict[str, int] = {}
    for name, s in settings.items():
        if s.pairing and sizes.setdefault(s.pairing, len(s.rows)) != len(s.rows):
            raise ValueError(f"statistics: paired settings ({s.pairing!r}) must have as many groups; {name!r} has "
                             f"{len(s.rows)}, another {sizes[s.pairing]}")
    ref = settings[reference]
    ref_signal = _signal(gram, ref)
    out = {}
    for name, s in settings.items():
        if len(s.rows) < 2:
            raise ValueError(f"statistics: setting {name!r} has {len(s.rows)} groups; at least 2 are needed")
        signal = _signal(gram, s)
        power = float(np.mean(np.diag(gram)[np.asarray(s.rows)]))
        noise = power - signal
        spread = signal + noise / batch_groups
        row = {"groups": len(s.rows), "signal": signal, "power": power, "noise": noise,
               "signal_fraction": signal / power if power > 0 else None,
               "cos_at_batch": signal / spread if spread > 0 else None}
        cross = ref_signal if name == reference else _cross(gram, s, ref)
        row["alignment"] = cross / np.sqrt(signal * ref_signal) if signal > 0 and ref_signal > 0 else None
        row["useful"] = cross / np.sqrt(ref_signal * spread) if ref_signal > 0 and spread > 0 else None
        out[name] = row
    return out


def bootstrap(gram: np.ndarray, settings: Mapping[str, Setting], *, reference: str, batch_groups: int,
              draws: int = 1000, seed: int = 0, keys: Sequence[str] = ("signal_fraction", "cos_at_batch", "alignment",
                                                                        "useful")) -> dict:
    """95% percentile intervals of :func:`statistics`'s ratios, resampling each setting's groups with
    replacement (paired settings together; a group drawn twice is not multiplied with its own copy). A resample
    whose ratio is undefined counts as below every value."""
    rng = np.random.default_rng(seed)
    samples: dict[str, dict[str, list[float]]] = {n: {k: [] for k in keys} for n in settings}
    for _ in range(draws):
        picks: dict[str, np.ndarray] = {}
        drawn = {}
        for n, s in settings.items():
            size = len(s.rows)
            pick = picks.setdefault(s.pairing, rng.integers(0, size, size)) if s.pairing else rng.integers(0, size, size)
            drawn[n] = Setting(np.asarray(s.rows)[pick], s.pairing, s.group_ids()[pick])
        stats = statistics(gram, drawn, reference=reference, batch_groups=batch_groups)
        for n in settings:
            for k in keys:
                v = stats[n][k]
                samples[n][k].append(-np.inf if v is None or not np.isfinite(v) else v)
    return {n: {k: _interval(v) for k, v in ks.items()} for n, ks in samples.items()}


def _interval(values: Sequence[float]) -> list[float]:
    """The 2.5th and 97.5th order statistics (no interpolation, so an undefined draw's -inf stays an end)."""
    ordered = np.sort(np.asarray(values, np.float64))
    last = len(ordered) - 1
    return [float(ordered[int(np.floor(0.025 * last))]), float(ordered[int(np.ceil(0.975 * last))])]


def gram_matrix(vectors: np.ndarray) -> np.ndarray:
    """``vectors @ vectors.T`` in float64 (the groups' gradients are small and many are near-orthogonal)."""
    v = np.asarray(vectors, np.float64)
    return v @ v.T
