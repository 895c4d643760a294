"""Named random streams: one root key (or seed) per run, one stream per use, found by name.

``stream_key(root, "styled_copies")`` folds a stable hash of the name (CRC-32, the same in every
process and Python version, unlike ``hash``) into the root key, so streams never collide by an
arithmetic accident (``seed + 7`` of one stage equal to ``seed`` of another) and adding a stream
changes no other. Host-side numpy draws use :func:`stream_rng` / :func:`stream_seed` the same way.
Inside a step keep the usual ``fold_in(stream, step)``: a resumed run then draws the same numbers.
"""

from __future__ import annotations

import zlib

import jax
import numpy as np


def stream_id(name: str) -> int:
    """The stable 32-bit id of a stream name (CRC-32 of its UTF-8 bytes)."""
    if not name:
        raise ValueError("stream_id: a stream needs a non-empty name")
    return zlib.crc32(name.encode("utf-8"))


def stream_key(root_key: jax.Array, name: str) -> jax.Array:
    """The key of stream ``name`` under ``root_key``: ``fold_in(root_key, crc32(name))``."""
    return jax.random.fold_in(root_key, stream_id(name))


def stream_rng(seed: int, name: str, *indices: int) -> np.random.Generator:
    """A numpy generator for stream ``name`` of ``seed``; ``indices`` (e.g. the step) pick sub-streams."""
    return np.random.default_rng([int(seed), stream_id(name), *(int(i) for i in indices)])


def stream_seed(seed: int, name: str, *indices: int) -> int:
    """A 31-bit integer seed for stream ``name`` of ``seed``, for APIs that take an int seed."""
    entropy = [int(seed), stream_id(name), *(int(i) for i in indices)]
    return int(np.random.SeedSequence(entropy).generate_state(1, np.uint32)[0] >> 1)
