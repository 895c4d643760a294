"""Saving and restoring policy / reward-model parameters (orbax, as pure dicts) with their RL config."""

from __future__ import annotations

import dataclasses
from typing import Any

from flax import nnx

from sword_jax import checkpoint
from sword_jax.rl.config import RLConfig


def save_params(path: str, params: nnx.State, cfg: RLConfig, *, kind: str, step: int = 0, **meta: Any) -> None:
    """Writes ``params`` under ``path`` (an orbax directory) with the RL config in the metadata."""
    ckpt = checkpoint.Checkpointer(path, max_to_keep=1)
    ckpt.save(step, nnx.to_pure_dict(params), {"kind": kind, "rl": dataclasses.asdict(cfg), **meta})
    ckpt.close()


def load_params(path: str, params: nnx.State, *, kind: str) -> tuple[nnx.State, dict[str, Any]]:
    """Restores into the structure of ``params`` (a freshly built state); checks the checkpoint kind."""
    ckpt = checkpoint.Checkpointer(path)
    restored, meta = ckpt.restore(checkpoint.abstract_like(nnx.to_pure_dict(params)))
    ckpt.close()
    if meta.get("kind") != kind:
        raise ValueError(f"{path} holds a {meta.get('kind')!r} checkpoint, expected {kind!r}")
    nnx.replace_by_pure_dict(params, restored)
    return params, meta
