"""A success detector honest on imagined frames: real episodes replayed in the learned simulator with
their frames kept and labelled by the real outcome, the threshold calibrated on held-out replays, and
detector batches mixing real and imagined frames."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import data as rl_data
from sword_jax.rl import sim_agreement as sa
from sword_jax.rl.learned_simulator import instruction_target, toy_reward_model, toy_simulator
from sword_jax.rl.policy import tokenize_instructions


def _toy_traced(steps=24):
    """Four toy episodes from the origin: two move to their goal (0.6 away), two move away."""
    tokens = jnp.asarray(tokenize_instructions(["go left", "go right", "go up", "go down"], 16))
    targets = np.asarray(jax.vmap(instruction_target)(tokens))
    towards = targets / np.linalg.norm(targets, axis=1, keepdims=True)
    actions = np.zeros((4, steps, 7), np.float32)
    actions[:2, :, :2] = towards[:2, None] * 0.5  # 24 x 0.08 x 0.5 = 0.96: passes the goal
    actions[2:, :, :2] = -towards[2:, None] * 0.5
    lengths = np.array([steps, steps - 8, steps, steps]) + 4
    actions[1, steps - 8:] = 0.0
    return sa.TracedEpisodes(np.zeros((4, 5, 16, 16, 3), np.uint8), np.zeros((4, 5, 8), np.float32),
                             np.concatenate([np.zeros((4, 4, 7), np.float32), actions], axis=1), lengths,
                             np.array([True, False, False, True]), ("go left", "go right", "go up", "go down"))


def test_replayed_episodes_keep_the_imagined_frames_and_label_them_with_the_real_outcome():
    sim, detector = toy_simulator(frame_size=16, chunk_len=8), toy_reward_model()
    traced = _toy_traced()
    encode = lambda f, h: jnp.zeros((f.shape[0], 2, 1, 1, 4))  # noqa: E731 - the toy simulator reads no latents
    episodes, real_lengths = sa.replayed_episodes(traced, sim, detector, encode, success_threshold=0.9,
                                                  key=jax.random.key(0), batch=3, max_instruction_bytes=16,
                                                  settle_steps=2)
    np.testing.assert_array_equal(real_lengths, [24, 16, 24, 24])
    np.testing.assert_array_equal(episodes.lengths, real_lengths + 2)
    assert episodes.frames.dtype == np.uint8 and episodes.frames.shape == (4, 26, 16, 16, 3)
    np.testing.assert_array_equal(episodes.success, traced.success)
    # the kept frames are the replay's own (the toy world is noiseless: any key), rounded to uint8
    start, actions, _ = sa.replay_starts(traced, encode, max_instruction_bytes=16)
    replay = sa.replay_actions(sim, detector, start, jnp.asarray(np.pad(actions, ((0, 0), (0, 2), (0, 0)))),
                               jnp.asarray(real_lengths), success_threshold=0.9, key=jax.random.key(1),
                               settle_steps=2, record_frames=True)
    valid = np.arange(26)[None] < episodes.lengths[:, None]
    np.testing.assert_array_equal(episodes.frames[valid], np.asarray(replay.frames)[:, :26][valid])
    peak = np.asarray(replay.scores).max(axis=1)
    rescored = np.asarray(detector.score(jnp.asarray(episodes.frames[np.arange(4), np.argmax(replay.scores, 1)],
                                                     jnp.float32) / 255.0))
    np.testing.assert_allclose(rescored, peak, atol=0.05)  # the detector reads the kept frames as it read them
    labels = sa.replay_labels(episodes, real_lengths, positive_tail=3)
    # episode 0 (real success): frames 21..25 (last 3 actions + 2 settle) positive, earlier unlabelled
    assert labels[0].tolist() == [-1] * 21 + [1] * 5
    assert labels[1].tolist() == [0] * 18 + [-1] * 8  # a real failure: negative up to its end, then padding
    assert labels[3, 21:].tolist() == [1] * 5 and (labels[2] == 0).all()
    with pytest.raises(ValueError, match="positive_tail"):
        sa.replay_labels(episodes, real_lengths, positive_tail=0)


def test_decisive_scores_read_the_imagined_success_rule():
    scores = np.array([[0.1, 0.9, 0.2, 0.8, 0.85], [0.5, 0.6, 0.7, 0.95, 0.0]])
    np.testing.assert_allclose(sa.decisive_scores(scores, np.array([5, 3])), [0.9, 0.7])  # frame 3 of row 1 is past its end
    np.testing.assert_allclose(sa.decisive_scores(scores, np.array([5, 5]), success_frames=2), [0.8, 0.7])
    with pytest.raises(ValueError, match="decisive_scores"):
        sa.decisive_scores(scores, np.array([5]))


def _episodes_of(values: np.ndarray, lengths, success) -> rl_data.EpisodeSet:
    """Frames whose every pixel is the value a fake detector reads back."""
    e, t = values.shape
    frames = np.repeat(np.round(values * 255).astype(np.uint8)[:, :, None, None, None], 2, axis=2)
    frames = np.repeat(np.repeat(frames, 2, axis=3), 3, axis=4)
    return rl_data.EpisodeSet(frames=frames, actions=np.zeros((e, t, 7), np.float32), proprio=np.zeros((e, t, 8), np.float32),
                              lengths=np.asarray(lengths), success=np.asarray(success, bool),
                              instructions=("x",) * e)


def test_the_calibrated_threshold_bounds_false_success_on_the_calibration_replays():
    rng = np.random.default_rng(0)
    n, t = 80, 10
    success = np.arange(n) % 2 == 0
    peak = np.where(success, rng.uniform(0.6, 1.0, n), rng.uniform(0.0, 0.8, n))  # failures overlap successes
    values = np.tile(np.linspace(0.0, 1.0, t), (n, 1)) * peak[:, None]
    episodes = _episodes_of(values, np.full(n, t), success)
    calibrate = np.arange(n) < 40
    score = lambda frames: jnp.mean(frames, axis=(1, 2, 3)) / 255.0  # noqa: E731
    report = sa.calibrated_detector_report(score, episodes, np.full(n, t - 2), positive_tail=3, calibrate=calibrate,
                                           max_false_success=0.1)
    decisive = np.round(peak * 255) / 255
    cal_fail = decisive[calibrate & ~success]
    assert (cal_fail >= report["threshold"]).mean() <= 0.1 and report["calibration"]["false_success"]["rate"] <= 0.1
    # the lowest such threshold: one more failure would pass at the next lower failure score
    assert (cal_fail >= np.sort(cal_fail)[::-1][2]).mean() > 0.1
    held = ~calibrate
    assert report["held_out_episodes"] == 40
    assert report["held_out"]["false_success"]["rate"] == pytest.approx(
        float((decisive[held & ~success] >= report["threshold"]).mean()))
    assert 0.0 < report["frame_precision"] <= 1.0 and 0.0 < report["frame_recall"] <= 1.0
    with pytest.raises(ValueError, match="some but not all"):
        sa.calibrated_detector_report(score, episodes, np.full(n, t), positive_tail=3, calibrate=np.ones(n, bool))


def test_mixed_detector_batches_take_each_source_s_share_class_balanced():
    rng = np.random.default_rng(0)
    real = _episodes_of(np.zeros((3, 4)), [4, 4, 4], [True, False, False])
    imagined = _episodes_of(np.ones((2, 4)), [4, 4], [True, False])
    real_labels = np.array([[0, 0, 1, 1], [0, 0, 0, 0], [0, 0, 0, 0]])
    imagined_labels = np.array([[-1, -1, 1, 1], [0, 0, 0, -1]])
    batch = rl_data.sample_mixed_reward_batch([(real, real_labels, 0.25), (imagined, imagined_labels, 0.75)], 16, rng)
    from_imagined = batch["frames"][:, 0, 0, 0] == 255
    assert from_imagined.sum() == 12 and batch["labels"][from_imagined].sum() == 6  # balanced within the source
    assert batch["labels"][~from_imagined].sum() == 2
    with pytest.raises(ValueError, match="sum to 1"):
        rl_data.sample_mixed_reward_batch([(real, real_labels, 0.5)], 8, rng)
