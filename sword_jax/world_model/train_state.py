"""The world-model train state: one pytree of arrays (+ a static graphdef), born sharded.

``TrainState`` holds the step, the trainable parameters and other model variables as plain
nested dicts (``nnx.to_pure_dict``), the optax state, optional EMA parameters, the optional DLB
latent cache and the first step whose loss was non-finite (-1 while none). It contains no ``nnx``
objects, so orbax saves it directly and ``jax.jit`` donates it whole.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx, struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from sword_jax import optim
from sword_jax import sharding as shd
from sword_jax.dlb import cache as dlb_cache
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model.config import TrainerConfig


@struct.dataclass
class TrainState:
    """Everything the train step reads and returns (a pytree of arrays)."""

    step: jax.Array  # int32 scalar
    params: dict
    buffers: dict  # non-trainable model variables (empty for the DiT)
    opt_state: Any
    ema_params: dict | None
    cache: dlb_cache.LatentCache | None
    first_nonfinite_step: jax.Array  # int32 scalar, -1 = none yet


def world_model_schedule(cfg: TrainerConfig) -> optax.Schedule:
    """Linear warmup from 0 to ``learning_rate`` over ``warmup_steps``, then constant or cosine decay."""
    return optim.learning_rate_schedule(cfg.learning_rate, warmup_steps=cfg.warmup_steps, kind=cfg.lr_schedule,
                                        total_steps=cfg.steps, end_fraction=cfg.lr_end_fraction)


def world_model_optimizer(cfg: TrainerConfig) -> optax.GradientTransformation:
    """Global-norm gradient clipping then AdamW on the warmup schedule."""
    return optim.make_optimizer(world_model_schedule(cfg), b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps,
                                weight_decay=cfg.weight_decay, grad_clip=cfg.grad_clip,
                                mu_dtype=None if cfg.adam_mu_dtype == "float32" else jnp.dtype(cfg.adam_mu_dtype))


def _replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def create_train_state(
    model_factory: Callable[[], nnx.Module],
    trainer_cfg: TrainerConfig,
    cache_cfg: CacheConfig,
    dataset_shape: Sequence[int] | None,
    mesh: Mesh,
    rules: Sequence = shd.DEFAULT_RULES,
) -> tuple[nnx.GraphDef, TrainState, TrainState]:
    """Creates the train state directly in its sharded layout.

    Args:
      model_factory: builds the world model; takes its randomness from inside (``nnx.Rngs(seed)``).
      trainer_cfg: optimiser and EMA settings.
      cache_cfg: DLB settings; the cache exists iff ``cache_cfg.enabled``.
      dataset_shape: ``(E, L, h, w, c)`` of the latent dataset (needed when the cache is enabled).
      mesh: device mesh; rules: logical -> mesh axis table.

    Returns:
      ``(graphdef, state, state_shardings)``; ``state_shardings`` mirrors ``state`` with
      ``NamedSharding`` leaves (for ``jax.jit`` in/out shardings and checkpoint restore).
    """
    graphdef, abstract_params, abstract_rest = nnx.split(shd.abstract_module(model_factory), nnx.Param, ...)
    param_shardings = shd.state_shardings(abstract_params, mesh, rules)
    rest_shardings = shd.state_shardings(abstract_rest, mesh, rules)

    def init_model():
        with nnx.use_eager_sharding(False):
            _, params, rest = nnx.split(model_factory(), nnx.Param, ...)
        return params, rest

    params, rest = jax.jit(init_model, out_shardings=(param_shardings, rest_shardings))()
    params, buffers = nnx.to_pure_dict(params), nnx.to_pure_dict(rest)
    param_sharding_tree = jax.tree.map(lambda a: a.sharding, params)
    buffer_sharding_tree = jax.tree.map(lambda a: a.sharding, buffers)

    tx = world_model_optimizer(trainer_cfg)
    abstract_opt = jax.eval_shape(tx.init, params)
    opt_shardings = optax.tree_map_params(
        tx, lambda _, sharding: sharding, abstract_opt, param_sharding_tree,
        transform_non_params=lambda _: _replicated(mesh),
    )
    opt_state = jax.jit(tx.init, out_shardings=opt_shardings)(params)
    ema_params = None
    if trainer_cfg.ema_decay > 0:
        ema_params = jax.jit(lambda p: jax.tree.map(jnp.copy, p), out_shardings=param_sharding_tree)(params)
    cache = cache_sharding = None
    if cache_cfg.enabled:
        if dataset_shape is None:
            raise ValueError("train state: the DLB cache is enabled but no dataset_shape was given")
        cache = dlb_cache.init_cache(cache_cfg, dataset_shape, mesh, rules)
        cache_sharding = dlb_cache.cache_shardings(dataset_shape, mesh, rules)
    scalar = shd.put(np.zeros((), np.int32), _replicated(mesh))
    state = TrainState(
        step=scalar,
        params=params,
        buffers=buffers,
        opt_state=opt_state,
        ema_params=ema_params,
        cache=cache,
        first_nonfinite_step=shd.put(np.full((), -1, np.int32), _replicated(mesh)),
    )
    shardings = TrainState(
        step=_replicated(mesh),
        params=param_sharding_tree,
        buffers=buffer_sharding_tree,
        opt_state=opt_shardings,
        ema_params=None if ema_params is None else param_sharding_tree,
        cache=cache_sharding,
        first_nonfinite_step=_replicated(mesh),
    )
    return graphdef, state, shardings
