"""Policy episodes in a pure JAX env as one scan (sword_jax.rl.scan_rollout) and ground-truth GRPO on it
(sword_jax.rl.jax_env_grpo): against the C-engine path's semantics, on a tiny analytic env (MJX itself
compiles for minutes on a CPU; its adapter's observations are checked against the C engine in
tests/test_sim_mjx_batch.py)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import configs
from sword_jax.rl import grpo
from sword_jax.rl.env_rollout import run_policy, make_act_fns
from sword_jax.rl.jax_env_grpo import EnvGRPO, mixed_groups, select_groups
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.scan_rollout import ensembled_action, ensemble_weights, scan_rollout

SIZE = 32


class SlideEnv:
    """A point pushed by the first action dimension towards 1.0; success once past it. Frames show
    the position as brightness; proprio is the position (pure jnp, both protocols)."""

    goal = 0.35

    def _obs(self, pos):
        n = pos.shape[0]
        level = jnp.clip(jnp.round((pos + 1.0) * 100.0), 0, 255).astype(jnp.uint8)
        frames = jnp.broadcast_to(level[:, None, None, None], (n, SIZE, SIZE, 3))
        proprio = jnp.concatenate([pos[:, None], jnp.zeros((n, 7), jnp.float32)], axis=1)
        return {"frames": frames, "proprio": proprio}

    def reset(self, starts):
        pos = jnp.asarray(starts, jnp.float32)[:, 0]
        return pos, self._obs(pos)

    def step(self, pos, actions):
        pos = pos + 0.1 * jnp.clip(actions[:, 0], -1.0, 1.0)
        return pos, self._obs(pos), pos > self.goal


class LockstepSlide:
    """The same env with the C engine's lockstep protocol (host numpy), for run_policy."""

    def __init__(self, starts, texts, max_steps):
        self.starts, self.language, self.n, self.max_steps = np.asarray(starts, np.float32), texts, len(texts), max_steps
        self.env = SlideEnv()

    def reset(self):
        self.pos, obs = self.env.reset(self.starts)
        self.done = np.zeros(self.n, bool)
        self.steps = np.zeros(self.n, int)
        return {k: np.asarray(v) for k, v in obs.items()}

    def step(self, actions):
        success = np.zeros(self.n, bool)
        executed = np.zeros(self.n, int)
        pos = np.asarray(self.pos).copy()
        for j in range(actions.shape[1]):
            active = ~self.done & ~success & (self.steps < self.max_steps)
            new, _, reached = self.env.step(jnp.asarray(pos), jnp.asarray(actions[:, j]))
            pos = np.where(active, np.asarray(new), pos)
            self.steps += active
            executed += active
            success |= np.asarray(reached) & active
        self.pos = jnp.asarray(pos)
        self.done |= success | (self.steps >= self.max_steps)
        obs = self.env._obs(self.pos)
        return {"frames": np.asarray(obs["frames"]), "proprio": np.asarray(obs["proprio"]), "success": success,
                "executed": executed, "done": self.done.copy()}

    def close(self):
        pass


@pytest.fixture(scope="module")
def setup():
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, grpo=dataclasses.replace(cfg.rl.grpo, rollout_batch=2, group_size=4,
                                                                                 temperature=1.0))
    graphdef, params = build_policy(rl, seed=0)
    return rl, graphdef, params


def _rollout(rl, graphdef, params, starts, tokens, *, greedy, ensemble, max_steps, key=0):
    fn = jax.jit(lambda p, s, t, k, g, e: scan_rollout(graphdef, p, SlideEnv(), s, t, rl, key=k, greedy=g, ensemble=e,
                                                       max_steps=max_steps))
    return fn(params, jnp.asarray(starts), jnp.asarray(tokens), jax.random.key(key), greedy, ensemble)


@pytest.mark.parametrize("ensemble,execute", [(True, 1), (False, 1), (False, 3)])
def test_greedy_scan_rollout_matches_the_lockstep_path(setup, ensemble, execute):
    """Greedy episodes (ensembled, every step, open-loop chunks of 3): the scan and run_policy on the C
    engine's protocol execute the same actions, so success, decisions and tokens agree."""
    rl, graphdef, params = setup
    rl = dataclasses.replace(rl, env=dataclasses.replace(rl.env, execute_steps=execute, action_ensemble=ensemble))
    starts = np.array([[0.3], [0.0], [-0.5], [0.33]], np.float32)
    texts = ["push it", "push it", "slide right", "push it"]
    tokens = tokenize_instructions(texts, rl.policy.max_instruction_bytes)
    max_steps = 7
    scan, steps = _rollout(rl, graphdef, params, starts, tokens, greedy=True, ensemble=ensemble, max_steps=max_steps)
    ref = run_policy(make_act_fns(graphdef, rl), params, LockstepSlide(starts, texts, max_steps), rl,
                     key=jax.random.key(0), greedy=True, max_steps=max_steps)
    np.testing.assert_array_equal(np.asarray(scan.success), ref.success)
    np.testing.assert_array_equal(np.asarray(scan.valid), ref.valid)
    mask = ref.valid > 0
    np.testing.assert_array_equal(np.asarray(scan.tokens)[mask], ref.tokens[mask])
    np.testing.assert_allclose(np.asarray(scan.log_probs)[mask], ref.log_probs[mask], atol=1e-4)
    np.testing.assert_array_equal(np.asarray(scan.obs_frames)[mask], ref.obs_frames[mask])
    np.testing.assert_allclose(np.asarray(scan.returns), ref.returns)
    np.testing.assert_allclose(np.asarray(scan.rewards), ref.rewards)
    assert np.asarray(steps.steps).max() <= max_steps and not np.asarray(steps.broken).any()


class BreakingSlideEnv(SlideEnv):
    """SlideEnv whose physics goes non-finite below -0.3."""

    def step(self, pos, actions):
        pos, obs, reached = super().step(pos, actions)
        broken = pos < -0.3
        obs = dict(obs, proprio=jnp.where(broken[:, None], jnp.nan, obs["proprio"]))
        return jnp.where(broken, jnp.nan, pos), obs, reached


def test_sampled_rollout_is_sampled_and_keyed(setup):
    rl, graphdef, params = setup
    starts = np.zeros((4, 1), np.float32)
    tokens = tokenize_instructions(["push it"] * 4, rl.policy.max_instruction_bytes)
    a, _ = _rollout(rl, graphdef, params, starts, tokens, greedy=False, ensemble=False, max_steps=4, key=1)
    b, _ = _rollout(rl, graphdef, params, starts, tokens, greedy=False, ensemble=False, max_steps=4, key=1)
    c, _ = _rollout(rl, graphdef, params, starts, tokens, greedy=False, ensemble=False, max_steps=4, key=2)
    np.testing.assert_array_equal(np.asarray(a.tokens), np.asarray(b.tokens))
    assert not np.array_equal(np.asarray(a.tokens), np.asarray(c.tokens))
    # identical episodes sample different tokens (a fresh draw per episode), at negative log-probs
    assert not np.array_equal(np.asarray(a.tokens)[0], np.asarray(a.tokens)[1])
    assert float(jnp.max(a.log_probs)) < 0.0


def test_ensembled_action_weights_only_chunks_made():
    history = jnp.zeros((1, 3, 3, 1)).at[0, 0, 0, 0].set(1.0).at[0, 1, 1, 0].set(4.0).at[0, 2, 2, 0].set(100.0)
    w = jnp.exp(-0.5 * jnp.arange(3.0))
    one = ensembled_action(history, jnp.asarray(1), w)
    two = ensembled_action(history, jnp.asarray(2), w)
    np.testing.assert_allclose(np.asarray(one), [[1.0]])
    np.testing.assert_allclose(np.asarray(two), [[(1.0 + 4.0 * np.exp(-0.5)) / (1 + np.exp(-0.5))]], rtol=1e-6)
    cfg = configs.get("sword:tiny").rl
    assert ensemble_weights(cfg).shape == (cfg.chunk_len,)


def test_select_groups_puts_mixed_groups_first():
    from sword_jax.rl.rollout import Rollout

    returns = jnp.asarray([0, 2, 2, 0, 2, 2, 2, 2, 0, 2, 0, 0], jnp.float32)  # groups of 2: mixed, mixed, none ...
    g = 2
    n = returns.shape[0]
    ids = jnp.arange(n, dtype=jnp.float32)
    ro = Rollout(ids[:, None, None, None, None], ids[:, None, None], ids[:, None], ids[:, None].astype(jnp.int32),
                 ids[:, None, None, None].astype(jnp.int32), ids[:, None, None, None], ids[:, None], ids[:, None],
                 ids[:, None], returns > 0, returns, jnp.zeros((0,)))
    np.testing.assert_array_equal(np.asarray(mixed_groups(returns, g)), [True, True, False, False, True, False])
    picked = select_groups(ro, g, 4)
    # mixed groups 0, 1, 4 (in order), then the first group without signal (2)
    np.testing.assert_array_equal(np.asarray(picked.returns), [0, 2, 2, 0, 0, 2, 2, 2])
    np.testing.assert_array_equal(np.asarray(picked.valid)[:, 0], [0, 1, 2, 3, 8, 9, 4, 5])
    with pytest.raises(ValueError, match="fewer than"):
        select_groups(ro, g, 7)


def test_env_grpo_steps_resample_survive_broken_physics_and_are_pure(setup, tmp_path):
    """Dynamic sampling resamples until enough mixed groups (or the round limit); an episode whose env goes
    non-finite ends as a failure with every record after it zero, so the update stays finite; the update
    takes minibatch steps whose ratio leaves 1; a step is a pure function of (state, step, key)."""
    rl, graphdef, params = setup
    rl = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, max_sample_rounds=3, minibatches=2, ppo_epochs=1,
                                                            learning_rate=1e-3, update_microbatch=0,
                                                            min_mixed_fraction=1.0))
    tokens = tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes)

    def starts_at(step, round_):  # one start near success, one near the region where the env breaks
        rng = np.random.default_rng([step, round_])
        return np.array([[rng.uniform(0.2, 0.34)], [rng.uniform(-0.3, -0.25)]], np.float32), tokens

    eval_starts = np.array([[0.3], [0.0], [0.33]], np.float32)
    runner = EnvGRPO(graphdef, rl, BreakingSlideEnv(), max_steps=4, starts_at=starts_at, eval_starts=eval_starts,
                     eval_tokens=tokenize_instructions(["push it"] * 3, rl.policy.max_instruction_bytes),
                     eval_tasks=[0, 0, 1], key=jax.random.key(3))
    starts, _ = starts_at(5, 0)
    rollout, stats = runner.rollout(params, jnp.asarray(np.repeat(starts, 4, 0)), jnp.asarray(np.repeat(tokens, 4, 0)),
                                    jax.random.key(4), False, False)
    broken = np.asarray(stats.broken)
    assert broken[4:].any() and not np.asarray(rollout.success)[broken].any()
    for name in ("obs_frames", "proprio", "log_probs", "tokens", "valid", "returns"):
        assert np.all(np.isfinite(np.asarray(getattr(rollout, name), np.float32))), name
    ended = np.asarray(rollout.valid) == 0
    assert ended.any() and np.all(np.asarray(rollout.log_probs)[ended] == 0) and np.all(np.asarray(rollout.proprio)[ended] == 0)

    state = grpo.init_state(jax.tree.map(jnp.copy, params), rl)
    copy = jax.tree.map(jnp.copy, state)
    s1, m1 = runner.step(state, 5, jax.random.key(7))
    s2, m2 = runner.step(copy, 5, jax.random.key(7))
    for a, b in zip(jax.tree.leaves(s1.params), jax.tree.leaves(s2.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(m1["finite"]) == 1.0 and float(m1["broken_episodes"]) > 0
    assert 1 <= float(m1["sample_rounds"]) <= 3
    assert float(m1["trajectories_sampled"]) == 8 * float(m1["sample_rounds"])
    assert float(m1["sample_rounds"]) == 3 or float(m1["sampled_mixed_groups"]) >= 2
    # the update batch holds the sampled mixed groups first, up to its 2 groups
    assert float(m1["mixed_groups"]) == min(float(m1["sampled_mixed_groups"]), 2.0)
    assert float(m1["skipped_update"]) == 0.0  # rl.grpo.min_mixed_groups = 0: every batch updates
    assert float(m1["updates"]) == 2.0
    if float(m1["kept_fraction"]) > 0:  # a second minibatch step is taken by a moved policy
        assert abs(float(m1["ratio_mean"]) - 1.0) > 0.0
    runner.start_probe(params, str(tmp_path / "probe"))
    point, extra = runner.evaluate(s1.params, step=1)
    assert point["episodes"] == 3 and set(point["per_task"]) == {"0", "1"}
    assert 0.0 <= extra["probe"]["flip_rate_vs_start"] <= 1.0 and "sampled" in extra
    point2, extra2 = runner.evaluate(s1.params, step=2)
    assert extra2["probe"]["flip_rate_vs_previous"] == 0.0 and point2["mean"] == point["mean"]


def test_the_masked_evaluation_runs_the_policy_without_proprio(tmp_path):
    """EnvGRPO.evaluate(masked=True) adds the sampled policy reading its "missing proprio" input: the rollout
    it runs marks every decision's proprio invalid, the others' valid."""
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, env=dataclasses.replace(cfg.rl.env, execute_steps=1,
                                                                             action_ensemble=False),
                             grpo=dataclasses.replace(cfg.rl.grpo, rollout_batch=1, group_size=4))
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 4, rl.policy.max_instruction_bytes)
    runner = EnvGRPO(graphdef, rl, SlideEnv(), max_steps=3, starts_at=lambda s, r: None,
                     eval_starts=np.array([[0.3], [0.0], [0.33], [0.1]], np.float32), eval_tokens=tokens,
                     eval_tasks=[0, 0, 1, 1], key=jax.random.key(3))
    kept, _ = runner.run_episodes(params, greedy=True, ensemble=False, key=jax.random.key(0))
    rollout_kept, _ = runner.rollout(params, jnp.asarray(runner.eval_starts), jnp.asarray(tokens), jax.random.key(0),
                                     True, False, runner._valid(1.0))
    rollout_masked, _ = runner.rollout(params, jnp.asarray(runner.eval_starts), jnp.asarray(tokens), jax.random.key(0),
                                       True, False, runner._valid(0.0))
    assert np.all(np.asarray(rollout_masked.proprio_valid) == 0) and np.all(np.asarray(rollout_kept.proprio_valid) == 1)
    runner.start_probe(params, str(tmp_path / "probe"))
    point, extra = runner.evaluate(params, step=0, sampled=True, masked=True)
    assert extra["sampled_proprio_masked"]["episodes"] == 4 and "sampled" in extra
    assert kept.shape == (4,)
    assert len(point["outcomes"]) == len(extra["sampled_proprio_masked"]["outcomes"]) == 4

    keys, run = [], runner.run_episodes  # every evaluation draws the same noise: common random numbers

    def recording(p, *, key, **kwargs):
        keys.append((kwargs["greedy"], kwargs.get("proprio", True), np.asarray(jax.random.key_data(key)).tolist()))
        return run(p, key=key, **kwargs)

    runner.run_episodes = recording
    for step in (0, 7):
        runner.evaluate(params, step=step, sampled=True, masked=True)
    assert len(keys) == 6 and keys[:3] == keys[3:]  # greedy, sampled, sampled with proprio masked: as at step 0
    assert len({str(k[2]) for k in keys[:3]}) == 3  # each policy its own noise


def test_env_grpo_counts_its_trajectories_by_where_their_starts_stood():
    """start_steps_at: each step counts its sampled trajectories and their real successes by their start's step in
    its episode (no detector: no verdict counts); without it the step logs no such count."""
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, grpo=dataclasses.replace(
        cfg.rl.grpo, rollout_batch=2, group_size=4, minibatches=1, ppo_epochs=1, update_microbatch=0))
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes)
    starts = np.array([[1.0], [-1.2]], np.float32)  # past the goal (every trajectory succeeds), far (none can)
    common = dict(max_steps=8, starts_at=lambda s, r: (starts, tokens), eval_starts=starts, eval_tokens=tokens,
                  eval_tasks=[0, 1], key=jax.random.key(3))
    runner = EnvGRPO(graphdef, rl, SlideEnv(), start_steps_at=lambda s, r: np.array([30, 100]), **common)
    _, metrics = runner.step(grpo.init_state(jax.tree.map(jnp.copy, params), rl), 0, jax.random.key(1))
    metrics = jax.device_get(metrics)
    counts = {k: float(v) for k, v in metrics.items() if k.startswith("start_a")}
    assert counts == {"start_a0_rollouts": 0.0, "start_a0_real": 0.0, "start_a24_rollouts": 4.0, "start_a24_real": 4.0,
                      "start_a48_rollouts": 0.0, "start_a48_real": 0.0, "start_a72_rollouts": 0.0,
                      "start_a72_real": 0.0, "start_a96_rollouts": 4.0, "start_a96_real": 0.0}
    assert float(metrics["rollout_success"]) == 0.5
    plain = EnvGRPO(graphdef, rl, SlideEnv(), **common)
    _, metrics = plain.step(grpo.init_state(jax.tree.map(jnp.copy, params), rl), 0, jax.random.key(1))
    assert not any(k.startswith("start_a") for k in metrics)


def test_env_grpo_trains_in_the_learned_simulators_setting_and_evaluates_in_the_real_one(tmp_path):
    """train_max_steps / train_execute_steps / train_proprio: the training rollouts run the learned
    simulator's horizon and execution with the policy's "missing proprio" input, while the evaluation keeps
    the episode limit, every-step ensembled execution and true proprio."""
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, grpo=dataclasses.replace(
        cfg.rl.grpo, rollout_batch=2, group_size=4, minibatches=1, ppo_epochs=1, update_microbatch=0))
    assert rl.env.execute_steps == 1 and rl.env.action_ensemble and rl.chunk_len % 4 == 0
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes)
    far = np.array([[-1.0], [-1.2]], np.float32)  # 8 actions of at most 0.1 cannot reach the goal
    runner = EnvGRPO(graphdef, rl, SlideEnv(), max_steps=20, starts_at=lambda s, r: (far, tokens),
                     eval_starts=np.array([[0.3], [-1.0]], np.float32),
                     eval_tokens=tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes),
                     eval_tasks=[0, 1], key=jax.random.key(3), train_max_steps=8, train_execute_steps=4,
                     train_proprio=False)
    assert runner.train_rl.env.execute_steps == 4 and not runner.train_rl.env.action_ensemble
    assert runner.rl.env.execute_steps == 1  # the evaluation's own execution is untouched
    _, metrics = runner.step(grpo.init_state(jax.tree.map(jnp.copy, params), rl), 0, jax.random.key(1))
    assert float(metrics["env_steps"]) == 8 * 8 and float(metrics["rollout_success"]) == 0.0
    starts = jnp.asarray(np.repeat(far, 4, 0))
    rollout, _ = runner.train_rollout(params, starts, jnp.asarray(np.repeat(tokens, 4, 0)), jax.random.key(0), False,
                                      False, runner._valid(0.0))
    assert rollout.valid.shape[1] == 2 and np.all(np.asarray(rollout.proprio_valid) == 0)  # 2 decisions of 4
    evaluated, _ = runner.rollout(params, jnp.asarray(runner.eval_starts[[1] * 8]),
                                  jnp.asarray(runner.eval_tokens[[1] * 8]), jax.random.key(0), True, True,
                                  runner._valid(1.0))
    assert evaluated.valid.shape[1] == 20  # the evaluation re-plans every action for its 20
    plain = EnvGRPO(graphdef, rl, SlideEnv(), max_steps=20, starts_at=lambda s, r: (far, tokens),
                    eval_starts=runner.eval_starts, eval_tokens=runner.eval_tokens, eval_tasks=[0, 1],
                    key=jax.random.key(3))
    assert plain.train_rollout is plain.rollout and plain.train_proprio
    # the training rollouts as plain.step samples them (its env_steps sums their steps; the update after them is
    # the runner's above): the whole episode limit, with true proprio
    trained, trained_stats = plain.train_rollout(params, starts, jnp.asarray(np.repeat(tokens, 4, 0)),
                                                 jax.random.key(1), False, False, plain._valid(1.0))
    assert int(jnp.sum(trained_stats.steps)) == 8 * 20 and np.all(np.asarray(trained.proprio_valid) == 1)
    with pytest.raises(ValueError, match="train_max_steps"):
        EnvGRPO(graphdef, rl, SlideEnv(), max_steps=20, starts_at=lambda s, r: (far, tokens), eval_starts=far,
                eval_tokens=tokens, eval_tasks=[0, 1], key=jax.random.key(3), train_max_steps=0)


def test_the_as_trained_evaluation_executes_the_sampled_policy_as_its_training_rollouts_do(tmp_path):
    """evaluate(as_trained=True) with training rollouts of 4 actions per decision and proprio missing adds the
    sampled policy executed that way from the evaluation's starts for their whole episodes: 5 decisions in 20
    actions, proprio invalid, with its own noise drawn alike at every evaluation; a runner that trains as it
    evaluates adds nothing."""
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, grpo=dataclasses.replace(
        cfg.rl.grpo, rollout_batch=1, group_size=4, minibatches=1, ppo_epochs=1, update_microbatch=0))
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 4, rl.policy.max_instruction_bytes)
    eval_starts = np.array([[0.3], [-1.0], [0.33], [0.1]], np.float32)
    kwargs = dict(max_steps=20, starts_at=lambda s, r: None, eval_starts=eval_starts, eval_tokens=tokens,
                  eval_tasks=[0, 0, 1, 1], key=jax.random.key(3))
    runner = EnvGRPO(graphdef, rl, SlideEnv(), train_max_steps=8, train_execute_steps=4, train_proprio=False,
                     **kwargs)
    calls, run = [], runner.run_episodes

    def recording(p, *, key, **kw):
        calls.append((kw.get("rollout"), kw.get("proprio", True), np.asarray(jax.random.key_data(key)).tolist()))
        return run(p, key=key, **kw)

    runner.run_episodes = recording
    runner.start_probe(params, str(tmp_path / "probe"))
    calls.clear()
    _, extra = runner.evaluate(params, step=0, as_trained=True)
    trained = extra["sampled_as_trained"]
    assert trained["episodes"] == 4 and trained["execute_steps"] == 4 and trained["proprio"] is False
    assert len(trained["outcomes"]) == 4
    assert calls[-1][0] is runner.as_trained_rollout and calls[-1][1] is False
    assert len({str(c[2]) for c in calls}) == len(calls)  # its own noise, not the other policies'
    rollout, _ = runner.as_trained_rollout(params, jnp.asarray(eval_starts), jnp.asarray(tokens), jax.random.key(0),
                                           False, False, runner._valid(0.0))
    assert rollout.valid.shape[1] == 5 and np.all(np.asarray(rollout.proprio_valid) == 0)  # 20 actions, 4 each
    first = calls[-1]
    runner.evaluate(params, step=3, as_trained=True)
    assert calls[-1] == first  # every evaluation draws the same noise: common random numbers
    _, without = runner.evaluate(params, step=4)
    assert "sampled_as_trained" not in without
    plain = EnvGRPO(graphdef, rl, SlideEnv(), **kwargs)
    plain.start_probe(params, str(tmp_path / "plain"))
    assert plain.as_trained_rollout is None
    assert "sampled_as_trained" not in plain.evaluate(params, step=0, as_trained=True)[1]


def test_the_learned_simulators_runs_are_evaluated_as_they_execute_the_policy_there():
    """sim.grpo_refresh.imagined_execution: an MJX evaluation of GRPO in the learned simulator runs its sampled policy
    as that GRPO executes it (rl.imagined.execute_steps actions per decision, proprio missing); with dead-reckoned
    proprio, which MJX evaluations do not compute, it adds nothing."""
    from sim.grpo_refresh import imagined_execution

    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, imagined=dataclasses.replace(
        cfg.rl.imagined, execute_steps=4, proprio="missing"))
    assert imagined_execution(rl) == {"train_execute_steps": 4, "train_proprio": False}
    graphdef, params = build_policy(rl, seed=0)
    tokens = tokenize_instructions(["push it"] * 2, rl.policy.max_instruction_bytes)
    runner = EnvGRPO(graphdef, rl, SlideEnv(), max_steps=8, starts_at=lambda s, r: None,
                     eval_starts=np.array([[0.3], [0.0]], np.float32), eval_tokens=tokens, eval_tasks=[0, 1],
                     key=jax.random.key(3), **imagined_execution(rl))
    assert runner.as_trained_rollout is not None and runner.train_rl.env.execute_steps == 4
    whole = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, execute_steps=None))
    assert imagined_execution(whole)["train_execute_steps"] == rl.chunk_len  # whole chunks
    reckoned = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, proprio="reckoned"))
    assert imagined_execution(reckoned) == {}
