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
