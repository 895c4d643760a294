"""The latent dataset of world-model training: pre-encoded episodes, segments and a resumable sampler.

Episodes are encoded once by the VAE to ``latents [E, L, h, w, c]`` (latent frame 0 = video frame 0,
latent frame ``j >= 1`` = video frames ``4j-3 .. 4j``) with ``actions [E, T, a]``, one per video
frame, ``T = 1 + 4 (L - 1)``. A training segment is addressed by ``(episode, start)`` where
``start`` is the latent-frame index of its first context latent; with ``k`` context and ``p``
future latents it holds

* latents ``[latents[e, 0], latents[e, start : start + k + p]]`` (``1 + k + p`` frames),
* actions ``[actions[e, 0], actions[e, 4 start - 3 : 4 (start + k + p - 1) + 1]]`` (``1 + 4(k + p)``).

The DLB cache indexes the same ``(episode, latent frame)`` slots. The sampler is a pure function
of ``(seed, epoch, index)``; that position is its whole state, so checkpoints resume exactly. With a
fixed batch size the position after ``s`` batches is a function of ``s`` alone, so the batch of a
step can also be made directly (:meth:`SegmentSampler.indices_at`, :meth:`SegmentLoader.host_batch_at`).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh

from sword_jax import sharding as shd


@dataclasses.dataclass(frozen=True)
class LatentDataset:
    """Pre-encoded episodes held on the host.

    Attributes:
      latents: ``[E, L, h, w, c]`` float32 (normalised VAE latents).
      actions: ``[E, 1 + 4 (L - 1), a]`` float32.
    """

    latents: np.ndarray
    actions: np.ndarray

    def __post_init__(self):
        if self.latents.ndim != 5:
            raise ValueError(f"latent dataset: latents must be [E, L, h, w, c], got {self.latents.shape}")
        if self.actions.ndim != 3:
            raise ValueError(f"latent dataset: actions must be [E, T, a], got {self.actions.shape}")
        num_episodes, num_latents = self.latents.shape[:2]
        expected = (num_episodes, 1 + 4 * (num_latents - 1))
        if self.actions.shape[:2] != expected:
            raise ValueError(
                f"latent dataset: actions shape {self.actions.shape} does not match {num_latents} latent frames "
                f"(expected [{expected[0]}, {expected[1]}, a]: one action per video frame)"
            )
        if not (np.all(np.isfinite(self.latents)) and np.all(np.isfinite(self.actions))):
            raise ValueError("latent dataset: latents or actions contain NaN/inf")

    @property
    def shape(self) -> tuple[int, ...]:
        """``(E, L, h, w, c)``: the slot layout the DLB cache mirrors."""
        return tuple(self.latents.shape)

    def segment(self, episodes: np.ndarray, starts: np.ndarray, num_context: int, num_future: int) -> dict[str, np.ndarray]:
        """Host batch of segments (see the module docstring) for index arrays ``episodes``/``starts``."""
        num_latents = self.latents.shape[1]
        if np.any(starts < 1) or np.any(starts + num_context + num_future > num_latents):
            raise ValueError(f"latent dataset: segment starts {starts} out of range for {num_latents} latent frames")
        span = num_context + num_future
        frame_idx = starts[:, None] + np.arange(span)[None, :]
        latents = np.concatenate([self.latents[episodes, :1], self.latents[episodes[:, None], frame_idx]], axis=1)
        action_idx = 4 * starts[:, None] - 3 + np.arange(4 * span)[None, :]
        actions = np.concatenate([self.actions[episodes, :1], self.actions[episodes[:, None], action_idx]], axis=1)
        return {
            "latents": latents.astype(np.float32),
            "actions": actions.astype(np.float32),
            "episode": episodes.astype(np.int32),
            "start": starts.astype(np.int32),
        }


def load_latent_dataset(path: str) -> LatentDataset:
    """Reads ``latents`` and ``actions`` from a ``.npz`` or ``.h5``/``.hdf5`` file."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"latent dataset: {path} does not exist")
    try:
        if path.endswith(".npz"):
            with np.load(path) as data:
                latents, actions = np.asarray(data["latents"]), np.asarray(data["actions"])
        elif path.endswith((".h5", ".hdf5")):
            import h5py

            with h5py.File(path, "r") as data:
                latents, actions = np.asarray(data["latents"]), np.asarray(data["actions"])
        else:
            raise ValueError(f"latent dataset: {path} is neither .npz nor .h5/.hdf5")
    except KeyError as err:
        raise ValueError(f"latent dataset: {path} lacks the array {err} (needs 'latents' and 'actions')") from None
    except OSError as err:
        raise ValueError(f"latent dataset: cannot read {path}: {err}") from None
    return LatentDataset(latents.astype(np.float32), actions.astype(np.float32))


def load_sources(path: str, num_episodes: int) -> np.ndarray | None:
    """The ``sources`` array of a latents ``.npz`` (one entry per episode: 0 the expert's, 1 a rollout of the
    supervised policy, 2 an episode of the expert with exploration noise, or a styled copy of one, as the pipeline's
    latents stage writes it), or None where the file holds none."""
    if not path.endswith(".npz"):
        return None
    with np.load(path) as data:
        if "sources" not in data.files:
            return None
        sources = np.asarray(data["sources"])
    if sources.shape != (num_episodes,) or not np.isin(sources, (0, 1, 2)).all():
        raise ValueError(f"latent dataset: {path}'s sources must be {num_episodes} values of 0 (expert), 1 "
                         f"(policy rollout) or 2 (exploring expert), one per episode; got shape {sources.shape}")
    return sources


# the held-out file's optional second split: held-out rollouts of the supervised policy, under these arrays
POLICY_ARRAYS = ("policy_latents", "policy_actions")


def load_heldout_splits(path: str) -> dict[str, LatentDataset]:
    """The held-out evaluation's episodes in ``path`` (``.npz``): ``{"heldout": latents/actions}`` and, where
    the file holds ``policy_latents``/``policy_actions`` (the pipeline's held-out rollouts of the supervised
    policy, ``data.heldout_policy_rollouts_per_task``), ``"policy"`` from them."""
    splits = {"heldout": load_latent_dataset(path)}
    if path.endswith(".npz"):
        with np.load(path) as data:
            present = [k for k in POLICY_ARRAYS if k in data.files]
            if len(present) == 1:
                raise ValueError(f"latent dataset: {path} holds {present[0]} without its pair "
                                 f"({' and '.join(POLICY_ARRAYS)} go together)")
            if present:
                splits["policy"] = LatentDataset(np.asarray(data[POLICY_ARRAYS[0]], np.float32),
                                                 np.asarray(data[POLICY_ARRAYS[1]], np.float32))
    return splits


def synthetic_latent_dataset(
    num_episodes: int, num_latents: int, height: int, width: int, channels: int, *, seed: int, action_dim: int = 7
) -> LatentDataset:
    """Episodes whose latent motion depends on the actions (for tests and smoke runs).

    ``z[j] = 0.8 z[j-1] + A(mean action of latent j's 4 frames) + shift_x(z[j-1]) * gate`` where the
    gate and the linear map ``A`` come from the actions, so the future is predictable only from them.
    """
    rng = np.random.default_rng(seed)
    num_frames = 1 + 4 * (num_latents - 1)
    actions = rng.uniform(-1.0, 1.0, (num_episodes, num_frames, action_dim)).astype(np.float32)
    mixing = rng.normal(0.0, 0.5, (action_dim, channels)).astype(np.float32)
    pattern = rng.normal(0.0, 1.0, (height, width, 1)).astype(np.float32)
    latents = np.zeros((num_episodes, num_latents, height, width, channels), np.float32)
    latents[:, 0] = rng.normal(0.0, 1.0, (num_episodes, height, width, channels))
    for j in range(1, num_latents):
        chunk_action = actions[:, 4 * j - 3 : 4 * j + 1].mean(axis=1)  # (E, a)
        drive = (chunk_action @ mixing)[:, None, None, :] * pattern[None]
        gate = (chunk_action[:, 0] > 0).astype(np.float32)[:, None, None, None]
        moved = np.roll(latents[:, j - 1], 1, axis=2)
        latents[:, j] = 0.8 * (gate * moved + (1.0 - gate) * latents[:, j - 1]) + drive
    return LatentDataset(latents, actions)


class SegmentSampler:
    """Deterministic, resumable sampler of ``(episode, start)`` segments.

    Each epoch visits every valid segment once in an order drawn from ``(seed, epoch)``; batches run
    on across epoch boundaries. ``position`` (epoch, index) is the whole state.
    """

    def __init__(self, num_episodes: int, num_latents: int, num_context: int, num_future: int, batch_size: int,
                 *, seed: int):
        max_start = num_latents - num_context - num_future
        if max_start < 1:
            raise ValueError(
                f"segment sampler: {num_latents} latent frames cannot hold 1 + {num_context} + {num_future} latents"
            )
        starts = np.arange(1, max_start + 1)
        self.slots = np.stack(np.meshgrid(np.arange(num_episodes), starts, indexing="ij"), -1).reshape(-1, 2)
        self.batch_size = batch_size
        self.seed = seed
        self.epoch = 0
        self.index = 0
        self._order = self._permutation(0)
        self._order_at: tuple[int, np.ndarray] = (0, self._order)  # indices_at's last epoch (one per step)

    def _permutation(self, epoch: int) -> np.ndarray:
        return np.random.default_rng([self.seed, epoch]).permutation(len(self.slots))

    @property
    def position(self) -> dict[str, int]:
        return {"epoch": int(self.epoch), "index": int(self.index)}

    def restore(self, position: dict[str, Any]) -> None:
        epoch, index = int(position["epoch"]), int(position["index"])
        if epoch < 0 or not 0 <= index <= len(self.slots):
            raise ValueError(f"segment sampler: invalid position {position} for {len(self.slots)} segments")
        self.epoch, self.index = epoch, index
        self._order = self._permutation(epoch)

    def position_at(self, step: int) -> dict[str, int]:
        """The ``position`` after ``step`` batches from the start (what ``next_indices`` leaves it at)."""
        taken = step * self.batch_size
        epoch, index = divmod(taken, len(self.slots))
        if taken and not index:  # next_indices moves to the next epoch only when it needs a segment from it
            epoch, index = epoch - 1, len(self.slots)
        return {"epoch": int(epoch), "index": int(index)}

    def indices_at(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """``(episodes [B], starts [B])`` of batch ``step`` (0-based): the batch ``next_indices`` returns
        after ``step`` earlier calls from the start, made without the sampler's position."""
        taken = step * self.batch_size + np.arange(self.batch_size)
        epochs, index = np.divmod(taken, len(self.slots))
        order = np.empty(self.batch_size, np.int64)
        for epoch in np.unique(epochs).tolist():
            if self._order_at[0] != epoch:
                self._order_at = (epoch, self._permutation(epoch))
            picked = epochs == epoch
            order[picked] = self._order_at[1][index[picked]]
        slots = self.slots[order]
        return slots[:, 0].astype(np.int32), slots[:, 1].astype(np.int32)

    def next_indices(self) -> tuple[np.ndarray, np.ndarray]:
        """The next batch's ``(episodes [B], starts [B])``."""
        picked, count = [], 0
        while count < self.batch_size:
            if self.index >= len(self.slots):
                self.epoch, self.index = self.epoch + 1, 0
                self._order = self._permutation(self.epoch)
            take = min(self.batch_size - count, len(self.slots) - self.index)
            picked.append(self._order[self.index : self.index + take])
            self.index += take
            count += take
        slots = self.slots[np.concatenate(picked)]
        return slots[:, 0].astype(np.int32), slots[:, 1].astype(np.int32)


def batch_shardings(mesh: Mesh, batch: dict[str, np.ndarray], rules=shd.DEFAULT_RULES) -> dict[str, Any]:
    """Shards every batch field over its leading (``batch``) axis; replicated if not divisible."""
    return {
        name: shd.logical_sharding(mesh, ("batch",) + (None,) * (value.ndim - 1), rules, value.shape)
        for name, value in batch.items()
    }


class SegmentLoader:
    """Yields sharded global batches of segments; ``position`` / ``restore`` checkpoint it.

    Each process reads from the dataset only the rows of a batch that its devices hold (``rows``); the
    global array is assembled from every process's rows.

    Raises:
      ValueError: the sampler's batch size does not split evenly over the devices the rows are sharded over
        (naming ``data.batch_size``, the devices, the mesh and the processes); replicating it instead would
        have every device compute the whole batch and every process read all of it.
    """

    def __init__(self, dataset: LatentDataset, sampler: SegmentSampler, num_context: int, num_future: int,
                 mesh: Mesh, rules=shd.DEFAULT_RULES):
        self.dataset, self.sampler = dataset, sampler
        self.num_context, self.num_future = num_context, num_future
        self.mesh, self.rules = mesh, rules
        shd.check_batch_divides(shd.batch_sharding(mesh, 1, rules), sampler.batch_size, "data.batch_size")
        example = dataset.segment(*sampler.slots[:1].T.astype(np.int32), num_context, num_future)
        example = {k: np.repeat(v, sampler.batch_size, axis=0) for k, v in example.items()}
        self.shardings = batch_shardings(mesh, example, rules)
        # the rows of each batch this process's devices hold: the only rows it reads from the dataset
        self.rows = shd.rows_held(self.shardings["episode"], sampler.batch_size)

    @property
    def position(self) -> dict[str, int]:
        return self.sampler.position

    def restore(self, position: dict[str, Any]) -> None:
        self.sampler.restore(position)

    def next(self) -> dict[str, jax.Array]:
        return self.place(self._held(*self.sampler.next_indices()))

    def host_batch_at(self, step: int) -> dict[str, np.ndarray]:
        """This process's rows (``rows``) of the batch of step ``step`` (0-based), a pure function of it (see
        ``SegmentSampler.indices_at``); on one process, the whole batch."""
        return self._held(*self.sampler.indices_at(step))

    def _held(self, episodes: np.ndarray, starts: np.ndarray) -> dict[str, np.ndarray]:
        return self.dataset.segment(episodes[self.rows], starts[self.rows], self.num_context, self.num_future)

    def place(self, batch: dict[str, np.ndarray]) -> dict[str, jax.Array]:
        """This process's rows of a batch (:meth:`host_batch_at`) -> global arrays with this loader's shardings."""
        return shd.to_global(batch, self.shardings, self.rows, self.sampler.batch_size)
