"""Weights for the light-decoder tests drawn without compiling an init: modules split from their abstract
shapes, arrays from numpy (one init program per weight shape costs seconds on a small CPU)."""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np
from flax import nnx

from sword_jax import sharding as shd


def numpy_weights(factory: Callable[[], nnx.Module], *, seed: int = 0, zeros: bool = False
                  ) -> tuple[nnx.GraphDef, nnx.State]:
    """``nnx.split(factory())`` with weights drawn by numpy: kernels (2-D and up) normal with std 1/sqrt(fan-in),
    norm scales (``gamma``, ``scale``) and standard deviations (``*std``) ones, every other vector 0; ``zeros``:
    every array 0 but those ones (for weights whose values a test never reads)."""
    graphdef, abstract = nnx.split(shd.abstract_module(factory))
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        name = jax.tree_util.keystr(path)
        if any(word in name for word in ("gamma", "'scale'", "std'")):
            return np.ones(leaf.shape, leaf.dtype)
        if leaf.ndim < 2 or zeros:
            return np.zeros(leaf.shape, leaf.dtype)
        return (rng.standard_normal(leaf.shape) / np.sqrt(np.prod(leaf.shape[:-1]))).astype(leaf.dtype)

    return graphdef, jax.tree_util.tree_map_with_path(draw, abstract)
