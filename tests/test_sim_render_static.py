"""The renderer's static-geometry split: a batch seen by a fixed camera computes the static geoms'
nearest hits once (sim/render.py::static_nearest); the frames must match testing every geom per frame.

They are the same computation in another XLA program, so depth may differ by float rounding (measured:
up to 4e-6 m at 32 px, none at 64 and 128 px); geom ids, classes and colours were identical. The
checks allow rounding in depth and a bounded share of silhouette pixels (tests/support/frames.py), nothing more."""

import jax
import mujoco
import numpy as np
import pytest

from sim import expert, render
from sim.config import SimConfig
from sim.env import CpuEnv
from tests.support.frames import assert_frames_agree


def _assert_same_frames(a, b):
    assert_frames_agree(a.depth, b.depth, a.geom_id, b.geom_id, rgb=a.rgb, ref_rgb=b.rgb)
    assert np.mean(a.seg == b.seg) >= 0.999


def _frames(scene, datas, camera, static_camera, size=32):
    cam_id, fovy = scene.cameras[camera]
    stack = lambda name: np.stack([getattr(d, name) for d in datas]).astype(np.float32)  # noqa: E731
    frame = render.render_batch(scene, stack("geom_xpos"), stack("geom_xmat"),
                                np.stack([d.cam_xpos[cam_id] for d in datas]).astype(np.float32),
                                np.stack([d.cam_xmat[cam_id] for d in datas]).astype(np.float32),
                                fovy=fovy, height=size, width=size, static_camera=static_camera)
    return jax.tree.map(np.asarray, frame)


def test_libero_scene_knows_its_static_geoms_and_cameras_and_the_split_matches():
    env = CpuEnv(SimConfig(), task_id=4)
    scene = render.build_scene(env.mj_model)
    assert scene.static_cameras == frozenset({"agentview", "frontview"})  # the wrist camera moves
    assert 0 < scene.static.sum() < len(scene.static)
    moving = set(scene.geom_class[scene.geom_ids[~scene.static]].tolist())
    fixed = set(scene.geom_class[scene.geom_ids[scene.static]].tolist())
    assert scene.class_names.index("robot") in moving and scene.class_names.index("table") in fixed - moving
    assert scene.class_names.index("akita_black_bowl_1") in moving - fixed
    out = expert.rollout_cpu(env, env.init_states[1], max_steps=30, record=True)
    datas = [s.data for s in out["states"][::10]]
    split, whole = _frames(scene, datas, "agentview", True), _frames(scene, datas, "agentview", False)
    _assert_same_frames(split, whole)
    assert len(np.unique(whole.geom_id)) > 10  # a real scene: table, fixtures, objects, robot
    # render_mjdata takes the split for a static camera by itself, with the same frames
    via = jax.tree.map(np.asarray, render.render_mjdata(scene, datas, "agentview", height=32, width=32))
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
    whole = _frames(scene, [data, data], "fixed", False, 16)
    box_pixels = np.isin(whole.geom_id, [0, 2])
    assert box_pixels.any() and (whole.geom_id[box_pixels] == 0).all()  # the tie: the first-tested box, b
    # Either group first: the same winners (the tie clause lets a later-tested, lower-ranked geom win).
    cam_id, fovy = scene.cameras["fixed"]
    pos, mat, cam_pos, dirs = render._view(scene, data.geom_xpos, data.geom_xmat, data.cam_xpos[cam_id],
                                           data.cam_xmat[cam_id], fovy=fovy, height=12, width=12)
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
    """make_renderer(model=...) closes over the static hits computed from the model once (the MJX env's
    camera renderer). On C-engine poses its frames equal the plain renderer's; MJX's float32
    kinematics place the static geoms within rounding of MuJoCo's (measured 5e-8 m), and its frames
    agree with testing every geom but for rounding at silhouettes."""
    from mujoco import mjx

    from sim.env import camera_renderer

    env = CpuEnv(SimConfig(), task_id=3)
    out = expert.rollout_cpu(env, env.init_states[0], max_steps=20, record=True)
    model, scene = env.mj_model, render.build_scene(env.mj_model)
    assert render.static_hits_of_model(scene, model, "eye_in_hand", height=8, width=8) is None  # it moves
    hook = jax.jit(camera_renderer(model, resolution=32, depth_and_seg=True))
    unrolled = jax.jit(camera_renderer(model, resolution=32, depth_and_seg=True, unroll=3))  # 43 boxes: a remainder
    # the hook culls by 8-px tiles (sim/render_cull.py, tested on its own); so does the plain renderer here
    plain = {"agentview": jax.jit(render.make_renderer(scene, "agentview", height=32, width=32, tile=8))}
    mx = mjx.put_model(model)
    kinematics = jax.jit(lambda d: mjx.camlight(mx, mjx.kinematics(mx, d)))
    for state in (out["states"][0], out["states"][-1]):
        c_poses = mjx.put_data(model, state.data)  # MuJoCo's own poses, as float32
        images = jax.tree.map(np.asarray, hook(c_poses))
        # Unrolling the per-type scans changes the schedule, not the frames.
        for key, value in jax.tree.map(np.asarray, unrolled(c_poses)).items():
            np.testing.assert_array_equal(value, images[key], err_msg=key)
        for cam, draw in plain.items():
            ref = jax.tree.map(np.asarray, draw(c_poses))
            assert_frames_agree(images[f"{cam}_depth"], ref.depth, images[f"{cam}_seg"], ref.seg,
                                rgb=images[f"{cam}_rgb"], ref_rgb=ref.rgb)
        with jax.numpy_dtype_promotion("standard"):  # MJX's own code mixes Python floats and bools
            mjx_poses = kinematics(c_poses)
        a = jax.tree.map(np.asarray, hook(mjx_poses))
        b = jax.tree.map(np.asarray, plain["agentview"](mjx_poses))
        assert_frames_agree(a["agentview_depth"], b.depth, a["agentview_seg"], b.seg, depth_atol=1e-4)
