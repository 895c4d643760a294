"""The world model's closed loop as training data (sword_jax.rl.closed_loop): segments laid out as the dataset's,
the train step's given-context rows (no cache read, no cache write), and the fine-tune's mixed batches."""

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.dlb.config import CacheConfig
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl import closed_loop as cl
from sword_jax.rl.refresh import given_rows
from sword_jax.world_model import data, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig
from tests.support.world_model import ProbeWorldModel, build, single_device_mesh


def _episode(num_latents=9, seed=0):
    rng = np.random.default_rng(seed)
    latents = rng.normal(size=(1, num_latents, 2, 2, 3)).astype(np.float32)
    actions = rng.normal(size=(1, 4 * (num_latents - 1) + 1, 2)).astype(np.float32)
    return data.LatentDataset(latents, actions)


@pytest.mark.parametrize("execute_latents", [1, 2])
def test_a_faithful_closed_loop_gives_the_datasets_own_segments(execute_latents):
    """A simulator whose closed loop were reality: its segments are the dataset's segments at the same latents
    (first frame, context, future and every action), except the last segment's last action, never executed."""
    ds = _episode()
    s0, decisions, x, p = 2, 3, execute_latents, 2
    lat, act = ds.latents[0], ds.actions[0]
    start_latents = np.stack([lat[0], lat[s0]])[None]
    start_actions = np.concatenate([act[:1], act[4 * s0 - 3: 4 * s0 + 1]])[None]
    length = decisions * x
    executed = act[4 * s0: 4 * s0 + 4 * length][None]  # frame 4 s0 + i carries action i
    real = lat[s0 + 1: s0 + 1 + length][None]
    contexts = np.stack([lat[s0 + (d + 1) * x][None] for d in range(decisions)])[None]  # [1, D, k=1, ...]
    segs = cl.closed_loop_segments(start_latents, start_actions, contexts, real, executed, num_future=p,
                                   execute_latents=x)
    kept = [d for d in range(decisions) if d * x + p <= length]
    assert list(segs.decision) == kept and segs.num == len(kept) and list(segs.trajectory) == [0] * len(kept)
    both = cl.ClosedLoopSegments.concatenate([segs, segs])
    assert both.num == 2 * segs.num and list(both.trajectory) == [0] * len(kept) + [1] * len(kept)
    assert both.subset(both.trajectory == 1).num == segs.num
    for i, d in enumerate(kept):
        want = ds.segment(np.array([0]), np.array([s0 + d * x]), 1, p)
        np.testing.assert_array_equal(segs.latents[i], want["latents"][0])
        last = d * x + p == length
        np.testing.assert_array_equal(segs.actions[i][: -1 if last else None],
                                      want["actions"][0][: -1 if last else None])
        if last:  # the action after the last executed one repeats it
            np.testing.assert_array_equal(segs.actions[i][-1], segs.actions[i][-2])
    # the closed loop's own context goes in where the simulator predicted from it
    drifted = contexts + 1.0
    segs = cl.closed_loop_segments(start_latents, start_actions, drifted, real, executed, num_future=p,
                                   execute_latents=x)
    np.testing.assert_array_equal(segs.latents[0, 1], lat[s0])  # decision 0: the start's real context
    for i, d in enumerate(kept[1:], start=1):
        np.testing.assert_array_equal(segs.latents[i, 1:2], drifted[0, d - 1])
    drift = cl.drift_by_decision(drifted, real, execute_latents=x)
    np.testing.assert_allclose(drift, np.ones(decisions))
    assert cl.drift_by_decision(contexts, real, execute_latents=x) == [0.0] * decisions


class _LatentToy(NamedTuple):
    toy: object
    context: jax.Array  # (1, k=1, 1, 1, 2): the toy gripper's position as a one-pixel latent


def _latent_toy():
    """The toy point world with a world model's context in its state: the gripper's position after each step."""
    toy = toy_simulator(frame_size=8, step_size=0.05, noise=0.05)

    def init_fn(params, start):
        state = toy.init_fn(params, start)
        return _LatentToy(state, state.position.reshape(1, 1, 1, 1, 2))

    def step_fn(params, state, chunk, key):  # re-plans after 4 actions, as the world model at 4 a decision
        moved, frames = toy.step_fn(params, state.toy, chunk[:4], key)
        return _LatentToy(moved, moved.position.reshape(1, 1, 1, 1, 2)), frames

    return toy.replace(init_fn=init_fn, step_fn=step_fn, observe_fn=lambda p, s: toy.observe_fn(p, s.toy),
                       execute_len=4)


def test_the_trace_keeps_each_decisions_actions_and_context_whatever_the_slicing():
    """trace_closed_loop: the executed actions of every decision (the simulator's execute_len of each chunk) and
    the context after it; the same trace with the simulator's calls in 2 slices (rl.imagined.sim_microbatches) as in
    one, group members differing by their sampled actions; a simulator whose state holds no context is refused."""
    rl = RLConfig(image_size=8, action_bins=8, proprio_dim=4, chunk_len=8,
                  policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
                  grpo=GRPOConfig(group_size=2), imagined=ImaginedConfig(max_chunks=3))
    graphdef, params = build_policy(rl, seed=0)
    tokens = jnp.asarray(tokenize_instructions(["put the bowl on the plate", "open the drawer"], 32))
    start = toy_start_states(tokens, key=jax.random.key(1), frame_size=8)
    sim, rm = _latent_toy(), toy_reward_model()
    traces = []
    for slices in (1, 2):
        r = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, sim_microbatches=slices))
        traces.append(jax.jit(lambda p, r=r: cl.trace_closed_loop(graphdef, p, sim, rm, start, r,
                                                                 key=jax.random.key(3), group_size=2,
                                                                 decisions=3))(params))
    one, two = traces
    assert one.actions.shape == (4, 12, 7) and one.contexts.shape == (4, 3, 1, 1, 1, 2)
    np.testing.assert_allclose(one.actions, two.actions, atol=1e-6)
    np.testing.assert_allclose(one.contexts, two.contexts, atol=1e-6)
    assert not np.allclose(one.actions[0], one.actions[1])  # a group's members sample their own actions
    # the context after a decision is where its 4 executed actions (and the noise) left the gripper: it moved
    moved = np.linalg.norm(np.diff(np.asarray(one.contexts)[..., 0, 0, 0, :], axis=1), axis=-1)
    assert np.all(moved > 0)
    with pytest.raises(ValueError, match="no context latents"):
        cl.trace_closed_loop(graphdef, params, toy_simulator(frame_size=8), rm, start, rl, key=jax.random.key(0),
                             group_size=1, decisions=1)


def test_closed_loop_segments_refuse_mismatched_arrays():
    z = np.zeros
    with pytest.raises(ValueError, match="real latents"):
        cl.closed_loop_segments(z((1, 2, 2, 2, 3)), z((1, 5, 2)), z((1, 3, 1, 2, 2, 3)), z((1, 2, 2, 2, 3)),
                                z((1, 12, 2)), num_future=2, execute_latents=1)
    with pytest.raises(ValueError, match="context latents"):
        cl.closed_loop_segments(z((1, 3, 2, 2, 3)), z((1, 5, 2)), z((1, 3, 1, 2, 2, 3)), z((1, 3, 2, 2, 3)),
                                z((1, 12, 2)), num_future=2, execute_latents=1)
    with pytest.raises(ValueError, match="no segment"):
        cl.closed_loop_segments(z((1, 2, 2, 2, 3)), z((1, 5, 2)), z((1, 1, 1, 2, 2, 3)), z((1, 1, 2, 2, 3)),
                                z((1, 4, 2)), num_future=2, execute_latents=1)


def test_real_latents_follow_the_keyframes_history_and_drop_it():
    seen = []

    def encode(video):  # a stand-in causal encoder: one latent for the first frame, one per 4 after it
        seen.append(video)
        n, f = video.shape[:2]
        groups = video[:, 1:].reshape(n, (f - 1) // 4, 4, *video.shape[2:]).mean(axis=(2, 3, 4, 5))
        return np.concatenate([video[:, :1].mean(axis=(2, 3, 4)), groups], axis=1)[..., None, None, None]

    first = np.full((3, 2, 2, 3), 255, np.uint8)
    history = np.full((3, 8, 2, 2, 3), 102, np.uint8)
    frames = np.stack([np.full((8, 2, 2, 3), v, np.uint8) for v in (0, 51, 102)])
    frames[:, 4:] += 51
    out = cl.real_latents(encode, first, history, frames, frames_per_latent=4, batch=2)
    assert out.shape == (3, 2, 1, 1, 1) and len(seen) == 2 and seen[0].shape[1] == 1 + 8 + 8
    np.testing.assert_allclose(seen[0][:, 1:9], 0.4)  # the history, in order, before the executed frames
    np.testing.assert_allclose(out[:, :, 0, 0, 0], [[0.0, 0.2], [0.2, 0.4], [0.4, 0.6]], atol=1e-6)
    with pytest.raises(ValueError, match="whole latents"):
        cl.real_latents(encode, first, history, frames[:, :7], frames_per_latent=4)
    with pytest.raises(ValueError, match="whole latents"):
        cl.real_latents(encode, first, history[:, :6], frames, frames_per_latent=4)


F32 = dict(dtype="float32")


def test_given_context_rows_are_neither_read_from_nor_written_to_the_cache(key):
    """Rows flagged ``given_context`` train on their own context even where the cache is filled and read at
    probability 1, and their predictions are not written into the cache; the other rows read it as before."""
    mesh = single_device_mesh()
    cfg = CacheConfig(read_prob_start=1.0, read_prob_end=1.0, **F32)
    graphdef, state, shardings, _, loader = build(mesh=mesh, cache_cfg=cfg, model_cls=ProbeWorldModel)
    shape = state.cache.latents.shape
    values = 100.0 + np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    state = state.replace(cache=state.cache.replace(
        latents=jax.device_put(jnp.asarray(values), shardings.cache.latents),
        filled=jax.device_put(jnp.ones(shape[:2], bool), shardings.cache.filled)))
    fn = train_step.make_train_step(graphdef, flow_cfg=FlowConfig(),
                                    trainer_cfg=TrainerConfig(learning_rate=1e-2, warmup_steps=0), cache_cfg=cfg,
                                    num_context=1, num_episodes=shape[0])
    batch_shardings = dict(loader.shardings, given_context=loader.shardings["episode"])
    step = train_step.compile_train_step(fn, shardings, batch_shardings, mesh)
    host = loader.host_batch_at(0)
    given = np.arange(len(host["episode"])) % 2 == 1
    host["given_context"] = given
    ProbeWorldModel.records.clear()
    new_state, metrics = step(state, jax.tree.map(jnp.asarray, host), key)
    jax.block_until_ready(metrics)
    seen = ProbeWorldModel.records[-1][0][:, 1]
    for i, (episode, start) in enumerate(zip(host["episode"], host["start"])):
        want = host["latents"][i, 1] if given[i] else values[episode, start]
        np.testing.assert_array_equal(seen[i], want)
    np.testing.assert_allclose(metrics["read_share"], 1.0 - given.mean())
    after = np.asarray(new_state.cache.latents)
    written_by_others = {(e, s + 1 + j) for e, s, g in zip(host["episode"], host["start"], given) if not g
                         for j in range(2)}
    for e, s, g in zip(host["episode"], host["start"], given):
        for j in range(2):
            if g and (e, s + 1 + j) not in written_by_others:
                np.testing.assert_array_equal(after[e, s + 1 + j], values[e, s + 1 + j])


def test_the_fine_tunes_mixed_batches_take_their_share_from_the_given_segments():
    ds = data.synthetic_latent_dataset(4, 6, 2, 2, 3, seed=0)
    mesh = single_device_mesh()
    loader = data.SegmentLoader(ds, data.SegmentSampler(4, 6, 1, 2, 8, seed=0), 1, 2, mesh)
    example = loader.host_batch_at(0)
    given = cl.ClosedLoopSegments(np.full((5,) + example["latents"].shape[1:], -7.0, np.float32),
                                  np.full((5,) + example["actions"].shape[1:], 3.0, np.float32), np.zeros(5, np.int32),
                                  np.arange(5, dtype=np.int32))
    host_batch_at, shardings = given_rows(loader, given, 0.25, seed=1)
    assert set(shardings) == set(loader.shardings) | {"given_context"}
    a, b = host_batch_at(3), host_batch_at(3)
    assert list(a["given_context"]) == [False] * 6 + [True] * 2
    assert np.all(a["latents"][6:] == -7.0) and np.all(a["actions"][6:] == 3.0)
    base = loader.host_batch_at(3)
    np.testing.assert_array_equal(a["latents"][:6], base["latents"][:6])
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])  # a function of the step
    for share in (0.0, 1.0, 0.01):
        with pytest.raises(ValueError, match="at least one row"):
            given_rows(loader, given, share, seed=1)
    wrong = given._replace(latents=given.latents[:, :3])
    with pytest.raises(ValueError, match="do not match"):
        given_rows(loader, wrong, 0.5, seed=1)


def test_segment_fit_is_a_function_of_the_weights_and_seed_and_keeps_its_compile():
    """segment_fit: the fixed-noise loss and sample error of a world model over segments, the same for the same
    weights and seed, other for other weights; the jitted measurement kept in ``compiled`` across calls."""
    import configs
    from flax import nnx

    from sword_jax.dit.action_dit import WorldModel
    from sword_jax.rl.refresh import segment_fit

    cfg = configs.get("sword:tiny")
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_layers=1))
    _, params, rest = nnx.split(WorldModel(cfg.model, rngs=nnx.Rngs(0)), nnx.Param, ...)
    other = jax.tree.map(lambda x: x + 0.01, params)  # (a fresh model's zero-initialised output ignores its seed)
    k, p = cfg.data.context_frames // cfg.vae.temporal_factor, cfg.data.predict_frames // cfg.vae.temporal_factor
    h = cfg.data.image_size // cfg.vae.spatial_factor
    rng = np.random.default_rng(0)
    latents = rng.normal(size=(5, 1 + k + p, h, h, cfg.model.in_dim)).astype(np.float32)
    actions = rng.normal(size=(5, 1 + 4 * (k + p), cfg.model.action_dim)).astype(np.float32)
    compiled = {}
    a = segment_fit(cfg, (params, rest), latents, actions, seed=3, batch=4, compiled=compiled)
    measure = compiled["measure"]
    b = segment_fit(cfg, (params, rest), latents, actions, seed=3, batch=4, compiled=compiled)
    c = segment_fit(cfg, (other, rest), latents, actions, seed=3, batch=4, compiled=compiled)
    assert compiled["measure"] is measure and set(a) == {"loss", "sample_error"}
    assert a == b and a != c and all(np.isfinite(v) and v > 0 for v in a.values())
    with pytest.raises(ValueError, match="no segments"):
        segment_fit(cfg, (params, rest), latents[:0], actions[:0], seed=3)



def test_segments_carry_the_actions_the_simulator_conditioned_each_decision_on(monkeypatch):
    """Against the world-model simulator itself (predict_chunk captured): at each decision the segment's first-frame
    and context actions and the decision's executed actions (the future frames it executes) are those the simulator
    passed the world model; later future frames carry the executed actions where the simulator had the plan."""
    from tests.test_rl_world_model_sim import START_ACTIONS, capturing_simulator

    sim, state, captured = capturing_simulator(monkeypatch, execute_latents=1)
    start_actions = START_ACTIONS
    chunks = [jnp.zeros((8, 7)).at[:, 0].set(base + jnp.arange(8.0)) for base in (10.0, 20.0, 30.0)]
    for i, chunk in enumerate(chunks):
        state, _ = sim.step(state, chunk, key=jax.random.key(i))
    executed = np.concatenate([np.asarray(c[:4]) for c in chunks])[None]  # [1, 12, 7]
    segs = cl.closed_loop_segments(np.zeros((1, 2, 2, 2, 3)), np.asarray(start_actions)[None],
                                   np.zeros((1, 3, 1, 2, 2, 3)), np.zeros((1, 3, 2, 2, 3)), executed, num_future=2,
                                   execute_latents=1)
    assert list(segs.decision) == [0, 1]
    for d in (0, 1):
        np.testing.assert_array_equal(segs.actions[d, :8, 0], captured[d][:8])
    np.testing.assert_array_equal(segs.actions[0, 8:, 0], [20, 21, 22, 23, 30])  # executed, not the plan 14..17


def test_with_the_prefix_the_real_latents_are_the_whole_episodes():
    """rl.imagined.start_encoding=prefix: the closed loop's start is a keyframe of a demonstration encoded from its
    frame 0 (``latent_index`` into its ``prefix``), its actions then executed; the real latents of the executed
    frames are those the latents stage makes of the whole episode, demonstration up to the keyframe then the
    executed frames, with keyframes at different latents padded to one prefix. The start latents of the same
    keyframes (keyframe_window, encode_prefix) are that episode's too."""
    from sword_jax.rl import data as rl_data
    from sword_jax.vae import api as vae_api
    from tests.support.vae import encoders, relative_error, tiny_vae, whole_latents

    cfg, vae_graphdef, vae_state = tiny_vae()
    size = cfg.data.image_size
    rng = np.random.default_rng(3)
    demos = rng.integers(0, 256, (3, 17, size, size, 3), dtype=np.uint8)
    executed = rng.integers(0, 256, (3, 8, size, size, 3), dtype=np.uint8)
    t = np.array([4, 12, 8])  # keyframes at latents 1, 3 and 2 of a prefix of 3
    window = rl_data.keyframe_window(demos, np.zeros((3, 17, 7), np.float32), np.zeros((3, 17, 8), np.float32),
                                     np.arange(3), t, prefix_latents=3)
    encoder = vae_api.encoder(vae_graphdef, vae_state)
    real = cl.real_latents(lambda video: encoder(video * np.float32(2.0) - np.float32(1.0)), window["first_frame"],
                           window["prefix"][:, 1:], executed, frames_per_latent=4, batch=2,
                           latent_index=window["latent_index"])
    _, encode_prefix = encoders()
    start = np.asarray(encode_prefix(jnp.asarray(window["prefix"], jnp.float32) / 255.0, window["latent_index"]))
    for i, keyframe in enumerate(t):
        whole = whole_latents(np.concatenate([demos[i, :keyframe + 1], executed[i]])[None])[0]
        s = keyframe // 4
        assert relative_error(real[i], whole[s + 1:s + 3]) < 1e-4, i
        assert relative_error(start[i], whole[[0, s]]) < 1e-4, i
    held = cl.real_latents(lambda video: encoder(video * np.float32(2.0) - np.float32(1.0)), window["first_frame"],
                           window["prefix"][:, 1:], executed, frames_per_latent=4)  # every row after the whole prefix
    assert relative_error(held[0], real[0]) > 0.05  # keyframe 4 held to frame 12 is another episode
    with pytest.raises(ValueError, match="latent_index"):
        cl.real_latents(encoder, window["first_frame"], window["prefix"][:, 1:], executed, frames_per_latent=4,
                        latent_index=np.array([1, 4, 2]))
