"""The value that closes short GRPO rollouts (sword_jax.rl.value, rl.value): its returns, its fit and calibration,
the rollout that pays it, and ground-truth GRPO fitting it once and loading the fit on resume."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import configs
from sword_jax.rl import grpo
from sword_jax.rl.config import RLConfig, ValueConfig
from sword_jax.rl.jax_env_grpo import EnvGRPO, advantage_sources, branch_starts, mixed_groups, start_value
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.scan_rollout import scan_rollout
from sword_jax.rl.value import (Value, ValueData, as_value, build_value, calibration, decision_samples, fit_value,
                                predict, split_episodes, terminal_returns)
from tests.test_scan_rollout import SIZE, BreakingSlideEnv, SlideEnv


class SnapshotSlideEnv(SlideEnv):
    """SlideEnv that can snapshot its state (the position), which reset continues."""

    def snapshot(self, pos):
        return pos[:, None]


def _rl(**value):
    cfg = configs.get("sword:tiny")
    return dataclasses.replace(cfg.rl, image_size=SIZE, grpo=dataclasses.replace(
        cfg.rl.grpo, rollout_batch=2, group_size=4, minibatches=1, ppo_epochs=1, update_microbatch=0, temperature=1.0),
        value=dataclasses.replace(cfg.rl.value, **value), env=dataclasses.replace(cfg.rl.env, backend="mjx"))


def test_terminal_returns_pay_success_the_value_at_the_horizon_and_nothing_for_failure():
    success = jnp.array([True, False, False, True])
    truncated = jnp.array([False, True, False, True])  # the last: a success is never paid its value on top
    out = terminal_returns(success, truncated, jnp.array([0.9, 0.25, 0.7, 0.5]), 2.0)
    np.testing.assert_allclose(np.asarray(out), [2.0, 0.5, 0.0, 2.0])
    np.testing.assert_allclose(np.asarray(terminal_returns(success, truncated, jnp.array([0, 1.7, 0, 0]), 1.0)),
                               [1.0, 1.0, 0.0, 1.0])  # a value outside [0, 1] is clipped


def test_calibration_on_designed_scores():
    labels = np.array([0, 0, 1, 1], np.float32)
    good = calibration(np.array([0.1, 0.2, 0.8, 0.9]), labels, bins=2)
    assert good["auc"] == 1.0 and good["brier"] == pytest.approx(0.025) and good["brier_constant"] == 0.25
    assert good["positive_rate"] == 0.5 and [b["count"] for b in good["bins"]] == [2, 2]
    assert good["bins"][1]["observed"] == 1.0 and good["bins"][1]["predicted"] == pytest.approx(0.85)
    assert calibration(np.array([0.9, 0.8, 0.2, 0.1]), labels)["auc"] == 0.0
    assert calibration(np.full(4, 0.5), labels)["auc"] == 0.5  # ties share their rank
    assert calibration(np.full(3, 0.5), np.ones(3))["auc"] is None  # one class: no ranking to judge
    with pytest.raises(ValueError, match="equal"):
        calibration(np.zeros(3), np.zeros(4))


def test_decision_samples_label_every_valid_decision_with_its_episode_outcome():
    frames = np.arange(2 * 3 * 2 * 2 * 3, dtype=np.uint8).reshape(2, 3, 2, 2, 3)
    valid = np.array([[1, 1, 0], [1, 1, 1]], np.float32)
    tokens = np.array([[5, 0], [7, 8]], np.int32)
    states = np.arange(2 * 3 * 2, dtype=np.float32).reshape(2, 3, 2)
    data = decision_samples(frames, valid, tokens, np.array([True, False]), states)
    np.testing.assert_array_equal(data.states[2], states[1, 0])
    assert decision_samples(frames, valid, tokens, np.array([True, False])).states.shape == (5, 0)
    both = ValueData.concatenate([data, data])
    assert len(both) == 10 and both.episode.tolist() == [0, 0, 1, 1, 1, 2, 2, 3, 3, 3]
    assert len(data) == 5 and data.labels.tolist() == [1, 1, 0, 0, 0] and data.episode.tolist() == [0, 0, 1, 1, 1]
    np.testing.assert_array_equal(data.frames[2], frames[1, 0])
    np.testing.assert_array_equal(data.tokens[3], tokens[1])
    fit, held = split_episodes(data, 0.5, np.random.default_rng(0))
    assert len(fit) + len(held) == 5 and set(fit.episode).isdisjoint(held.episode) and len(set(held.episode)) == 1
    with pytest.raises(ValueError, match="agree"):
        decision_samples(frames, valid[:, :2], tokens, np.array([True, False]))
    with pytest.raises(ValueError, match="no valid decision"):
        decision_samples(frames, np.zeros_like(valid), tokens, np.array([True, False]))


# A learning property (11 s on 2 cores); the default run fits the value in
# test_a_runner_without_a_value_fits_it_but_pays_success_alone_and_branches_where_its_env_snapshots.
@pytest.mark.slow
def test_fit_value_learns_what_the_frame_and_the_instruction_say_together():
    """Designed data: the episode succeeds when the frame is bright for instruction A and dark for instruction B,
    so neither the frame nor the instruction alone predicts it; held-out Brier far below the constant's."""
    rl = _rl(steps=100, batch_size=64, learning_rate=3e-3, width=8)  # Brier ~1e-4 of the constant's at 100 steps
    rng = np.random.default_rng(0)
    n = 400
    bright = rng.random(n) < 0.5
    which = rng.random(n) < 0.5
    frames = np.where(bright[:, None, None, None], 200, 40).astype(np.uint8) * np.ones((1, SIZE, SIZE, 3), np.uint8)
    frames = np.clip(frames.astype(np.int32) + rng.integers(-20, 20, frames.shape), 0, 255).astype(np.uint8)
    tokens = np.where(which[:, None], tokenize_instructions(["pick a"], 16), tokenize_instructions(["put b"], 16))
    labels = (bright == which).astype(np.float32)
    data = ValueData(frames, tokens.astype(np.int32), labels, np.arange(n, dtype=np.int32), np.zeros((n, 0), np.float32))
    fit, held = split_episodes(data, 0.25, np.random.default_rng(1))
    graphdef, params = build_value(rl, seed=0)
    params, metrics = fit_value(graphdef, params, rl, fit, seed=0, log=lambda _: None)
    report = calibration(predict(as_value(graphdef, params), held), held.labels)
    assert report["brier"] < 0.25 * report["brier_constant"] and report["auc"] > 0.95, report
    assert np.isfinite(metrics["loss"])


def _value_fn(p, frames, tokens):  # a designed value: the final frame's brightness, scaled by p
    del tokens
    return jnp.mean(frames, axis=(1, 2, 3)) * p


def test_scan_rollout_pays_a_rollout_cut_at_its_horizon_its_final_frames_value():
    rl = _rl()
    graphdef, params = build_policy(rl, seed=0)
    starts = np.array([[0.34], [0.34], [-0.6], [-0.6]], np.float32)  # near the goal, and too far for 4 actions
    tokens = jnp.asarray(tokenize_instructions(["push it"] * 4, rl.policy.max_instruction_bytes))
    bonus = 1.0 + rl.grpo.success_bonus

    def run(value, max_steps, env=SlideEnv()):
        return jax.jit(lambda p, s, k, vp: scan_rollout(
            graphdef, p, env, s, tokens, rl, key=k, greedy=False, ensemble=False, max_steps=max_steps,
            value=None if value is None else Value(value, vp)))(params, jnp.asarray(starts), jax.random.key(2),
                                                              jnp.float32(0.5))

    plain, _ = run(None, 4)
    valued, stats = run(_value_fn, 4)
    longer, _ = run(None, 5)  # the same draws: its decision 4 sees the frame the 4-action rollout ended on
    success = np.asarray(valued.success)
    np.testing.assert_array_equal(success, np.asarray(plain.success))
    final = np.asarray(longer.obs_frames)[:, 4].astype(np.float32).mean(axis=(1, 2, 3)) / 255.0
    expected = np.where(success, bonus, bonus * 0.5 * final)
    assert (~success).sum() >= 2
    np.testing.assert_allclose(np.asarray(valued.returns), expected, rtol=1e-5)
    assert np.all(final[~success] > 0.0)
    np.testing.assert_allclose(np.asarray(stats.terminal_value)[~success], 0.5 * final[~success], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(plain.returns), np.where(success, bonus, 0.0))
    np.testing.assert_allclose(np.asarray(valued.rewards).sum(axis=1), expected / bonus, rtol=1e-5)
    # a rollout whose physics broke is a failure, whatever its frame is worth
    broken_starts = np.array([[-0.25], [-0.25], [-0.25], [-0.25]], np.float32)
    out, b_stats = jax.jit(lambda p, k: scan_rollout(
        graphdef, p, BreakingSlideEnv(), jnp.asarray(broken_starts), tokens, rl, key=k, greedy=False, ensemble=False,
        max_steps=8, value=Value(lambda p, f, t: jnp.ones(f.shape[0]), jnp.float32(1.0))))(params, jax.random.key(5))
    broke = np.asarray(b_stats.broken)
    assert broke.any() and np.all(np.asarray(out.returns)[broke] == 0.0)


def _runner(rl, params, graphdef, value_graphdef, value_params, tmp_starts):
    tokens = tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes)
    return EnvGRPO(graphdef, rl, SnapshotSlideEnv(), max_steps=12, starts_at=lambda s, r: (tmp_starts(s, r), tokens),
                   eval_starts=np.array([[0.3], [-1.0]], np.float32), eval_tokens=tokens, eval_tasks=[0, 1],
                   key=jax.random.key(3), train_max_steps=4, train_execute_steps=4, train_proprio=False,
                   value=as_value(value_graphdef, value_params))


@pytest.mark.slow  # an env GRPO run with the value; the fit and the branching tests keep the value in the default run
def test_env_grpo_fits_the_value_once_pays_its_rollouts_with_it_and_loads_the_fit_on_resume(tmp_path):
    rl = _rl(episodes=12, steps=20, batch_size=16, width=4, holdout=0.25)
    graphdef, params = build_policy(rl, seed=0)
    value_graphdef, value_params = build_value(rl, seed=0)
    drawn = []

    def starts(round_):
        drawn.append(round_)
        return np.array([[-0.2], [0.1]], np.float32), tokenize_instructions(["push it"] * 2, 96)

    runner = _runner(rl, params, graphdef, value_graphdef, value_params,
                     lambda s, r: np.array([[-0.2], [0.1]], np.float32))
    record, decisions = start_value(runner, params, str(tmp_path / "value"), seed=0, max_steps=12,
                                    starts_at=starts, log=lambda _: None)
    assert drawn == [0, 1]  # 12 episodes: two rounds of 8
    assert len(decisions) == record["decisions"] and decisions.states.shape == (len(decisions), 1)
    assert np.all(decisions.states[decisions.episode == 0][:1] == -0.2)  # the first decision is the start state
    assert record["real_episodes"] == 12 and record["held_out_episodes"] == 3 and record["fit_episodes"] == 9
    assert 0.0 <= record["episode_success"] <= 1.0 and record["held_out"]["samples"] > 0
    fitted = runner.value.params
    assert not all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(fitted), jax.tree.leaves(value_params)))

    state = grpo.init_state(jax.tree.map(jnp.copy, params), rl)
    _, metrics = runner.step(state, 0, jax.random.key(1))
    assert 0.0 < float(metrics["truncated_fraction"]) <= 1.0 and 0.0 < float(metrics["terminal_value"]) < 1.0
    assert 0.0 <= float(metrics["success_advantage_share"]) <= 1.0 and float(metrics["return_spread"]) > 0.0

    # a resumed run loads the fit: same params, no episodes collected
    drawn.clear()
    again = _runner(rl, params, graphdef, value_graphdef, build_value(rl, seed=1)[1],
                    lambda s, r: np.array([[-0.2], [0.1]], np.float32))
    record_again, decisions_again = start_value(again, params, str(tmp_path / "value"), seed=0,
                                                max_steps=12, starts_at=starts, log=lambda _: None)
    assert record_again == record and drawn == []
    np.testing.assert_array_equal(decisions_again.states, decisions.states)
    np.testing.assert_array_equal(decisions_again.labels, decisions.labels)
    np.testing.assert_array_equal(decisions_again.predicted, decisions.predicted)
    for a, b in zip(jax.tree.leaves(again.value.params), jax.tree.leaves(fitted)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    _, again_metrics = again.step(grpo.init_state(jax.tree.map(jnp.copy, params), rl), 0, jax.random.key(1))
    assert float(again_metrics["terminal_value"]) == pytest.approx(float(metrics["terminal_value"]), rel=1e-5)


def test_groups_gain_a_signal_when_the_horizon_cuts_every_rollout():
    """From starts no 4-action rollout can finish, success alone gives no group a spread; the value gives all."""
    rl = _rl()
    graphdef, params = build_policy(rl, seed=0)
    far = jnp.asarray(np.full((8, 1), -0.6, np.float32))
    tokens = jnp.asarray(tokenize_instructions(["push it"] * 8, rl.policy.max_instruction_bytes))
    kwargs = dict(key=jax.random.key(0), greedy=False, ensemble=False, max_steps=4)
    plain, _ = scan_rollout(graphdef, params, SlideEnv(), far, tokens, rl, **kwargs)
    valued, _ = scan_rollout(graphdef, params, SlideEnv(), far, tokens, rl, value=Value(_value_fn, 1.0), **kwargs)
    assert not np.asarray(mixed_groups(plain.returns, 4)).any()
    assert np.asarray(mixed_groups(valued.returns, 4)).all()


def test_open_branch_starts_favour_decisions_whose_outcome_the_value_leaves_open():
    n = 1000
    decisions = ValueData(np.zeros((n, 0, 0, 3), np.uint8), np.ones((n, 4), np.int32), np.zeros(n, np.float32),
                          np.arange(n, dtype=np.int32), np.arange(n, dtype=np.float32)[:, None],
                          np.where(np.arange(n) < 100, 0.5, 0.01).astype(np.float32))
    states, _ = branch_starts(decisions, 2000, np.random.default_rng(0), "open")
    share = np.mean(states[:, 0] < 100)  # 100 x 0.2525 against 900 x 0.0124 (1% of 0.25 added): 0.69 of the draws
    assert 0.65 < share < 0.74, share
    uniform, _ = branch_starts(decisions, 2000, np.random.default_rng(0))
    assert np.mean(uniform[:, 0] < 100) < 0.15
    decided = dataclasses.replace(decisions, predicted=np.ones(n, np.float32))  # every outcome settled: uniform
    assert len(np.unique(branch_starts(decided, 500, np.random.default_rng(0), "open")[0])) > 300
    with pytest.raises(ValueError, match="needs the fitted value's prediction"):
        branch_starts(dataclasses.replace(decisions, predicted=None), 5, np.random.default_rng(0), "open")


def test_advantage_sources_say_how_much_of_the_update_real_outcomes_carry():
    """A group split by success and a group of values differing by 0.1: the group std gives them equal weight,
    centred advantages (Dr. GRPO) give the success group 91% of it."""
    returns = np.array([2.0, 0.0, 0.0, 0.0, 0.2, 0.4, 0.2, 0.2], np.float32)
    success = np.array([1, 0, 0, 0, 0, 0, 0, 0], bool)
    rl = _rl()
    assert rl.grpo.group_size == 4 and rl.grpo.success_bonus == 1.0
    by_std = advantage_sources(returns, success, rl)
    assert by_std["success_advantage_share"] == pytest.approx(0.5, abs=1e-4)
    assert by_std["return_spread"] == pytest.approx((np.std([2, 0, 0, 0]) + np.std([0.2, 0.4, 0.2, 0.2])) / 2 / 2)
    centred = advantage_sources(returns, success, dataclasses.replace(
        rl, grpo=dataclasses.replace(rl.grpo, scale_by_std=False)))
    assert centred["success_advantage_share"] == pytest.approx(3.0 / 3.3, abs=1e-4)
    everyone = advantage_sources(returns, np.ones(8, bool), rl)  # a group that all succeeded is not split
    assert everyone["success_advantage_share"] == 0.0


def test_value_config_is_checked_and_runs_on_mjx_only():
    ValueConfig().validate()
    for bad in (dict(episodes=-1), dict(steps=0), dict(batch_size=0), dict(width=0), dict(learning_rate=0.0),
                dict(holdout=1.0), dict(holdout=-0.1), dict(episodes=True), dict(steps=2.5)):
        with pytest.raises(ValueError, match="rl.value"):
            ValueConfig(**bad).validate()
    with pytest.raises(ValueError, match="rl.value.episodes > 0 .* rl.env.backend=mjx"):
        RLConfig(value=ValueConfig(episodes=8)).validate()
    mjx = dataclasses.replace(RLConfig().env, backend="mjx")
    RLConfig(value=ValueConfig(episodes=8), env=mjx).validate()
    RLConfig(value=ValueConfig(episodes=8), env=dataclasses.replace(mjx, starts="branch")).validate()
    with pytest.raises(ValueError, match="rl.env.starts=branch .* rl.value.episodes > 0"):
        RLConfig(env=dataclasses.replace(mjx, starts="branch")).validate()
    with pytest.raises(ValueError, match="rl.value.bootstrap"):
        ValueConfig(bootstrap="yes").validate()
    with pytest.raises(ValueError, match="rl.value.branch_starts"):
        ValueConfig(branch_starts="hard").validate()
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--rl.value.episodes=64", "--rl.env.backend=mjx"])
    assert cfg.rl.value.episodes == 64


def test_a_runner_without_a_value_fits_it_but_pays_success_alone_and_branches_where_its_env_snapshots(tmp_path):
    """rl.value.bootstrap=false: the control arm. The value is fitted and reported, the rollouts are paid success
    alone; branch starts come from the recorded decisions, and an environment without snapshots has none."""
    rl = _rl(episodes=8, steps=5, batch_size=8, width=4, bootstrap=False)
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes)
    far = np.array([[-0.6], [-0.6]], np.float32)
    runner = EnvGRPO(graphdef, rl, SnapshotSlideEnv(), max_steps=12, starts_at=lambda s, r: (far, tokens),
                     eval_starts=far, eval_tokens=tokens, eval_tasks=[0, 1], key=jax.random.key(0), train_max_steps=4,
                     train_execute_steps=4)
    record, decisions = start_value(runner, params, str(tmp_path), seed=0, max_steps=12,
                                    starts_at=lambda r: (far, tokens), log=lambda _: None)
    assert runner.value is None and record["real_episodes"] == 8
    _, metrics = runner.step(grpo.init_state(jax.tree.map(jnp.copy, params), rl), 0, jax.random.key(1))
    assert "terminal_value" not in metrics and float(metrics["rollout_success"]) == 0.0
    states, picked_tokens = branch_starts(decisions, 5, np.random.default_rng(0))
    assert states.shape == (5, 1) and picked_tokens.shape == (5, tokens.shape[1])
    assert np.all(np.isin(states[:, 0], decisions.states[:, 0]))
    assert decisions.predicted is not None and decisions.predicted.shape == (len(decisions),)
    with pytest.raises(ValueError, match="uniform or open"):
        branch_starts(decisions, 5, np.random.default_rng(0), "hardest")
    with pytest.raises(ValueError, match="without a value"):
        runner.set_value({})
    plain = EnvGRPO(graphdef, rl, SlideEnv(), max_steps=12, starts_at=lambda s, r: (far, tokens), eval_starts=far,
                    eval_tokens=tokens, eval_tasks=[0, 1], key=jax.random.key(0))
    unsnapped = plain.value_episodes(params, 2, max_steps=4, key=jax.random.key(0), starts_at=lambda r: (far, tokens))
    assert unsnapped.states.shape == (len(unsnapped), 0)
    with pytest.raises(ValueError, match="no environment snapshots"):
        branch_starts(unsnapped, 3, np.random.default_rng(0))
    with pytest.raises(ValueError, match="record_states needs an environment with snapshot"):
        scan_rollout(graphdef, params, SlideEnv(), jnp.asarray(far), jnp.asarray(tokens), rl, key=jax.random.key(0),
                     greedy=True, ensemble=False, max_steps=4, record_states=True)


@pytest.mark.slow  # an env GRPO run with the KL anchor; test_grpo keeps the KL term in the default run
def test_env_grpo_anchored_by_kl_measures_its_distance_from_the_starting_policy():
    # rl.grpo.kl_coef > 0 (bench_grpo_value --kl-coef): the state keeps the starting policy, whose k3 KL is 0 on the
    # first step and positive once the policy has moved; the anchor changes the update
    def run(kl_coef):
        rl = _rl(episodes=12, steps=20, batch_size=16, width=4, holdout=0.25)
        rl = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, kl_coef=kl_coef, learning_rate=1e-2))
        graphdef, params = build_policy(rl, seed=0)
        value_graphdef, value_params = build_value(rl, seed=0)
        runner = _runner(rl, params, graphdef, value_graphdef, value_params,
                         lambda s, r: np.array([[-0.2], [0.1]], np.float32))
        state = grpo.init_state(jax.tree.map(jnp.copy, params), rl)
        kls = []
        for step in range(3):
            state, metrics = runner.step(state, step, jax.random.key(1))
            kls.append(float(metrics["kl"]))
        return state, kls

    anchored, kls = run(2.0)
    assert anchored.ref_params is not None
    assert kls[0] == pytest.approx(0.0, abs=1e-6) and np.isfinite(kls).all() and max(kls[1:]) > 0.0
    free, free_kls = run(0.0)
    assert free.ref_params is None and free_kls == [0.0, 0.0, 0.0]
    assert not all(np.allclose(a, b) for a, b in zip(jax.tree.leaves(anchored.params), jax.tree.leaves(free.params)))


def test_evaluations_and_value_episodes_roll_out_no_surplus_of_a_large_training_batch():
    """A training batch (rollout_batch x group_size trajectories) larger than what is asked for: the evaluation
    runs its E episodes as one slice of E (not a batch padded by repeats), and the value's episodes roll out only
    the groups they need; every episode's outcome lands in its own place."""
    rl = _rl(episodes=5, steps=5, batch_size=8, width=4)
    rl = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, rollout_batch=4, group_size=4))
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 4, rl.policy.max_instruction_bytes)
    starts = np.array([[0.6], [-0.6], [0.6], [-0.6]], np.float32)  # two past the goal whatever they do, two too far
    runner = EnvGRPO(graphdef, rl, SnapshotSlideEnv(), max_steps=4, starts_at=lambda s, r: (starts, tokens),
                     eval_starts=starts[:3], eval_tokens=tokens[:3], eval_tasks=[0, 1, 0], key=jax.random.key(0),
                     train_max_steps=4, train_execute_steps=4)
    assert runner.batch == 16
    shapes, rollout = [], runner.rollout

    def recording(params, starts, *args):
        shapes.append(starts.shape[0])
        return rollout(params, starts, *args)

    runner.rollout = recording
    success, first = runner.run_episodes(params, greedy=True, ensemble=False, key=jax.random.key(0))
    assert shapes == [3] and success.shape == (3,) and np.asarray(first["valid"]).shape[0] == 3
    assert success.tolist() == [True, False, True]  # each episode's outcome in its own place

    traced, impl = [], runner._rollout_impl

    def tracing(params, starts, *args, **kwargs):
        traced.append(starts.shape[0])
        return impl(params, starts, *args, **kwargs)

    runner._rollout_impl = tracing
    data = runner.value_episodes(params, 5, max_steps=4, key=jax.random.key(0), starts_at=lambda r: (starts, tokens))
    assert traced == [8] and len(np.unique(data.episode)) == 5  # two groups of 4 rolled out, 5 episodes kept
