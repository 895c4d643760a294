"""Inference weights in the compute dtype: half the parameter memory, the same outputs.

A model built with ``compute_dtype='bfloat16'`` and float32 parameters (the training layout) casts
each matmul's weights to bfloat16 at every call. For inference the cast can happen once:
:func:`store_in_compute_dtype` stores, in their layer's compute dtype, exactly the weights that are
only ever used cast to it (the kernels, biases and embeddings of Flax's ``Linear``,
``LinearGeneral``, ``Einsum``, ``Conv``, ``ConvTranspose`` and ``Embed`` layers whose ``dtype`` is a
16-bit float), so every output is bit-identical; everything a layer reads in float32 (norm scales,
AdaLN modulation tables, custom parameters such as the DiT's patch embedding) is left as it is.
For the 5B world model this halves the ~20 GB of float32 weights an imagined rollout holds.

    wm_state = store_in_compute_dtype(wm_graphdef, wm_state)   # then world_model_simulator(...) as before
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

CAST_LAYERS = (nnx.Linear, nnx.LinearGeneral, nnx.Einsum, nnx.Conv, nnx.ConvTranspose, nnx.Embed)
CAST_PARAMS = ("kernel", "bias", "embedding")


def _low_precision(dtype: Any) -> bool:
    return dtype is not None and jnp.issubdtype(jnp.dtype(dtype), jnp.floating) and jnp.dtype(dtype).itemsize < 4


def store_in_compute_dtype(graphdef: nnx.GraphDef, state: Any) -> Any:
    """``state`` with each 16-bit-compute layer's weights stored in that dtype (module docstring);
    the model ``nnx.merge(graphdef, new_state)`` gives bit-identical outputs. ``state`` is what
    ``nnx.merge`` takes after the graphdef: one ``nnx.State`` or pure dict, or a tuple of them (e.g. a
    loaded world model's ``(params, buffers)``); the result has the same layout. Arrays keep their
    sharding; ``state`` itself is not modified."""
    states = state if isinstance(state, tuple) else (state,)
    model = nnx.merge(graphdef, *states)  # read only: its layers' dtypes and paths
    cast = {}  # path of each weight stored in its layer's compute dtype -> that dtype
    for path, node in nnx.iter_graph(model):
        if not isinstance(node, CAST_LAYERS) or not _low_precision(getattr(node, "dtype", None)):
            continue
        for name in CAST_PARAMS:
            param = getattr(node, name, None)
            if isinstance(param, nnx.Param) and param.get_value() is not None:
                cast[(*path, name)] = node.dtype

    def store(path, leaf):
        names = tuple(k.key for k in path if isinstance(k, jax.tree_util.DictKey))
        return leaf.astype(cast[names]) if names in cast else leaf

    stored = tuple(jax.tree_util.tree_map_with_path(store, s) for s in states)
    return stored if isinstance(state, tuple) else stored[0]


def parameter_bytes(state: nnx.State) -> int:
    """Bytes of a state's arrays."""
    return sum(int(x.size) * x.dtype.itemsize for x in jax.tree.leaves(state) if hasattr(x, "dtype"))
