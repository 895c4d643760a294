"""sim.mjx_batch: the MJX episodes GRPO and its evaluations run on the accelerator see what the C engine's
lockstep episodes show the policy (frames, proprio, success), and the starts are stratified.

MJX's physics compiles for minutes on a CPU: the default test reads observations of C-engine states
through the MJX adapter (renderer, proprio, success: no physics); the episode check runs on a GPU."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sim import expert, tasks
from sim.config import SimConfig
from sim.env import CpuEnv
from sim.lockstep import LockstepEnvs
from sim.mjx_batch import MjxEpisodes, episode_starts, stratified_train_starts

RES = 32


# the episodes test below keeps the frames and proprio of restored states in the default run, and
# test_sim_mjx.py::test_init_sampling_success_and_expert_match_under_jit the success predicate under jit
@pytest.mark.slow
def test_mjx_observations_of_c_engine_states_match_the_lockstep_envs():
    """Two tasks' states along an expert episode: the frames the MJX adapter renders from their poses
    equal the lockstep envs' (the same ray caster), proprio and success agree."""
    from mujoco import mjx

    env = CpuEnv(SimConfig(), task_id=3)
    out = expert.rollout_cpu(env, env.init_states[0], max_steps=90, record=True)
    chosen = [out["states"][0], out["states"][len(out["states"]) // 2], out["states"][-1]]
    batch = MjxEpisodes(SimConfig(), resolution=RES)
    flat = [np.concatenate([[s.data.time], s.data.qpos, s.data.qvel]) for s in chosen]
    restored = [env.restore(f) for f in flat]  # poses computed at the recorded qpos, as the lockstep envs do
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *[mjx.put_data(env.mj_model, r.data) for r in restored])
    obs = jax.tree.map(np.asarray, jax.jit(batch.observe)(stacked))
    with LockstepEnvs([(3, f) for f in flat], resolution=RES, max_steps=5) as ref_envs:
        ref = ref_envs.reset()
    assert obs["frames"].dtype == np.uint8 and obs["frames"].shape == (3, RES, RES, 3)
    diff = np.abs(obs["frames"].astype(np.int32) - ref["frames"].astype(np.int32))
    assert diff.mean() < 0.3 and np.mean(diff == 0) > 0.97, (diff.mean(), np.mean(diff == 0))  # float32 poses, edges
    np.testing.assert_allclose(obs["proprio"], ref["proprio"], atol=2e-4)
    solved = [bool(r.done) for r in restored]
    step_success = jax.jit(lambda d: jax.vmap(lambda x: batch.env._state(x, info={}).done)(d))(stacked)
    np.testing.assert_array_equal(np.asarray(step_success) > 0.5, solved)
    assert solved[-1] and not solved[0]  # the expert's episode ends solved


def test_stratified_starts_cover_every_task_and_are_training_states():
    rng = np.random.default_rng(0)
    picked = stratified_train_starts(list(range(10)), 64, rng)
    counts = np.bincount([t for t, _ in picked], minlength=10)
    assert counts.min() >= 6 and counts.max() <= 7 and counts.sum() == 64
    evaluation = tasks.evaluation_episodes(range(10), 50)
    for t in range(10):
        mine = np.stack([q for task, q in picked if task == t])
        theirs = np.stack([q for task, q in evaluation if task == t])
        assert not np.any(tasks.coinciding(mine, theirs))
    qpos, texts = episode_starts(picked)
    assert qpos.shape[0] == 64 and qpos.dtype == np.float32 and texts[0] == tasks.LANGUAGE[picked[0][0]]
    again = stratified_train_starts(list(range(10)), 64, np.random.default_rng(0))
    assert all(a[0] == b[0] and np.array_equal(a[1], b[1]) for a, b in zip(picked, again))
    with pytest.raises(ValueError, match="no episodes"):
        episode_starts([])


@pytest.mark.gpu
def test_mjx_episodes_follow_the_c_engine_under_the_same_actions():
    """On a GPU: reset and 12 steps of the same actions from two tasks' evaluation states, MJX against
    the lockstep C engine: the frames stay close and proprio agrees to millimetres."""
    if jax.default_backend() != "gpu":
        pytest.skip("MJX physics compiles for minutes on a CPU")
    starts = tasks.evaluation_episodes([0, 7], 1)
    qpos, _ = episode_starts(starts)
    batch = MjxEpisodes(SimConfig(), resolution=128)
    data, obs = jax.jit(batch.reset)(jnp.asarray(qpos))
    step = jax.jit(batch.step)
    actions = np.tile(np.array([[0.4, -0.2, -0.5, 0.0, 0.0, 0.1, -1.0]], np.float32), (2, 1))
    with LockstepEnvs(starts, resolution=128, max_steps=50) as ref_envs:
        ref = ref_envs.reset()
        for _ in range(12):
            data, obs, _ = step(data, jnp.asarray(actions))
            ref = ref_envs.step(actions[:, None])
    np.testing.assert_allclose(np.asarray(obs["proprio"])[:, :3], ref["proprio"][:, :3], atol=5e-3)
    diff = np.abs(np.asarray(obs["frames"]).astype(np.int32) - ref["frames"].astype(np.int32))
    assert diff.mean() < 2.0


def test_mjx_episodes_continue_recorded_states_as_the_c_engine_restores_them():
    """MjxEpisodes.reset of recorded flat states ([time, qpos, qvel], a dataset's states[t]) continues them
    without settling: the frames and proprio are the C engine's restored ones, the snapshot of the restored state is
    the recorded one; a wrong width is refused."""
    env = CpuEnv(SimConfig(), task_id=5)
    out = expert.rollout_cpu(env, env.init_states[1], max_steps=60, record=True)
    chosen = [out["states"][10], out["states"][40]]
    flat = np.stack([np.concatenate([[s.data.time], s.data.qpos, s.data.qvel]) for s in chosen]).astype(np.float32)
    batch = MjxEpisodes(SimConfig(), resolution=RES)
    assert flat.shape[1] == batch.flat_size != batch.nq
    data, obs = jax.jit(batch.reset)(jnp.asarray(flat))
    with LockstepEnvs([(5, f) for f in flat.astype(np.float64)], resolution=RES, max_steps=5) as ref_envs:
        ref = ref_envs.reset()
    np.testing.assert_allclose(np.asarray(data.qpos), flat[:, 1: 1 + batch.nq], atol=1e-6)
    np.testing.assert_allclose(np.asarray(data.time), flat[:, 0], atol=1e-6)
    # the snapshot GRPO branches from is the flat state reset continued (sword_jax.rl.jax_env_grpo.branch_starts)
    np.testing.assert_allclose(np.asarray(jax.jit(batch.snapshot)(data)), flat, atol=1e-6)
    np.testing.assert_allclose(obs["proprio"], ref["proprio"], atol=2e-4)
    diff = np.abs(np.asarray(obs["frames"]).astype(np.int32) - ref["frames"].astype(np.int32))
    assert diff.mean() < 0.3 and np.mean(diff == 0) > 0.97, (diff.mean(), np.mean(diff == 0))
    assert not np.array_equal(np.asarray(obs["frames"][0]), np.asarray(obs["frames"][1]))  # two different states
    with pytest.raises(ValueError, match="flat states"):
        batch.reset(jnp.zeros((2, batch.flat_size + 1)))


@pytest.mark.slow  # ~2 min on 2 cores: MJX's physics compiles on the CPU
def test_a_recorded_state_given_its_recorded_actions_succeeds_where_the_episode_did(tmp_path):
    """What ``rl.imagined.reward=executed`` pays: MJX restored to a demonstration's recorded state (its dataset's
    ``states[t]``) 12 actions before its success and given the recorded actions open loop succeeds where the
    episode did (within one action: MJX and the C engine are not bit-identical); lifting the arm instead, the
    gripper held as recorded, does not."""
    from sim.dataset import read_dataset
    from sword_jax.rl import data as rl_data
    from sword_jax.rl.imagined_check import execute_open_loop
    from train import gen_data

    path = str(tmp_path / "demo.hdf5")
    gen_data.main(["--task", "0", "--episodes", "1", "--out", path, "--resolution", str(RES), "--stop-at-success",
                   "--no-wrist"])
    eps = rl_data.load_episodes([path], read=read_dataset)
    length = int(eps.lengths[0])
    assert eps.success[0] and length > 20 and eps.states is not None
    t = length - 12
    replay = eps.actions[0, t: length + 4].astype(np.float32)  # padding repeats the last action
    lift = np.zeros_like(replay)
    lift[:, 2] = 1.0
    lift[:, 6] = replay[:, 6]
    flat = np.repeat(eps.states[0, t][None].astype(np.float32), 2, axis=0)
    batch = MjxEpisodes(SimConfig(), resolution=RES)
    first = np.asarray(jax.jit(lambda s, a, n: execute_open_loop(batch, s, a, n))(
        jnp.asarray(flat), jnp.asarray(np.stack([replay, lift])), jnp.asarray([16, 16])))
    assert abs(int(first[0]) - 11) <= 1, first  # the episode's last action, 11 after the keyframe, solved it
    assert first[1] == -1, first
