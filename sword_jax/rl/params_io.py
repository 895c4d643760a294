"""Saving and restoring policy / reward-model parameters: orbax directories (pure dicts with the RL config),
or single ``.npz`` files (one array per parameter path, e.g. ``benchmarks.bench_policy``'s policies)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from flax import nnx

from sword_jax import checkpoint
from sword_jax.rl.config import RLConfig


def save_params(path: str, params: nnx.State, cfg: RLConfig, *, kind: str, step: int = 0, **meta: Any) -> None:
    """Writes ``params`` under ``path`` (an orbax directory) with the RL config in the metadata."""
    ckpt = checkpoint.Checkpointer(path, max_to_keep=1)
    ckpt.save(step, nnx.to_pure_dict(params), {"kind": kind, "rl": dataclasses.asdict(cfg), **meta})
    ckpt.close()


def load_params(path: str, params: nnx.State, *, kind: str) -> tuple[nnx.State, dict[str, Any]]:
    """Restores into the structure of ``params`` (a freshly built state); checks the checkpoint kind (an
    ``.npz`` file carries none: :func:`load_params_npz`)."""
    if path.endswith(".npz"):
        return load_params_npz(path, params), {"kind": kind, "format": "npz"}
    ckpt = checkpoint.Checkpointer(path)
    restored, meta = ckpt.restore(checkpoint.abstract_like(nnx.to_pure_dict(params)))
    ckpt.close()
    if meta.get("kind") != kind:
        raise ValueError(f"{path} holds a {meta.get('kind')!r} checkpoint, expected {kind!r}")
    nnx.replace_by_pure_dict(params, restored)
    return params, meta


def _paths(tree: dict, prefix: tuple = ()):
    for k, v in tree.items():
        if isinstance(v, dict):
            yield from _paths(v, prefix + (k,))
        else:
            yield prefix + (k,), v


def save_params_npz(path: str, params: nnx.State) -> None:
    """``params`` as one ``.npz`` file, an array per parameter path (``"layer/0/kernel"``)."""
    np.savez(path, **{"/".join(map(str, k)): np.asarray(v) for k, v in _paths(nnx.to_pure_dict(params))})


def load_params_npz(path: str, params: nnx.State) -> nnx.State:
    """Restores :func:`save_params_npz`'s file into the structure of ``params``.

    Raises:
      ValueError: a parameter missing from the file, or of another shape (another architecture).
    """
    pure = nnx.to_pure_dict(params)
    with np.load(path) as data:
        for key, old in _paths(pure):
            name = "/".join(map(str, key))
            if name not in data.files:
                raise ValueError(f"{path}: no parameter {name!r} (a file of another architecture?)")
            if data[name].shape != np.shape(old):
                raise ValueError(f"{path}: parameter {name!r} has shape {data[name].shape}, the model's {np.shape(old)}")
            node = pure
            for k in key[:-1]:
                node = node[k]
            node[key[-1]] = data[name]
    nnx.replace_by_pure_dict(params, pure)
    return params
