"""A retrace guard that belongs to one step function, not to the process.

``chex.assert_max_traces`` counts traces per *definition site* (call stack + source), so two runs
in one process -- ``train.compare`` calling the pipeline for every variant, a notebook re-running
an entry point -- each build their own step and together trip it. :func:`max_traces` counts the
traces of the one function it wraps.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax

# Entry points (and the runs the orchestration sets up for them) let a jitted step trace twice before
# the retrace guard fires. On the GPU image (jax 0.11.2) the VAE step traced a second time because avals there record the mesh of a jit's
# output sharding, so a state made outside such a jit changed type after one step; entry points now
# pass their state through ``sharding.settle`` first, and the margin of one trace is kept for type
# changes of that kind that the CPU tests (jax 0.10.2) cannot show. A step that retraces on every
# call still fails at its third trace, naming the function.
ENTRY_MAX_TRACES = 2


def _has_tracers(tree: Any) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(tree))


def max_traces(fn: Callable[..., Any], n: int) -> Callable[..., Any]:
    """Wraps ``fn`` (before ``jax.jit``) to raise a RuntimeError when it is traced more than ``n`` times."""
    if n < 1:
        raise ValueError(f"max_traces: n must be >= 1, got {n}")
    count = [0]

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        if _has_tracers((args, kwargs)):
            count[0] += 1
            if count[0] > n:
                raise RuntimeError(
                    f"{fn.__qualname__} was traced {count[0]} times (at most {n} allowed): an argument's shape, "
                    "dtype, weak type or pytree structure changed between calls; set JAX_EXPLAIN_CACHE_MISSES=1 "
                    "to see which")
        return fn(*args, **kwargs)

    return wrapped
