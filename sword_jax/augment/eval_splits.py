"""LIBERO-Original and LIBERO-Mixed evaluation splits, built deterministically from held-out episodes.

* **LIBERO-Original**: the held-out episodes, raw.
* **LIBERO-Mixed**: the same episodes, a ``mixed_fraction`` share (half by default) restyled in
  *held-out* styles (never seen in training), the rest raw.

Which episodes are styled and each one's style depend only on ``seed`` and the episode ids
(not on the order the episodes are passed in), and are recorded in :meth:`EvalSplits.manifest`.
"""

from __future__ import annotations

import json
import os
from typing import NamedTuple

import jax
import numpy as np

from sword_jax.augment.episodes import Episodes, as_episodes
from sword_jax.augment.style import DEFAULT_CLASSES, SegClasses, Style, identity_style, sample_style, split_violations, style_to_record
from sword_jax.augment.transforms import augment
from sword_jax.rng import stream_key


class EvalSplit(NamedTuple):
    """One evaluation split (episodes sorted by id).

    Attributes:
      name: "libero_original" or "libero_mixed".
      frames: ``[N, T, H, W, 3]`` float32 in [0, 1].
      actions: ``[N, T, A]``.
      episode_ids: ``[N]``.
      styled: ``[N]`` bool, which episodes were restyled.
      styles: :class:`Style` with leading dim ``N`` (the identity style for raw episodes).
    """

    name: str
    frames: np.ndarray
    actions: np.ndarray
    episode_ids: np.ndarray
    styled: np.ndarray
    styles: Style


class EvalSplits(NamedTuple):
    original: EvalSplit
    mixed: EvalSplit
    seed: int
    mixed_fraction: float

    def manifest(self) -> dict:
        """JSON-ready record: seed, fraction and per episode of LIBERO-Mixed: id, styled, style params."""
        entries = []
        for i, episode_id in enumerate(self.mixed.episode_ids):
            style = jax.tree.map(lambda x, i=i: x[i], self.mixed.styles)
            entries.append({
                "episode_id": int(episode_id),
                "styled": bool(self.mixed.styled[i]),
                "style": style_to_record(style) if self.mixed.styled[i] else None,
            })
        return {
            "seed": int(self.seed),
            "mixed_fraction": float(self.mixed_fraction),
            "libero_original": [int(i) for i in self.original.episode_ids],
            "libero_mixed": entries,
        }

    def write_manifest(self, path: str) -> str:
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        with open(path, "w") as f:
            json.dump(self.manifest(), f, indent=1)
        return path


def build_eval_splits(
    episodes: Episodes | dict,
    *,
    seed: int,
    mixed_fraction: float = 0.5,
    intensity: float = 1.0,
    training_ids: np.ndarray | None = None,
    classes: SegClasses = DEFAULT_CLASSES,
    fov_deg: float = 45.0,
) -> EvalSplits:
    """LIBERO-Original (raw) and LIBERO-Mixed (``mixed_fraction`` in held-out styles) from held-out episodes.

    Args:
      episodes: the held-out episodes (frames, depth, seg, actions, episode_ids).
      seed: the only source of randomness: which episodes are styled and their styles.
      mixed_fraction: share of LIBERO-Mixed episodes restyled (rounded to the nearest count).
      intensity: style intensity of the restyled episodes.
      training_ids: optional ids of the training episodes; overlap raises (evaluation must use
        episodes the world model never trained on).

    Raises:
      ValueError: empty input, fraction outside [0, 1], overlap with ``training_ids``.
    """
    if not 0.0 <= mixed_fraction <= 1.0:
        raise ValueError(f"build_eval_splits: mixed_fraction must be in [0, 1], got {mixed_fraction}")
    eps = as_episodes(episodes)
    if eps.num == 0:
        raise ValueError("build_eval_splits: no episodes")
    if training_ids is not None:
        overlap = np.intersect1d(eps.episode_ids, np.asarray(training_ids))
        if overlap.size:
            raise ValueError(f"build_eval_splits: episodes {overlap[:10].tolist()} are also training episodes")
    eps = eps.take(np.argsort(eps.episode_ids, kind="stable"))
    root = jax.random.key(seed)
    ids_root, style_root = stream_key(root, "eval_splits/styled_ids"), stream_key(root, "eval_splits/styles")
    # Rank episodes by a per-id random number: order-independent and stable under adding episodes.
    scores = np.asarray(jax.vmap(lambda i: jax.random.uniform(jax.random.fold_in(ids_root, i)))(
        np.asarray(eps.episode_ids, np.uint32)))
    num_styled = int(round(mixed_fraction * eps.num))
    styled = np.zeros(eps.num, bool)
    styled[np.argsort(scores, kind="stable")[:num_styled]] = True

    identity = identity_style()
    frames, styles = eps.frames.copy(), []
    for i, episode_id in enumerate(eps.episode_ids):
        if not styled[i]:
            styles.append(identity)
            continue
        style = sample_style(jax.random.fold_in(style_root, int(episode_id)), "heldout")
        bad = split_violations(style, "heldout")
        if bad:  # the held-out sampler must only produce held-out styles
            raise AssertionError(f"held-out sampler produced a style outside the held-out region: {bad}")
        frames[i] = np.asarray(augment(eps.frames[i], eps.depth[i], eps.seg[i], style, intensity=intensity,
                                       classes=classes, fov_deg=fov_deg))
        styles.append(style)
    styles = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *styles)
    raw_styles = jax.tree.map(lambda x: np.stack([np.asarray(x)] * eps.num), identity)
    original = EvalSplit("libero_original", eps.frames, eps.actions, eps.episode_ids, np.zeros(eps.num, bool), raw_styles)
    mixed = EvalSplit("libero_mixed", frames, eps.actions, eps.episode_ids, styled, styles)
    return EvalSplits(original, mixed, int(seed), float(mixed_fraction))
