"""Imagined rollouts: deterministic for a key, done-masked, sharded over devices."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax import sharding as shd
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.env import ImaginedEnv
from sword_jax.rl.learned_simulator import (ToyState, instruction_target, toy_render, toy_reward_model,
                                            toy_simulator, toy_start_states)
from sword_jax.rl.policy import build_policy, tokenize_instructions, tokens_to_actions
from sword_jax.rl.rollout import expand_groups, group_view, imagined_rollout

CFG = RLConfig(image_size=8, action_bins=8, proprio_dim=4,
               policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
               grpo=GRPOConfig(group_size=4), imagined=ImaginedConfig(max_chunks=4))
TEXTS = ["pick up the black bowl on the plate", "put the bowl on the stove"]


def _setup(noise=0.02):
    graphdef, params = build_policy(CFG, seed=0)
    sim, reward_model = toy_simulator(frame_size=8, step_size=0.02, noise=noise), toy_reward_model()
    tokens = jnp.asarray(tokenize_instructions(TEXTS, 32))
    start = toy_start_states(tokens, key=jax.random.key(5), frame_size=8)
    # trajectory group 1 starts ON its target: the first chunk succeeds, then it must stay done
    target = instruction_target(tokens[1])
    proprio = start.proprio.at[1, :2].set(target)
    frames = start.frame.at[1].set(toy_render(ToyState(target, target), 8))
    start = start._replace(proprio=proprio, frame=frames)
    return graphdef, params, sim, reward_model, expand_groups(start, CFG.grpo.group_size)


def test_rollout_deterministic_and_respects_done():
    graphdef, params, sim, reward_model, start = _setup()
    run = jax.jit(lambda p, k: imagined_rollout(graphdef, p, sim, reward_model, start, CFG, key=k, record_frames=True))
    a, b = run(params, jax.random.key(0)), run(params, jax.random.key(0))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    c = run(params, jax.random.key(1))
    assert not np.array_equal(np.asarray(a.tokens), np.asarray(c.tokens))

    valid, rewards = np.asarray(a.valid), np.asarray(a.rewards)
    assert np.all(np.diff(valid, axis=1) <= 0), "valid must never switch back on"
    assert np.all(rewards[valid == 0] == 0.0), "no reward after done"
    success = np.asarray(a.success)
    started_at_goal = np.asarray(group_view(a.success, CFG.grpo.group_size))[1]
    assert started_at_goal.all()
    # successful trajectories stop right after the chunk that succeeded; the rest run to the limit
    n_valid = valid.sum(1)
    frame_scores = np.asarray(reward_model.score(a.frames.reshape((-1, 8, 8, 3)))).reshape(a.frames.shape[:3])
    chunk_hit = (frame_scores >= CFG.success_threshold).any(axis=2)  # (N, C)
    first_hit = np.argmax(chunk_hit, axis=1)
    np.testing.assert_array_equal(chunk_hit.any(axis=1), success | ~valid.all(axis=1))
    np.testing.assert_array_equal(n_valid[success], first_hit[success] + 1)
    assert np.all(n_valid[~success] == CFG.imagined.max_chunks)
    np.testing.assert_array_equal(n_valid[CFG.grpo.group_size:], 1)  # the on-goal group: one chunk
    # frozen after done: the score stays put; the return is success alone (as in the real environments)
    scores = np.asarray(a.scores)
    for i in np.flatnonzero(success):
        assert np.all(scores[i, first_hit[i]:] == scores[i, first_hit[i]])
    assert CFG.imagined.return_rule == "success"
    np.testing.assert_array_equal(np.asarray(a.returns), success * (1.0 + CFG.grpo.success_bonus))
    # rl.imagined.return_rule=score: the score changes plus the bonus, so failures differ by the detector's score
    score_cfg = dataclasses.replace(CFG, imagined=dataclasses.replace(CFG.imagined, return_rule="score"))
    s = jax.jit(lambda p, k: imagined_rollout(graphdef, p, sim, reward_model, start, score_cfg, key=k))(
        params, jax.random.key(0))
    np.testing.assert_array_equal(np.asarray(s.success), success)
    np.testing.assert_allclose(np.asarray(s.returns), rewards.sum(1) + success.astype(np.float32), rtol=1e-5)
    assert np.ptp(np.asarray(s.returns)[~success]) > 0 and np.ptp(np.asarray(a.returns)[~success]) == 0
    assert a.frames.shape == (8, CFG.imagined.max_chunks, 8, 8, 8, 3)


def test_env_steps_by_the_rollout_rule():
    """ImaginedEnv's rewards, done and success are the GRPO rollout's on the same world and actions."""
    graphdef, params, sim, reward_model, start = _setup(noise=0.0)  # noise-free: the key schedules may differ
    rollout = jax.jit(lambda p: imagined_rollout(graphdef, p, sim, reward_model, start, CFG, key=jax.random.key(4)))(params)
    success = np.asarray(rollout.success)
    assert success.any() and not success.all(), "both endings (success, chunk limit) must be exercised"
    env = ImaginedEnv(sim, reward_model, success_threshold=CFG.success_threshold, max_chunks=CFG.imagined.max_chunks)
    n = start.frame.shape[0]
    state = jax.vmap(lambda s, k: env.reset(s, key=k))(start, jax.random.split(jax.random.key(1), n))
    actions = tokens_to_actions(rollout.tokens, CFG.action_bins)  # (N, C, T, A): the chunks the rollout executed
    step = jax.jit(jax.vmap(env.step))
    rewards, scores, done = [], [], []
    for c in range(CFG.imagined.max_chunks):
        state = step(state, actions[:, c])
        rewards.append(state.reward), scores.append(state.info["score"]), done.append(state.done)
    rewards, scores, done = (np.stack(x, axis=1) for x in (rewards, scores, done))  # (N, C)
    # the env scores [T] frames per trajectory, the rollout [N * T] at once: equal up to float rounding
    np.testing.assert_allclose(rewards, np.asarray(rollout.rewards), rtol=0, atol=1e-6)
    np.testing.assert_allclose(scores, np.asarray(rollout.scores), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(done[:, :-1], 1.0 - np.asarray(rollout.valid)[:, 1:])  # done after c = c+1 not taken
    np.testing.assert_array_equal(done[:, -1], 1.0)
    np.testing.assert_array_equal(np.asarray(state.info["success"]) > 0, success)
    np.testing.assert_array_equal(np.asarray(state.info["truncation"]) > 0, ~success)
    # the env's episode return plus the success bonus is the GRPO return of rl.imagined.return_rule=score
    score_cfg = dataclasses.replace(CFG, imagined=dataclasses.replace(CFG.imagined, return_rule="score"))
    scored = jax.jit(lambda p: imagined_rollout(graphdef, p, sim, reward_model, start, score_cfg,
                                                key=jax.random.key(4)))(params)
    np.testing.assert_allclose(rewards.sum(1) + CFG.grpo.success_bonus * success, np.asarray(scored.returns), atol=1e-5)


def test_rollout_sharded_over_devices_matches_single_device():
    graphdef, params, sim, reward_model, start = _setup()
    mesh = shd.make_mesh(shd.MeshConfig(data=-1))
    run = lambda p, s: imagined_rollout(graphdef, p, sim, reward_model, s, CFG, key=jax.random.key(2))  # noqa: E731
    ref = jax.jit(run)(params, start)
    sharded_start = jax.tree.map(lambda x: jax.device_put(x, shd.batch_sharding(mesh, x.ndim)), start)
    with shd.use_mesh(mesh):
        out = jax.jit(run)(params, sharded_start)
    assert len(out.returns.sharding.device_set) == len(jax.devices())
    np.testing.assert_allclose(np.asarray(out.returns), np.asarray(ref.returns), rtol=1e-4, atol=1e-5)


def test_success_frames_needs_consecutive_success_frames_across_chunks():
    """rl.imagined.success_frames: a detector flicker no longer ends an episode as a success; a run of
    success frames counts across chunk boundaries; done trajectories keep their run."""
    import pytest

    from sword_jax.rl.rollout import chunk_outcome

    def outcome(scores, prev_run, done=False, k=3):
        return chunk_outcome(jnp.asarray(scores, jnp.float32), jnp.float32(0.0), jnp.asarray(done), jnp.int32(0),
                             success_threshold=0.9, max_chunks=8, prev_run=jnp.int32(prev_run), success_frames=k)

    first = outcome([0.0, 1.0, 0.0, 1.0], 0)  # two flickers: not 3 in a row
    assert not bool(first.success) and int(first.run) == 1
    second = outcome([1.0, 1.0, 0.0, 0.0], int(first.run))  # 1 carried + 2 = 3 at the chunk's second frame
    assert bool(second.success) and int(second.run) == 0
    assert bool(outcome([0.0, 1.0, 0.0, 1.0], 0, k=1).success)  # k = 1: any frame, the rule so far
    frozen = outcome([1.0, 1.0, 1.0, 1.0], 2, done=True)
    assert not bool(frozen.success) and int(frozen.run) == 2
    with pytest.raises(ValueError, match="success_frames"):
        outcome([0.0], 0, k=0)
    with pytest.raises(ValueError, match=r"rl\.imagined\.success_frames"):
        RLConfig(imagined=ImaginedConfig(success_frames=0)).validate()

    # the rollout and the env read it: a run longer than an episode can show never succeeds, even for the
    # group that starts on its goal (which the default rule ends as a success in its first chunk)
    graphdef, params, sim, reward_model, start = _setup(noise=0.0)
    never = dataclasses.replace(CFG, imagined=dataclasses.replace(CFG.imagined, success_frames=10_000))
    strict = imagined_rollout(graphdef, params, sim, reward_model, start, never, key=jax.random.key(4))
    assert not np.asarray(strict.success).any()
    n, on_goal = start.frame.shape[0], slice(CFG.grpo.group_size, None)
    still = jnp.zeros((n, CFG.chunk_len, CFG.action_dim))
    for k, succeeds in ((1, True), (10_000, False)):
        env = ImaginedEnv(sim, reward_model, success_threshold=CFG.success_threshold, max_chunks=CFG.imagined.max_chunks,
                          success_frames=k)
        state = jax.vmap(lambda s, key: env.reset(s, key=key))(start, jax.random.split(jax.random.key(1), n))
        state = jax.vmap(env.step)(state, still)
        assert (np.asarray(state.info["success"])[on_goal] > 0).all() == succeeds
        assert (np.asarray(state.pipeline_state.run)[on_goal] > 0).all()


def test_a_rollout_that_runs_on_past_success_keeps_the_detectors_verdict_by_its_rule():
    """stop_on_success=False (the real environment pays, rl.imagined.reward=executed): every trajectory runs the
    whole horizon, and ``success`` is the verdict the detector's reward would have paid, by its own rule (any
    frame of a chunk, not only the last)."""
    from sword_jax.rl.rollout import chunk_outcome

    def outcome(chunk, stop):
        return chunk_outcome(jnp.asarray([0.0, 1.0, 0.0]), jnp.float32(0.0), jnp.asarray(False), jnp.int32(chunk),
                             success_threshold=0.9, max_chunks=4, stop_on_success=stop)

    stopped, running, last = outcome(1, True), outcome(1, False), outcome(3, False)
    assert bool(stopped.success) and bool(stopped.done)  # a success frame mid-chunk, the last frame under it
    assert bool(running.success) and not bool(running.done) and not bool(running.truncated)
    assert bool(last.success) and bool(last.done) and bool(last.truncated)

    graphdef, params, sim, reward_model, start = _setup()
    run = lambda stop: imagined_rollout(graphdef, params, sim, reward_model, start, CFG,  # noqa: E731
                                        key=jax.random.key(4), stop_on_success=stop)
    stops, runs_on = jax.device_get(run(True)), jax.device_get(run(False))
    np.testing.assert_array_equal(runs_on.success, stops.success)
    assert stops.success.any(), "the group that starts on its goal succeeds"
    assert (runs_on.valid == 1).all()
    assert (stops.valid.sum(1)[stops.success] < CFG.imagined.max_chunks).any()  # where it stopped, this one ran on
    # each chunk's highest frame score: with success_frames = 1 the verdict is the highest peak reaching the
    # threshold, and a chunk after a stop scores nothing
    assert runs_on.peaks.shape == runs_on.valid.shape
    np.testing.assert_array_equal(runs_on.peaks.max(1) >= CFG.success_threshold, runs_on.success)
    assert (stops.peaks[stops.valid == 0] == 0).all()
    recorded = jax.device_get(imagined_rollout(graphdef, params, sim, reward_model, start, CFG, key=jax.random.key(4),
                                               stop_on_success=False, record_frames=True))
    scored = reward_model.score(jnp.asarray(recorded.frames.reshape((-1,) + recorded.frames.shape[3:])))
    np.testing.assert_allclose(recorded.peaks, np.asarray(scored).reshape(recorded.frames.shape[:3]).max(2),
                               atol=1e-6)


def test_sim_microbatches_equal_one_vmapped_step_and_stay_sharded():
    """rl.imagined.sim_microbatches=S runs the simulator over S interleaved slices: the same rollout as one
    vmapped step (sharded too), a slice count that does not divide the trajectories is refused."""
    import pytest

    graphdef, params, sim, reward_model, start = _setup()
    n = start.frame.shape[0]  # 8 trajectories

    def rollout(slices, s=start):
        cfg = dataclasses.replace(CFG, imagined=dataclasses.replace(CFG.imagined, sim_microbatches=slices))
        return jax.jit(lambda p, st: imagined_rollout(graphdef, p, sim, reward_model, st, cfg, key=jax.random.key(2),
                                                      record_frames=True))(params, s)

    ref = rollout(1)
    # The slices really are sequential: one scan of length S over vmapped slices of n / S.
    from sword_jax.rl.rollout import from_slices, map_over_slices, to_slices

    def doubled_in_slices(x):
        return from_slices(map_over_slices(lambda r: r * 2.0, to_slices((x,), 4)))

    rows = jnp.arange(n, dtype=jnp.float32)
    jaxpr = str(jax.make_jaxpr(doubled_in_slices)(rows))
    assert "scan" in jaxpr and "length=4" in jaxpr
    np.testing.assert_array_equal(np.asarray(doubled_in_slices(rows)), 2.0 * np.arange(n))
    np.testing.assert_array_equal(np.asarray(to_slices(rows, 4))[1], np.arange(n)[1::4])  # slice j: rows j, j + S, ...
    # Four slices of a data-sharded batch: the same rollout, still spread over every device.
    mesh = shd.make_mesh(shd.MeshConfig(data=-1))
    sharded = jax.tree.map(lambda x: jax.device_put(x, shd.batch_sharding(mesh, x.ndim)), start)
    with shd.use_mesh(mesh):
        out = rollout(4, sharded)
    assert len(out.returns.sharding.device_set) == len(jax.devices())
    np.testing.assert_array_equal(np.asarray(out.tokens), np.asarray(ref.tokens))
    np.testing.assert_allclose(np.asarray(out.frames), np.asarray(ref.frames), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(out.success), np.asarray(ref.success))
    np.testing.assert_allclose(np.asarray(out.returns), np.asarray(ref.returns), atol=1e-5)
    with pytest.raises(ValueError, match="sim_microbatches=3 does not divide the 8"):
        rollout(3)
    with pytest.raises(ValueError, match=r"rl\.imagined\.sim_microbatches"):
        RLConfig(imagined=ImaginedConfig(sim_microbatches=-1)).validate()  # 0 = the simulator chooses


def test_a_group_s_simulator_start_up_runs_once_and_is_broadcast():
    """group_size: the simulator is initialised once per start state and its state broadcast to the
    group; the rollout equals the one from the expanded start states, and init runs on B, not B x G."""
    graphdef, params, sim, reward_model, start = _setup()
    distinct = jax.tree.map(lambda x: x[:: CFG.grpo.group_size], start)
    calls = []
    counting = dataclasses.replace(sim, init_fn=lambda p, s: (calls.append(s.frame.shape), sim.init_fn(p, s))[1])
    cfg = dataclasses.replace(CFG, imagined=dataclasses.replace(CFG.imagined, sim_microbatches=2))  # sliced layout

    @jax.jit
    def both(p):
        expanded = imagined_rollout(graphdef, p, sim, reward_model, start, cfg, key=jax.random.key(0))
        grouped = imagined_rollout(graphdef, p, counting, reward_model, distinct, cfg, key=jax.random.key(0),
                                   group_size=CFG.grpo.group_size)
        return expanded, grouped

    expanded, grouped = both(params)
    for x, y in zip(jax.tree.leaves(expanded), jax.tree.leaves(grouped)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert calls and all(shape == distinct.frame.shape[1:] for shape in calls)  # vmapped over the 2 starts
