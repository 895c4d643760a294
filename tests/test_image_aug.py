"""sword_jax.rl.image_aug (``rl.sft.image_aug``): each jitter does what it names, draws per image and keeps
frames in [0, 1]; the SFT step uses it on the training batch only when the option is on."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import image_aug as aug
from sword_jax.rl.config import GRPOConfig, PolicyConfig, RLConfig, SFTConfig
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.sft import make_sft_step


def test_jitter_is_per_image_in_range_and_reproducible():
    frames = jnp.asarray(np.random.default_rng(0).random((6, 16, 16, 3)), jnp.float32)
    a = aug.augment_frames(frames, jax.random.key(0))
    assert a.shape == frames.shape and a.dtype == jnp.float32
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    np.testing.assert_array_equal(a, aug.augment_frames(frames, jax.random.key(0)))
    assert not np.allclose(a, aug.augment_frames(frames, jax.random.key(1)))
    same = jnp.repeat(frames[:1], 6, axis=0)  # one image six times: six different draws
    out = np.asarray(aug.augment_frames(same, jax.random.key(2)))
    assert len({out[i].tobytes() for i in range(6)}) == 6
    with pytest.raises(ValueError, match="frames must be"):
        aug.augment_frames(frames[0], jax.random.key(0))


def test_colour_jitter_acts_around_the_mean_and_the_grey_axis():
    """A flat grey image has no contrast, saturation or hue to change: only its brightness moves, by at most the
    delta; the hue rotation keeps luma and undoes itself; saturation 0 would be grey."""
    grey = jnp.full((32, 8, 8, 3), 0.5, jnp.float32)
    out = np.asarray(aug.augment_frames(grey, jax.random.key(3)))
    for image in out:
        np.testing.assert_allclose(image, image[0, 0, 0], atol=1e-5)  # still flat and grey
    assert np.all(np.abs(out[:, 0, 0, 0] - 0.5) <= aug.BRIGHTNESS + 1e-5)
    assert np.ptp(out[:, 0, 0, 0]) > 0.2  # the brightness really moves
    colour = jnp.asarray(np.random.default_rng(1).random((2, 4, 4, 3)), jnp.float32)
    turned = aug.rotate_hue(colour, jnp.asarray([0.05, -0.05]))
    luma = jnp.asarray(aug.LUMA)
    np.testing.assert_allclose(turned @ luma, colour @ luma, atol=1e-5)
    assert not np.allclose(turned, colour, atol=1e-3)
    np.testing.assert_allclose(aug.rotate_hue(turned, jnp.asarray([-0.05, 0.05])), colour, atol=1e-5)


def test_shift_moves_a_point_by_at_most_the_shift_with_edges_repeated():
    assert aug.shift_pixels(64) == 4 and aug.shift_pixels(8) == 1
    image = jnp.zeros((1, 16, 16, 3), jnp.float32).at[0, 8, 8].set(1.0)
    s = aug.shift_pixels(16)
    for dy in range(2 * s + 1):
        for dx in (0, 2 * s):
            moved = np.asarray(aug.shift(image, jnp.asarray([[dy, dx]]), s))[0, ..., 0]
            assert moved.sum() == 1.0 and tuple(np.argwhere(moved)[0]) == (8 + s - dy, 8 + s - dx)
    np.testing.assert_array_equal(aug.shift(image, jnp.asarray([[s, s]]), s), image)  # the centre is no move
    ramp = jnp.broadcast_to(jnp.arange(16, dtype=jnp.float32)[None, :, None, None] / 15, (1, 16, 16, 3))
    np.testing.assert_array_equal(np.asarray(aug.shift(ramp, jnp.asarray([[0, 0]]), s))[0, :s + 1, 0, 0], 0.0)


def test_the_sft_step_augments_only_when_asked():
    cfg = RLConfig(image_size=8, action_bins=8, chunk_len=4, proprio_dim=4,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16, proprio_encoding="raw"),
                   grpo=GRPOConfig(group_size=2, ppo_epochs=1))
    graphdef, params = build_policy(cfg, seed=0)
    rng = np.random.default_rng(0)
    batch = {"frames": rng.random((4, 8, 8, 3), np.float32),
             "instruction_tokens": tokenize_instructions(["pick", "place", "open", "close"], 16),
             "proprio": rng.random((4, 4), np.float32), "actions": rng.uniform(-1, 1, (4, 4, 7)).astype(np.float32)}

    def losses(config):  # the first step's loss, twice from the same start
        init, step = make_sft_step(graphdef, config, total_steps=2)
        first, metrics = step(init(jax.tree.map(jnp.copy, params)), batch, jax.random.key(0))
        # the second start placed as the step placed the first (an unplaced one would compile the step again)
        again = jax.device_put(init(jax.tree.map(jnp.copy, params)), jax.tree.map(lambda x: x.sharding, first))
        return [float(metrics["loss"]), float(step(again, batch, jax.random.key(0))[1]["loss"])]

    plain, augmented = losses(cfg), losses(dataclasses.replace(cfg, sft=dataclasses.replace(cfg.sft, image_aug=True)))
    assert plain[0] == plain[1] and augmented[0] == augmented[1]
    assert augmented[0] != plain[0]
    with pytest.raises(ValueError, match="rl.sft.image_aug must be true or false"):
        SFTConfig(image_aug="yes").validate()
