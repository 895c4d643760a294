"""JAX ray-cast renderer: analytic scenes, jit/vmap over MJX states, parity with mujoco.Renderer."""

import chex
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from sim import render as R
from sim.render_classes import segmentation_classes
from sim.render_gl import GLRenderer, gl_available
from tests.support.frames import assert_frames_agree

SPHERE_XML = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 0.1" pos="0 0 -1" rgba="0.4 0.4 0.4 1"/>
    <body name="ball" pos="0 0 0"><freejoint/><geom name="ball" type="sphere" size="0.2" rgba="1 0 0 1"/></body>
    <camera name="down" pos="0 0 2" fovy="40"/>
  </worldbody>
</mujoco>
"""

# Every primitive type, a robot-like chain, free objects, a fixture and a hidden geom.
PRIMITIVES_XML = """
<mujoco>
  <visual><global offwidth="128" offheight="128"/></visual>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 0.1" rgba="0.3 0.3 0.3 1"/>
    <body name="table" pos="0 0 0.4"><geom name="table_top" type="box" size="0.5 0.6 0.02" rgba="0.6 0.4 0.2 1"/></body>
    <body name="arm_link0" pos="-0.4 0 0.42"><joint type="hinge" axis="0 0 1"/>
      <geom type="capsule" size="0.04 0.15" pos="0 0 0.15" rgba="0.9 0.9 0.9 1"/>
      <body name="arm_link1" pos="0 0 0.3"><joint type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.035" rgba="0.9 0.9 0.9 1"/>
        <body name="arm_hand" pos="0.25 0 0"><joint type="hinge" axis="1 0 0"/>
          <geom type="box" size="0.02 0.05 0.02" rgba="0.2 0.2 0.2 1"/></body></body></body>
    <body name="bowl" pos="0.1 0.1 0.5"><freejoint/>
      <geom type="cylinder" size="0.05 0.025" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0"/></body>
    <body name="ball" pos="-0.1 -0.15 0.5"><freejoint/><geom type="sphere" size="0.04" rgba="0.8 0.1 0.1 1"/></body>
    <body name="egg" pos="0.15 -0.2 0.48"><freejoint/>
      <geom type="ellipsoid" size="0.05 0.03 0.02" rgba="0.1 0.7 0.1 1" contype="0" conaffinity="0"/></body>
    <body name="cabinet" pos="0.35 0.35 0.52"><geom type="box" size="0.08 0.1 0.1" euler="0 0 30" rgba="0.5 0.3 0.1 1"/></body>
    <geom name="hidden" type="box" size="0.1 0.1 0.1" pos="0 0 1" group="3"/>
    <camera name="agentview" pos="0.9 0 1.1" xyaxes="0 1 0 -0.6 0 0.8" fovy="45"/>
    <camera name="top" pos="0 0 2.0" fovy="60"/>
  </worldbody>
</mujoco>
"""


def _forward(model, qpos=None):
    data = mujoco.MjData(model)
    if qpos is not None:
        data.qpos[: len(qpos)] = qpos
    mujoco.mj_forward(model, data)
    return data


def _render_one(scene, data, camera, size):
    frame = R.render_mjdata(scene, [data], camera, height=size, width=size)
    return jax.tree.map(lambda x: np.asarray(x[0]), frame)


def test_sphere_depth_and_ids_analytic():
    model = mujoco.MjModel.from_xml_string(SPHERE_XML)
    scene = R.build_scene(model)
    frame = _render_one(scene, _forward(model), "down", 33)
    ball = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "ball")
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    # Centre pixel looks straight down the axis: depth = distance - radius.
    np.testing.assert_allclose(frame.depth[16, 16], 2.0 - 0.2, atol=1e-5)
    assert frame.geom_id[16, 16] == ball and frame.geom_id[0, 0] == floor
    np.testing.assert_allclose(frame.depth[0, 0], 3.0, atol=1e-4)  # floor plane at z = -1
    assert scene.class_names[frame.seg[16, 16]] == "ball" and frame.seg[0, 0] == 0
    # The sphere's silhouette: pixel rays within asin(r / d) of the axis hit it.
    tan = np.tan(np.deg2rad(40) / 2)
    u = ((np.arange(33) + 0.5) / 33 * 2 - 1) * tan
    angle = np.arctan(np.hypot(u[None, :], u[:, None]))
    expect = angle < np.arcsin(0.2 / 2.0)
    assert np.mean((frame.geom_id == ball) == expect) > 0.99
    # Lit from above: the red channel dominates on the ball, and the top (facing the light) is bright.
    assert frame.rgb[16, 16, 0] > 200 and frame.rgb[16, 16, 1] == 0
    assert np.all(np.isfinite(frame.depth)) and frame.rgb.dtype == np.uint8


def test_deterministic_and_camera_errors():
    model = mujoco.MjModel.from_xml_string(PRIMITIVES_XML)
    scene = R.build_scene(model)
    data = _forward(model)
    a, b = _render_one(scene, data, "top", 32), _render_one(scene, data, "top", 32)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(KeyError, match="nope"):
        R.make_renderer(scene, "nope", height=8, width=8)
    with pytest.raises(ValueError, match="positive"):
        R.make_renderer(scene, "top", height=0, width=8)
    cam_id, fovy = scene.cameras["top"]
    with pytest.raises(ValueError, match="geom poses must be"):
        R.render(scene, data.geom_xpos[:-1], data.geom_xmat[:-1], data.cam_xpos[cam_id], data.cam_xmat[cam_id],
                 fovy=fovy, height=8, width=8)
    hidden = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "hidden")
    assert hidden not in scene.geom_ids  # group 3 is not drawn, as in MuJoCo's default


def test_segmentation_classes_from_body_tree():
    model = mujoco.MjModel.from_xml_string(PRIMITIVES_XML)
    geom_class, names = segmentation_classes(model)
    assert names[:3] == ("background", "table", "robot")
    assert set(names[3:]) == {"bowl", "ball", "egg", "cabinet"}
    by_body = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g])): names[geom_class[g]]
               for g in range(model.ngeom) if model.geom_bodyid[g] > 0}
    assert by_body["table"] == "table" and by_body["arm_hand"] == "robot" and by_body["bowl"] == "bowl"
    geom_class2, names2 = segmentation_classes(model, overrides={"cabinet": "fixtures"})
    assert "fixtures" in names2 and "cabinet" not in names2
    with pytest.raises(KeyError, match="unknown body"):
        segmentation_classes(model, overrides={"no_such_body": "x"})


def test_shadow_darkens_floor_under_object():
    model = mujoco.MjModel.from_xml_string(SPHERE_XML.replace('pos="0 0 -1"', 'pos="0 0 -0.5"'))
    scene = R.build_scene(model, light_dir=(1.0, 0.0, 1.0))
    data = _forward(model)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    cam_id, fovy = scene.cameras["down"]
    args = (data.geom_xpos, data.geom_xmat, data.cam_xpos[cam_id], data.cam_xmat[cam_id])
    render = jax.jit(R.render, static_argnames=("scene", "fovy", "height", "width", "shadows"))
    lit = render(scene, *args, fovy=fovy, height=33, width=33)
    shaded = render(scene, *args, fovy=fovy, height=33, width=33, shadows=True)
    # Light from +x at 45 degrees: the ball's shadow centre is on the floor at x = -0.5,
    # seen 2.5 m away at column (-0.5 / 2.5 / tan(20 deg) + 1) / 2 * 33 ~ 7; x = +0.5 is lit.
    in_shadow, in_light = (16, 7), (16, 25)
    assert int(lit.geom_id[in_shadow]) == floor and int(lit.geom_id[in_light]) == floor
    assert int(shaded.rgb[in_shadow].sum()) < int(lit.rgb[in_shadow].sum())
    np.testing.assert_array_equal(np.asarray(shaded.rgb[in_light]), np.asarray(lit.rgb[in_light]))
    np.testing.assert_array_equal(np.asarray(lit.depth), np.asarray(shaded.depth))


def test_jit_vmap_over_mjx_batch_matches_c_engine():
    """The same function renders a vmapped batch of ``mjx.Data`` and of C-engine states."""
    model = mujoco.MjModel.from_xml_string(SPHERE_XML)
    scene = R.build_scene(model)
    mx = mjx.put_model(model)
    offsets = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [-0.25, 0.1, 0.4]])
    datas = [_forward(model, np.asarray(model.qpos0[:3]) + off) for off in offsets]
    # Poses computed by the C engine, carried as mjx.Data (MJX's physics compile is too slow here).
    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *[mjx.put_data(model, d) for d in datas])

    @jax.jit
    @chex.assert_max_traces(n=1)
    def render_all(mjx_datas):
        return jax.vmap(R.make_renderer(scene, "down", height=24, width=24))(mjx_datas)

    frames = render_all(batch)
    render_all(batch)  # no retrace
    assert frames.rgb.shape == (3, 24, 24, 3) and frames.depth.shape == (3, 24, 24)
    assert not np.array_equal(np.asarray(frames.geom_id[0]), np.asarray(frames.geom_id[1]))
    ref = R.render_mjdata(scene, datas, "down", height=24, width=24)
    # two programs: equal but for rounding at silhouettes
    assert_frames_agree(frames.depth, ref.depth, frames.geom_id, ref.geom_id, depth_atol=1e-4, rgb=frames.rgb,
                        ref_rgb=ref.rgb)
    same = np.asarray(frames.geom_id) == np.asarray(ref.geom_id)
    np.testing.assert_array_equal(np.asarray(frames.rgb)[same], np.asarray(ref.rgb)[same])


@pytest.fixture(scope="module")
def gl():
    ok, reason = gl_available()
    if not ok:
        pytest.skip(reason)


@pytest.mark.parametrize("camera", ["agentview"])
def test_matches_mujoco_renderer_on_primitives(gl, camera):
    """Segmentation agrees on >= 95% of pixels; depth within 2 mm on 99% of shared pixels."""
    model = mujoco.MjModel.from_xml_string(PRIMITIVES_XML)
    scene = R.build_scene(model)
    rng = np.random.default_rng(0)
    for _ in range(2):
        data = _forward(model, np.concatenate([rng.uniform(-0.8, 0.8, 3)]))
        mine = _render_one(scene, data, camera, 64)
        with GLRenderer(model, scene, camera, height=64, width=64) as ref_renderer:
            ref = ref_renderer.render(data)
        assert np.mean(mine.seg == ref.seg) >= 0.95
        assert np.mean(mine.geom_id == ref.geom_id) >= 0.95
        shared = (mine.geom_id == ref.geom_id) & (ref.geom_id >= 0)
        err = np.abs(mine.depth - ref.depth)[shared]
        assert np.quantile(err, 0.99) < 2e-3, np.quantile(err, 0.99)
