"""Named random streams (sword_jax.rng): stable, distinct per name, deterministic."""

import zlib

import jax
import numpy as np
import pytest

from sword_jax import rng


def test_stream_key_is_fold_in_of_the_names_crc32():
    root = jax.random.key(3)
    expected = jax.random.fold_in(root, zlib.crc32(b"grpo/starts"))
    np.testing.assert_array_equal(jax.random.key_data(rng.stream_key(root, "grpo/starts")),
                                  jax.random.key_data(expected))
    # a process-independent id (Python's str hash is salted per process; CRC-32 is not)
    assert rng.stream_id("grpo/starts") == 0xF71DD609  # pinned: changing the hash would move every stream


def test_streams_differ_by_name_and_repeat_by_name():
    root = jax.random.key(0)
    draws = {name: np.asarray(jax.random.uniform(rng.stream_key(root, name), (4,)))
             for name in ("data/train_episodes", "data/heldout_episodes", "augment/styled_copies")}
    assert len({d.tobytes() for d in draws.values()}) == 3
    np.testing.assert_array_equal(draws["data/train_episodes"],
                                  np.asarray(jax.random.uniform(rng.stream_key(root, "data/train_episodes"), (4,))))
    a, b = rng.stream_rng(5, "grpo/keyframes", 7).random(3), rng.stream_rng(5, "grpo/keyframes", 7).random(3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, rng.stream_rng(5, "grpo/keyframes", 8).random(3))
    assert not np.array_equal(a, rng.stream_rng(5, "grpo/env_starts", 7).random(3))
    seeds = {rng.stream_seed(0, name) for name in ("data/train_episodes", "data/heldout_episodes", "data/policy_demos")}
    assert len(seeds) == 3 and all(0 <= s < 2**31 for s in seeds)
    assert rng.stream_seed(0, "data/policy_demos") == rng.stream_seed(0, "data/policy_demos")
    with pytest.raises(ValueError, match="name"):
        rng.stream_key(root, "")
