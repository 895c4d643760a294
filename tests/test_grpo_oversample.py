"""rl.imagined.oversample: GRPO in the learned simulator rolls out k x rollout_batch groups and updates on
rollout_batch of them, the mixed-outcome ones first (static shapes, inside the jitted step)."""

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.grpo_loop import grpo_run_id
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.policy import build_policy, tokenize_instructions

# 6 groups of 4: groups 1, 3 and 4 are mixed
RETURNS = jnp.asarray([[0, 0, 0, 0], [1, 0, 0, 0], [2, 2, 2, 2], [0, 2, 0, 2], [1, 1, 0, 1], [0, 0, 0, 0]],
                      jnp.float32)
MIXED = {1, 3, 4}


def test_select_groups_keeps_the_mixed_groups_first():
    for seed in range(8):
        picked = np.asarray(grpo.select_groups(RETURNS, 3, key=jax.random.key(seed)))
        assert picked.shape == (3,) and set(picked.tolist()) == MIXED  # exactly the mixed ones
        # fewer mixed than kept: every mixed group, first, then distinct groups without signal
        picked = np.asarray(grpo.select_groups(RETURNS, 5, key=jax.random.key(seed)))
        assert len(set(picked.tolist())) == 5 and set(picked[:3].tolist()) == MIXED
        assert not set(picked[3:].tolist()) & MIXED
    # more mixed than kept: the choice among them is the key's, not the lowest start indices
    choices = {tuple(sorted(np.asarray(grpo.select_groups(RETURNS, 2, key=jax.random.key(s))).tolist()))
               for s in range(16)}
    assert all(set(c) <= MIXED for c in choices) and len(choices) == 3, choices
    with pytest.raises(ValueError, match="keep must be in"):
        grpo.select_groups(RETURNS, 7, key=jax.random.key(0))


def test_select_groups_jits_once():
    select = jax.jit(chex.assert_max_traces(lambda r, key: grpo.select_groups(r, 3, key=key), n=1))
    for seed in range(3):
        assert set(np.asarray(select(RETURNS, jax.random.key(seed))).tolist()) == MIXED
    np.testing.assert_array_equal(np.asarray(grpo.group_trajectories(jnp.asarray([2, 0]), 3)), [6, 7, 8, 0, 1, 2])


def _coin_world(frame_size: int = 8) -> tuple[LearnedSimulator, RewardModel]:
    """A designed world: a start whose proprio[0] is 1 succeeds when the chunk's first action moves +x (about
    half of a fresh policy's samples: its groups are mixed), one whose proprio[0] is 0 never succeeds (no
    signal). The frame's red channel is the success; the reward model reads it."""

    def step_fn(params, can_succeed, chunk, key):
        del params, key
        hit = can_succeed * (chunk[0, 0] > 0).astype(jnp.float32)
        frames = jnp.zeros((chunk.shape[0], frame_size, frame_size, 3), jnp.float32).at[..., 0].set(hit)
        return can_succeed, frames

    sim = LearnedSimulator(params={}, init_fn=lambda params, start: start.proprio[0], step_fn=step_fn,
                           observe_fn=lambda params, state: (jnp.zeros((4,), jnp.float32), jnp.float32(1.0)),
                           chunk_len=8, frame_size=frame_size)
    return sim, RewardModel(params={}, score_fn=lambda params, frames: jnp.mean(frames[..., 0], axis=(-2, -1)))


def _starts(can_succeed) -> StartState:
    n = len(can_succeed)
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl"] * n, 32))
    proprio = jnp.zeros((n, 4), jnp.float32).at[:, 0].set(jnp.asarray(can_succeed, jnp.float32))
    return StartState(jnp.zeros((n, 8, 8, 3), jnp.float32), proprio, tokens, jnp.zeros((n, 0), jnp.float32))


def _cfg(oversample: int) -> RLConfig:
    return RLConfig(image_size=8, action_bins=8, proprio_dim=4,
                    policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
                    grpo=GRPOConfig(rollout_batch=2, group_size=8, learning_rate=1e-2),
                    imagined=ImaginedConfig(max_chunks=1, oversample=oversample))


def _skip_below(cfg: RLConfig, groups: int) -> RLConfig:
    return dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, min_mixed_groups=groups))


@pytest.mark.slow  # test_oversampled_step_on_a_mesh_matches_one_device runs an oversampled update in the default run
def test_oversampled_step_updates_on_the_mixed_groups():
    """Starts [never, never, coin, coin]: the plain step on the first rollout_batch=2 has no signal (and with
    rl.grpo.min_mixed_groups=1 applies no update); the oversampled one (k=2) rolls all 4 out and updates on the
    mixed coin groups."""
    sim, reward_model = _coin_world()
    base = _skip_below(_cfg(1), 1)
    graphdef, params = build_policy(base, seed=0)
    can_succeed = [0, 0, 1, 1]

    plain = grpo.make_grpo_step(graphdef, base, donate=False)
    first = grpo.init_state(params, base)
    after_one, one = plain(first, (sim, reward_model, _starts(can_succeed[:2])), jax.random.key(0))
    assert float(one["kept_fraction"]) == 0.0 == float(one["sampled_mixed_fraction"])
    assert float(one["imagined_success_sampled"]) == float(one["success_rate"]) == 0.0
    assert "mean_chunks_sampled" not in one  # only oversampling adds it
    assert float(one["mixed_groups"]) == 0.0 and float(one["skipped_update"]) == 1.0
    for before, after in zip(jax.tree.leaves((first.params, first.opt_state)),
                             jax.tree.leaves((after_one.params, after_one.opt_state)), strict=True):
        np.testing.assert_array_equal(np.asarray(after), np.asarray(before))
    assert int(after_one.step) == 1

    cfg = _skip_below(_cfg(2), 1)
    assert cfg.imagined_starts_per_step == 4
    state = grpo.init_state(params, cfg)
    step = grpo.make_grpo_step(graphdef, cfg, donate=False, max_traces=2)  # the last call is a refused shape
    new_state, two = step(state, (sim, reward_model, _starts(can_succeed)), jax.random.key(0))
    mixed_sampled = round(float(two["sampled_mixed_fraction"]) * 4)
    assert mixed_sampled == 2, two  # both coin groups are mixed (8 fair-ish coins each), the others never
    assert float(two["kept_fraction"]) == min(mixed_sampled, 2) / 2 == 1.0 > float(one["kept_fraction"])
    assert float(two["mixed_groups"]) == 2.0 and float(two["skipped_update"]) == 0.0  # the updated groups'
    # the sampled success counts all 32 trajectories; the updated 16 are the coin groups' (none of the never-groups)
    assert np.isclose(float(two["imagined_success_sampled"]) * 2, float(two["success_rate"]))
    assert float(two["mean_chunks_sampled"]) == 1.0 and float(two["updates"]) == 1.0
    moved = jax.tree.map(lambda a, b: float(jnp.max(jnp.abs(a - b))), new_state.params, state.params)
    assert max(jax.tree.leaves(moved)) > 0.0
    with pytest.raises(ValueError, match="oversample=2 must divide the step's 3 start states"):
        step(state, (sim, reward_model, _starts([0, 1, 1])), jax.random.key(0))


def test_oversample_config_and_run_identity():
    with pytest.raises(ValueError, match=r"rl\.imagined\.oversample must be >= 1"):
        _cfg(0).validate()
    plain, over = _cfg(1), _cfg(2)
    assert plain.imagined_starts_per_step == plain.grpo.rollout_batch
    # an oversample of 1 leaves the identity as it was (runs from before the setting resume); 2 changes it
    before = grpo_run_id(plain, seed=0, simulator="world_model")
    assert "rl.imagined.oversample" not in before
    assert before == grpo_run_id(dataclasses.replace(plain, imagined=dataclasses.replace(plain.imagined)), seed=0,
                                 simulator="world_model")
    after = grpo_run_id(over, seed=0, simulator="world_model")
    assert after["rl.imagined.oversample"] == 2 and after != before


def test_toy_setup_makes_the_oversampled_start_count():
    import configs
    from sword_jax.pipeline.grpo import toy_setup

    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, oversample=3))
    start = toy_setup(cfg, rl).starts(jax.random.key(0), 0)
    assert start.frame.shape[0] == 3 * rl.grpo.rollout_batch == rl.imagined_starts_per_step


@pytest.mark.slow
def test_grpo_entry_point_toy_oversampled(tmp_path):
    """``train.grpo --simulator toy`` with oversample 2: the starts, the step and the frames step_times counts."""
    import json
    import os

    from tests.support.rl import TINY_RL
    from train import grpo as grpo_main

    out = grpo_main.main(["--config", "sword:tiny", f"--workdir={tmp_path}", "--simulator", "toy",
                          "--rl.imagined.max_chunks=2", "--rl.grpo.rollout_batch=2", "--rl.grpo.group_size=2",
                          "--rl.grpo.eval_every=2", "--rl.grpo.steps=2", "--rl.imagined.oversample=2"] + TINY_RL)
    history = out["history"]
    assert [p["step"] for p in history] == [1, 2]
    assert all(0.0 <= p["sampled_mixed_fraction"] <= 1.0 and "imagined_success_sampled" in p for p in history)
    # a step's kept share is its mixed groups' among the update's 2, at most all of them
    for p in history:
        assert p["kept_fraction"] == min(round(p["sampled_mixed_fraction"] * 4), 2) / 2
    with open(os.path.join(out["workdir"], "step_times.jsonl")) as f:
        times = [json.loads(line) for line in f]
    import configs

    chunk_len = configs.get("sword:tiny").rl.chunk_len  # the toy simulator renders whole chunks
    for row, p in zip(times, history, strict=True):  # 4 starts x 2 trajectories rendered, not the update's 2 x 2
        assert row["imagined_frames"] == pytest.approx(4 * 2 * chunk_len * p["mean_chunks_sampled"])


def test_oversampled_step_on_a_mesh_matches_one_device():
    """The selection gathers trajectories across the data-sharded rollout: the same step on 8 devices."""
    from sword_jax import sharding as shd

    sim, reward_model = _coin_world()
    base = _cfg(2)
    cfg = dataclasses.replace(base, grpo=dataclasses.replace(base.grpo, rollout_batch=4, group_size=4))
    graphdef, params = build_policy(cfg, seed=0)
    batch = (sim, reward_model, _starts([0, 1, 0, 1, 0, 0, 1, 1]))
    one = grpo.make_grpo_step(graphdef, cfg, donate=False)
    mesh = shd.make_mesh(shd.MeshConfig(data=2, fsdp=2, tensor=2))
    sharded = grpo.make_grpo_step(graphdef, cfg, donate=False, mesh=mesh)
    _, want = one(grpo.init_state(params, cfg), batch, jax.random.key(3))
    _, got = sharded(grpo.init_state(params, cfg), batch, jax.random.key(3))
    for name in ("kept_fraction", "sampled_mixed_fraction", "success_rate", "mean_return", "imagined_success_sampled"):
        assert float(got[name]) == float(want[name]), name
    assert float(want["kept_fraction"]) == min(round(float(want["sampled_mixed_fraction"]) * 8), 4) / 4
    # the same selected trajectories give the same gradient (the parameters are no test: Adam's first step is
    # about lr x sign(grad), so summation-order noise on near-zero gradients flips whole steps, as without oversampling)
    np.testing.assert_allclose(float(got["grad_norm"]), float(want["grad_norm"]), rtol=1e-5)


def test_ground_truth_grpo_refuses_oversample():
    import configs
    from sim.grpo_training import run_grpo
    from sword_jax.pipeline.grpo import GRPOInputs

    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--rl.imagined.oversample=2"])
    with pytest.raises(SystemExit, match=r"rl\.grpo\.max_sample_rounds"):
        run_grpo(cfg, GRPOInputs(), simulator="env")
