"""Replaying real episodes in a learned simulator: the trace, the start layout, the replay and the agreement."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import sim_agreement as sa
from sword_jax.rl.config import EnvConfig, GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.env_rollout import make_act_fns, run_policy
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState, instruction_target
from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import build_policy, tokenize_instructions


class _StepEnvs:
    """Lockstep envs whose frame shows the number of actions executed; episode i succeeds after
    ``solve_at[i]`` actions. Records the action blocks it is given."""

    def __init__(self, solve_at, max_steps: int):
        self.solve_at, self.max_steps = np.asarray(solve_at), max_steps
        self.n = len(self.solve_at)
        self.language = [f"task {i}" for i in range(self.n)]
        self.blocks, self.received = [], [[] for _ in range(self.n)]

    def _obs(self):
        frames = np.broadcast_to(self.steps[:, None, None, None].astype(np.uint8), (self.n, 8, 8, 3)).copy()
        proprio = np.repeat(self.steps[:, None].astype(np.float32), 8, axis=1)
        return {"frames": frames, "proprio": proprio}

    def reset(self):
        self.steps, self.done = np.zeros(self.n, np.int64), np.zeros(self.n, bool)
        self.received = [[] for _ in range(self.n)]
        return self._obs()

    def step(self, actions):
        self.blocks.append(actions.shape[1])
        success, executed = np.zeros(self.n, bool), np.zeros(self.n, np.int64)
        for i in np.flatnonzero(~self.done):
            for j in range(actions.shape[1]):
                if self.steps[i] >= self.max_steps:
                    break
                self.received[i].append(actions[i, j].copy())
                self.steps[i] += 1
                executed[i] += 1
                if self.steps[i] >= self.solve_at[i]:
                    success[i] = True
                    break
        self.done |= success | (self.steps >= self.max_steps)
        return dict(self._obs(), success=success, executed=executed, done=self.done.copy())

    def close(self):
        pass


def _policy(execute_steps=3):
    cfg = RLConfig(image_size=8, action_bins=16,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16),
                   env=EnvConfig(execute_steps=execute_steps, action_ensemble=False))
    graphdef, params = build_policy(cfg, seed=0)
    return cfg, make_act_fns(graphdef, cfg), params


def test_trace_records_the_head_frame_by_frame_and_every_executed_action_without_changing_the_episodes():
    cfg, act, params = _policy(execute_steps=3)
    plain, traced_envs = _StepEnvs([2, 9, 100], 20), _StepEnvs([2, 9, 100], 20)
    a = run_policy(act, params, plain, cfg, key=jax.random.key(0), greedy=False, max_steps=20)
    trace = sa.EpisodeTrace(4)
    b = run_policy(act, params, traced_envs, cfg, key=jax.random.key(0), greedy=False, max_steps=20, trace=trace)
    # the same episodes: outcomes, tokens and every action each env executed
    np.testing.assert_array_equal(a.success, b.success)
    np.testing.assert_array_equal(a.tokens, b.tokens)
    for x, y in zip(plain.received, traced_envs.received):
        np.testing.assert_array_equal(np.stack(x), np.stack(y))
    # the head (4 actions) was stepped one action at a time, the rest of its decision at once, then blocks of 3
    assert traced_envs.blocks[:5] == [1, 1, 1, 1, 2] and set(traced_envs.blocks[5:]) == {3}
    assert set(plain.blocks) == {3}
    out = trace.result()
    assert out.frames.shape == (3, 5, 8, 8, 3) and out.proprio.shape == (3, 5, 8)
    # frame j shows j actions executed (the episode solved after 2 holds its last frame)
    np.testing.assert_array_equal(out.frames[:, :, 0, 0, 0], [[0, 1, 2, 2, 2], [0, 1, 2, 3, 4], [0, 1, 2, 3, 4]])
    np.testing.assert_array_equal(out.lengths, [2, 9, 20])
    np.testing.assert_array_equal(out.success, [True, True, False])
    for i, received in enumerate(traced_envs.received):
        np.testing.assert_array_equal(out.actions[i, : out.lengths[i]], np.stack(received))
        assert not out.actions[i, out.lengths[i]:].any()
    assert out.language == ("task 0", "task 1", "task 2")


def test_replay_starts_lay_out_the_real_history_as_grpo_keyframes_do():
    n, t, a = 2, 12, 7
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 255, (n, 5, 4, 4, 3)).astype(np.uint8)
    actions = rng.normal(size=(n, t, a)).astype(np.float32)
    traced = sa.TracedEpisodes(frames, rng.normal(size=(n, 5, 8)).astype(np.float32), actions, np.array([12, 3]),
                               np.array([True, False]), ("a", "b"))
    seen = {}

    def encode(first, history):
        seen["first"], seen["history"] = np.asarray(first), np.asarray(history)
        return jnp.zeros((n, 2, 1, 1, 4))

    start, rest, lengths = sa.replay_starts(traced, encode, num_context=1, frames_per_latent=4, proprio_dim=8)
    np.testing.assert_allclose(seen["first"] * 255, frames[:, 0], atol=1e-3)
    # the 8 frames up to frame 4, the oldest clamped at frame 0
    np.testing.assert_allclose(seen["history"] * 255, frames[:, [0, 0, 0, 0, 1, 2, 3, 4]], atol=1e-3)
    np.testing.assert_allclose(np.asarray(start.frame) * 255, frames[:, 4], atol=1e-3)
    np.testing.assert_allclose(start.proprio, traced.proprio[:, 4])
    np.testing.assert_array_equal(np.asarray(start.latents[1]), actions[:, [0, 1, 2, 3, 4]])  # a_0, then a_1..a_4
    np.testing.assert_array_equal(rest, actions[:, 4:])
    np.testing.assert_array_equal(lengths, [8, -1])
    with pytest.raises(ValueError, match="head holds 2 steps"):
        sa.replay_starts(traced._replace(frames=frames[:, :3], proprio=traced.proprio[:, :3]), encode)


def _summing_simulator(chunk_len: int, execute_len: int) -> LearnedSimulator:
    """State = running sum of action dim 0; each executed action's frame shows the sum after it."""

    def init_fn(params, start):
        return start.proprio[0]

    def step_fn(params, state, chunk, key):
        sums = state + jnp.cumsum(chunk[:execute_len, 0])
        return sums[-1], jnp.broadcast_to(sums[:, None, None, None], (execute_len, 2, 2, 3))

    return LearnedSimulator(params={}, init_fn=init_fn, step_fn=step_fn, observe_fn=lambda p, s: (jnp.zeros(2), 0.0),
                            chunk_len=chunk_len, frame_size=2, execute_len=execute_len)


@pytest.mark.parametrize("chunk_len, execute_len", [(8, 8), (8, 4)])
def test_replay_executes_each_action_once_and_scores_the_frame_after_it(chunk_len, execute_len):
    sim = _summing_simulator(chunk_len, execute_len)
    detector = RewardModel(params={}, score_fn=lambda p, frames: frames[:, 0, 0, 0])
    actions = np.zeros((3, 13, 7), np.float32)
    actions[:, :, 0] = 0.1
    actions[1, :, 0] = -0.1
    lengths = np.array([13, 13, 5])
    start = StartState(jnp.zeros((3, 2, 2, 3)), jnp.zeros((3, 8)), jnp.zeros((3, 4), jnp.int32))
    out = jax.jit(lambda s, a, n: sa.replay_actions(sim, detector, s, a, n, success_threshold=0.75,
                                                    key=jax.random.key(0)))(start, actions, lengths)
    expected = np.cumsum(actions[:, :, 0], axis=1) * (np.arange(13)[None] < lengths[:, None])
    np.testing.assert_allclose(out.scores, expected, atol=1e-6)
    # 0.8 >= 0.75 is first reached after action 8 (index 7); episode 2 stopped after 5 actions
    np.testing.assert_array_equal(out.success, [True, False, False])
    np.testing.assert_array_equal(out.first_success, [7, -1, -1])


def _lagging_simulator(chunk_len: int, execute_len: int, lag: int = 2) -> LearnedSimulator:
    """State = the running sums of action dim 0; each frame shows the sum ``lag`` actions earlier
    (a world model whose scene catches up with the actions a little late); channel 1 shows the
    executed action's gripper command."""

    def init_fn(params, start):
        return jnp.zeros(lag + 1)

    def step_fn(params, state, chunk, key):
        def one(hist, action):
            hist = jnp.concatenate([hist[:1] + action[0], hist[:-1]])
            return hist, jnp.stack([hist[-1], action[sa.GRIPPER], 0.0])

        state, shown = jax.lax.scan(one, state, chunk[:execute_len])
        return state, jnp.broadcast_to(shown[:, None, None, :], (execute_len, 2, 2, 3))

    return LearnedSimulator(params={}, init_fn=init_fn, step_fn=step_fn, observe_fn=lambda p, s: (jnp.zeros(2), 0.0),
                            chunk_len=chunk_len, frame_size=2, execute_len=execute_len)


def test_settle_steps_hold_the_arm_and_let_a_late_scene_show_the_success():
    """A real episode ended at the action that reached success; in a world model whose scene lags
    two actions behind, its replay shows the success only after that action. The settle window
    scores a few more frames, driven by hold actions (zero deltas, the last gripper command)."""
    sim = _lagging_simulator(chunk_len=8, execute_len=4)
    detector = RewardModel(params={}, score_fn=lambda p, frames: frames[:, 0, 0, 0])
    gripper = RewardModel(params={}, score_fn=lambda p, frames: frames[:, 0, 0, 1])
    actions = np.zeros((2, 16, 7), np.float32)
    actions[:, :8, 0] = 0.1  # the running sum reaches 0.8 >= 0.75 at action 8 (index 7)
    actions[:, :8, sa.GRIPPER] = -0.5
    actions[:, 8:, 0] = 5.0  # what lies beyond the episode's end in the array must not be executed
    lengths = np.array([8, 16])
    start = StartState(jnp.zeros((2, 2, 2, 3)), jnp.zeros((2, 8)), jnp.zeros((2, 4), jnp.int32))

    def replay(settle, model=detector):
        return jax.jit(lambda s, a, n: sa.replay_actions(sim, model, s, a, n, success_threshold=0.75, key=jax.random.key(0),
                                                         settle_steps=settle))(start, actions, lengths)

    late = replay(0)
    np.testing.assert_array_equal(late.success, [False, True])  # the 8-action episode ends before its scene shows it
    settled = replay(3)
    np.testing.assert_array_equal(settled.success, [True, True])
    np.testing.assert_array_equal(settled.first_success, [9, 9])  # index 9: two actions after index 7
    # hold actions: the sum stays at 0.8 (no motion, not the 5.0 in the array) for exactly 3 scored frames
    np.testing.assert_allclose(np.asarray(settled.scores[0, 8:11]), [0.7, 0.8, 0.8], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(settled.scores[0, 11:]), 0.0)
    np.testing.assert_allclose(np.asarray(replay(3, gripper).scores[0, :11]), -0.5, atol=1e-6)  # the last gripper command
    with pytest.raises(ValueError, match="settle_steps"):
        replay(-1)
    # rl.imagined.success_frames = 3: episode 0 shows success on 2 scored frames (9, 10) only; episode 1
    # from index 9 to its end
    strict = jax.jit(lambda s, a, n, k: sa.replay_actions(sim, detector, s, a, n, success_threshold=0.75, key=k,
                                                          settle_steps=3, success_frames=3))(start, actions, lengths,
                                                                                             jax.random.key(0))
    np.testing.assert_array_equal(strict.success, [False, True])
    np.testing.assert_array_equal(strict.first_success, [-1, 11])  # the third frame of the run that starts at 9
    with pytest.raises(ValueError, match=r"rl\.imagined\.eval_replay_settle_steps"):
        RLConfig(imagined=ImaginedConfig(eval_replay_settle_steps=-1)).validate()


def test_replay_in_the_toy_world_tells_reaching_from_leaving():
    sim, detector = toy_simulator(frame_size=16, chunk_len=8), toy_reward_model()
    tokens = jnp.asarray(tokenize_instructions(["go left", "go right", "go up", "go down"], 16))
    targets = np.asarray(jax.vmap(instruction_target)(tokens))
    steps = 40
    towards = targets / np.linalg.norm(targets, axis=1, keepdims=True)
    actions = np.zeros((4, steps, 7), np.float32)
    actions[:2, :, :2] = towards[:2, None] * 0.25  # 40 x 0.08 x 0.25 = 0.8 along the way: passes the goal at 0.6
    actions[2:, :, :2] = -towards[2:, None] * 0.25  # away from it
    # traced episodes whose proprio (the toy gripper position) is 0 at the start frame
    traced = sa.TracedEpisodes(np.zeros((4, 5, 16, 16, 3), np.uint8), np.zeros((4, 5, 8), np.float32),
                               np.concatenate([np.zeros((4, 4, 7), np.float32), actions], axis=1),
                               np.full(4, steps + 4), np.array([True, False, False, True]),
                               ("go left", "go right", "go up", "go down"))
    report = sa.replay_report(traced, sim, detector, lambda f, h: jnp.zeros((4, 2, 1, 1, 4)),
                              success_threshold=0.9, key=jax.random.key(0), batch=3, max_instruction_bytes=16,
                              max_steps=60)
    assert report["imagined_first_success"][2:] == [-1, -1] and min(report["imagined_first_success"][:2]) > 0
    assert report["counts"] == {"real_and_imagined": 1, "imagined_only": 1, "real_only": 1, "neither": 1}
    assert report["false_success"]["rate"] == 0.5 and report["missed_success"]["rate"] == 0.5
    assert report["left_out"] == 0 and report["real_lengths"] == [steps] * 4
    # a noiseless world: the same actions end the same way under any noise draw
    assert report["resample_disagreement"]["rate"] == 0.0 and report["imagined_success_repeats"] == [0.5, 0.5]
    # a world whose motion is mostly noise: the outcome of the same actions follows the draw
    noisy = sa.replay_report(traced._replace(actions=traced.actions * 0.3), toy_simulator(frame_size=16, noise=1.0),
                             detector, lambda f, h: jnp.zeros((4, 2, 1, 1, 4)), success_threshold=0.9,
                             key=jax.random.key(0), batch=4, max_instruction_bytes=16, max_steps=60, repeats=3)
    assert noisy["resample_disagreement"]["rate"] > 0 and len(noisy["imagined_success_repeats"]) == 3
    # rl.imagined.confirm_success's rule on the same replays: an imagined success needs both draws
    assert report["confirmed_by_second_replay"]["imagined_success"] == 0.5  # noiseless: nothing changes
    both = noisy["confirmed_by_second_replay"]["imagined_success"]
    assert both <= min(noisy["imagined_success_repeats"][:2])


def test_longest_run_and_the_sustained_success_sweep_from_the_replay_scores():
    from sword_jax.rl.rollout import success_runs

    hit = np.array([[0, 1, 1, 0, 1, 1, 1], [0, 0, 0, 0, 0, 0, 0], [1, 1, 1, 1, 1, 1, 1]], bool)
    np.testing.assert_array_equal(np.asarray(success_runs(hit)).max(axis=1), [3, 0, 7])
    np.testing.assert_array_equal(np.asarray(success_runs(hit, jnp.asarray([2, 2, 2])))[:, :2], [[0, 1], [0, 0], [3, 4]])
    steps = 12
    designed = np.zeros((4, steps), np.float32)  # the detector's scores the "simulator" gives each episode
    designed[0, 3] = 1.0  # a one-frame flicker on a real failure
    designed[1, 2:7] = 1.0  # five frames on a real failure
    designed[3, 1:11] = 1.0  # ten frames on a real success; episode 2 (a real success) never fires

    def replay_fn(sim, rm, start, actions, lengths, key):
        n = actions.shape[0]
        scores = jnp.asarray(designed[:n, : actions.shape[1]])
        hit = scores >= 0.9
        return sa.ReplayOutcome(jnp.any(hit, 1), jnp.where(jnp.any(hit, 1), jnp.argmax(hit, 1), -1), scores)

    traced = sa.TracedEpisodes(np.zeros((4, 5, 4, 4, 3), np.uint8), np.zeros((4, 5, 8), np.float32),
                               np.zeros((4, steps + 4, 7), np.float32), np.full(4, steps + 4),
                               np.array([False, False, True, True]), ("a", "b", "c", "d"))
    report = sa.replay_report(traced, toy_simulator(frame_size=4), toy_reward_model(),
                              lambda f, h: jnp.zeros((4, 2, 1, 1, 4)), success_threshold=0.9, key=jax.random.key(0),
                              batch=4, max_instruction_bytes=16, replay_fn=replay_fn, repeats=1)
    assert report["imagined_longest_success_run"] == [1, 5, 0, 10]
    sweep = report["sustained_success_sweep"]
    assert sorted(sweep, key=int) == ["1", "2", "4", "8"]
    assert sweep["1"]["false_success"] == report["false_success"]  # k = 1 is the rule in use
    assert [sweep[k]["false_success"]["rate"] for k in ("1", "2", "4", "8")] == [1.0, 0.5, 0.5, 0.0]
    assert [sweep[k]["missed_success"]["rate"] for k in ("1", "2", "4", "8")] == [0.5, 0.5, 0.5, 0.5]
    assert sweep["8"]["agreement"]["rate"] == 0.75
    by_h = report["imagined_success_by_horizon"]
    assert list(by_h) == ["24", "48", "96", "all"]
    assert by_h["all"]["real_failure"] == report["false_success"]  # the whole replay: the rule in use
    assert by_h["all"]["real_success"]["rate"] == 1 - report["missed_success"]["rate"]


def test_success_by_horizon_compares_successes_and_failures_at_common_horizons():
    # Real successes (short episodes) imagined as successes early; real failures only late, after the
    # successes' episodes have ended: the whole-episode rates agree, the early ones separate the groups.
    real = np.array([1, 1, 1, 1, 0, 0, 0, 0, 0], bool)
    first = np.array([10, 30, -1, 20, 150, 90, -1, -1, 5])
    out = sa.success_by_horizon(real, first, horizons=(24, 100))
    assert out["24"]["real_success"]["rate"] == 0.5 and out["24"]["real_failure"]["rate"] == 0.2
    assert out["100"]["real_success"]["rate"] == 0.75 and out["100"]["real_failure"]["rate"] == 0.4
    assert out["all"]["real_success"]["rate"] == 0.75 and out["all"]["real_failure"]["rate"] == 0.6
    assert out["24"]["real_failure"]["of"] == 5 and out["24"]["real_success"]["ci95"][0] < 0.5
    empty = sa.success_by_horizon(np.zeros(3, bool), np.array([1, -1, 4]), horizons=(2,))
    assert empty["2"]["real_success"]["rate"] is None and empty["2"]["real_failure"]["rate"] == 1 / 3
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        sa.success_by_horizon(real, first[:3])


def test_agreement_counts_and_rates():
    real = np.array([1, 1, 1, 0, 0, 0, 0, 0], bool)
    imagined = np.array([1, 1, 0, 1, 0, 0, 0, 0], bool)
    out = sa.agreement(real, imagined)
    assert out["counts"] == {"real_and_imagined": 2, "imagined_only": 1, "real_only": 1, "neither": 4}
    assert out["agreement"]["rate"] == 6 / 8 and out["false_success"]["rate"] == 1 / 5
    assert out["missed_success"]["rate"] == 1 / 3 and out["real_success"] == 3 / 8 and out["imagined_success"] == 3 / 8
    lo, hi = out["false_success"]["ci95"]
    assert lo < 0.2 < hi
    assert sa.agreement(np.zeros(3, bool), np.zeros(3, bool))["missed_success"]["rate"] is None
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        sa.agreement(real, imagined[:4])


def test_spread_covers_every_task_of_a_task_major_list():
    picked = sa.spread(200, 100)
    assert len(picked) == 100 and set(picked // 20) == set(range(10))
    np.testing.assert_array_equal(sa.spread(3, 10), [0, 1, 2])


def _episodes_with_states(e=3, t=40, s=5):
    from sword_jax.rl import data as rl_data

    rng = np.random.default_rng(0)
    return rl_data.EpisodeSet(np.zeros((e, t, 4, 4, 3), np.uint8), np.zeros((e, t, 7), np.float32),
                              np.zeros((e, t, 8), np.float32), np.array([40, 30, 20]), np.ones(e, bool),
                              ("a", "b", "c"), states=rng.normal(size=(e, t, s)), tasks=np.array([4, 5, 6]))


def test_keyframe_steps_are_the_steps_of_the_keyframes_picked_at_the_same_step_and_round():
    """keyframe_steps: each picked start's step in its demonstration, the same draw as keyframe_picks' (its
    recorded state is the episode's state at that step), a function of (seed, step, round)."""
    from sim.grpo_env import keyframe_picks, keyframe_steps

    episodes = _episodes_with_states()
    rl = RLConfig(chunk_len=8, grpo=GRPOConfig(rollout_batch=6, group_size=3), imagined=ImaginedConfig(max_chunks=16))
    for step, round_ in ((2, 0), (2, 1), (5, 0)):
        picks = keyframe_picks(episodes, rl, seed=7, step=step, round_=round_)
        steps = keyframe_steps(episodes, rl, seed=7, step=step, round_=round_)
        assert steps.shape == (6,) and steps.dtype == np.int32 and np.all(steps % 4 == 0) and np.all(steps >= 4)
        for (task, state), t in zip(picks, steps):
            e = int(np.flatnonzero(episodes.tasks == task)[0])  # one episode per task here
            np.testing.assert_array_equal(state, episodes.states[e, t])
    assert not np.array_equal(keyframe_steps(episodes, rl, seed=7, step=2),
                              keyframe_steps(episodes, rl, seed=7, step=3))


def test_ground_truth_grpo_keyframe_starts_are_the_learned_simulators_keyframes_as_recorded_states():
    from sword_jax.rl import data as rl_data
    from sword_jax.rng import stream_rng
    from sim.grpo_env import keyframe_env_starts, keyframe_horizon

    episodes = _episodes_with_states()
    rl = RLConfig(chunk_len=8, grpo=GRPOConfig(rollout_batch=4, group_size=3), imagined=ImaginedConfig(max_chunks=16))
    starts = keyframe_env_starts(episodes, rl, seed=7, step=2)
    pick = rl_data.keyframe_starts(episodes, 4, stream_rng(7, "grpo/env_keyframes", 2))
    assert len(starts) == 12
    for j, (task, state) in enumerate(starts):  # start-major groups of 3
        e, t = pick["episode"][j // 3], pick["t"][j // 3]
        assert task == episodes.tasks[e] and t % 4 == 0 and t < episodes.lengths[e] // 2 + 4
        np.testing.assert_array_equal(state, episodes.states[e, t])
    again = keyframe_env_starts(episodes, rl, seed=7, step=2)  # a function of (seed, step)
    assert [x[0] for x in again] == [x[0] for x in starts]
    assert all(np.array_equal(x[1], y[1]) for x, y in zip(again, starts))
    # keyframe_fraction 0: every start is the first keyframe (frame 4), as the real evaluations start
    at_rest = RLConfig(chunk_len=8, grpo=GRPOConfig(rollout_batch=4, group_size=3),
                       imagined=ImaginedConfig(max_chunks=16, keyframe_fraction=0.0))
    first = rl_data.keyframe_starts(episodes, 4, stream_rng(7, "grpo/env_keyframes", 2), max_fraction=0.0)
    assert set(first["t"].tolist()) == {4}
    for j, (task, state) in enumerate(keyframe_env_starts(episodes, at_rest, seed=7, step=2)):
        np.testing.assert_array_equal(state, episodes.states[first["episode"][j // 3], 4])
    with pytest.raises(ValueError, match="keyframe_fraction must be in"):
        RLConfig(imagined=ImaginedConfig(keyframe_fraction=1.5)).validate()
    half_chunks = RLConfig(imagined=ImaginedConfig(max_chunks=16, execute_steps=4))
    assert keyframe_horizon(rl) == 128 and keyframe_horizon(half_chunks) == 64
    sub = episodes.subset(np.array([2, 0]))
    np.testing.assert_array_equal(sub.states, episodes.states[[2, 0]])
    np.testing.assert_array_equal(sub.tasks, [6, 4])
    stateless = rl_data.EpisodeSet(episodes.frames, episodes.actions, episodes.proprio, episodes.lengths,
                                   episodes.success, episodes.instructions)
    with pytest.raises(ValueError, match="no states or task ids"):
        keyframe_env_starts(stateless, rl, seed=7, step=0)
    with pytest.raises(ValueError, match="rl.env.starts must be initial"):
        RLConfig(env=EnvConfig(starts="middle")).validate()
    with pytest.raises(ValueError, match="reckoned runs on rl.env.backend=cpu only"):
        RLConfig(env=EnvConfig(backend="mjx", proprio="reckoned")).validate()
    RLConfig(env=EnvConfig(backend="mjx", proprio="missing", starts="keyframes")).validate()
    # from rest, cut at the learned simulator's horizon: whole-episode GRPO's starts with a short rollout's cut
    from sim.grpo_env import cut_at_horizon

    RLConfig(env=EnvConfig(starts="rest")).validate()
    assert [cut_at_horizon(RLConfig(env=EnvConfig(starts=k))) for k in ("initial", "keyframes", "branch", "rest")] == [
        False, True, True, True]
    from sim.grpo_env import training_horizon

    rest = RLConfig(env=EnvConfig(starts="rest"))
    assert training_horizon(rest, 220) == rest.imagined.max_chunks * rest.imagined_actions_per_decision < 220
    whole = dataclasses.replace(rest, imagined=dataclasses.replace(rest.imagined, max_chunks=55))
    assert training_horizon(whole, 200) == 200 and training_horizon(RLConfig(), 220) == 220  # never past the limit
    # MJX draws a round's starts with the same sampler: round 0 is the C engine's step, a later round another draw
    from sim.grpo_env import keyframe_picks

    first = keyframe_picks(episodes, rl, seed=7, step=3)
    again = keyframe_picks(episodes, rl, seed=7, step=3, round_=0)
    assert [t for t, _ in first] == [t for t, _ in again]
    assert [t for t, _ in keyframe_env_starts(episodes, rl, seed=7, step=3)][:: rl.grpo.group_size] == [t for t, _ in first]
    from sim.grpo_env import keyframe_env_draw, keyframe_steps

    drawn, at = keyframe_env_draw(episodes, rl, seed=7, step=3)  # the starts and their steps from one draw
    assert [t for t, _ in drawn] == [t for t, _ in keyframe_env_starts(episodes, rl, seed=7, step=3)]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(drawn, keyframe_env_starts(episodes, rl, seed=7, step=3)))
    np.testing.assert_array_equal(at, np.repeat(keyframe_steps(episodes, rl, seed=7, step=3), rl.grpo.group_size))
    assert at.dtype == np.int32
    assert len(first) == rl.grpo.rollout_batch and all(f.shape == episodes.states.shape[2:] for _, f in first)
    other = keyframe_picks(episodes, rl, seed=7, step=3, round_=1)
    assert any(not np.array_equal(a, b) for (_, a), (_, b) in zip(first, other))
    # a run from keyframes is another run than one from rest: resuming one from the other's checkpoint is refused
    from sword_jax.rl.grpo_loop import grpo_run_id

    keyed = RLConfig(env=EnvConfig(starts="keyframes"))
    assert grpo_run_id(keyed, seed=0, simulator="env")["rl.env.starts"] == "keyframes"
    assert grpo_run_id(RLConfig(), seed=0, simulator="env")["rl.env.starts"] == "initial"
    assert grpo_run_id(RLConfig(env=EnvConfig(starts="rest")), seed=0, simulator="env")["rl.env.starts"] == "rest"


def test_keyframe_from_bounds_the_ground_truth_and_learned_simulators_keyframes_from_below():
    """rl.imagined.keyframe_from: the keyframes both simulators start from lie between it and keyframe_fraction of
    each demonstration; it is set from the command line, refused outside [0, keyframe_fraction] by name, and
    enters a run's identity only when above 0 (runs from before it still resume)."""
    import configs
    from configs.cli import ConfigError
    from sim.grpo_env import keyframe_picks, keyframe_steps
    from sword_jax.rl.grpo_loop import grpo_run_id

    episodes = _episodes_with_states()  # lengths 40, 30, 20
    late = RLConfig(chunk_len=8, grpo=GRPOConfig(rollout_batch=64, group_size=3),
                    imagined=ImaginedConfig(max_chunks=16, keyframe_fraction=1.0, keyframe_from=0.5))
    whole = dataclasses.replace(late, imagined=dataclasses.replace(late.imagined, keyframe_from=0.0))
    lengths = episodes.lengths[[int(np.flatnonzero(episodes.tasks == task)[0])
                                for task, _ in keyframe_picks(episodes, late, seed=7, step=2)]]
    steps = keyframe_steps(episodes, late, seed=7, step=2)
    assert np.all(steps >= 0.5 * (lengths - 1)) and np.all(steps <= lengths - 1) and np.all(steps % 4 == 0)
    assert np.any(keyframe_steps(episodes, whole, seed=7, step=2) < 0.5 * (lengths - 1))
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--rl.imagined.keyframe_from=0.25"])
    assert cfg.rl.imagined.keyframe_from == 0.25 and isinstance(cfg.rl.imagined.keyframe_from, float)
    with pytest.raises(ConfigError, match=r"rl\.imagined\.keyframe_from .*keyframe_fraction=0\.5"):
        configs.from_argv(["--config", "sword:tiny", "--rl.imagined.keyframe_from=0.7"])
    for bad in (-0.1, 0.6):
        with pytest.raises(ValueError, match=r"keyframe_from must be in \[0, rl\.imagined\.keyframe_fraction\]"):
            ImaginedConfig(keyframe_fraction=0.5, keyframe_from=bad).validate()
    ImaginedConfig(keyframe_fraction=0.5, keyframe_from=0.5).validate()  # a window of one fraction
    assert "rl.imagined.keyframe_from" not in grpo_run_id(whole, seed=0, simulator="env")
    assert grpo_run_id(late, seed=0, simulator="env")["rl.imagined.keyframe_from"] == 0.5


@pytest.mark.slow
def test_ground_truth_grpo_from_keyframes_runs_in_the_real_environments(tmp_path):
    """Tiny end to end: GRPO in the C-engine envs from expert keyframe states (about a minute)."""
    import dataclasses

    import configs
    from sim import expert
    from sim.config import SimConfig
    from sim.env import CpuEnv
    from sword_jax.rl import data as rl_data
    from sim.datagen import flat_state
    from sim.grpo_env import run_in_env

    cfg = configs.get("sword:tiny")
    states, tasks, lengths = [], [], []
    for task in cfg.sim.tasks:
        env = CpuEnv(SimConfig(), task)
        out = expert.rollout_cpu(env, env.init_states[0], record=True, max_steps=60)
        n = len(out["actions"])
        states.append(np.stack([flat_state(s.data) for s in out["states"][:n]])[:40])
        tasks.append(task)
        lengths.append(min(n, 40))
    t = max(lengths)
    pad = lambda x: np.concatenate([x, np.repeat(x[-1:], t - len(x), axis=0)])  # noqa: E731
    e = len(tasks)
    episodes = rl_data.EpisodeSet(np.zeros((e, t, 4, 4, 3), np.uint8), np.zeros((e, t, 7), np.float32),
                                  np.zeros((e, t, 8), np.float32), np.asarray(lengths), np.ones(e, bool),
                                  tuple(f"task {k}" for k in tasks), states=np.stack([pad(s) for s in states]),
                                  tasks=np.asarray(tasks))
    rl = dataclasses.replace(cfg.rl, grpo=dataclasses.replace(cfg.rl.grpo, steps=1, eval_every=1),
                             imagined=dataclasses.replace(cfg.rl.imagined, max_chunks=2),
                             env=dataclasses.replace(cfg.rl.env, execute_steps=4, action_ensemble=False, proprio="missing",
                                                     starts="keyframes"))
    graphdef, params = build_policy(rl, seed=0)
    result = run_in_env(dataclasses.replace(cfg, rl=rl), rl, graphdef, params, str(tmp_path), episodes_per_task=1,
                        keyframes=episodes)
    assert [p["step"] for p in result["curve"]] == [0, 1]
    assert result["curve"][0]["train_mode"]["proprio"] == "missing"
    assert len(result["history"]) == 1 and 0.0 <= result["history"][0]["rollout_success"] <= 1.0
    # the trajectories counted by their keyframe's step, every one in some bin, their successes the rollouts'
    row, n = result["history"][0], rl.grpo.rollout_batch * rl.grpo.group_size
    counted = {k: v for k, v in row.items() if k.startswith("start_a")}
    assert sum(v for k, v in counted.items() if k.endswith("_rollouts")) == n and not any("said" in k for k in counted)
    assert sum(v for k, v in counted.items() if k.endswith("_real")) == pytest.approx(row["rollout_success"] * n)
    assert counted["start_a0_rollouts"] == n  # the demonstrations are 40 actions: every keyframe lies before 24


def test_ground_truth_grpo_from_rest_is_cut_at_the_learned_simulators_horizon(tmp_path, monkeypatch):
    """Tiny end to end (about 30 s on 2 cores): rl.env.starts=rest in the C-engine envs runs 2 decisions of 4
    actions from rest."""
    import configs
    from sim import grpo_env

    made = []

    class Recorded(grpo_env.LockstepEnvs):
        def __init__(self, starts, **kwargs):
            made.append((list(starts), kwargs["max_steps"]))
            super().__init__(starts, **kwargs)

    monkeypatch.setattr(grpo_env, "LockstepEnvs", Recorded)
    cfg = configs.get("sword:tiny")
    cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, max_steps=16))  # short evaluation episodes
    rl = dataclasses.replace(cfg.rl, grpo=dataclasses.replace(cfg.rl.grpo, steps=1, eval_every=1),
                             imagined=dataclasses.replace(cfg.rl.imagined, max_chunks=2),
                             env=dataclasses.replace(cfg.rl.env, execute_steps=4, action_ensemble=False, proprio="missing",
                                                     starts="rest"))
    graphdef, params = build_policy(rl, seed=0)
    result = grpo_env.run_in_env(dataclasses.replace(cfg, rl=rl), rl, graphdef, params, str(tmp_path),
                                 episodes_per_task=1)
    training = [m for m in made if m[1] == 2 * rl.imagined_actions_per_decision]
    assert len(training) == 1 and len(training[0][0]) == rl.grpo.rollout_batch * rl.grpo.group_size
    assert all(task in cfg.sim.tasks for task, _ in training[0][0])  # training-split states at rest, by task
    assert [p["step"] for p in result["curve"]] == [0, 1] and len(result["history"]) == 1


def test_ground_truth_grpo_from_keyframes_needs_the_demonstrations(tmp_path):
    from train import grpo as grpo_main

    with pytest.raises(SystemExit, match="rl.env.starts=keyframes needs --demos"):
        grpo_main.main(["--config", "sword:tiny", f"--workdir={tmp_path}", "--simulator", "env",
                        "--rl.env.starts=keyframes", "--rl.policy.width=16", "--rl.policy.heads=2",
                        "--rl.policy.layers=1"])


def test_separation_is_paired_over_the_same_episodes_and_refuses_one_sided_data():
    from sword_jax.rl.sim_agreement import separation

    real = np.array([1] * 40 + [0] * 60, bool)
    blind = np.where(np.arange(100) % 5 == 0, 30, -1)  # 20% of each group, whatever the outcome
    seeing = np.where(real, np.where(np.arange(100) % 2 == 0, 30, -1), np.where(np.arange(100) % 10 == 0, 30, -1))
    late = np.where(real, 200, -1)  # separates perfectly, but only after the horizon
    out = separation(real, [blind, seeing], 48, resamples=500)
    (b, s) = out["per_simulator"]
    assert b["separation"] == 0.0 and np.isclose(s["separation"], 0.5 - 0.1)
    assert b["ci95"][0] < 0 < b["ci95"][1] and s["ci95"][0] > 0.1
    assert np.isclose(out["difference"]["separation"], 0.4) and out["difference"]["ci95"][0] > 0.1
    assert separation(real, [late], 48)["per_simulator"][0]["separation"] == 0.0
    assert separation(real, [late], None)["per_simulator"][0]["separation"] == 1.0
    assert "difference" not in separation(real, [late], None)
    with pytest.raises(ValueError, match="both real successes and real failures"):
        separation(np.ones(4, bool), [np.zeros(4)], 48)
    with pytest.raises(ValueError, match="equal 1-D shapes"):
        separation(real, [blind[:10]], 48)


def test_threshold_calibration_keeps_false_successes_within_the_bound_and_recall_highest():
    from sword_jax.rl.sim_agreement import calibrate_threshold

    rng = np.random.default_rng(0)
    real = np.r_[np.ones(60, bool), np.zeros(140, bool)]
    scores = np.r_[rng.uniform(0.6, 1.0, 60), rng.uniform(0.0, 0.8, 140)]  # the classes overlap on [0.6, 0.8]
    out = calibrate_threshold(scores, real, max_false_success=0.05)
    fails = scores[~real]
    assert np.sum(fails >= out["threshold"]) <= 7 and out["false_success"]["rate"] <= 0.05
    # the next lower failure score would let one failure too many through: the threshold is the lowest allowed
    assert np.sum(fails >= np.sort(fails)[::-1][7]) == 8
    assert out["missed_success"]["rate"] == pytest.approx(np.mean(scores[real] < out["threshold"]))
    strict = calibrate_threshold(scores, real, max_false_success=0.0)
    assert strict["false_success"]["rate"] == 0.0 and strict["threshold"] > fails.max()
    assert strict["missed_success"]["rate"] >= out["missed_success"]["rate"]
    with pytest.raises(ValueError, match="no real failure"):
        calibrate_threshold(scores[:60], real[:60])
    with pytest.raises(ValueError, match="must be finite"):
        calibrate_threshold(np.r_[np.nan, scores[1:]], real)


def _coin_world(frame_size: int = 4, chunk_len: int = 2):
    """A simulator whose every frame is one uniform draw of its noise key, and a detector that reads it:
    an outcome made by the noise alone."""
    def init_fn(params, start):
        return jnp.zeros(())

    def step_fn(params, state, chunk, key):
        value = jax.random.uniform(key, ())
        return state, jnp.full((chunk.shape[0], frame_size, frame_size, 3), value, jnp.float32)

    sim = LearnedSimulator(params={}, init_fn=init_fn, step_fn=step_fn,
                           observe_fn=lambda params, state: (jnp.zeros((4,), jnp.float32), jnp.float32(1.0)),
                           chunk_len=chunk_len, frame_size=frame_size)
    return sim, RewardModel(params={}, score_fn=lambda params, frames: jnp.mean(frames, axis=(1, 2, 3)))


def test_confirm_successes_keeps_what_the_actions_made_and_drops_what_the_noise_made():
    """rl.imagined.confirm_success: in a noiseless world the second imagination reproduces every outcome;
    in a world whose outcome is a coin flip of the noise, about half of the successes are dropped, never
    added, and the returns follow the confirmed successes."""
    from sword_jax.rl.rollout import expand_groups, imagined_rollout

    cfg = RLConfig(image_size=8, action_bins=8, proprio_dim=4,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
                   grpo=GRPOConfig(group_size=8), imagined=ImaginedConfig(max_chunks=3, confirm_success=True))
    graphdef, params = build_policy(cfg, seed=0)
    tokens = jnp.asarray(tokenize_instructions(["go left", "go right", "go up", "go down"], 32))
    start = expand_groups(toy_start_states(tokens, key=jax.random.key(1), frame_size=8), cfg.grpo.group_size)

    def run(sim, detector, threshold):
        c = dataclasses.replace(cfg, success_threshold=threshold)

        @jax.jit
        def both(sim, detector):
            rollout = imagined_rollout(graphdef, params, sim, detector, start, c, key=jax.random.key(0))
            return rollout, *sa.confirm_successes(rollout, sim, detector, start, c, key=jax.random.key(1))

        rollout, confirmed, unconfirmed = both(sim, detector)
        return rollout, confirmed, float(unconfirmed)

    sim, detector = toy_simulator(frame_size=8, step_size=0.3), toy_reward_model()
    rollout, confirmed, unconfirmed = run(sim, detector, 0.5)
    assert 0 < int(rollout.success.sum()) < 32 and unconfirmed == 0.0
    np.testing.assert_array_equal(confirmed.success, rollout.success)
    np.testing.assert_array_equal(confirmed.returns, rollout.returns)

    coin = _coin_world(frame_size=8, chunk_len=cfg.chunk_len)
    rollout, confirmed, unconfirmed = run(*coin, 0.8)  # a chunk of 2 frames succeeds with p = 1 - 0.8^2 = 0.36
    first, kept = np.asarray(rollout.success), np.asarray(confirmed.success)
    assert first.sum() >= 10 and np.all(kept <= first) and 0 < kept.sum() < first.sum()
    assert unconfirmed == pytest.approx((first & ~kept).mean())
    np.testing.assert_allclose(confirmed.returns, kept * (1.0 + cfg.grpo.success_bonus))
    np.testing.assert_array_equal(confirmed.tokens, rollout.tokens)


def test_separation_calibration_takes_the_threshold_that_separates_outcomes_best():
    from sword_jax.rl.sim_agreement import calibrate_separation, calibrate_threshold

    # 4 real successes, 6 real failures; one failure's replay looks solved at 0.99
    real = np.r_[np.ones(4, bool), np.zeros(6, bool)]
    scores = np.array([0.9, 0.8, 0.7, 0.2, 0.99, 0.6, 0.3, 0.1, 0.1, 0.05])
    out = calibrate_separation(scores, real)
    # at 0.7: 3/4 successes and 1/6 failures fire (0.583); at 0.6: 3/4 and 2/6; at 0.99: 0 and 1/6
    assert out["threshold"] == 0.7 and out["separation"] == pytest.approx(0.75 - 1 / 6)
    assert out["false_success"]["rate"] == pytest.approx(1 / 6)
    # the false-success bound must pass the failure at 0.99 and keeps almost no success
    strict = calibrate_threshold(scores, real, max_false_success=0.05)
    assert strict["threshold"] > 0.99 and strict["missed_success"]["rate"] == 1.0
    # ties go to the higher threshold (fewer false successes)
    tie = calibrate_separation(np.array([0.9, 0.5, 0.4, 0.1]), np.array([True, False, True, False]))
    assert tie["threshold"] == 0.9 and tie["separation"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="needs real successes and real failures"):
        calibrate_separation(scores[4:], real[4:])
    with pytest.raises(ValueError, match="must be finite"):
        calibrate_separation(np.r_[np.inf, scores[1:]], real)


def test_calibrating_over_the_rollout_horizon_ignores_drift_past_it():
    from sword_jax.rl.sim_agreement import calibrate_replays, roc_points

    # one frame per action, 12 actions; successes score high from action 3 on; failures drift into a solved
    # look (0.95) only after action 8
    real = np.r_[np.ones(5, bool), np.zeros(5, bool)]
    scores = np.full((10, 12), 0.1)
    scores[:5, 3:] = np.linspace(0.6, 0.9, 5)[:, None]
    scores[5:, 8:] = 0.95
    lengths = np.full(10, 12)
    out = calibrate_replays(scores, lengths, real, horizons=[None, 6], max_false_success=0.0)
    assert out["all"]["threshold"] > 0.95 and out["all"]["missed_success"]["rate"] == 1.0
    assert out["6"]["threshold"] == pytest.approx(np.nextafter(0.1, 1.0)) and out["6"]["separation"] == 1.0
    # a shorter replay reads only its own frames, and the rule's consecutive frames count: successes
    # replayed for 4 actions show one high frame, for 5 actions two
    for length, separation in ((4, 0.0), (5, 1.0)):
        short = calibrate_replays(scores, np.r_[np.full(5, length), np.full(5, 12)], real, horizons=[6],
                                  success_frames=2, calibration="separation")
        assert short["6"]["separation"] == separation
    assert roc_points(np.array([0.9, 0.2, 0.5]), np.array([True, False, False])) == [[0.9, 0.0, 1.0], [0.5, 0.5, 1.0],
                                                                                      [0.2, 1.0, 1.0]]
    with pytest.raises(ValueError, match="calibration must be"):
        calibrate_replays(scores, lengths, real, horizons=[6], calibration="youden")
    with pytest.raises(ValueError, match="horizons must be >= 1"):
        calibrate_replays(scores, lengths, real, horizons=[0])


def test_within_group_separation_reads_the_actions_not_the_start():
    """Groups of 4 episodes from one start each: a simulator that follows the actions separates the real
    outcomes inside every mixed group; one whose verdict follows the start (the same verdict for a whole
    group) separates them across groups, yet by 0 inside them and leaves no imagined group mixed."""
    within_group_separation = sa.within_group_separation
    real = np.array([1, 0, 0, 1,  1, 1, 1, 1,  0, 1, 0, 0], bool)  # groups 0 and 2 mixed, group 1 all successes
    follows = np.where(real, 10, -1)  # imagined success at action 10 exactly where the real episode succeeded
    out = within_group_separation(real, follows, 4, horizons=(8, 48))
    assert (out["groups"], out["mixed_real_groups"], out["group_size"]) == (3, 2, 4)
    assert out["48"]["separation"] == 1.0 and out["all"]["separation"] == 1.0
    assert out["8"]["separation"] == 0.0 and out["8"]["imagined_mixed"] == 0.0  # nothing succeeds by action 8
    assert out["48"]["imagined_mixed"] == pytest.approx(2 / 3)
    by_start = np.repeat(np.array([20, 20, -1]), 4)  # verdicts by group: the starts of groups 0 and 1 look solvable
    start = within_group_separation(real, by_start, 4, horizons=(48,))
    assert start["48"]["separation"] == 0.0 and start["48"]["imagined_mixed"] == 0.0
    # across episodes the same verdicts look informative: P(imagined | real success) - P(imagined | real failure) > 0
    across = sa.success_by_horizon(real, by_start, horizons=(48,))["48"]
    assert across["real_success"]["rate"] - across["real_failure"]["rate"] > 0.3
    half = np.array([10, -1, 10, -1] * 3)  # a verdict that ignores what happened, but varies inside each group
    assert within_group_separation(real, half, 4, horizons=(48,))["48"]["separation"] == pytest.approx(
        np.mean([0.5 - 0.5, 0.0 - 2 / 3]))
    assert within_group_separation(np.ones(4, bool), np.full(4, 3), 2)["all"]["separation"] is None
    # scores, threshold-free: a detector that ranks a group's real successes first has AUC 1 inside the groups,
    # one whose scores follow the start has 0.5 (ties), and the horizon cuts what each episode may show
    t = np.arange(60)
    ranked = np.where(real[:, None], 0.2 + 0.01 * t[None], 0.1 + 0.0 * t[None])  # successes score higher, rising
    scored = within_group_separation(real, follows, 4, horizons=(8, 48), scores=ranked)
    assert scored["48"]["auc"] == 1.0 and scored["all"]["auc"] == 1.0
    flat = within_group_separation(real, by_start, 4, horizons=(48,), scores=np.repeat([[0.9], [0.8], [0.1]], 4, 0)
                                   * np.ones((1, 60)))
    assert flat["48"]["auc"] == 0.5
    late = np.where(real[:, None] & (t[None] >= 30), 0.9, 0.1)  # the successes show only after action 30
    cut = within_group_separation(real, follows, 4, horizons=(8, 48), scores=late)
    assert cut["8"]["auc"] == 0.5 and cut["48"]["auc"] == 1.0
    assert "auc" not in within_group_separation(real, follows, 4, horizons=(48,))["48"]
    with pytest.raises(ValueError, match="scores must be"):
        within_group_separation(real, follows, 4, scores=np.zeros(12))
    with pytest.raises(ValueError, match="whole groups"):
        within_group_separation(real, follows, 5)
    with pytest.raises(ValueError, match="whole groups"):
        within_group_separation(real, follows, 1)


def test_replay_starts_with_the_prefix_are_the_whole_episodes_latents_the_window_ones_are_not():
    """rl.imagined.start_encoding=prefix: a replay's start latents (first frame and context at t0 = 4) are the
    latents the latents stage makes of the whole episode; with the window (``encode`` alone) they are
    encode_history's of the same first frame and history, as before, and differ from those."""
    from sword_jax.rl.world_model_sim import encode_history
    from tests.support.vae import encoders, relative_error, tiny_vae, whole_latents

    cfg, vae_graphdef, vae_state = tiny_vae()
    n, size = 3, cfg.data.image_size
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (n, 9, size, size, 3), dtype=np.uint8)  # the episode's first 9 frames
    traced = sa.TracedEpisodes(frames, np.zeros((n, 9, 8), np.float32), np.zeros((n, 12, 7), np.float32),
                               np.array([12, 10, 3]), np.array([True, False, False]), ("a", "b", "c"))
    whole = whole_latents(frames)  # (n, 3, ...): latent 1 ends at t0 = 4
    truth = whole[:, :2]
    encode, encode_prefix = encoders()
    prefix, _, lengths = sa.replay_starts(traced, encode, encode_prefix=encode_prefix, max_instruction_bytes=16)
    window, _, same_lengths = sa.replay_starts(traced, encode, max_instruction_bytes=16)
    assert relative_error(prefix.latents[0], truth) < 1e-4
    np.testing.assert_array_equal(lengths, same_lengths)
    np.testing.assert_array_equal(np.asarray(prefix.latents[1]), np.asarray(window.latents[1]))
    unit = jnp.asarray(frames, jnp.float32) / jnp.float32(255.0)
    before = encode_history(vae_graphdef, vae_state, unit[:, 0], unit[:, [0, 0, 0, 0, 1, 2, 3, 4]])
    np.testing.assert_array_equal(np.asarray(window.latents[0]), np.asarray(before))  # the window: unchanged
    assert relative_error(window.latents[0][:, 1], truth[:, 1]) > 0.05
