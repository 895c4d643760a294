"""Safetensors checkpoints as numpy (:func:`~sword_jax.metrics.torch_io.read_safetensors`), with the
constructor config from the metadata and the PyTorch -> JAX layout of each parameter.

The Wan 2.2 reference files store tensors under the official ``state_dict()`` key names and the
constructor arguments as JSON in the metadata field ``config``.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from sword_jax.checkpoint import CheckpointError
from sword_jax.metrics.torch_io import read_safetensors

__all__ = ["CheckpointError", "read_config", "read_safetensors", "torch_to_jax_layout"]


def read_config(metadata: dict[str, str], path: str) -> dict[str, Any]:
    """Parses the JSON constructor config stored under the metadata field ``config``."""
    if "config" not in metadata:
        raise CheckpointError(f"{path}: safetensors metadata has no 'config' field (keys: {sorted(metadata)})")
    try:
        config = json.loads(metadata["config"])
    except json.JSONDecodeError as err:
        raise CheckpointError(f"{path}: metadata 'config' is not valid JSON: {err}") from err
    if not isinstance(config, dict):
        raise CheckpointError(f"{path}: metadata 'config' must be a JSON object, got {type(config).__name__}")
    return config


def torch_to_jax_layout(name: str, array: np.ndarray, target_shape: tuple[int, ...]) -> np.ndarray:
    """Converts one PyTorch parameter to the JAX layout of a parameter of ``target_shape``.

    Conv3d ``[out, in, kt, kh, kw]`` -> ``[kt, kh, kw, in, out]``; Conv2d ``[out, in, kh, kw]`` ->
    ``[kh, kw, in, out]`` (or a 1x1 Conv2d -> dense ``[in, out]`` when the target is 2-D);
    Linear ``[out, in]`` -> ``[in, out]``; norm gammas ``[C, 1, ...]`` -> ``[C]``; biases as they are.

    Raises:
      CheckpointError: the shapes cannot correspond.
    """
    src = np.asarray(array)
    if src.ndim == 5 and len(target_shape) == 5:
        out = src.transpose(2, 3, 4, 1, 0)
    elif src.ndim == 4 and len(target_shape) == 4:
        out = src.transpose(2, 3, 1, 0)
    elif src.ndim == 4 and len(target_shape) == 2 and src.shape[2:] == (1, 1):
        out = src[:, :, 0, 0].T
    elif src.ndim == 2 and len(target_shape) == 2:
        out = src.T
    elif len(target_shape) == 1 and src.size == int(np.prod(target_shape)) and src.shape[0] == target_shape[0]:
        out = src.reshape(target_shape)
    else:
        raise CheckpointError(f"{name}: cannot map PyTorch shape {src.shape} to JAX shape {target_shape}")
    if tuple(out.shape) != tuple(target_shape):
        raise CheckpointError(
            f"{name}: shape {src.shape} (JAX layout {out.shape}) does not match the model's {tuple(target_shape)}"
        )
    return np.ascontiguousarray(out)
