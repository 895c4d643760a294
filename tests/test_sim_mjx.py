"""The MJX backend: the shared math under jit, and (slow) MJX-vs-C agreement on a trajectory.

MJX's JAX implementation compiles this scene's physics in minutes on a 2-core CPU and runs
~0.4 s per physics step, so default tests only jit the backend-shared code (controller,
observations, success, initial-state sampling, expert) and compare it with the numpy path
on C-engine states; the physics comparison is marked slow.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sim import controller as ctl
from sim import expert, tasks
from sim.config import SimConfig
from sim.env import CpuEnv


@pytest.fixture(scope="module")
def cpu_state():
    env = CpuEnv(SimConfig(), 5)
    state = env.reset_to(env.init_states[2])
    state = env.step(state, np.array([0.3, -0.2, -0.4, 0.1, 0.0, 0.2, 0.5]))
    return env, state


def test_controller_and_proprio_match_between_numpy_and_jitted_jax(cpu_state):
    env, state = cpu_state
    import mujoco

    jacp, jacr = np.zeros((3, env.nv)), np.zeros((3, env.nv))
    mujoco.mj_jacSite(env.mj_model, state.data, jacp, jacr, env.site_id)
    action = np.array([0.7, -1.3, 0.2, -0.4, 0.9, 0.1, 0.3])
    ref = ctl.servo_targets(action, state.data.qpos[:7], jacp[:, :7], jacr[:, :7], xp=np)
    fn = jax.jit(lambda a, q, jp, jr: ctl.servo_targets(a, q, jp, jr, xp=jnp))
    got = fn(*(jnp.asarray(x, jnp.float32) for x in (action, state.data.qpos[:7], jacp[:, :7], jacr[:, :7])))
    np.testing.assert_allclose(np.asarray(got), ref, atol=2e-4)
    assert ref[7] == pytest.approx(ref[8])
    mat = state.data.site_xmat[env.site_id].reshape(3, 3)
    proprio = jax.jit(lambda p, m, f: ctl.proprio(p, m, f, xp=jnp))(
        jnp.asarray(state.data.site_xpos[env.site_id], jnp.float32), jnp.asarray(mat, jnp.float32),
        jnp.asarray(state.data.qpos[7:9], jnp.float32))
    np.testing.assert_allclose(np.asarray(proprio), state.obs["proprio"], atol=1e-4)


def test_init_sampling_success_and_expert_match_under_jit(cpu_state):
    env, state = cpu_state
    draws = np.random.default_rng(0).random(tasks.NUM_DRAWS)
    ref = tasks.init_qpos(4, draws, xp=np)
    got = jax.jit(lambda d: tasks.init_qpos(4, d, xp=jnp))(jnp.asarray(draws, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-6)

    priv = expert.privileged(env, state.data)
    est = expert.init(priv, xp=np)
    action_np, est_np = expert.act(priv, est, np.zeros(6), xp=np)
    priv_j = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), priv)
    est_j = jax.tree.map(jnp.asarray, expert.init(priv_j, xp=jnp))
    act = jax.jit(jax.vmap(lambda p, e, n: expert.act(p, e, n, xp=jnp)))
    batch = lambda t: jax.tree.map(lambda x: jnp.stack([x, x]), t)  # noqa: E731
    action_j, est_j2 = act(batch(priv_j), batch(est_j), jnp.zeros((2, 6), jnp.float32))
    np.testing.assert_allclose(np.asarray(action_j[0]), action_np, atol=1e-4)
    assert int(est_j2.phase[1]) == int(est_np.phase)
    solved = jax.jit(lambda b, z, p: tasks.success(b, z, p, xp=jnp))(
        jnp.asarray([0.0, 0.1, 0.911]), jnp.float32(1.0), jnp.asarray([0.0, 0.1, 0.9]))
    assert bool(solved)


@pytest.mark.slow
def test_mjx_and_c_backends_agree_on_a_short_trajectory():
    from sim.mjx_env import MjxEnv

    config = SimConfig(settle_steps=0)
    mjx_env = MjxEnv(config, 2)
    cpu_env = CpuEnv(config, 2)
    qpos = mjx_env.init_states[0]
    actions = [np.array([0.5, -0.3, -0.4, 0.0, 0.0, 0.2, -1.0]), np.array([0.0, 0.4, 0.2, 0.2, 0.0, 0.0, 1.0])]
    step = jax.jit(mjx_env.step)
    mstate = jax.jit(mjx_env.reset_to)(jnp.asarray(qpos, jnp.float32))
    cstate = cpu_env.reset_to(qpos)
    for action in actions:
        mstate = step(mstate, jnp.asarray(action, jnp.float32))
        cstate = cpu_env.step(cstate, action)
    # float32 MJX vs float64 C engine, same model and controller, the arm's servos saturated by the
    # first action: the same motion to float32 rounding (with mjx.step, whose implicit update damps a
    # saturated servo, the end effector was 3-6 mm and the joints 0.02 rad apart after one step).
    np.testing.assert_allclose(np.asarray(mstate.obs["proprio"][:3]), cstate.obs["proprio"][:3], atol=2e-4)
    np.testing.assert_allclose(np.asarray(mstate.data.qpos[:9]), cstate.data.qpos[:9], atol=1e-3)
    np.testing.assert_allclose(np.asarray(mstate.data.qpos[9:]), cstate.data.qpos[9:], atol=1e-3)


@pytest.mark.slow
def test_mjx_step_integrates_a_saturated_servo_like_the_c_engine():
    import copy

    import mujoco
    from mujoco import mjx

    from sim.env import mjx_step

    env = CpuEnv(SimConfig(), 6)
    state = env.reset_to(env.init_states[5])
    data = copy.copy(state.data)
    data.ctrl[:7] = data.qpos[:7] + np.array([-0.3, -0.3, -0.1, -0.3, 0.0, 0.3, 0.3])  # kp x 0.3 rad > 87 N m
    mujoco.mj_forward(env.mj_model, data)
    limited = env.mj_model.actuator_forcelimited.astype(bool)
    assert np.any(np.abs(data.actuator_force[limited]) >= env.mj_model.actuator_forcerange[limited, 1] - 1e-9)
    model = mjx.put_model(env.mj_model)
    ours = jax.jit(mjx_step)(model, mjx.put_data(env.mj_model, data))
    mujoco.mj_step(env.mj_model, data)
    np.testing.assert_allclose(np.asarray(ours.qvel), data.qvel, atol=1e-4)
    np.testing.assert_allclose(np.asarray(ours.qpos), data.qpos, atol=1e-6)


@pytest.mark.slow
def test_mjx_step_places_box_contacts_and_their_forces_like_the_c_engine():
    """A pinch grasp (task 7, state 3, the C expert's step 45: both finger pads on one bowl wall, 5-6 mm
    deep): MJX's box-box collider puts contacts on a reference face, half a depth from the C engine's
    midpoints, which moved the held bowl's constraint force 4%; at the midpoints it matches."""
    import mujoco
    from mujoco import mjx

    from sim.env import _midpoint_box_contacts, _mjx_forward, _mjx_promotion

    env = CpuEnv(SimConfig(), 7)
    run = expert.rollout_cpu(env, env.init_states[3], cfg=expert.ExpertConfig(noise=0.0), max_steps=46, record=True,
                             stop_at_success=False)
    data = run["states"][45].data
    mujoco.mj_forward(env.mj_model, data)
    model, mjx_data = mjx.put_model(env.mj_model), mjx.put_data(env.mj_model, data)
    with _mjx_promotion():
        collided = jax.jit(lambda d: mjx.collision(model, mjx.kinematics(model, d)))(mjx_data)
        moved = jax.jit(lambda d: _midpoint_box_contacts(model, d))(collided)
        plain, ours = jax.jit(mjx.forward)(model, mjx_data), jax.jit(_mjx_forward)(model, mjx_data)
    contact, midpoint = collided._impl.contact, moved._impl.contact
    geom, dist = np.asarray(contact.geom), np.asarray(contact.dist)
    deep = 0
    for c in data.contact[:data.ncon]:
        if c.dist > -1e-3:
            continue  # shallow resting contacts: several share a depth, so the match below is ambiguous
        j = int(np.argmin(np.where((geom == sorted((c.geom1, c.geom2))).all(1) | (geom == [c.geom1, c.geom2]).all(1),
                                   np.abs(dist - c.dist), np.inf)))
        assert abs(dist[j] - c.dist) < 1e-5
        off = np.asarray(contact.pos)[j] - c.pos
        assert abs(abs(off @ c.frame[:3]) - 0.5 * abs(c.dist)) < 2e-4  # MJX: on a face, half a depth away
        np.testing.assert_allclose(np.asarray(midpoint.pos)[j], c.pos, atol=2e-4)
        deep += 1
    assert deep == 8  # four contacts of each finger pad on the bowl wall
    bowl = env.mj_model.jnt_dofadr[env.mj_model.body_jntadr[env.bowl_body]]
    c_force = data.qfrc_constraint[bowl:bowl + 6]
    assert np.abs(np.asarray(plain.qfrc_constraint)[bowl:bowl + 6] - c_force).max() > 0.03  # the departure
    np.testing.assert_allclose(np.asarray(ours.qfrc_constraint)[bowl:bowl + 6], c_force, atol=5e-3)


@pytest.mark.slow
def test_vmapped_jax_expert_solves_the_task_on_mjx():
    from sim.mjx_env import MjxEnv

    env = MjxEnv(SimConfig(backend="mjx"), 2)
    qpos = jnp.asarray(env.init_states[:2], jnp.float32)
    rollout = jax.jit(lambda qpos, key: expert.rollout_mjx(env, qpos, key, 90))
    solved, phases = rollout(qpos, jax.random.key(0))
    assert np.all(np.asarray(solved) == 1), f"phases reached: {np.asarray(phases).max(axis=0)}"
