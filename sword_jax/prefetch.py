"""Host batches made ahead of the training step, on one background thread.

A training loop whose batch is a pure function of the step (``make(step)``) can read it through
:func:`prefetched`: the batches arrive in step order and are the same arrays the loop would have
made itself, so exact resume is unchanged, but making batch ``s + 1`` (slicing episodes, restyling
clips, copying) overlaps the device's work on step ``s`` instead of waiting for it.
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")


def prefetched(make: Callable[[int], T], steps: Iterable[int], *, depth: int = 2) -> Iterator[T]:
    """``make(step)`` for each step in order, up to ``depth`` steps ahead on a background thread.

    An exception raised by ``make`` is raised here, at the step it belongs to. Closing the generator
    (or leaving the loop) stops the thread after the batches already started.

    Raises:
      ValueError: ``depth < 1``.
    """
    if depth < 1:
        raise ValueError(f"prefetch depth must be >= 1, got {depth}")
    steps = iter(steps)
    pending: collections.deque = collections.deque()
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="prefetch") as pool:
        try:
            for step in steps:
                pending.append(pool.submit(make, step))
                if len(pending) >= depth:
                    break
            while pending:
                batch = pending.popleft().result()
                for step in steps:
                    pending.append(pool.submit(make, step))
                    break
                yield batch
        finally:
            for future in pending:
                future.cancel()
