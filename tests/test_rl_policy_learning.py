"""A policy that learns: the SFT schedule, continuous proprio, re-planning, and GRPO in real MuJoCo."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl.config import EnvConfig, GRPOConfig, PolicyConfig, RLConfig, SFTConfig
from sword_jax.rl.env_rollout import make_act_fns, max_decisions, run_policy, wilson_interval
from sword_jax.rl.policy import (axis_angle_to_matrix, build_policy, compute_proprio_stats, policy_logits,
                                 proprio_features, set_proprio_stats)
from sword_jax.rl.sft import sft_schedule


def test_sft_schedule_warms_up_then_decays_to_a_fraction_of_the_peak():
    cfg = RLConfig(sft=SFTConfig(learning_rate=1e-3, warmup_steps=50, lr_end_fraction=0.1))
    lr = sft_schedule(cfg, 1000)
    values = np.asarray([float(lr(s)) for s in range(0, 1001, 10)])
    assert float(lr(0)) == 0.0
    np.testing.assert_allclose(float(lr(50)), 1e-3, rtol=1e-6)
    np.testing.assert_allclose(float(lr(525)), 0.55e-3, rtol=1e-3)  # cosine midpoint between 1e-3 and 1e-4
    np.testing.assert_allclose(float(lr(1000)), 1e-4, rtol=1e-5)
    assert values.max() <= 1e-3 * (1 + 1e-6)
    assert np.all(np.diff(values[5:]) <= 1e-12)  # never rises after the warm-up


def test_rotation_features_are_continuous_across_the_axis_angle_flip():
    axis = np.array([0.6, 0.8, 0.0], np.float32)
    # a rotation just under and just over 180 degrees about `axis`: LIBERO's axis-angle flips sign
    below = (np.pi - 0.01) * axis
    above = -(np.pi - 0.01) * axis  # = rotation by pi + 0.01 about `axis`
    prop = np.zeros((2, 8), np.float32)
    prop[0, 3:6], prop[1, 3:6] = below, above
    feats = np.asarray(proprio_features(jnp.asarray(prop), "rot6d"))
    assert feats.shape == (2, 11)
    assert np.abs(prop[0] - prop[1]).max() > 3.0
    assert np.abs(feats[0] - feats[1]).max() < 0.03
    # Rodrigues agrees with a direct construction and is orthonormal
    rot = np.asarray(axis_angle_to_matrix(jnp.asarray(below)))
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-5)
    np.testing.assert_allclose(rot @ axis, axis, atol=1e-5)
    np.testing.assert_allclose(np.asarray(axis_angle_to_matrix(jnp.zeros(3))), np.eye(3), atol=1e-7)


def test_proprio_stats_normalise_and_round_trip_with_the_policy(tmp_path):
    from sword_jax.rl.params_io import load_params, save_params

    cfg = RLConfig(image_size=8, action_bins=16,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16))
    graphdef, params = build_policy(cfg, seed=0)
    proprio = np.random.default_rng(0).normal(size=(100, 8)).astype(np.float32) * 0.3 + 2.0
    stats = compute_proprio_stats(proprio, cfg)
    feats = np.asarray(proprio_features(jnp.asarray(proprio), "rot6d"))
    normalised = (feats - stats["mean"]) / stats["std"]
    np.testing.assert_allclose(normalised[:, :3].mean(0), 0.0, atol=1e-4)
    np.testing.assert_allclose(normalised[:, :3].std(0), 1.0, atol=1e-3)
    params = set_proprio_stats(params, stats)
    save_params(str(tmp_path / "p"), params, cfg, kind="policy")
    _, fresh = build_policy(cfg, seed=1)
    restored, _ = load_params(str(tmp_path / "p"), fresh, kind="policy")
    np.testing.assert_allclose(np.asarray(restored["proprio_mean"][...]), stats["mean"])
    np.testing.assert_allclose(np.asarray(restored["proprio_std"][...]), stats["std"])
    with pytest.raises(ValueError, match="std > 0"):
        set_proprio_stats(params, {"mean": stats["mean"], "std": np.zeros_like(stats["std"])})


class _CountingEnvs:
    """A lockstep env that records the action blocks it receives; succeeds after `solve_at` actions."""

    def __init__(self, n: int, solve_at: int, max_steps: int):
        self.n, self.language = n, ["reach the goal"] * n
        self.solve_at, self.max_steps = solve_at, max_steps
        self.blocks, self.steps = [], np.zeros(n, int)
        self.done = np.zeros(n, bool)

    def _obs(self):
        return {"frames": np.zeros((self.n, 16, 16, 3), np.uint8), "proprio": np.zeros((self.n, 8), np.float32)}

    def reset(self):
        self.steps[:] = 0
        self.done[:] = False
        return self._obs()

    def step(self, actions):
        self.blocks.append(actions.shape[1])
        before = self.steps.copy()
        self.steps = np.where(self.done, self.steps, np.minimum(self.steps + actions.shape[1], self.max_steps))
        success = ~self.done & (self.steps >= self.solve_at)
        self.steps = np.where(success, np.maximum(before, self.solve_at), self.steps)
        self.done |= success | (self.steps >= self.max_steps)
        return dict(self._obs(), success=success, executed=self.steps - before, done=self.done.copy())

    def close(self):
        pass


@pytest.mark.parametrize("execute_steps", [8, 3, 1])
def test_replanning_executes_the_configured_number_of_actions(execute_steps):
    cfg = RLConfig(image_size=8, action_bins=16,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16),
                   env=EnvConfig(execute_steps=execute_steps, action_ensemble=False))
    graphdef, params = build_policy(cfg, seed=0)
    envs = _CountingEnvs(n=2, solve_at=1000, max_steps=20)
    rollout = run_policy(make_act_fns(graphdef, cfg), params, envs, cfg, key=jax.random.key(0), greedy=False,
                         max_steps=20)
    assert set(envs.blocks) == {execute_steps}
    assert len(envs.blocks) == max_decisions(cfg, 20) == -(-20 // execute_steps)
    assert rollout.tokens.shape == (2, max_decisions(cfg, 20), execute_steps, 7)
    assert not rollout.success.any() and np.all(rollout.returns == 0)


def test_temporal_ensembling_averages_overlapping_chunk_predictions():
    from sword_jax.rl.env_rollout import _ensemble

    old = np.zeros((1, 4, 7), np.float32)
    old[0, :, 0] = [0.0, 1.0, 2.0, 3.0]
    new = np.full((1, 4, 7), 10.0, np.float32)
    # the newest chunk's step 0 and the older chunk's step 1 cover the same step; decay 0 = plain mean
    np.testing.assert_allclose(_ensemble([new, old], 0.0)[0, 0], 5.5)
    w = np.exp(-1.0)
    np.testing.assert_allclose(_ensemble([new, old], 1.0)[0, 0], (10.0 + w * 1.0) / (1 + w), rtol=1e-6)


def test_success_rates_come_with_wilson_intervals():
    lo, hi = wilson_interval(205, 500)
    assert lo < 0.41 < hi and hi - lo < 0.09
    assert wilson_interval(0, 10)[0] == 0.0


_HOME_TCP_X = None


def _moved_forward(env, state) -> bool:
    """Success of the test task: the tool centre moved >= 4 cm along +x from the home posture."""
    return bool(state.data.site_xpos[env.site_id][0] > _HOME_TCP_X + 0.04)


def test_grpo_against_the_mujoco_environment_improves_the_policy():
    """Real physics, real renderer, a reward that depends on the actions; the GRPO update of the
    ground-truth path (run_policy -> grpo_update) must raise the success rate within a few steps."""
    global _HOME_TCP_X
    from sim import tasks
    from sim.lockstep import LockstepEnvs
    from sword_jax.rl import grpo

    cfg = RLConfig(image_size=16, action_bins=16, chunk_len=4,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16),
                   grpo=GRPOConfig(group_size=8, rollout_batch=2, learning_rate=3e-3, clip_low=0.2, clip_high=0.28),
                   env=EnvConfig(execute_steps=4, action_ensemble=False))
    graphdef, params = build_policy(cfg, seed=0)
    starts = [(0, q) for q in tasks.split_init_states(0, "train", 2)]
    episodes = [s for s in starts for _ in range(cfg.grpo.group_size)]
    with LockstepEnvs(episodes[:1], resolution=16, max_steps=1, renderer="jax") as probe:
        probe.reset()
        env = probe._local.envs[0]
        _HOME_TCP_X = float(probe._local.states[0].data.site_xpos[env.site_id][0])
    act = make_act_fns(graphdef, cfg)
    update = jax.jit(lambda s, b: grpo.grpo_update(graphdef, cfg, s, b))
    state = grpo.init_state(params, cfg)
    rates = []
    with LockstepEnvs(episodes, resolution=16, max_steps=8, renderer="jax", success_fn=_moved_forward) as envs:
        for step in range(8):
            rollout = run_policy(act, state.params, envs, cfg, key=jax.random.key(step), greedy=False, max_steps=8)
            rates.append(float(np.mean(rollout.success)))
            state, metrics = update(state, jax.tree.map(jnp.asarray, rollout))
            assert np.isfinite(float(metrics["loss"]))
    assert np.mean(rates[-3:]) > np.mean(rates[:2]) + 0.25, rates
    # the learned behaviour is in the policy: its greedy x-action is now forward
    # jitted: eager op-by-op dispatch of the forward pass takes several times longer
    logits = jax.jit(lambda p, f, t, q: policy_logits(graphdef, p, f, t, q))(
        state.params, jnp.asarray(rollout.obs_frames[:2, 0] / 255.0), jnp.asarray(rollout.instruction_tokens[:2]),
        jnp.asarray(rollout.proprio[:2, 0]))
    assert np.all(np.asarray(jnp.argmax(logits[:, 0, 0, :], -1)) >= cfg.action_bins // 2)  # first x-action forward


@pytest.mark.parametrize("greedy", [True, False])
def test_default_execution_re_plans_every_step_and_ensembles_only_greedy_rollouts(greedy):
    cfg = RLConfig(image_size=8, action_bins=16,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16))
    assert cfg.env.execute_steps == 1 and cfg.env.action_ensemble  # the mode measured best (README)
    graphdef, params = build_policy(cfg, seed=0)
    envs = _CountingEnvs(n=2, solve_at=1000, max_steps=6)
    rollout = run_policy(make_act_fns(graphdef, cfg), params, envs, cfg, key=jax.random.key(0), greedy=greedy,
                         max_steps=6)
    assert envs.blocks == [1] * 6 and rollout.tokens.shape == (2, 6, 1, 7)
    with pytest.raises(ValueError, match="action_ensemble=false"):
        dataclasses.replace(cfg, env=dataclasses.replace(cfg.env, execute_steps=4)).validate()


def test_evaluate_in_sim_runs_the_given_episodes_in_the_given_envs():
    from sword_jax.rl.policy_success import evaluate_in_sim

    cfg = RLConfig(image_size=8, action_bins=16,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16),
                   env=EnvConfig(execute_steps=2, action_ensemble=False))
    graphdef, params = build_policy(cfg, seed=0)
    episodes = [(3, np.zeros(2)), (3, np.ones(2)), (1, np.zeros(2)), (1, np.ones(2)), (1, np.ones(2))]
    made = []

    class Envs(_CountingEnvs):
        def close(self):
            made.append("closed")

    def factory(eps):
        made.append(list(eps))
        return Envs(n=len(eps), solve_at=np.array([2, 2, 100, 100, 4]), max_steps=6)

    result = evaluate_in_sim(graphdef, params, cfg, episodes=episodes, envs_factory=factory, max_steps=6)
    assert made == [episodes, "closed"]
    assert list(result["per_task"].items()) == [("3", 1.0), ("1", 1 / 3)]  # in the episodes' task order
    assert (result["episodes"], result["successes"], result["mean"]) == (5, 3, 0.6)
    assert result["ci95"] == list(wilson_interval(3, 5))
    with pytest.raises(ValueError, match=r"needs envs_factory: .*lockstep_evaluation"):
        evaluate_in_sim(graphdef, params, cfg, episodes=episodes)
    with pytest.raises(ValueError, match=r"needs episodes and envs_factory"):
        evaluate_in_sim(graphdef, params, cfg)


def test_lockstep_evaluation_gives_the_fixed_evaluation_states_and_a_lockstep_factory():
    from sim import tasks
    from sim.lockstep import LockstepEnvs, lockstep_evaluation

    setup = lockstep_evaluation((2, 5), 3, resolution=16, max_steps=9, renderer="gl", workers=2)
    assert [t for t, _ in setup["episodes"]] == [2, 2, 2, 5, 5, 5] and setup["max_steps"] == 9
    np.testing.assert_array_equal(np.stack([q for _, q in setup["episodes"][3:]]),
                                  tasks.split_init_states(5, "eval", 3))
    factory = setup["envs_factory"]
    assert factory.func is LockstepEnvs
    assert factory.keywords == dict(resolution=16, max_steps=9, renderer="gl", workers=2)
    with pytest.raises(ValueError, match="episodes_per_task"):
        lockstep_evaluation((0,), tasks.NUM_INIT_STATES + 1, resolution=16)


def test_evaluate_in_sim_can_run_the_sampled_policy():
    """``greedy=False`` evaluates the policy GRPO trains: identical episodes then act differently
    (each samples its own tokens), where the greedy evaluation acts identically; a key fixes them."""
    from sword_jax.rl.policy_success import evaluate_in_sim

    cfg = RLConfig(image_size=8, action_bins=16,
                   policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16),
                   env=EnvConfig(execute_steps=2, action_ensemble=False))
    graphdef, params = build_policy(cfg, seed=0)
    episodes = [(0, np.zeros(2))] * 4

    def actions_of(**kwargs):
        received = []

        class Envs(_CountingEnvs):
            def step(self, actions):
                received.append(np.asarray(actions))
                return super().step(actions)

        result = evaluate_in_sim(graphdef, params, cfg, episodes=episodes, max_steps=4,
                                 envs_factory=lambda eps: Envs(n=len(eps), solve_at=100, max_steps=4), **kwargs)
        assert result["episodes"] == 4
        return np.concatenate(received, axis=1)  # (episodes, actions, 7)

    greedy = actions_of()
    assert all(np.array_equal(greedy[0], row) for row in greedy[1:])
    sampled = actions_of(greedy=False, key=jax.random.key(1))
    assert not all(np.array_equal(sampled[0], row) for row in sampled[1:])
    np.testing.assert_array_equal(actions_of(greedy=False, key=jax.random.key(1)), sampled)
    assert not np.array_equal(actions_of(greedy=False, key=jax.random.key(2)), sampled)
