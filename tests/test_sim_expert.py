"""Scripted expert on the C backend: a few init states per task (the full 50 x 10 is slow)."""

import numpy as np
import pytest

from sim import expert, tasks
from sim.config import SimConfig
from sim.env import CpuEnv


@pytest.mark.parametrize("task_id", range(10))
def test_expert_solves_an_init_state_of_every_task(task_id):
    env = CpuEnv(SimConfig(), task_id)
    for idx in (17 * (task_id % 3),):
        out = expert.rollout_cpu(env, env.init_states[idx], record=True)
        assert out["success"], f"task {task_id} init {idx}: stopped in phase {out['phase']}"
        assert out["steps"] < 150
        actions = out["actions"]
        assert actions.shape == (out["steps"], 7)
        assert np.all(np.abs(actions) <= 1.0)
        assert set(np.unique(actions[:, 6])) == {-1.0, 1.0}, "gripper opens and closes"


def test_expert_with_noise_still_succeeds_and_differs():
    env = CpuEnv(SimConfig(), 0)
    clean = expert.rollout_cpu(env, env.init_states[3], record=True)
    noisy = expert.rollout_cpu(env, env.init_states[3], cfg=expert.ExpertConfig(noise=0.1),
                               rng=np.random.default_rng(1), record=True)
    assert noisy["success"]
    n = min(len(clean["actions"]), len(noisy["actions"]))
    assert not np.allclose(clean["actions"][:n], noisy["actions"][:n])
    with pytest.raises(ValueError, match="noise"):
        expert.rollout_cpu(env, env.init_states[3], cfg=expert.ExpertConfig(noise=2.0))


def test_correlated_noise_is_a_unit_variance_ar1_process_and_independent_at_zero():
    draw = np.random.default_rng(0).standard_normal(6)
    assert expert.correlated(np.ones(6), draw, 0.0) is draw  # rho 0: the draw itself, bit for bit
    rng, x, xs = np.random.default_rng(1), np.zeros(1), []
    for _ in range(40000):
        x = expert.correlated(x, rng.standard_normal(1), 0.9)
        xs.append(x[0])
    xs = np.asarray(xs[100:])
    assert np.var(xs) == pytest.approx(1.0, abs=0.08)
    assert np.corrcoef(xs[:-1], xs[1:])[0, 1] == pytest.approx(0.9, abs=0.02)
    with pytest.raises(ValueError, match="noise_correlation"):
        expert.ExpertConfig(noise=0.1, noise_correlation=1.0).validate()


def test_correlated_exploration_noise_holds_its_direction_and_zero_changes_nothing():
    """The executed actions' departure from the expert's labels keeps its sign from step to step with correlation
    0.9 (lag-one autocorrelation of the position noise), not with independent draws; correlation 0 is the DART
    expert of before, bit for bit."""
    env = CpuEnv(SimConfig(), 0)
    runs = {}
    for rho in (0.0, 0.9):
        out = expert.rollout_cpu(env, env.init_states[3], cfg=expert.ExpertConfig(noise=0.3, noise_correlation=rho),
                                 rng=np.random.default_rng(5), record=True, max_steps=60, stop_at_success=False)
        runs[rho] = out
        d = (out["executed"] - out["actions"])[:, :3]
        on = np.all(d != 0, axis=1)  # the phases with motion noise
        pairs = on[:-1] & on[1:]
        lag1 = np.corrcoef(d[:-1][pairs].ravel(), d[1:][pairs].ravel())[0, 1]
        assert pairs.sum() > 20
        assert (lag1 > 0.6) if rho else (lag1 < 0.3), (rho, lag1)
    default = expert.rollout_cpu(env, env.init_states[3], cfg=expert.ExpertConfig(noise=0.3),
                                 rng=np.random.default_rng(5), record=True, max_steps=60, stop_at_success=False)
    np.testing.assert_array_equal(default["executed"], runs[0.0]["executed"])


def test_expert_does_not_succeed_without_moving():
    # Sanity: success really needs the placement (zero actions for 30 steps never solve it).
    env = CpuEnv(SimConfig(), 2)
    state = env.reset_to(env.init_states[0])
    for _ in range(30):
        state = env.step(state, np.array([0, 0, 0, 0, 0, 0, -1.0]))
    assert state.done == 0


@pytest.mark.slow
@pytest.mark.parametrize("task_id", range(10))
def test_expert_success_at_least_90_percent_on_all_50_init_states(task_id):
    env = CpuEnv(SimConfig(), task_id)
    wins = sum(expert.rollout_cpu(env, q)["success"] for q in env.init_states)
    assert wins >= 0.9 * tasks.NUM_INIT_STATES, f"task {task_id}: {wins}/50"


def test_an_episode_continued_from_a_recorded_state_follows_the_recording():
    """CpuEnv.restore continues a dataset's flat state [time, qpos, qvel]: the rest of the expert's
    executed actions reproduce the recorded trajectory and its success (GRPO's keyframe starts in the
    real environments rely on it)."""
    from sim.lockstep import LockstepEnvs
    from sim.datagen import flat_state

    env = CpuEnv(SimConfig(), 0)
    out = expert.rollout_cpu(env, env.init_states[3], record=True)
    assert out["success"]
    t = 20
    state = env.restore(flat_state(out["states"][t].data))
    np.testing.assert_array_equal(state.data.qpos, out["states"][t].data.qpos)
    for action in out["executed"][t:]:
        state = env.step_inplace(state, action)
    np.testing.assert_allclose(state.data.qpos, out["states"][-1].data.qpos, atol=1e-6)
    assert bool(state.done)
    with pytest.raises(ValueError, match=r"flat state must be finite with shape"):
        env.restore(np.zeros(5))
    # the lockstep envs continue a flat state and settle an initial qpos
    envs = LockstepEnvs([(0, flat_state(out["states"][t].data)), (0, env.init_states[3])], resolution=16,
                        max_steps=200)
    try:
        obs = envs.reset()
        # a recorded step's proprio is read before its last physics substep's kinematics are refreshed;
        # the restored state's are fresh: they differ by one substep of motion (~1e-4)
        np.testing.assert_allclose(obs["proprio"][0], out["states"][t].obs["proprio"], atol=1e-3)
        np.testing.assert_allclose(obs["proprio"][1], out["states"][0].obs["proprio"], atol=1e-6)
    finally:
        envs.close()
