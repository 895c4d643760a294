"""Style augmentation in world-model training: per-step on device, or pre-encoded styled copies.

Two ways to feed styled video to the world model:

(a) **per step** (:func:`make_step_augmenter`): inside the train step, sample a training style per
    episode, restyle the raw pixel segment on device, VAE-encode it, train. Every step sees a
    new style, but every step pays a VAE encode of the whole batch and the pixels (and depth /
    segmentation) of the batch must be on device.
(b) **pre-encoded copies** (:func:`make_styled_copies`, :func:`encode_styled_copies`): restyle
    each episode ``n_copies`` times once, VAE-encode once, and train on latents as if the copies
    were more episodes (the raw episode stays too). The train step touches no pixels.

Decision: **(b), pre-encoded copies** (what the pipeline does; (a) stays a library function), because the VAE encode
is a large fraction of a train step at every size, while copies cost a one-off encode and a
little host memory. Figures from ``python -m benchmarks.bench_augment --variant V --flops-only``
(XLA's FLOP count of the real jitted ``vae.encode``, lowered abstractly so it is exact at
paper size on any machine; DiT step = 6 x params x latent tokens), per training batch:

==========  =====================  ==================  ================  ========  =========
variant     batch (frames, size)   DiT step (GFLOP)    encode (GFLOP)    ratio     copies
==========  =====================  ==================  ================  ========  =========
paper       64 x 13 @ 256          493,400             190,800           0.39      7.3 GB
small       32 x 13 @ 128          451                 966               2.1       0.13 GB
tiny        2 x 13 @ 32            0.0025              0.117             46        --
==========  =====================  ==================  ================  ========  =========

* Per-step augmentation would add 39% FLOPs to every paper-size step (more in time: the
  encoder's full-resolution 3-D convolutions run far below the DiT matmuls' utilisation; on
  CPU, tiny: encode 135 ms vs augment 13 ms per batch) and 2x at the small size.
* Copies: 1,500 episodes x 2 styled copies x 129 frames is a one-off encode of ~8.9e16 FLOPs
  = ~180 paper train steps (0.9% of a 20k-step run), and the latent dataset grows from 2.4 to
  7.3 GB of host memory (float32 latents, 33 x 16 x 16 x 48 per episode).
* The augmentation itself is elementwise work (tiny, CPU: ~10% of an encode): not the cost.
* What (a) buys, a new style per step, matters little: each episode is seen ~850 times
  (20k steps x 64 / 1,500); two styled copies already give each three appearances drawn from
  the training style space; raise ``augment.styled_copies`` for more.

The world-model data path (``sword_jax.world_model.data``) already trains on pre-encoded
latents; styled copies enter it as extra episodes with the same actions.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from sword_jax.augment.config import AugmentConfig
from sword_jax.augment.episodes import Episodes, as_episodes
from sword_jax.augment.style import DEFAULT_CLASSES, SegClasses, Style, assert_training_style, sample_styles
from sword_jax.augment.transforms import augment_batch, augment_styles, to_signed_range


def seg_classes_from_config(cfg: AugmentConfig) -> SegClasses:
    """The config's id groups, or the default convention when empty."""
    return SegClasses.from_mapping(dict(cfg.seg_classes)) if cfg.seg_classes else DEFAULT_CLASSES


# ---------------------------------------------------------------------------------------------
# (a) per step, on device.


def make_step_augmenter(
    cfg: AugmentConfig, classes: SegClasses | None = None, *, raw_fraction: float = 0.25
) -> Callable[..., tuple[jax.Array, Style, jax.Array]]:
    """A jittable ``fn(frames, depth, seg, *, key) -> (styled, styles, styled_mask)`` for the train step.

    ``frames [B, T, H, W, 3]`` in [0, 1]; each episode gets its own *training* style (the only
    sampler reachable from here), and a ``raw_fraction`` share (in [0, 1]) stay raw. ``styled`` is in
    [0, 1]: use :func:`~sword_jax.augment.transforms.to_signed_range` before ``vae.encode``.
    """
    cfg.validate()
    if not 0.0 <= raw_fraction <= 1.0:
        raise ValueError(f"make_step_augmenter: raw_fraction must be in [0, 1], got {raw_fraction}")
    classes = classes or seg_classes_from_config(cfg)

    def step_augment(
        frames: Float[Array, "b t h w 3"],
        depth: Float[Array, "b t h w"],
        seg: Int[Array, "b t h w"],
        *,
        key: jax.Array,
    ) -> tuple[Float[Array, "b t h w 3"], Style, jax.Array]:
        k_style, k_raw = jax.random.split(key)
        styles = sample_styles(k_style, frames.shape[0], "train")
        styled_mask = jax.random.uniform(k_raw, (frames.shape[0],)) >= raw_fraction
        if not cfg.enabled:
            styled_mask = jnp.zeros_like(styled_mask)
        intensity = jnp.where(styled_mask, jnp.float32(cfg.intensity), jnp.float32(0.0))

        styled = augment_batch(frames, depth, seg, styles, intensity=intensity, classes=classes, fov_deg=cfg.fov_deg)
        # Intensity 0 is the identity up to rounding; pass raw episodes through bit-exactly.
        styled = jnp.where(styled_mask[:, None, None, None, None], styled, frames.astype(jnp.float32))
        return styled, styles, styled_mask

    return step_augment


# ---------------------------------------------------------------------------------------------
# (b) pre-encoded styled copies.


class StyledCopies(NamedTuple):
    """``C`` training-styled copies of each of ``N`` episodes.

    Attributes:
      frames: ``[N, C, T, H, W, 3]`` float32 in [0, 1] (or latents, from :func:`encode_styled_copies`).
      styles: :class:`Style` with leading dims ``[N, C]``.
      episode_ids: ``[N]`` the source episodes' ids.
      actions: ``[N, T, A]`` the source episodes' actions (shared by all copies).
    """

    frames: np.ndarray
    styles: Style
    episode_ids: np.ndarray
    actions: np.ndarray

    def flatten(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(frames [N*C, ...], actions [N*C, T, A], episode_ids [N*C])``, copy-major within an episode."""
        n, c = self.frames.shape[:2]
        return (
            self.frames.reshape(n * c, *self.frames.shape[2:]),
            np.repeat(self.actions, c, axis=0),
            np.repeat(self.episode_ids, c),
        )


def _copy_keys(key: jax.Array, episode_ids: np.ndarray, n_copies: int) -> jax.Array:
    # Keyed by episode id, not position: a copy's style does not depend on which other episodes are in the call.
    return jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.asarray(episode_ids, jnp.uint32))


@functools.partial(jax.jit, static_argnames=("n_copies", "classes", "fov_deg"))
def _style_episode(frames, depth, seg, episode_key, intensity, *, n_copies: int, classes: SegClasses, fov_deg: float):
    """``n_copies`` training styles of one episode: ``([C, T, H, W, 3], Style[C])``."""
    styles = sample_styles(episode_key, n_copies, "train")
    styled = augment_styles(frames, depth, seg, styles, intensity=intensity, classes=classes, fov_deg=fov_deg)
    return styled, styles


def _styled_copies(episodes, n_copies: int, key: jax.Array, keep: Callable, *, name: str, intensity: float,
                   classes: SegClasses, fov_deg: float) -> StyledCopies:
    """Styles each episode ``n_copies`` times, checks the styles are training styles and keeps
    ``keep(styled [C, T, H, W, 3] in [0, 1])`` per episode (only one episode's pixels alive at a time)."""
    if n_copies < 1:
        raise ValueError(f"{name}: n_copies must be >= 1, got {n_copies}")
    eps = as_episodes(episodes)
    keys = _copy_keys(key, eps.episode_ids, n_copies)
    style_one = functools.partial(_style_episode, intensity=jnp.float32(intensity), n_copies=n_copies,
                                  classes=classes, fov_deg=float(fov_deg))
    kept, styles = [], []
    for i in range(eps.num):
        styled, st = style_one(eps.frames[i], eps.depth[i], eps.seg[i], keys[i])
        assert_training_style(st)
        kept.append(np.asarray(keep(styled)))
        styles.append(st)
    styles = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *styles)
    return StyledCopies(np.stack(kept), styles, eps.episode_ids.copy(), eps.actions.copy())


def make_styled_copies(
    episodes: Episodes | dict,
    n_copies: int,
    key: jax.Array,
    *,
    intensity: float = 1.0,
    classes: SegClasses = DEFAULT_CLASSES,
    fov_deg: float = 45.0,
) -> StyledCopies:
    """Restyle every episode ``n_copies`` times in training styles (episode by episode, on device).

    Deterministic for ``key`` and each episode's id. The styles are checked with
    :func:`assert_training_style` before anything is returned.
    """
    return _styled_copies(episodes, n_copies, key, lambda styled: styled, name="make_styled_copies",
                          intensity=intensity, classes=classes, fov_deg=fov_deg)


def encode_styled_copies(
    episodes: Episodes | dict,
    n_copies: int,
    key: jax.Array,
    encode_fn: Callable[[Float[Array, "c t h w 3"]], jax.Array],
    *,
    intensity: float = 1.0,
    classes: SegClasses = DEFAULT_CLASSES,
    fov_deg: float = 45.0,
) -> StyledCopies:
    """Like :func:`make_styled_copies` but VAE-encodes each episode's copies at once, keeping only latents.

    ``encode_fn`` takes ``[C, T, H, W, 3]`` video in **[-1, 1]** (e.g.
    ``lambda v: vae_api.encode(graphdef, state, v)``) and returns ``[C, ...]`` latents; the
    returned ``frames`` field holds the latents ``[N, C, ...]``. Pixels of at most one episode's
    copies are alive at a time.
    """
    return _styled_copies(episodes, n_copies, key, lambda styled: encode_fn(to_signed_range(styled)),
                          name="encode_styled_copies", intensity=intensity, classes=classes, fov_deg=fov_deg)
