"""Metric networks built and compiled once per process.

Building a metric network reads tens of MB of weights and its first call compiles it (most of an
evaluation's time on a small run). Both are cached here per weight key -- the metric, the LPIPS
backbone, every config field and environment variable that decides the weights -- so every
:class:`~sword_jax.metrics.suite.MetricSuite` and the ``score`` CLI in one process share them.
Forwards are split once (``nnx.split``) and ``jax.jit``-ed on the state; callers feed fixed-size
batches (:func:`batched`), so each input shape compiles once.

Nothing runs at import: the caches fill on first use.
"""

from __future__ import annotations

import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.flolpips import flow_weighted_lpips
from sword_jax.metrics.networks import SOURCES, MetricNetwork, build_i3d, build_inception, build_lpips
from sword_jax.metrics.preprocess import fvd_preprocess

_WEIGHT_FIELDS = ("lpips_weights", "lpips_lin_weights", "inception_weights", "i3d_weights",
                  "allow_random_weights", "allow_random_weights_for", "random_weights_seed")

# (metric, forward name) -> fn(module, *inputs); "fvd" forwards also take the I3D input resolution.
FORWARDS: dict[tuple[str, str], Callable] = {
    ("lpips", "distance"): lambda m, a, b: m(a, b)[0],  # inputs in [-1, 1]
    ("lpips", "distance01"): lambda m, a, b: m(a, b, normalize=True)[0],  # inputs in [0, 1]
    ("lpips", "flow_weighted"): flow_weighted_lpips,
    ("fid", "pool3"): lambda m, x: m(x),
}

_networks: dict[tuple, MetricNetwork] = {}
_forwards: dict[tuple, Callable] = {}


def _network_key(metric: str, config: EvalConfig, net: str | None) -> tuple:
    if metric == "lpips":
        net = net or config.lpips_net
    env = tuple(os.environ.get(source.env, "") for source in SOURCES.values())
    return (metric, net) + tuple(getattr(config, name) for name in _WEIGHT_FIELDS) + env


def network(metric: str, config: EvalConfig, *, net: str | None = None) -> MetricNetwork:
    """The built network of ``metric`` (``"lpips"``, ``"fid"``, ``"fvd"``), shared per process.

    Args:
      metric: which network.
      config: decides the weights (see :mod:`sword_jax.metrics.networks`).
      net: LPIPS backbone (default ``config.lpips_net``).
    """
    key = _network_key(metric, config, net)
    if key not in _networks:
        if metric == "lpips":
            _networks[key] = build_lpips(config, net=key[1])
        elif metric == "fid":
            _networks[key] = build_inception(config)
        elif metric == "fvd":
            _networks[key] = build_i3d(config)
        else:
            raise ValueError(f"no network for metric {metric!r}; known: lpips, fid, fvd")
    return _networks[key]


def forward(metric: str, name: str, config: EvalConfig, *, net: str | None = None) -> Callable:
    """The jitted forward ``name`` of :func:`network` ``(metric, config, net)``, shared per process.

    ``("fvd", "logits")`` is the FVD embedding of [0, 1] clips after the FVD resize/crop to
    ``config.fvd_resolution``; the other names are listed in :data:`FORWARDS`.
    """
    key = _network_key(metric, config, net) + (name, config.fvd_resolution if metric == "fvd" else None)
    if key not in _forwards:
        if (metric, name) == ("fvd", "logits"):
            resolution = config.fvd_resolution
            fn = lambda m, video: m(fvd_preprocess(video, resolution))  # noqa: E731
        elif (metric, name) in FORWARDS:
            fn = FORWARDS[(metric, name)]
        else:
            raise ValueError(f"no forward {name!r} for {metric!r}; known: {sorted(FORWARDS) + [('fvd', 'logits')]}")
        graphdef, state = nnx.split(network(metric, config, net=net).module)
        jitted = jax.jit(lambda state, *args: fn(nnx.merge(graphdef, state), *args))
        call = lambda *args: jitted(state, *args)  # noqa: E731
        call.jitted = jitted  # for trace-count checks
        _forwards[key] = call
    return _forwards[key]


def clear() -> None:
    """Drops every cached network and compiled forward (tests; freeing memory)."""
    _networks.clear()
    _forwards.clear()


def batched(fn: Callable, inputs: tuple[np.ndarray, ...], batch: int) -> np.ndarray:
    """Calls ``fn`` on chunks of exactly ``batch`` rows (the last one padded by repeating its last
    row, so one compilation per input shape) and concatenates the valid rows.

    Every chunk is dispatched before any result is read back, so copying the next chunk to the device
    overlaps the current one's compute."""
    n = inputs[0].shape[0]
    pending = []
    for start in range(0, n, batch):
        chunk = [x[start : start + batch] for x in inputs]
        valid = chunk[0].shape[0]
        if valid < batch:
            chunk = [np.concatenate([c, np.repeat(c[-1:], batch - valid, axis=0)]) for c in chunk]
        pending.append((fn(*[jnp.asarray(c) for c in chunk]), valid))
    return np.concatenate([np.asarray(out)[:valid] for out, valid in pending])
