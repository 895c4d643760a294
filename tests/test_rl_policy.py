"""Policy text conditioning via behaviour cloning, action binning, and the success detector."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import data as rl_data
from sword_jax.rl.policy import (actions_to_tokens, build_policy, greedy_chunk, policy_logits, tokenize_instructions,
                                 tokens_to_actions)
from sword_jax.rl.reward_model import as_reward_model, build_detector, make_detector_step
from sword_jax.rl.sft import make_sft_step
from tests.support.rl import POLICY_CFG, TEXTS, brightening_episodes


def test_tokenizer_and_binning():
    tok = tokenize_instructions(TEXTS, 48)
    assert tok.shape == (2, 48) and tok.dtype == np.int32 and not np.array_equal(tok[0], tok[1])
    with pytest.raises(ValueError, match="non-empty"):
        tokenize_instructions([""], 8)
    actions = jnp.linspace(-1.0, 1.0, 33)
    back = tokens_to_actions(actions_to_tokens(actions, 256), 256)
    assert float(jnp.max(jnp.abs(back - actions))) <= 1.0 / 256 + 1e-6


def test_policy_distinguishes_instructions_by_text():
    """Same frame and proprio, two instructions, opposite expert actions: BC must separate them."""
    graphdef, params = build_policy(POLICY_CFG, seed=0)
    init, step = make_sft_step(graphdef, POLICY_CFG, total_steps=60)
    state = init(params)
    frames = np.full((8, 8, 8, 3), 0.5, np.float32)
    tokens = tokenize_instructions([TEXTS[i % 2] for i in range(8)], 48)
    sign = np.where(np.arange(8) % 2 == 0, 0.6, -0.6).astype(np.float32)
    actions = np.broadcast_to(sign[:, None, None], (8, 8, 7)).copy()
    batch = {"frames": frames, "instruction_tokens": tokens, "proprio": np.zeros((8, 4), np.float32), "actions": actions}
    for _ in range(60):
        state, metrics = step(state, batch, jax.random.key(0))
    assert float(metrics["token_accuracy"]) > 0.9
    # jitted: eager op-by-op dispatch compiles each of the forward pass's ops on its own, several times slower
    logits = jax.jit(lambda p, f, t, q: policy_logits(graphdef, p, f, t, q))(
        state.params, jnp.asarray(frames[:2]), jnp.asarray(tokens[:2]), jnp.zeros((2, 4)))
    acts = np.asarray(tokens_to_actions(greedy_chunk(logits), POLICY_CFG.action_bins))
    np.testing.assert_allclose(acts[0], 0.6, atol=0.1)
    np.testing.assert_allclose(acts[1], -0.6, atol=0.1)


def test_policy_rejects_bad_shapes():
    graphdef, params = build_policy(POLICY_CFG, seed=0)
    tok = jnp.asarray(tokenize_instructions(TEXTS, 48))
    with pytest.raises(ValueError, match="frames"):
        policy_logits(graphdef, params, jnp.zeros((2, 16, 16, 3)), tok, jnp.zeros((2, 4)))
    with pytest.raises(ValueError, match="proprio"):
        policy_logits(graphdef, params, jnp.zeros((2, 8, 8, 3)), tok, jnp.zeros((2, 3)))


def test_success_labels_and_detector_learns():
    episodes = brightening_episodes()
    labels = rl_data.success_labels(episodes, positive_tail=3)
    np.testing.assert_array_equal(labels[0], [0] * 9 + [1] * 3)
    np.testing.assert_array_equal(labels[2], 0)
    graphdef, params = build_detector(POLICY_CFG)
    init, step = make_detector_step(graphdef, POLICY_CFG)
    state = init(params)
    rng = np.random.default_rng(0)
    for _ in range(80):
        state, metrics = step(state, rl_data.sample_reward_batch(episodes, labels, 16, rng), jax.random.key(1))
    scores = np.asarray(as_reward_model(graphdef, state.params).score(jnp.asarray(episodes.frames[0])))
    assert np.all((scores >= 0) & (scores <= 1))
    assert scores[-1] > 0.8 and scores[0] < 0.2, scores


def _sim_episode(text, rewards):
    from types import SimpleNamespace

    t = len(rewards)
    return SimpleNamespace(agentview_rgb=np.zeros((t, 8, 8, 3), np.uint8), actions=np.zeros((t, 7)),
                           ee_states=np.zeros((t, 6)), gripper_states=np.zeros((t, 2)),
                           rewards=np.asarray(rewards, float), num_samples=t, language_instruction=text)


def test_state_labels_mark_the_frames_that_show_a_solved_state():
    # rewards[t] = solved after action t, so frame t + 1 is the first to show it; solved, undone, solved again.
    rewards = [0, 0, 1, 1, 0, 0, 1, 0]
    eps = rl_data.from_sim_episodes([_sim_episode(TEXTS[0], rewards), _sim_episode(TEXTS[1], [0] * 6)],
                                    stop_at_success=False)
    np.testing.assert_array_equal(eps.frame_success[0], [0, 0, 0, 1, 1, 0, 0, 1])
    np.testing.assert_array_equal(rl_data.success_labels(eps, 3, "state")[0], [0, 0, 0, 1, 1, 0, 0, 1])
    np.testing.assert_array_equal(rl_data.success_labels(eps, 3, "state")[1], [0] * 6 + [-1] * 2)
    # The tail labels of the same episode read up to its first success mark only frames before it.
    cut = rl_data.from_sim_episodes([_sim_episode(TEXTS[0], rewards)], stop_at_success=True)
    assert cut.lengths.tolist() == [3] and not cut.frame_success[0, :3].any()
    np.testing.assert_array_equal(rl_data.success_labels(cut, 2, "tail")[0], [0, 1, 1])
    assert eps.subset(np.array([1])).frame_success.shape == (1, 8)
    with pytest.raises(ValueError, match="source must be one of"):
        rl_data.success_labels(eps, 3, "end")
    with pytest.raises(ValueError, match="frame_success"):
        rl_data.success_labels(brightening_episodes(), 3, "state")
    with pytest.raises(ValueError, match=r"rl\.reward_model\.labels"):
        dataclasses.replace(POLICY_CFG, reward_model=dataclasses.replace(POLICY_CFG.reward_model, labels="last")).validate()


def test_detector_report_reads_scores_as_the_rollout_rule_does():
    from sword_jax.rl.reward_model import detector_report

    # Episode 0 solved from frame 6, episode 1 never, episode 2 ends at its success (no solved frame shown),
    # episode 3 solved from frame 2 and never fired on.
    solved = np.zeros((4, 10), bool)
    solved[0, 6:] = True
    solved[3, 2:4] = True
    eps = rl_data.EpisodeSet(np.zeros((4, 10, 4, 4, 3), np.uint8), np.zeros((4, 10, 7), np.float32),
                             np.zeros((4, 10, 4), np.float32), np.array([10, 10, 5, 4]),
                             np.array([True, False, True, True]), tuple(TEXTS) * 2, solved)
    scores = np.zeros((4, 10))
    scores[0, 1] = 0.95  # fires 5 frames early
    scores[0, 6:] = 0.95
    scores[1, 3] = 0.99  # a false success
    scores[2, 4] = 0.99  # fires on an episode whose solved frame is never shown: frame metrics only
    scores[3, 5] = 0.99  # past the episode's end: ignored -> a miss
    report = detector_report(scores, eps, 0.9)
    assert report["frame_precision"] == 4 / 7 and report["frame_recall"] == 4 / 6
    assert (report["episodes_succeeded"], report["episodes_failed"], report["episodes_unobserved"]) == (2, 1, 1)
    assert report["fires_on_failed"] == 1.0 and report["fires_early"] == 0.5 and report["misses"] == 0.5
    assert report["mean_lead_frames"] == 5.0
    with pytest.raises(ValueError, match="scores must be"):
        detector_report(scores[:2], eps, 0.9)


def test_detector_report_applies_the_consecutive_frames_rule():
    from sword_jax.rl.reward_model import detector_report

    # Episode 0 fails with a one-frame spike; episode 1 is solved from frame 5 and scores high from frame 4.
    solved = np.zeros((2, 10), bool)
    solved[1, 5:] = True
    eps = rl_data.EpisodeSet(np.zeros((2, 10, 4, 4, 3), np.uint8), np.zeros((2, 10, 7), np.float32),
                             np.zeros((2, 10, 4), np.float32), np.array([10, 10]), np.array([False, True]),
                             tuple(TEXTS), solved)
    scores = np.zeros((2, 10))
    scores[0, 3] = 0.99
    scores[1, 4:] = 0.95
    one, two = detector_report(scores, eps, 0.9), detector_report(scores, eps, 0.9, success_frames=2)
    assert one["fires_on_failed"] == 1.0 and two["fires_on_failed"] == 0.0
    # k=1 fires on frames 3 (ep 0) and 4..9 (ep 1); k=2 on frames 5..9 of episode 1 only, all solved
    assert one["frame_precision"] == 5 / 7 and two["frame_precision"] == 1.0 and two["frame_recall"] == 1.0
    assert one["mean_lead_frames"] == 1.0 and two["mean_lead_frames"] == 0.0
    four = detector_report(scores, eps, 0.9, success_frames=4)
    assert four["frame_recall"] == 3 / 5 and four["misses"] == 0.0
    assert detector_report(scores, eps, 0.9, success_frames=11)["misses"] == 1.0
    with pytest.raises(ValueError, match="success_frames"):
        detector_report(scores, eps, 0.9, success_frames=0)


def test_load_episodes_reads_every_file_with_the_given_reader():
    from types import SimpleNamespace

    def episode(text, t, success_at):
        rewards = np.zeros(t)
        rewards[success_at:] = 1
        task = TEXTS.index(text)
        return SimpleNamespace(agentview_rgb=np.zeros((t, 8, 8, 3), np.uint8), actions=np.zeros((t, 7)),
                               ee_states=np.zeros((t, 6)), gripper_states=np.zeros((t, 2)), rewards=rewards,
                               num_samples=t, language_instruction=text, task_id=task,
                               states=np.arange(t * 3, dtype=np.float64).reshape(t, 3) + 100 * task)

    files = {"a.hdf5": [episode(TEXTS[0], 6, 3)], "b.hdf5": [episode(TEXTS[1], 5, 9), episode(TEXTS[0], 4, 1)]}
    read = []
    episodes = rl_data.load_episodes(["a.hdf5", "b.hdf5"], read=lambda path: (read.append(path), files[path]))
    assert read == ["a.hdf5", "b.hdf5"]
    assert episodes.instructions == (TEXTS[0], TEXTS[1], TEXTS[0])
    assert episodes.lengths.tolist() == [4, 5, 2] and episodes.success.tolist() == [True, False, True]
    assert episodes.proprio.shape == (3, 5, 8)
    # the recorded states (padded as the rest: the last kept step repeats) and task ids come along
    assert episodes.tasks.tolist() == [0, 1, 0] and episodes.states.shape == (3, 5, 3)
    np.testing.assert_array_equal(episodes.states[0], np.concatenate([np.arange(12).reshape(4, 3)] + [[[9, 10, 11]]]))
    np.testing.assert_array_equal(episodes.subset(np.array([1])).states[0], np.arange(15).reshape(5, 3) + 100)
    with pytest.raises(ValueError, match=r"read=sim\.dataset\.read_dataset"):
        rl_data.load_episodes(["a.hdf5"])


def test_the_detector_reads_its_own_frame_size_and_refuses_a_checkpoint_of_another(tmp_path):
    """rl.reward_model.image_size sets the size the detector resizes every frame to (scoring and training), apart
    from the policy's; a detector saved at one size is refused by a config that reads another (its weights fit
    any size, so nothing else would notice)."""
    from sword_jax.rl.config import RewardModelConfig
    from sword_jax.rl.params_io import save_params
    from sword_jax.rl.policy import resize_frames
    from sword_jax.rl.reward_model import load_detector

    big = dataclasses.replace(POLICY_CFG, reward_model=dataclasses.replace(POLICY_CFG.reward_model, image_size=16))
    assert POLICY_CFG.detector_image_size == 8 and big.detector_image_size == 16 and big.image_size == 8
    graphdef, params = build_detector(big, seed=0)
    score = jax.jit(as_reward_model(graphdef, params).score)
    frames = jnp.asarray(np.random.default_rng(0).uniform(0, 1, (3, 32, 32, 3)), jnp.float32)
    np.testing.assert_allclose(score(frames), score(resize_frames(frames, 16)), rtol=1e-6, atol=1e-6)
    assert not np.allclose(score(frames), score(resize_frames(frames, 8)), atol=1e-4)
    init, step = make_detector_step(graphdef, big)  # training reads the same size (the step donates its state)
    labels = jnp.asarray([1.0, 0.0, 1.0])
    trained = [step(init(build_detector(big, seed=0)[1]), {"frames": f, "labels": labels}, jax.random.key(0))[1]["loss"]
               for f in (frames, resize_frames(frames, 16), resize_frames(frames, 8))]
    assert float(trained[0]) == pytest.approx(float(trained[1]), abs=1e-6) and float(trained[0]) != pytest.approx(
        float(trained[2]), abs=1e-6)
    path = str(tmp_path / "detector")
    save_params(path, params, big, kind="reward_model")
    _, loaded = load_detector(path, big)
    np.testing.assert_array_equal(jax.tree.leaves(loaded)[0], jax.tree.leaves(params)[0])
    with pytest.raises(ValueError, match="trained on 16 px frames, this config's reads 8 px"):
        load_detector(path, POLICY_CFG)
    with pytest.raises(ValueError, match="rl.reward_model.image_size must be 0"):
        RewardModelConfig(image_size=12).validate()


def test_the_reward_stage_reports_true_success_under_the_runs_consecutive_frames_rule():
    """sim.reward_training.holdout_report reads the detector's scores as the run's imagined-success rule does: a
    one-frame spike on a failed episode is a false success at k = 1, not at k = 2."""
    from sim.reward_training import holdout_report

    episodes = brightening_episodes()
    solved = np.zeros((4, 12), bool)
    solved[:2, 9:] = True  # the successes are solved over their last 3 frames
    episodes = dataclasses.replace(episodes, frame_success=solved)

    def score(frames):  # bright frames (the successes' last ones) score 1, and so does the failures' last frame
        level = jnp.mean(frames.astype(jnp.float32), axis=(1, 2, 3))
        return jnp.where((level > 180) | ((level > 80) & (level < 90)), 1.0, 0.0)

    reports = {k: holdout_report(score, episodes, dataclasses.replace(
        POLICY_CFG, imagined=dataclasses.replace(POLICY_CFG.imagined, success_frames=k)))["true_success"]
        for k in (1, 2)}
    assert reports[1]["fires_on_failed"] == 1.0 and reports[2]["fires_on_failed"] == 0.0
    assert reports[1]["misses"] == reports[2]["misses"] == 0.0
