"""The WorldModel + streaming VAE learned simulator inside the imagined rollout (tiny shapes)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.learned_simulator import StartState, toy_reward_model
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.rollout import expand_groups, imagined_rollout
from sword_jax.rl.world_model_sim import encode_keyframes, world_model_simulator


@functools.cache
def _tiny_models():
    """``(cfg, wm_graphdef, wm_state, vae_graphdef, vae_state)``: the tiny world model and VAE, random weights,
    built once per process (their eager initialisation costs 5 s; the tests only read them)."""
    from sword_jax.dit.action_dit import WorldModel
    from sword_jax.vae import api as vae_api

    cfg = configs.get("sword:tiny")
    with nnx.use_eager_sharding(False):
        wm_graphdef, wm_state = nnx.split(WorldModel(cfg.model, rngs=nnx.Rngs(0)))
    vae_graphdef, vae_state = nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(1)))
    return cfg, wm_graphdef, wm_state, vae_graphdef, vae_state


@pytest.mark.slow
def test_world_model_simulator_rollout_deterministic_and_streams_frames():
    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    frames = jax.random.uniform(jax.random.key(2), (2, 32, 32, 3))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    assert latents.shape == (2, 2, 2, 2, cfg.vae.z_dim)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                                sample_steps=2)
    rl = RLConfig(image_size=8, action_bins=8, success_threshold=1.0,
                  policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32),
                  grpo=GRPOConfig(group_size=2), imagined=ImaginedConfig(max_chunks=2))
    graphdef, params = build_policy(rl)
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl", "open the drawer"], 32))
    start = expand_groups(StartState(frames, jnp.zeros((2, 8)), tokens, latents), 2)
    run = jax.jit(lambda p, s, k: imagined_rollout(graphdef, p, s, toy_reward_model(), start, rl, key=k, record_frames=True))
    a, b = run(params, sim, jax.random.key(0)), run(params, sim, jax.random.key(0))
    np.testing.assert_array_equal(np.asarray(a.frames), np.asarray(b.frames))
    assert a.frames.shape == (4, 2, 8, 32, 32, 3)
    assert np.all(np.isfinite(np.asarray(a.frames))) and float(a.frames.min()) >= 0 and float(a.frames.max()) <= 1
    # different sampled actions / noise give different imagined futures
    c = run(params, sim, jax.random.key(1))
    assert not np.allclose(np.asarray(a.frames), np.asarray(c.frames))
    np.testing.assert_array_equal(np.asarray(a.proprio_valid), 0.0)  # the world model reports no proprio
    # one start-up decode per start state, broadcast to its group: the same rollout
    starts = StartState(frames, jnp.zeros((2, 8)), tokens, latents)
    grouped = jax.jit(lambda p, s, k: imagined_rollout(graphdef, p, s, toy_reward_model(), starts, rl, key=k,
                                                       record_frames=True, group_size=2))(params, sim, jax.random.key(0))
    np.testing.assert_array_equal(np.asarray(grouped.tokens), np.asarray(a.tokens))
    np.testing.assert_allclose(np.asarray(grouped.frames), np.asarray(a.frames), atol=1e-5)


START_ACTIONS = jnp.zeros((5, 7)).at[:, 0].set(jnp.asarray([100.0, 1.0, 2.0, 3.0, 4.0]))


def capturing_simulator(monkeypatch, **kw):
    """``(sim, state, captured)``: the tiny world-model simulator (``kw``: its options) whose world model is replaced
    by a stand-in that records the first action dimension of every call's actions in ``captured`` and predicts zeros,
    started from zero latents with :data:`START_ACTIONS` (first frame 100, context frames 1-4)."""
    from sword_jax.rl import world_model_sim

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    captured = []

    def fake_predict(model_fn, first, context, actions, *, key, num_future, cfg, num_steps):
        captured.append(np.asarray(actions[0, :, 0]))
        return jnp.zeros((1, num_future) + context.shape[2:], jnp.float32)

    monkeypatch.setattr(world_model_sim, "predict_chunk", fake_predict)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32, **kw)
    latents = jnp.zeros((2, 2, 2, cfg.vae.z_dim))
    state = sim.init(StartState(jnp.zeros((32, 32, 3)), jnp.zeros(8), jnp.zeros(8, jnp.int32), (latents, START_ACTIONS)))
    return sim, state, captured


def test_policy_actions_condition_the_frames_training_pairs_them_with(monkeypatch):
    """Frame t carries the action taken after seeing it (world_model/data.py). The policy acts on the
    last context frame, so its first action must fill that frame's slot, not the first predicted
    frame's; the start's real first/context actions (not zeros) condition the first chunk."""
    sim, state, captured = capturing_simulator(monkeypatch)
    chunk = lambda base: jnp.zeros((8, 7)).at[:, 0].set(base + jnp.arange(8.0))  # noqa: E731
    state, _ = sim.step(state, chunk(10.0), key=jax.random.key(0))
    state, _ = sim.step(state, chunk(20.0), key=jax.random.key(1))
    np.testing.assert_array_equal(captured[0], [100, 1, 2, 3, 10, 11, 12, 13, 14, 15, 16, 17, 17])
    np.testing.assert_array_equal(captured[1], [100, 15, 16, 17, 20, 21, 22, 23, 24, 25, 26, 27, 27])


def test_keyframe_starts_are_latent_aligned_with_real_history():
    from sword_jax.rl import data as rl_data

    e, t = 3, 30
    frames = np.broadcast_to(np.arange(t, dtype=np.uint8)[None, :, None, None, None], (e, t, 4, 4, 3)).copy()
    actions = np.broadcast_to(np.arange(t, dtype=np.float32)[None, :, None], (e, t, 7)).copy()
    eps = rl_data.EpisodeSet(frames, actions, np.zeros((e, t, 8), np.float32), np.full(e, t), np.ones(e, bool),
                             ("a", "b", "c"))
    pick = rl_data.keyframe_starts(eps, 16, np.random.default_rng(0))
    assert np.all(pick["t"] % 4 == 0) and np.all(pick["t"] >= 4) and np.all(pick["t"] <= (t - 1) // 2)
    for i, ti in enumerate(pick["t"]):
        np.testing.assert_array_equal(pick["history"][i, :, 0, 0, 0], np.maximum(np.arange(ti - 7, ti + 1), 0))
        np.testing.assert_array_equal(pick["actions"][i, :, 0], [0, ti - 3, ti - 2, ti - 1, ti])
        assert pick["frame"][i, 0, 0, 0] == ti and pick["first_frame"][i, 0, 0, 0] == 0



def _keyframes_before_the_lower_bound(episodes, count, rng, *, max_fraction, num_context=1, frames_per_latent=4):
    """keyframe_indices as it drew before rl.imagined.keyframe_from existed (its upper bound alone)."""
    k, f = num_context, frames_per_latent
    ep = rng.integers(0, episodes.num_episodes, count)
    last = np.maximum((episodes.lengths[ep] - 1) * max_fraction // f, k).astype(np.int64)
    s = k + (rng.random(count) * (last - k + 1)).astype(np.int64)
    return ep, np.minimum(f * s, episodes.lengths[ep] - 1)


@pytest.mark.parametrize("max_fraction,num_context", [(0.5, 1), (1.0, 1), (0.0, 1), (0.75, 2)])
def test_keyframes_from_the_first_keyframe_are_drawn_as_before_the_lower_bound(max_fraction, num_context):
    """min_fraction 0 (rl.imagined.keyframe_from's default) draws the same keyframes with the same generator calls
    as the sampler before it had a lower bound, so runs started then resume to the same starts."""
    import argparse

    from sword_jax.rl import data as rl_data

    episodes = argparse.Namespace(num_episodes=5, lengths=np.array([60, 90, 120, 200, 33]))
    rng_now, rng_before = np.random.default_rng(11), np.random.default_rng(11)
    for _ in range(3):  # consecutive draws from one generator: each leaves it where the old draw did
        ep, t = rl_data.keyframe_indices(episodes, 64, rng_now, max_fraction=max_fraction, min_fraction=0.0,
                                         num_context=num_context)
        ep_before, t_before = _keyframes_before_the_lower_bound(episodes, 64, rng_before, max_fraction=max_fraction,
                                                                num_context=num_context)
        np.testing.assert_array_equal(ep, ep_before)
        np.testing.assert_array_equal(t, t_before)
    assert rng_now.random() == rng_before.random()
    default = rl_data.keyframe_indices(episodes, 64, np.random.default_rng(3), max_fraction=max_fraction,
                                       num_context=num_context)
    explicit = rl_data.keyframe_indices(episodes, 64, np.random.default_rng(3), max_fraction=max_fraction,
                                        min_fraction=0.0, num_context=num_context)
    for got, want in zip(explicit, default):
        np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("min_fraction,max_fraction", [(0.25, 0.5), (0.5, 1.0), (0.375, 0.75), (0.75, 1.0)])
def test_keyframes_are_drawn_from_every_latent_aligned_frame_of_their_window(min_fraction, max_fraction):
    """Between fractions min_fraction and max_fraction of each episode (min_fraction = rl.imagined.keyframe_from):
    each drawn keyframe is a latent-aligned frame inside the window, and every such frame is drawn."""
    import argparse

    from sword_jax.rl import data as rl_data

    lengths = np.array([60, 90, 121, 200, 33])
    episodes = argparse.Namespace(num_episodes=len(lengths), lengths=lengths)
    ep, t = rl_data.keyframe_indices(episodes, 4000, np.random.default_rng(0), max_fraction=max_fraction,
                                     min_fraction=min_fraction)
    for e, length in enumerate(lengths):
        got = set(t[ep == e].tolist())
        window = [frame for frame in range(4, length, 4)
                  if min_fraction * (length - 1) <= frame <= max_fraction * (length - 1)]
        assert window and got == set(window), (e, length, sorted(got), window)
    # the window's keyframes as rl_data.keyframe_starts cuts them, history included
    pick = rl_data.keyframe_starts(_counting_episodes(3, 40), 16, np.random.default_rng(0), max_fraction=max_fraction,
                                   min_fraction=min_fraction)
    assert np.all(pick["t"] % 4 == 0)
    assert np.all(pick["t"] >= min_fraction * 39) and np.all(pick["t"] <= max_fraction * 39)
    assert np.array_equal(pick["frame"][:, 0, 0, 0], pick["t"])


def test_a_window_of_one_fraction_draws_each_episodes_one_keyframe_there():
    """min_fraction == max_fraction: every draw of an episode is its latest keyframe at or before that fraction
    (the first keyframe where it comes earlier); a lower bound above the upper one is refused by name."""
    import argparse

    from sword_jax.rl import data as rl_data

    lengths = np.array([60, 90, 121, 200, 3])
    episodes = argparse.Namespace(num_episodes=len(lengths), lengths=lengths)
    for fraction in (0.0, 0.3, 0.5, 1.0):
        ep, t = rl_data.keyframe_indices(episodes, 500, np.random.default_rng(1), max_fraction=fraction,
                                         min_fraction=fraction)
        for e, length in enumerate(lengths):
            only = min(4 * max(int(fraction * (length - 1)) // 4, 1), length - 1)
            assert set(t[ep == e].tolist()) == {only}, (fraction, length)
    with pytest.raises(ValueError, match="min_fraction <= max_fraction"):
        rl_data.keyframe_indices(episodes, 4, np.random.default_rng(0), max_fraction=0.5, min_fraction=0.6)
    with pytest.raises(ValueError, match="min_fraction"):
        rl_data.keyframe_indices(episodes, 4, np.random.default_rng(0), max_fraction=0.5, min_fraction=-0.1)



def test_grpo_in_the_world_model_draws_its_starts_from_the_configured_keyframe_window():
    """The pipeline's GRPO setup draws each step's keyframes (start states, recorded states, start steps) with
    rl.imagined.keyframe_from and keyframe_fraction: the keyframes of that window of each demonstration."""
    import dataclasses

    from sword_jax.pipeline.grpo import setup_from_weights
    from sword_jax.rl import data as rl_data
    from sword_jax.rl.reward_model import build_detector
    from sword_jax.rng import stream_rng

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    base = _counting_episodes(4, 80)
    lengths = np.array([80, 64, 50, 41])
    states = np.broadcast_to(np.arange(80.0)[None, :, None], (4, 80, 3)).copy()  # state i at frame i
    episodes = dataclasses.replace(base, lengths=lengths, states=states)
    rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, keyframe_from=0.5,
                                                                  keyframe_fraction=0.75))
    setup = setup_from_weights(cfg, rl, episodes, world_model=(wm_graphdef, wm_state),
                               vae=(vae_graphdef, vae_state), detector=build_detector(rl))
    for step in (0, 3):
        rng = stream_rng(cfg.seed, "grpo/keyframes", step)  # the pipeline's keyframe stream
        ep, t = rl_data.keyframe_indices(episodes, rl.imagined_starts_per_step, rng, max_fraction=0.75,
                                         min_fraction=0.5)
        np.testing.assert_array_equal(setup.start_steps(step), t)
        np.testing.assert_array_equal(setup.env_starts(step)[:, 0], t)
        assert np.all(t >= 0.5 * (lengths[ep] - 1)) and np.all(t <= 0.75 * (lengths[ep] - 1))

def _counting_episodes(e, t):
    """``e`` episodes of ``t`` frames whose frame i shows the value i."""
    from sword_jax.rl import data as rl_data

    frames = np.broadcast_to(np.arange(t, dtype=np.uint8)[None, :, None, None, None], (e, t, 4, 4, 3)).copy()
    return rl_data.EpisodeSet(frames, np.zeros((e, t, 7), np.float32), np.zeros((e, t, 8), np.float32), np.full(e, t),
                              np.ones(e, bool), tuple("abcdefgh"[:e]))

def test_pixel_round_trip_sets_the_learned_simulators_next_context(monkeypatch):
    """With flow.pixel_round_trip the next context is the VAE's re-encoding of the decoded chunk
    (as in evaluation's rollout), not the predicted latent itself."""
    import dataclasses

    from sword_jax.rl import world_model_sim
    from sword_jax.world_model.rollout import make_pixel_round_trip

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    future = jax.random.normal(jax.random.key(3), (1, 2, 2, 2, cfg.vae.z_dim))
    monkeypatch.setattr(world_model_sim, "predict_chunk", lambda *a, **k: future)
    latents = jax.random.normal(jax.random.key(4), (2, 2, 2, cfg.vae.z_dim))
    contexts = {}
    for round_trip in (False, True):
        sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, frame_size=32,
                                    flow_cfg=dataclasses.replace(cfg.flow, pixel_round_trip=round_trip))
        state = sim.init(StartState(jnp.zeros((32, 32, 3)), jnp.zeros(8), jnp.zeros(8, jnp.int32), latents))
        state, _ = sim.step(state, jnp.zeros((8, 7)), key=jax.random.key(0))
        contexts[round_trip] = np.asarray(state.context)
    np.testing.assert_array_equal(contexts[False], np.asarray(future[:, -1:]))
    expected = make_pixel_round_trip(vae_graphdef, vae_state, 1)(latents[None, :1], future)
    np.testing.assert_allclose(contexts[True], np.asarray(expected), rtol=1e-4, atol=1e-4)
    assert not np.allclose(contexts[True], contexts[False], atol=1e-3)


def test_replanning_every_latent_executes_four_actions_and_keeps_their_frames(monkeypatch):
    """execute_latents=1: the model predicts from the whole chunk, the first latent (4 frames, the
    chunk's first 4 actions) becomes context, the policy re-plans; GRPO sees only executed tokens."""
    from sword_jax.rl import world_model_sim

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    captured = []

    def fake_predict(model_fn, first, context, actions, *, key, num_future, cfg, num_steps):
        captured.append(np.asarray(actions[0, :, 0]))
        # latent i of this call holds the call index * 10 + i, so the kept one is identifiable
        marks = len(captured) * 10.0 + jnp.arange(num_future, dtype=jnp.float32)
        return jnp.broadcast_to(marks[None, :, None, None, None], (1, num_future) + context.shape[2:])

    monkeypatch.setattr(world_model_sim, "predict_chunk", fake_predict)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                                execute_latents=1)
    assert (sim.chunk_len, sim.frames_per_step) == (8, 4)
    with pytest.raises(ValueError, match="execute_latents"):
        world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                              execute_latents=3)
    latents = jnp.zeros((2, 2, 2, cfg.vae.z_dim))
    start_actions = jnp.zeros((5, 7)).at[:, 0].set(jnp.asarray([100.0, 1.0, 2.0, 3.0, 4.0]))
    state = sim.init(StartState(jnp.zeros((32, 32, 3)), jnp.zeros(8), jnp.zeros(8, jnp.int32), (latents, start_actions)))
    chunk = lambda base: jnp.zeros((8, 7)).at[:, 0].set(base + jnp.arange(8.0))  # noqa: E731
    state, frames = sim.step(state, chunk(10.0), key=jax.random.key(0))
    assert frames.shape == (4, 32, 32, 3)
    np.testing.assert_array_equal(np.asarray(state.context)[0, :, 0, 0, 0], [10.0])  # the first latent is kept
    state, _ = sim.step(state, chunk(20.0), key=jax.random.key(1))
    np.testing.assert_array_equal(captured[0], [100, 1, 2, 3, 10, 11, 12, 13, 14, 15, 16, 17, 17])
    # after 4 executed actions the last context frame is 14's frame, and its slot takes the new chunk's first
    np.testing.assert_array_equal(captured[1], [100, 11, 12, 13, 20, 21, 22, 23, 24, 25, 26, 27, 27])
    np.testing.assert_array_equal(np.asarray(state.context)[0, :, 0, 0, 0], [20.0])


@pytest.mark.slow
def test_imagined_rollout_replanning_every_latent_records_executed_tokens():
    from sword_jax.rl import grpo

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    frames = jax.random.uniform(jax.random.key(2), (2, 32, 32, 3))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                                sample_steps=2, execute_latents=1)
    rl = RLConfig(image_size=8, action_bins=8, success_threshold=1.0,
                  policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32),
                  grpo=GRPOConfig(group_size=2), imagined=ImaginedConfig(max_chunks=3, execute_steps=4))
    graphdef, params = build_policy(rl)
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl", "open the drawer"], 32))
    start = expand_groups(StartState(frames, jnp.zeros((2, 8)), tokens, latents), 2)
    rollout = jax.jit(lambda p, s, k: imagined_rollout(graphdef, p, s, toy_reward_model(), start, rl, key=k,
                                                       record_frames=True))(params, sim, jax.random.key(0))
    assert rollout.frames.shape == (4, 3, 4, 32, 32, 3) and rollout.tokens.shape == (4, 3, 4, 7)
    state = grpo.init_state(params, rl)
    _, metrics = grpo.grpo_update(graphdef, rl, state, rollout)
    assert np.isfinite(float(metrics["loss"]))


@pytest.mark.parametrize("steps", [2, 6, 12])
def test_imagined_execute_steps_must_be_whole_latents_dividing_the_chunk(steps):
    with pytest.raises(ValueError, match=r"rl\.imagined\.execute_steps"):
        RLConfig(imagined=ImaginedConfig(execute_steps=steps)).validate()


def test_reckoned_proprio_follows_the_executed_actions_and_is_valid():
    """With proprio reckoning the policy reads the start proprio integrated over the executed actions
    (only the executed ones, when the simulator re-plans before the chunk ends)."""
    from sword_jax.rl.proprio_reckoning import ReckoningConfig, reckon

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    frames = jax.random.uniform(jax.random.key(2), (1, 32, 32, 3))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    proprio = jnp.asarray([0.1, 0.0, 1.0, 0.0, 0.0, 0.5, 0.04, -0.04], jnp.float32)
    start = StartState(frames[0], proprio, jnp.zeros((32,), jnp.int32), latents[0])
    chunk = jax.random.uniform(jax.random.key(3), (8, 7), minval=-1.0, maxval=1.0)
    reck = ReckoningConfig(rot_gain=(1.0, 1.0, 0.4))
    for execute_latents in (1, 2):
        sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                                    sample_steps=1, execute_latents=execute_latents, proprio_reckoning=reck)
        state = jax.jit(lambda s, x: s.init(x))(sim, start)  # jitted: eager op-by-op dispatch is far slower
        p0, valid0 = sim.observe(state)
        np.testing.assert_allclose(np.asarray(p0), np.asarray(proprio))
        state, _ = jax.jit(lambda s, st, c, k: s.step(st, c, key=k))(sim, state, chunk, jax.random.key(4))
        p1, valid1 = sim.observe(state)
        assert float(valid0) == float(valid1) == 1.0
        want = reckon(proprio, chunk[:4 * execute_latents], reck)[-1]
        np.testing.assert_allclose(np.asarray(p1), np.asarray(want), atol=1e-5)
    plain = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow, frame_size=32,
                                  sample_steps=1)
    assert float(plain.observe(plain.init(start))[1]) == 0.0


def test_the_simulators_chunk_follows_its_key_only_through_the_samplers_noise():
    """``flow.noise_scale`` reaches the learned simulator GRPO imagines in: at 0 a chunk's frames are the same under
    any key (one deterministic prediction per condition), at 1 two keys give two futures, and at 0.5 the future
    lies between them and the deterministic one."""
    import dataclasses

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    frames = jax.random.uniform(jax.random.key(2), (1, 32, 32, 3))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    start = StartState(frames[0], jnp.zeros((8,)), jnp.zeros((32,), jnp.int32), latents[0])
    chunk = jax.random.uniform(jax.random.key(3), (8, 7), minval=-1.0, maxval=1.0)

    def chunk_frames(scale, key):
        flow = dataclasses.replace(cfg.flow, noise_scale=scale)
        sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=flow, frame_size=32,
                                    sample_steps=2)
        run = jax.jit(lambda s, x, k: s.step(s.init(x), chunk, key=k)[1])
        return np.asarray(run(sim, start, jax.random.key(key)))

    still = chunk_frames(0.0, 0)
    np.testing.assert_array_equal(chunk_frames(0.0, 1), still)
    a, b = chunk_frames(1.0, 0), chunk_frames(1.0, 1)
    assert np.abs(a - b).mean() > 1e-4
    half = chunk_frames(0.5, 0)
    assert 0 < np.abs(half - still).mean() < np.abs(a - still).mean()


def _one_step(sim, latents, frames):
    """The simulator's start-up and first chunk on fixed inputs: ``(frames [2, T, H, W, 3], proprio_valid)``."""
    start = StartState(frames, jnp.zeros((2, 8)), jnp.zeros((2, 8), jnp.int32), latents)
    chunk = jax.random.uniform(jax.random.key(7), (2, sim.chunk_len, sim.action_dim), minval=-1.0, maxval=1.0)

    def run(sim, start, chunk, key):
        state = jax.vmap(sim.init)(start)
        _, out = jax.vmap(lambda s, c, k: sim.step(s, c, key=k))(state, chunk, jax.random.split(key, 2))
        return out

    return np.asarray(jax.jit(run)(sim, start, chunk, jax.random.key(3)))


def test_fast_simulator_is_within_tolerance_of_the_float32_path_which_stays_exact():
    """precision=float32 is the exact path (the simulator as built before the builder, bit for bit); the fast one
    (bf16 decode with bf16-stored VAE weights, sub-pixel upsampling) differs from it by rounding only."""
    from sword_jax.rl.sim_builder import FAST_FRAME_TOL, build_simulator

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    frames = jax.random.uniform(jax.random.key(2), (2, 32, 32, 3))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    kw = dict(flow_cfg=cfg.flow, frame_size=32, sample_steps=2)
    exact = _one_step(world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, **kw), latents, frames)
    f32_sim = build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, precision="float32", **kw)
    fast_sim = build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, **kw)  # the default
    np.testing.assert_array_equal(_one_step(f32_sim, latents, frames), exact)
    fast = _one_step(fast_sim, latents, frames)
    gap = float(np.abs(fast - exact).max())
    assert 0.0 < gap <= FAST_FRAME_TOL, gap  # not the same program, and close to it
    vae_kernels = {x.dtype for x in jax.tree.leaves(fast_sim.params[1]["decoder"]["head_conv"])}
    assert vae_kernels == {jnp.dtype(jnp.bfloat16)}
    assert {x.dtype for x in jax.tree.leaves(f32_sim.params)} == {jnp.dtype(jnp.float32)}
    with pytest.raises(ValueError, match="precision"):
        build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, precision="bf16", **kw)


def test_the_simulators_round_trip_is_its_vaes_still_keyframe_round_trip():
    """The frame the simulator shows of a real one: the real frame encoded as a still keyframe and decoded by the
    simulator's own VAE (float32: the loaded VAE's round trip; fast: the same up to its bfloat16 rounding)."""
    from sword_jax.rl.sim_builder import FAST_FRAME_TOL, build_simulator
    from sword_jax.rl.world_model_sim import vae_round_trip

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    frames = jax.random.uniform(jax.random.key(2), (3, 32, 32, 3))
    expected = np.asarray(jax.jit(vae_round_trip(vae_graphdef, vae_state))(frames))
    latents = encode_keyframes(vae_graphdef, vae_state, frames)
    decoded = _decoded_last_frame(vae_graphdef, vae_state, latents)
    np.testing.assert_allclose(expected, decoded, atol=1e-6)
    assert np.abs(expected - np.asarray(frames)).mean() > 0.01  # a random VAE does change the frames
    kw = dict(flow_cfg=cfg.flow, frame_size=32, sample_steps=2)
    for precision, tol in (("float32", 1e-5), ("fast", FAST_FRAME_TOL)):
        sim = build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, precision=precision, **kw)
        trip = np.asarray(jax.jit(lambda s, f: s.round_trip(f))(sim.replace(max_slice=2), frames))
        assert trip.shape == frames.shape and float(np.abs(trip - expected).max()) <= tol, precision


def _decoded_last_frame(vae_graphdef, vae_state, latents):
    """The last frame of the VAE's decode of ``latents``, in [0, 1]."""
    from sword_jax.vae import api as vae_api

    video = vae_api.decode(vae_graphdef, vae_state, latents, clamp=True)[:, -1]
    return np.clip((np.asarray(video) + 1.0) * 0.5, 0.0, 1.0)


def test_fast_simulator_stores_the_world_models_bfloat16_layers_in_bfloat16():
    """A bf16-compute world model (the default DiT) keeps its matmul weights in bf16 inside the fast simulator,
    loaded as ``(params, buffers)`` pure dicts or as one state; the float32 path keeps them as loaded."""
    import dataclasses

    from sword_jax.dit.action_dit import WorldModel
    from sword_jax.rl.sim_builder import build_simulator

    cfg, _, _, vae_graphdef, vae_state = _tiny_models()
    model = WorldModel(dataclasses.replace(cfg.model, compute_dtype="bfloat16"), rngs=nnx.Rngs(0))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    kw = dict(flow_cfg=cfg.flow, frame_size=32, sample_steps=2)
    for state in ((nnx.to_pure_dict(params), nnx.to_pure_dict(rest)), nnx.split(model)[1]):
        fast = build_simulator(graphdef, state, vae_graphdef, vae_state, **kw).params[0]
        q_kernel = (fast[0] if isinstance(fast, tuple) else fast)["dit"]["blocks"]["self_attn"]["q"]["kernel"]
        norm_scale = (fast[0] if isinstance(fast, tuple) else fast)["dit"]["blocks"]["self_attn"]["norm_q"]
        assert jnp.asarray(q_kernel).dtype == jnp.bfloat16
        assert {x.dtype for x in jax.tree.leaves(norm_scale)} == {jnp.dtype(jnp.float32)}  # read in float32
        exact = build_simulator(graphdef, state, vae_graphdef, vae_state, precision="float32", **kw).params[0]
        assert {x.dtype for x in jax.tree.leaves(exact)} == {jnp.dtype(jnp.float32)}


def test_simulator_microbatches_are_chosen_to_fit_the_decoders_features():
    """rl.imagined.sim_microbatches=0: the fewest slices of at most max_slice trajectories dividing the batch; the
    rule gives the 5B run's 4 slices of 8 at 256 px with the full Wan 2.2 decoder and one slice for small's."""
    from sword_jax.rl.rollout import microbatches_for
    from sword_jax.rl.sim_builder import max_slice_trajectories

    wan = {"decoder": {"head_conv": {"kernel": jax.ShapeDtypeStruct((3, 3, 3, 256, 12), jnp.float32)}}}
    small = {"decoder": {"head_conv": {"kernel": jax.ShapeDtypeStruct((3, 3, 3, 48, 12), jnp.float32)}}}
    assert max_slice_trajectories(wan, 256) == 8
    assert microbatches_for(32, 0, max_slice_trajectories(wan, 256)) == 4
    assert microbatches_for(64, 0, max_slice_trajectories(small, 128)) == 1
    assert microbatches_for(12, 0, 5) == 3 and microbatches_for(7, 0, 2) == 7  # slices must divide the batch
    assert microbatches_for(32, 2, 8) == 2 and microbatches_for(32, 0, None) == 1  # explicit; no limit
    with pytest.raises(ValueError, match="sim_microbatches"):
        ImaginedConfig(sim_microbatches=-1).validate()


def test_a_keyframes_prefix_is_its_episode_from_frame_0_held_at_the_keyframe():
    from sword_jax.rl import data as rl_data

    episodes = _counting_episodes(3, 40)
    s = rl_data.prefix_latents_for(episodes, max_fraction=0.5)
    assert s == 39 * 0.5 // 4  # the latest keyframe the draw can reach: latent 4 (frame 16)
    pick = rl_data.keyframe_starts(episodes, 16, np.random.default_rng(0), prefix_latents=s)
    assert pick["prefix"].shape[1] == 1 + 4 * s
    for i, t in enumerate(pick["t"]):
        np.testing.assert_array_equal(pick["prefix"][i, :, 0, 0, 0], np.minimum(np.arange(1 + 4 * s), t))
        assert pick["latent_index"][i] == t // 4
    with pytest.raises(ValueError, match="prefix_latents=1"):
        rl_data.keyframe_window(episodes.frames, episodes.actions, episodes.proprio, np.array([0]), np.array([8]),
                                prefix_latents=1)


def test_prefix_start_latents_are_the_whole_episodes_latents_the_window_ones_are_not():
    """rl.imagined.start_encoding=prefix: GRPO's start latents (first frame and context) are exactly the latents the
    latents stage makes by encoding whole episodes; the default window encoding differs from them once the
    keyframe has a past longer than its window (a random VAE here, whose causal cache reaches back far)."""
    import dataclasses

    from sword_jax.pipeline.grpo import setup_from_weights
    from sword_jax.rl import data as rl_data
    from sword_jax.rl.reward_model import build_detector
    from sword_jax.vae import api as vae_api

    cfg, wm_graphdef, wm_state, vae_graphdef, vae_state = _tiny_models()
    e, t, size = 3, 41, cfg.data.image_size
    frames = np.random.default_rng(0).integers(0, 256, (e, t, size, size, 3), dtype=np.uint8)
    episodes = rl_data.EpisodeSet(frames, np.zeros((e, t, 7), np.float32), np.zeros((e, t, 8), np.float32),
                                  np.array([41, 33, 29]), np.ones(e, bool), ("a", "b", "c"))
    whole = np.asarray(vae_api.encode(vae_graphdef, vae_state, jnp.asarray(frames, jnp.float32) / 127.5 - 1.0,
                                      check_values=False))  # (e, 1 + 10, ...): the latents stage's encoding
    errors = {}
    for encoding in ("prefix", "window"):
        rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, keyframe_fraction=1.0,
                                                                      start_encoding=encoding))
        setup = setup_from_weights(cfg, rl, episodes, world_model=(wm_graphdef, wm_state),
                                   vae=(vae_graphdef, vae_state), detector=build_detector(rl))
        pick = setup.windows(2)
        latents = np.asarray(setup.starts(None, 2).latents[0])
        truth = np.stack([whole[pick["episode"], 0], whole[pick["episode"], pick["t"] // 4]], axis=1)
        later = pick["t"] >= 12  # a past longer than the window's 8 frames
        assert later.any(), pick["t"]
        norm = lambda x: np.sqrt(np.sum(np.square(x), axis=(2, 3, 4)))  # noqa: E731 - per row and latent
        errors[encoding] = norm(latents - truth) / norm(truth)
    np.testing.assert_allclose(errors["prefix"], 0.0, atol=1e-3)
    np.testing.assert_allclose(errors["window"][:, 0], 0.0, atol=1e-3)  # the first frame's latent is its own
    assert errors["window"][later, 1].min() > 0.05, errors["window"]
    with pytest.raises(ValueError, match="start_encoding"):
        ImaginedConfig(start_encoding="whole").validate()


def test_prefix_encoding_in_slices_of_rows_is_the_same():
    from sword_jax.rl.world_model_sim import encode_prefix

    cfg, _, _, vae_graphdef, vae_state = _tiny_models()
    prefix = jax.random.uniform(jax.random.key(0), (5, 9, cfg.data.image_size, cfg.data.image_size, 3))
    index = np.array([1, 2, 2, 1, 2])
    whole = encode_prefix(vae_graphdef, vae_state, prefix, index, frames_per_call=10_000)
    sliced = encode_prefix(vae_graphdef, vae_state, prefix, index, frames_per_call=18)  # two rows a call
    np.testing.assert_allclose(np.asarray(sliced), np.asarray(whole), rtol=1e-5, atol=1e-5)
    assert whole.shape[:2] == (5, 2)
