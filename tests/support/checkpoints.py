"""Reading a finished run's checkpoint back as flat numpy arrays, on whatever devices this process has; and
comparing restored weights bit for bit."""

from __future__ import annotations

import os

import jax
import numpy as np

from sword_jax.checkpoint import read_arrays


def trees_equal(a, b) -> bool:
    """Two pytrees of arrays bit-identical: the same structure, shapes, dtypes and values."""
    flat_a, flat_b = jax.tree.leaves_with_path(a), jax.tree.leaves_with_path(b)
    return [p for p, _ in flat_a] == [p for p, _ in flat_b] and all(
        np.asarray(x).dtype == np.asarray(y).dtype and np.array_equal(np.asarray(x), np.asarray(y))
        for (_, x), (_, y) in zip(flat_a, flat_b, strict=True))


def final_arrays(workdir: str) -> tuple[dict[str, np.ndarray], dict]:
    """``({"/path/to/leaf": array}, meta)`` of the newest checkpoint in ``<workdir>/checkpoints``, on this
    process's first device whatever topology wrote it."""
    return read_arrays(os.path.join(workdir, "checkpoints"))


def assert_same_final_checkpoint(reference: str, other: str, steps: int) -> tuple[dict[str, np.ndarray], dict, dict]:
    """Both runs' newest checkpoints hold bit-identical arrays, ``steps`` steps and the same data position;
    returns ``(reference arrays, reference meta, other meta)`` for further checks."""
    want, want_meta = final_arrays(reference)
    got, got_meta = final_arrays(other)
    assert want.keys() == got.keys() and len(want) > 10
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert got_meta["step"] == want_meta["step"] == steps
    assert got_meta["data_position"] == want_meta["data_position"]
    return want, want_meta, got_meta
