"""VAE training clips: raw frames plus frames restyled in *training* styles (never held-out ones).

The world model's augmentation arm feeds it training-styled latents, and LIBERO-Mixed scores
held-out-styled frames through the same VAE. A VAE that only ever saw raw frames adds its own
reconstruction error on styled frames to *both* arms of the augmentation comparison and can hide
the effect, so the VAE trains on raw plus training-styled clips (``vae.train_styles``).

Held-out styles cannot reach the VAE from here: styles are drawn with
``sample_styles(..., "train")`` and checked on the host with
:func:`~sword_jax.augment.style.assert_training_style` before any pixel is restyled; held-out
*episodes* (``init_split == "heldout"``) are refused when the clips are built from simulator data.

Clips are cut on the host from uint8 episodes (a pure function of the step: exact resume), then
restyled on device by one jitted :func:`~sword_jax.augment.transforms.augment_batch`. In a job of
several processes each one cuts and restyles only the rows of a batch its devices hold
(:class:`VideoLoader`); every draw is made for the whole batch, so a row is the same whichever process makes it.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from sword_jax.augment.style import DEFAULT_CLASSES, SegClasses, Style, assert_training_style, sample_styles
from sword_jax import sharding as shd
from sword_jax.augment.transforms import augment_batch
from sword_jax.rng import stream_key, stream_rng


class VAEClips(NamedTuple):
    """Training episodes for the VAE (host arrays; lengths may differ).

    Attributes:
      frames: per episode ``[T, H, W, 3]`` uint8.
      depth: per episode ``[T, H, W]`` float32 metres, or ``None`` (no styled clips possible).
      seg: per episode ``[T, H, W]`` integer class map, or ``None``.
    """

    frames: list[np.ndarray]
    depth: list[np.ndarray] | None
    seg: list[np.ndarray] | None

    @property
    def can_style(self) -> bool:
        return self.depth is not None and self.seg is not None


def clips_from_sim(episodes: Sequence, *, name: str = "episodes") -> VAEClips:
    """From ``sim.dataset.Episode`` objects; refuses held-out episodes (evaluation data).

    Raises:
      ValueError: an episode comes from the ``heldout`` initial-state split.
    """
    held_out = [i for i, e in enumerate(episodes) if getattr(e, "init_split", "") == "heldout"]
    if held_out:
        raise ValueError(f"{name}: episodes {held_out[:10]} start from held-out initial states; "
                         "the VAE trains on training episodes only")
    frames = [np.asarray(e.agentview_rgb, np.uint8) for e in episodes]
    geometry = all(e.agentview_depth is not None and e.agentview_seg is not None for e in episodes)
    depth = [np.asarray(e.agentview_depth, np.float32) for e in episodes] if geometry else None
    seg = [np.asarray(e.agentview_seg, np.int32) for e in episodes] if geometry else None
    return VAEClips(frames, depth, seg)


def _cut(video: np.ndarray, start: int, frames: int) -> np.ndarray:
    if video.shape[0] < frames:  # short episodes repeat their last frame
        video = np.concatenate([video, np.repeat(video[-1:], frames - video.shape[0], axis=0)])
    return video[start:start + frames]


def sample_clips(clips: VAEClips, batch: int, frames: int, rng: np.random.Generator, *, with_geometry: bool,
                 rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``(frames uint8 [R, T, H, W, 3], depth [R, T, H, W] | None, seg | None)`` at random episodes/offsets.

    The episode and offset of all ``batch`` clips are drawn; only ``rows`` of them (default: all, ``R = batch``)
    are cut, so a row is the same whichever rows are cut.
    """
    picks = []
    for index in rng.integers(0, len(clips.frames), batch):
        length = max(clips.frames[index].shape[0], frames)
        picks.append((int(index), int(rng.integers(0, length - frames + 1))))
    if rows is not None:
        picks = [picks[row] for row in rows]
    video = np.stack([_cut(clips.frames[i], s, frames) for i, s in picks])
    if not with_geometry:
        return video, None, None
    depth = np.stack([_cut(clips.depth[i], s, frames) for i, s in picks])
    seg = np.stack([_cut(clips.seg[i], s, frames) for i, s in picks])
    return video, depth, seg


def training_styles(key: jax.Array, num: int) -> Style:
    """``num`` training styles, checked on the host (raises ``HeldOutStyleError`` otherwise)."""
    styles = jax.device_get(sample_styles(key, num, "train"))
    assert_training_style(styles)
    return styles


@functools.partial(jax.jit, static_argnames=("classes", "fov_deg"))
def restyle(frames: Float[Array, "b t h w 3"], depth: Float[Array, "b t h w"], seg: Array, styles: Style,
            styled: Array, *, intensity: float | Array = 1.0, classes: SegClasses = DEFAULT_CLASSES,
            fov_deg: float = 45.0) -> Float[Array, "b t h w 3"]:
    """Restyles the clips where ``styled [B]`` is set; the others pass through bit-exactly. Output in [0, 1]."""
    out = augment_batch(frames, depth, seg, styles, intensity=intensity, classes=classes, fov_deg=fov_deg)
    return jnp.where(styled[:, None, None, None, None], out, frames)


class ClipSampler:
    """``batch(step) -> [B, T, H, W, 3]`` float32 in [-1, 1]: raw clips, a ``styled_fraction`` share of them
    restyled in training styles. A pure function of ``(seed, step)``.

    Args:
      clips: the training episodes.
      batch, frames: clips per batch and frames per clip.
      seed: the run's seed.
      styled_fraction: share of clips restyled (0 = raw only).
      intensity, classes, fov_deg: of the restyling (``augment`` config).
    """

    def __init__(self, clips: VAEClips, *, batch: int, frames: int, seed: int, styled_fraction: float = 0.0,
                 intensity: float = 1.0, classes: SegClasses = DEFAULT_CLASSES, fov_deg: float = 45.0):
        if styled_fraction > 0 and not clips.can_style:
            raise ValueError("VAE styled clips need agentview depth and segmentation in the episodes "
                             "(record them, or set --vae.train_styles=false)")
        self.clips, self.batch_size, self.frames, self.seed = clips, batch, frames, seed
        self.styled_fraction, self.intensity = float(styled_fraction), float(intensity)
        self.classes, self.fov_deg = classes, float(fov_deg)
        self.styled_clips = 0  # running count, for the run summary
        self.first_batch_seconds: dict[str, float] = {}  # clip sampling and restyling of the first batch (compile in it)

    def batch(self, step: int, rows: np.ndarray | None = None) -> np.ndarray:
        """Rows ``rows`` (default: all) of step ``step``'s batch, ``[R, T, H, W, 3]`` float32 in [-1, 1].

        Only those rows are cut and restyled; the draws (clips, which are styled, styles) are the whole
        batch's, and ``styled_clips`` counts the whole batch's styled clips.
        """
        first = not self.first_batch_seconds
        start = time.perf_counter()
        rng = stream_rng(self.seed, "vae/clips", step)
        styling = self.styled_fraction > 0
        video, depth, seg = sample_clips(self.clips, self.batch_size, self.frames, rng, with_geometry=styling,
                                         rows=rows)
        unit = video.astype(np.float32) / np.float32(255.0)
        sampled = time.perf_counter()
        if styling:
            styled = rng.random(self.batch_size) < self.styled_fraction
            if styled.any():
                key = jax.random.fold_in(stream_key(jax.random.key(self.seed), "vae/styles"), step)
                styles = training_styles(key, self.batch_size)  # all checked, whichever rows are restyled here
                held = np.arange(self.batch_size) if rows is None else np.asarray(rows)
                if styled[held].any():
                    unit = np.asarray(restyle(unit, depth, seg, jax.tree.map(lambda x: x[held], styles), styled[held],
                                              intensity=np.float32(self.intensity), classes=self.classes,
                                              fov_deg=self.fov_deg))
                self.styled_clips += int(styled.sum())
        if first:  # what a slow first batch waited on: the sampling, or the restyling's compile on the device
            self.first_batch_seconds = {"sample": sampled - start, "restyle": time.perf_counter() - sampled}
        return unit * np.float32(2.0) - np.float32(1.0)


class VideoLoader(shd.RowLoader):
    """The VAE's batches in a job of one or several processes: :meth:`host_batch_at` makes only the rows of a
    step's batch that this process's devices hold (``rows``), :meth:`place` assembles the global
    ``{"video": [B, T, H, W, 3]}`` from every process's rows (:class:`sword_jax.sharding.RowLoader`).

    Args:
      rows_at: ``rows_at(step, rows) -> [len(rows), T, H, W, 3]`` float32, those rows of the 0-based step's
        batch; a pure function of both (exact resume), each row the same whichever rows are asked for.
      batch_size: the global batch size ``B``.
      mesh, rules: the rows are split over the mesh axes of the ``batch`` logical axis, as the VAE step's input.
      devices: whose rows to make (default: this process's devices).

    Raises:
      ValueError: ``batch_size`` does not split evenly over the devices the rows are sharded over.
    """

    def __init__(self, rows_at: Callable[[int, np.ndarray], np.ndarray], batch_size: int, mesh: jax.sharding.Mesh,
                 rules=shd.DEFAULT_RULES, *, devices: Sequence[jax.Device] | None = None):
        super().__init__(rows_at, batch_size, mesh, rules, field="video", ndim=5, name="vae.batch_size",
                         devices=devices)
