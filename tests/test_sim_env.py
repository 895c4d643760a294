"""Scene, tasks, controller and the C-backend pure env (fast: MuJoCo's C engine)."""

import numpy as np
import pytest

import sim
from sim import controller as ctl
from sim import scene, tasks
from sim.config import SimConfig
from sim.env import CpuEnv


@pytest.fixture(scope="module")
def env():
    return CpuEnv(SimConfig(), 2)


def test_scene_compiles_with_materials_and_named_parts():
    model = scene.build_model()
    assert np.all(model.geom_matid >= 0), "every geom needs a material (mjx.ray)"
    for name in scene.OBJECTS + scene.FIXTURES + ("table", "panda_mount", "panda_hand"):
        assert model.body(name).id > 0
    for cam in ("agentview", "eye_in_hand"):
        assert model.camera(cam).id >= 0
    labels, names = scene.geom_segment_labels(model)
    assert names[:3] == ("background", "table", "robot")
    assert set(scene.OBJECTS + scene.FIXTURES) <= set(names)
    hand_geom = model.geom("panda_hand_geom").id
    assert names[labels[hand_geom]] == "robot"
    assert names[labels[model.geom("akita_black_bowl_1_base").id]] == "akita_black_bowl_1"
    # Arm links never collide: only finger pads, bowls, supports have contype/conaffinity.
    arm = [model.geom(f"panda_link{k}_geom0").id for k in range(1, 8)]
    assert np.all(model.geom_contype[arm] == 0) and np.all(model.geom_conaffinity[arm] == 0)


def test_language_and_init_states_are_deterministic():
    assert len(tasks.LANGUAGE) == 10
    assert tasks.LANGUAGE[4] == (
        "pick up the black bowl in the top drawer of the wooden cabinet and place it on the plate")
    a = tasks.fixed_init_states(3)
    b = tasks.fixed_init_states(3)
    c = tasks.fixed_init_states(3, seed=1)
    assert a.shape == (50, scene.build_model().nq)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)
    # Different tasks differ only in the bowls' placements (objects 0 and 1).
    other = tasks.fixed_init_states(7)
    np.testing.assert_array_equal(a[:, :9], other[:, :9])
    with pytest.raises(ValueError, match="task_id"):
        tasks.init_qpos(10, np.zeros(tasks.NUM_DRAWS))


@pytest.mark.parametrize("task_id", range(10))
def test_reset_is_settled_and_bowls_start_where_the_task_says(task_id):
    env = CpuEnv(SimConfig(), task_id)
    state = env.reset_to(env.init_states[0])
    data = state.data
    assert np.all(np.isfinite(data.qpos))
    assert state.done == 0, "no task starts solved"
    assert np.abs(data.qvel).max() < 0.5, "objects should be at rest after the settle steps"
    # Every object rests upright on its support (z within 1.5 cm of the sampled start).
    for k, name in enumerate(scene.OBJECTS):
        start = env.init_states[0][9 + 7 * k: 12 + 7 * k]
        np.testing.assert_allclose(data.body(name).xpos, start, atol=0.015, err_msg=name)
        assert data.body(name).xmat[8] > 0.98, f"{name} tipped over"
    placement = tasks.BOWLS[task_id][0]
    if placement.support != "table":
        assert data.body(scene.TARGET_BOWL).xpos[2] > scene.TABLE_TOP_Z + 0.015


def test_reset_starts_from_initial_qpos(env):
    qpos = env.initial_qpos(np.random.default_rng(5))
    assert any(np.array_equal(qpos, state) for state in env.init_states)  # init="fixed": one of the 50
    np.testing.assert_array_equal(env.reset_to(qpos).data.qpos, env.reset(np.random.default_rng(5)).data.qpos)


def test_reset_and_step_are_deterministic_and_pure(env):
    s0 = env.reset(np.random.default_rng(5))
    s1 = env.reset(np.random.default_rng(5))
    np.testing.assert_array_equal(s0.data.qpos, s1.data.qpos)
    qpos_before = s0.data.qpos.copy()
    action = np.array([0.3, -0.2, 0.1, 0.0, 0.1, 0.0, -1.0])
    a = env.step(s0, action)
    b = env.step(s0, action)
    np.testing.assert_array_equal(s0.data.qpos, qpos_before)  # step did not mutate its input
    np.testing.assert_array_equal(a.data.qpos, b.data.qpos)
    c = env.step_inplace(env.reset(np.random.default_rng(5)), action)
    np.testing.assert_array_equal(a.data.qpos, c.data.qpos)
    assert a.obs["proprio"].shape == (8,) and np.all(np.isfinite(a.obs["proprio"]))
    with pytest.raises(ValueError, match="shape"):
        env.step(s0, np.zeros(6))
    with pytest.raises(ValueError, match="finite"):
        env.step(s0, np.full(7, np.nan))


@pytest.mark.parametrize("axis", range(3))
def test_controller_moves_the_end_effector_the_commanded_way(env, axis):
    state = env.reset_to(env.init_states[0])
    start = state.obs["proprio"][:3].copy()
    action = np.zeros(7)
    action[axis], action[6] = 0.5, -1.0
    for _ in range(4):
        state = env.step(state, action)
    moved = state.obs["proprio"][:3] - start
    assert moved[axis] > 0.04, moved  # 4 steps x 2.5 cm commanded
    off_axis = np.delete(moved, axis)
    assert np.abs(off_axis).max() < 0.3 * moved[axis], moved


def test_controller_rotation_and_gripper(env):
    state = env.reset_to(env.init_states[0])
    q7 = state.data.qpos[6]
    for _ in range(3):
        state = env.step(state, np.array([0, 0, 0, 0, 0, 0.6, 1.0]))
    # +z world rotation of a downward-pointing hand turns joint 7 negatively.
    assert q7 - state.data.qpos[6] > 0.3
    assert np.all(state.data.qpos[7:9] < 0.005), "closed gripper"
    for _ in range(5):
        state = env.step(state, np.array([0, 0, 0, 0, 0, 0, -1.0]))
    assert np.all(state.data.qpos[7:9] > 0.035), "open gripper"


def test_rotation_helpers_roundtrip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.1, np.pi - 0.01)
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        mat = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
        np.testing.assert_allclose(ctl.quat_to_axis_angle(ctl.mat_to_quat(mat)), axis * angle, atol=1e-6)


def _placed_state(env, dz, dxy):
    """Init state 0 with the target bowl teleported onto the plate (offsets dz, dxy), settled."""
    qpos = env.init_states[0].copy()
    plate = qpos[9 + 14: 12 + 14]
    qpos[9:12] = plate + np.array([dxy[0], dxy[1], scene.PLATE_TOP + dz])
    qpos[12:16] = [1, 0, 0, 0]
    return qpos


def test_success_triggers_when_placed_and_not_in_a_near_miss(env):
    placed = env.reset_to(_placed_state(env, 0.002, (0.005, 0.0)))
    assert placed.done == 1 and placed.reward == 1 and placed.metrics["success"] == 1
    beside = env.reset_to(_placed_state(env, 0.002, (0.045, 0.0)))  # centres 4.5 cm apart
    assert beside.done == 0
    # Predicate alone: hovering 8 mm above the plate is a near miss, 4 mm counts.
    plate = np.array([0.0, 0.1, scene.TABLE_TOP_Z])
    bowl = plate + np.array([0.01, 0.0, scene.PLATE_TOP])
    assert tasks.success(bowl + [0, 0, 0.004], 1.0, plate)
    assert not tasks.success(bowl + [0, 0, 0.008], 1.0, plate)
    assert not tasks.success(bowl + [0.025, 0.0, 0.0], 1.0, plate)
    assert not tasks.success(bowl, 0.5, plate)  # tipped


def test_registry_load_and_errors():
    env = sim.load("libero_spatial_4")
    assert isinstance(env, CpuEnv) and env.task_id == 4
    assert sim.load("libero_spatial", task_id=1, init="random").config.init == "random"
    from sim.mjx_env import MjxEnv

    mjx_env = sim.load("libero_spatial", task_id=9, backend="mjx")  # the scene converts to MJX
    assert isinstance(mjx_env, MjxEnv) and mjx_env.substeps == 10
    with pytest.raises(KeyError, match="unknown sim env"):
        sim.load("libero_goal")
    with pytest.raises(TypeError, match="unknown sim overrides"):
        sim.load("libero_spatial", resolutoin=64)
    with pytest.raises(ValueError, match="task_id"):
        sim.load("libero_spatial", task_id=12)
    with pytest.raises(ValueError, match="physics_dt"):
        sim.load("libero_spatial", physics_dt=0.003)


def test_solver_settings_are_per_engine():
    """MJX solves with sim.mjx_solver_iterations/mjx_ls_iterations (4/4), the C engine keeps 6/8 (its data
    behind the comparisons do not change); each pair is set on its own and checked."""
    cpu_env, mjx_env = sim.load("libero_spatial"), sim.load("libero_spatial", backend="mjx")
    assert (cpu_env.mj_model.opt.iterations, cpu_env.mj_model.opt.ls_iterations) == (6, 8)
    assert (int(mjx_env.mjx_model.opt.iterations), int(mjx_env.mjx_model.opt.ls_iterations)) == (4, 4)
    assert (mjx_env.mj_model.opt.iterations, mjx_env.mj_model.opt.ls_iterations) == (6, 8)
    tuned = sim.load("libero_spatial", backend="mjx", mjx_solver_iterations=6, mjx_ls_iterations=8, solver_iterations=3)
    assert (int(tuned.mjx_model.opt.iterations), int(tuned.mjx_model.opt.ls_iterations)) == (6, 8)
    assert sim.load("libero_spatial", solver_iterations=3).mj_model.opt.iterations == 3
    with pytest.raises(ValueError, match="sim.mjx_ls_iterations must be >= 1"):
        SimConfig(mjx_ls_iterations=0).validate()


def test_initial_layouts_never_overlap():
    """Footprints (circles; the cookie box by its half-diagonal) keep >= 3 mm apart, and
    table-level objects stay clear of the stove and of the cabinet with its open drawer."""
    radius = (scene.BOWL_RADIUS, scene.BOWL_RADIUS, scene.PLATE_RADIUS, scene.RAMEKIN_RADIUS,
              float(np.hypot(*scene.COOKIES_HALF[:2])))
    rects = [(scene.STOVE_POS[:2], scene.STOVE_HALF[:2]),
             ((scene.CABINET_POS[0] - scene.DRAWER_OUT / 2, scene.CABINET_POS[1]),
              (scene.CABINET_HALF[0] + scene.DRAWER_OUT / 2, scene.CABINET_HALF[1]))]
    for task_id in range(10):
        on_table = [k for k in range(5) if k > 0 or tasks.BOWLS[task_id][0].support == "table"]
        for qpos in tasks.fixed_init_states(task_id):
            xy = [qpos[9 + 7 * k: 11 + 7 * k] for k in range(5)]
            for i in on_table:
                for j in on_table:
                    if i < j:
                        gap = np.linalg.norm(xy[i] - xy[j]) - radius[i] - radius[j]
                        assert gap > 0.003, (task_id, scene.OBJECTS[i], scene.OBJECTS[j], gap)
                for centre, half in rects:
                    outside = np.maximum(np.abs(xy[i] - np.asarray(centre)) - np.asarray(half), 0)
                    assert np.hypot(*outside) > radius[i], (task_id, scene.OBJECTS[i])


@pytest.mark.slow  # ~30 s here: the JAX renderer runs op by op on C-engine data
def test_camera_renderer_plugs_images_into_observations():
    pytest.importorskip("sim.render")
    from sim.env import camera_renderer

    base = CpuEnv(SimConfig(), 0)
    renderer = camera_renderer(base.mj_model, resolution=16, wrist_camera=True, depth_and_seg=True)
    env = CpuEnv(SimConfig(), 0, renderer=renderer)
    state = env.reset_to(env.init_states[0])
    rgb = np.asarray(state.obs["agentview_rgb"])
    assert rgb.shape == (16, 16, 3) and rgb.dtype == np.uint8 and rgb.std() > 3
    assert np.asarray(state.obs["eye_in_hand_rgb"]).shape == (16, 16, 3)
    assert np.asarray(state.obs["agentview_depth"]).shape == (16, 16)
    assert len(np.unique(np.asarray(state.obs["agentview_seg"]))) >= 2
    np.testing.assert_array_equal(state.obs["proprio"], base.reset_to(base.init_states[0]).obs["proprio"])
