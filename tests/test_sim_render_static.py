"""The renderer's static-geometry split: a batch seen by a fixed camera computes the static geoms'
nearest hits once (sim/render.py::static_nearest); the frames must equal testing every geom per frame."""

import jax
import mujoco
import numpy as np
import pytest

from sim import expert, render
from sim.config import SimConfig
from sim.env import CpuEnv


def _frames(scene, datas, camera, static_camera, size=48):
    cam_id, fovy = scene.cameras[camera]
    stack = lambda name: np.stack([getattr(d, name) for d in datas]).astype(np.float32)  # noqa: E731
    frame = render.render_batch(scene, stack("geom_xpos"), stack("geom_xmat"),
                                np.stack([d.cam_xpos[cam_id] for d in datas]).astype(np.float32),
                                np.stack([d.cam_xmat[cam_id] for d in datas]).astype(np.float32),
                                fovy=fovy, height=size, width=size, static_camera=static_camera)
    return jax.tree.map(np.asarray, frame)


def test_libero_scene_knows_its_static_geoms_and_cameras_and_the_split_is_exact():
    env = CpuEnv(SimConfig(), task_id=4)
    scene = render.build_scene(env.mj_model)
    assert scene.static_cameras == frozenset({"agentview", "frontview"})  # the wrist camera moves
    assert 0 < scene.static.sum() < len(scene.static)
    moving = set(scene.geom_class[scene.geom_ids[~scene.static]].tolist())
    fixed = set(scene.geom_class[scene.geom_ids[scene.static]].tolist())
    assert scene.class_names.index("robot") in moving and scene.class_names.index("table") in fixed - moving
    assert scene.class_names.index("akita_black_bowl_1") in moving - fixed
    out = expert.rollout_cpu(env, env.init_states[1], max_steps=40, record=True)
    datas = [s.data for s in out["states"][::8]]
    split, whole = _frames(scene, datas, "agentview", True), _frames(scene, datas, "agentview", False)
    for name in ("rgb", "depth", "geom_id", "seg"):
        np.testing.assert_array_equal(getattr(split, name), getattr(whole, name), err_msg=name)
    assert len(np.unique(whole.geom_id)) > 10  # a real scene: table, fixtures, objects, robot
    # render_mjdata takes the split for a static camera by itself, with the same frames
    via = jax.tree.map(np.asarray, render.render_mjdata(scene, datas, "agentview", height=48, width=48))
    np.testing.assert_array_equal(via.seg, whole.seg)


def test_equally_near_static_and_moving_geoms_resolve_as_when_all_are_tested_together():
    """A moving box exactly where a static one is: every ray ties, and the winner (the lower rank in
    the test order) is the same whichever group is tested first."""
    xml = """<mujoco><worldbody>
      <camera name="fixed" pos="0 -1 0.3" xyaxes="1 0 0 0 0.3 1"/>
      <body name="mover" pos="0 0 0.1"><freejoint/><geom name="a" type="box" size="0.1 0.1 0.1" rgba="1 0 0 1"/></body>
      <geom name="b" type="box" pos="0 0 0.1" size="0.1 0.1 0.1" rgba="0 1 0 1"/>
      <geom name="c" type="sphere" pos="0.3 0 0.1" size="0.08" rgba="0 0 1 1"/>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    scene = render.build_scene(model)
    assert scene.static.tolist() == [True, True, False] and scene.static_cameras == frozenset({"fixed"})  # b, c, a
    split, whole = _frames(scene, [data, data], "fixed", True), _frames(scene, [data, data], "fixed", False)
    np.testing.assert_array_equal(split.geom_id, whole.geom_id)
    box_pixels = np.isin(whole.geom_id, [0, 2])
    assert box_pixels.any() and (whole.geom_id[box_pixels] == 0).all()  # the tie: the first-tested box, b
    # Either group first: the same winners (the tie clause lets a later-tested, lower-ranked geom win).
    cam_id, fovy = scene.cameras["fixed"]
    pos, mat, cam_pos, dirs = render._view(scene, data.geom_xpos, data.geom_xmat, data.cam_xpos[cam_id],
                                           data.cam_xmat[cam_id], fovy=fovy, height=24, width=24)
    first, second = np.array([True, False, False]), np.array([False, True, True])
    for a_mask, b_mask in ((first, second), (second, first)):
        start = render._nearest_ranked(scene, pos, mat, cam_pos[None], dirs, which=a_mask)
        t, rank = render._nearest_ranked(scene, pos, mat, cam_pos[None], dirs, which=b_mask, start=start)
        t_all, rank_all = render._nearest_ranked(scene, pos, mat, cam_pos[None], dirs)
        np.testing.assert_array_equal(np.asarray(rank), np.asarray(rank_all))
        np.testing.assert_array_equal(np.asarray(t), np.asarray(t_all))


def test_a_scene_without_static_information_is_refused_by_static_nearest():
    import dataclasses

    model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom type="sphere" size="0.1"/></worldbody></mujoco>')
    scene = dataclasses.replace(render.build_scene(model), static=None)
    with pytest.raises(ValueError, match="does not say which geoms are static"):
        render.static_nearest(scene, np.zeros((1, 3)), np.eye(3).reshape(1, 9), np.zeros(3), np.eye(3),
                              fovy=45.0, height=4, width=4)


def test_per_state_renderer_with_the_models_static_hits_draws_the_same_frames():
    """make_renderer(model=...) closes over the static hits computed from the model once (the path the
    MJX env takes, state by state); on C-engine states its frames equal the plain renderer's."""
    from sim.env import camera_renderer

    env = CpuEnv(SimConfig(), task_id=7)
    out = expert.rollout_cpu(env, env.init_states[2], max_steps=24, record=True)
    scene = render.build_scene(env.mj_model)
    assert render.static_hits_of_model(scene, env.mj_model, "eye_in_hand", height=8, width=8) is None  # it moves
    hook = camera_renderer(env.mj_model, resolution=40, wrist_camera=True, depth_and_seg=True)
    plain = {cam: render.make_renderer(scene, cam, height=40, width=40) for cam in ("agentview", "eye_in_hand")}
    for state in out["states"][::12]:
        images = jax.tree.map(np.asarray, hook(state.data))
        for cam, draw in plain.items():
            ref = jax.tree.map(np.asarray, draw(state.data))
            np.testing.assert_array_equal(images[f"{cam}_rgb"], ref.rgb)
            np.testing.assert_array_equal(images[f"{cam}_depth"], ref.depth)
            np.testing.assert_array_equal(images[f"{cam}_seg"], ref.seg)


def test_mjx_states_render_the_same_with_the_models_static_hits():
    """MJX's float32 kinematics place the static geoms within rounding of MuJoCo's (measured 5e-8 m);
    the split renderer's frames from MJX states agree with testing every geom."""
    from mujoco import mjx

    env = CpuEnv(SimConfig(), task_id=3)
    out = expert.rollout_cpu(env, env.init_states[0], max_steps=20, record=True)
    model, scene = env.mj_model, render.build_scene(env.mj_model)
    mx = mjx.put_model(model)
    kinematics = jax.jit(lambda d: mjx.camlight(mx, mjx.kinematics(mx, d)))
    split = jax.jit(render.make_renderer(scene, "agentview", height=64, width=64, model=model))
    plain = jax.jit(render.make_renderer(scene, "agentview", height=64, width=64))
    for state in (out["states"][0], out["states"][-1]):
        with jax.numpy_dtype_promotion("standard"):  # MJX's own code mixes Python floats and bools
            data = kinematics(mjx.put_data(model, state.data))
        a, b = jax.tree.map(np.asarray, split(data)), jax.tree.map(np.asarray, plain(data))
        assert np.mean(a.seg == b.seg) >= 0.999 and np.mean(a.geom_id == b.geom_id) >= 0.999
        assert np.abs(a.depth - b.depth).max() < 1e-4
