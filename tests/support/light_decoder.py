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


def save_random_light_decoder(directory: str, cfg, seed: int = 0) -> nnx.State:
    """Random light-decoder weights for ``cfg``'s geometry, saved in ``directory`` as the pipeline's stage saves
    them (``sword_jax.load.load_light_decoder`` reads them back); returns the weights."""
    from sword_jax.pipeline.light_decoder import light_geometry, save_light_decoder
    from sword_jax.vae import light_decoder as light

    latent_size, frame_size = light_geometry(cfg)
    _, params = numpy_weights(lambda: light.LightDecoder(cfg.light_decoder, z_dim=cfg.vae.z_dim,
                                                         scale=frame_size // latent_size,
                                                         temporal_factor=cfg.vae.temporal_factor, rngs=nnx.Rngs(seed)),
                              seed=seed)
    save_light_decoder(str(directory), params, cfg)
    return params
