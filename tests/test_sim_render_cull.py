"""Tile culling (sim/render_cull.py): each camera ray tests only the geoms whose projected bounding box
covers its pixel tile. The frames must be those of testing every geom (measured: bit-identical on
LIBERO states), the bounds must contain everything a ray hits, and on the LIBERO agentview most
(tile, geom) pairs must be culled."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from sim import expert, render, render_cull
from sim.config import SimConfig
from sim.env import CpuEnv
from tests.support.frames import SILHOUETTE_SHARE, assert_frames_agree


@functools.lru_cache(maxsize=1)
def _libero():
    env = CpuEnv(SimConfig(), task_id=4)
    out = expert.rollout_cpu(env, env.init_states[1], max_steps=60, record=True, stop_at_success=False)
    datas = [s.data for s in out["states"][::20]]
    return env, render.build_scene(env.mj_model), datas


def _poses(scene, datas, camera):
    cam_id, fovy = scene.cameras[camera]
    stack = lambda rows: jnp.asarray(np.stack(rows).astype(np.float32))  # noqa: E731
    return (stack([d.geom_xpos for d in datas]), stack([d.geom_xmat for d in datas]),
            stack([d.cam_xpos[cam_id] for d in datas]), stack([d.cam_xmat[cam_id] for d in datas]), fovy)


def _frames(scene, poses, *, height, width, tile, static_hits=None, chunk=4):
    xpos, xmat, cpos, cmat, fovy = poses
    draw = functools.partial(render.render, scene, fovy=fovy, height=height, width=width, tile=tile, chunk=chunk,
                             static_hits=static_hits)
    return jax.tree.map(np.asarray, jax.jit(jax.vmap(draw))(xpos, xmat, cpos, cmat))


def _assert_identical(culled, dense):
    # the same arithmetic in another XLA program: depth may differ by float rounding (measured 6e-6 m),
    # and so may a silhouette pixel
    assert_frames_agree(culled.depth, dense.depth, culled.geom_id, dense.geom_id, depth_atol=2e-5)
    same = culled.geom_id == dense.geom_id
    assert np.mean(culled.seg == dense.seg) >= 1 - SILHOUETTE_SHARE
    assert np.abs(culled.rgb.astype(np.int32) - dense.rgb)[same].max() <= 1


@pytest.mark.parametrize("camera,tile,split", [("agentview", 8, True), ("eye_in_hand", 16, False)])
def test_culled_frames_equal_testing_every_geom_on_libero_states(camera, tile, split):
    """Fixed camera with the static split, and the moving wrist camera (robot links beside and behind
    it) testing every geom; 30x44 pixels, so the edge tiles are partial."""
    env, scene, datas = _libero()
    poses = _poses(scene, datas, camera)
    static = None
    if split:
        t, rank = render.static_hits_of_model(scene, env.mj_model, camera, height=30, width=44)
        static = (jnp.asarray(t), jnp.asarray(rank))
    dense = _frames(scene, poses, height=30, width=44, tile=None, static_hits=static)
    culled = _frames(scene, poses, height=30, width=44, tile=tile, static_hits=static)
    _assert_identical(culled, dense)
    assert len(np.unique(dense.geom_id)) > 8  # a real view: table, fixtures, objects, robot
    if split:  # vmap of vmap: the inner batch goes through the loop's custom_vmap rule, the outer through
        # ordinary batching of it; the frames must be the flat batch's
        xpos, xmat, cpos, cmat, fovy = poses
        draw = functools.partial(render.render, scene, fovy=fovy, height=30, width=44, tile=tile, chunk=4,
                                 static_hits=static)
        pairs = lambda x: x[:4].reshape(2, 2, *x.shape[1:])  # noqa: E731
        nested = jax.jit(jax.vmap(jax.vmap(draw)))(pairs(xpos), pairs(xmat), pairs(cpos), pairs(cmat))
        np.testing.assert_array_equal(np.asarray(nested.geom_id).reshape(4, 30, 44), culled.geom_id[:4])


def test_every_hit_lies_inside_its_geoms_projected_bound():
    """Conservativeness: for every pixel of a dense frame, its ray direction falls inside the winning
    geom's screen-space rectangle (both cameras, every geom, 48 px)."""
    _, scene, datas = _libero()
    for camera in ("agentview", "eye_in_hand"):
        xpos, xmat, cpos, cmat, fovy = _poses(scene, datas, camera)
        dense = _frames(scene, (xpos, xmat, cpos, cmat, fovy), height=48, width=48, tile=None)
        dirs = render_cull.camera_dirs(fovy, 48, 48)
        half = render_cull.bound_half_extents(scene.geom_type, scene.size)
        index = {int(g): i for i, g in enumerate(scene.geom_ids)}
        for f in range(len(datas)):
            pos, mat, cam_pos, cam_mat = render._poses(scene, xpos[f], xmat[f], cpos[f], cmat[f])
            rect = np.asarray(render_cull.geom_rects(pos, mat, scene.offset, half, cam_pos, cam_mat))
            ids = dense.geom_id[f].reshape(-1)
            hit = ids >= 0
            r = rect[[index[int(g)] for g in ids[hit]]]
            x, y = dirs[hit, 0], dirs[hit, 1]
            inside = (x >= r[:, 0] - 1e-5) & (x <= r[:, 1] + 1e-5) & (y >= r[:, 2] - 1e-5) & (y <= r[:, 3] + 1e-5)
            assert inside.all(), (camera, f, int((~inside).sum()))


def test_most_tile_geom_pairs_are_culled_on_the_agentview():
    """The point of culling: on LIBERO agentview frames at 128 px, fewer than 6% of the (8-px tile,
    moving geom) pairs overlap (measured about 2%), so the culled loop tests a small share of them."""
    _, scene, datas = _libero()
    xpos, xmat, cpos, cmat, fovy = _poses(scene, datas, "agentview")
    layout = render_cull.tile_layout(fovy, 128, 128, 8)
    half = render_cull.bound_half_extents(scene.geom_type, scene.size)
    moving = ~np.asarray(scene.static, bool)
    shares = []
    for f in range(len(datas)):
        pos, mat, cam_pos, cam_mat = render._poses(scene, xpos[f], xmat[f], cpos[f], cmat[f])
        rect = np.asarray(render_cull.geom_rects(pos, mat, scene.offset, half, cam_pos, cam_mat))[moving]
        t = layout.rect
        overlap = ((rect[None, :, 0] <= t[:, 1:2]) & (rect[None, :, 1] >= t[:, 0:1])
                   & (rect[None, :, 2] <= t[:, 3:4]) & (rect[None, :, 3] >= t[:, 2:3]))
        shares.append(overlap.mean())
    assert 0 < max(shares) < 0.06, shares


_EDGE_XML = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="0 0 0.1" rgba="0.3 0.3 0.3 1"/>
  <body name="cam_body" pos="0 0 0.5"><freejoint/><inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/><camera name="eye" pos="0 0 0" xyaxes="1 0 0 0 1 0" fovy="60"/></body>
  <body name="around" pos="0 0 0.5"><freejoint/><geom type="box" size="0.3 0.3 0.05" rgba="1 0 0 1"/></body>
  <body name="ahead" pos="0.05 0 0.2"><freejoint/><geom type="capsule" size="0.03 0.2" euler="0 60 0" rgba="0 1 0 1"/></body>
  <body name="behind" pos="0 0 0.9"><freejoint/><geom type="sphere" size="0.05" rgba="0 0 1 1"/></body>
  <body name="side" pos="0.2 0.1 0.25"><freejoint/><geom type="cylinder" size="0.04 0.03" rgba="1 1 0 1"/></body>
  <body name="egg" pos="-0.15 -0.1 0.3"><freejoint/><geom type="ellipsoid" size="0.05 0.03 0.02" rgba="0 1 1 1"/></body>
</worldbody></mujoco>"""


def test_bounds_straddling_or_behind_the_camera_keep_the_frames():
    """A box around the camera (covers every tile), a sphere wholly behind it (covers none), a tilted
    capsule, a cylinder, an ellipsoid and an infinite floor plane, looked at from inside the box."""
    model = mujoco.MjModel.from_xml_string(_EDGE_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    scene = render.build_scene(model)
    cam_id, fovy = scene.cameras["eye"]
    args = (data.geom_xpos.astype(np.float32), data.geom_xmat.astype(np.float32),
            data.cam_xpos[cam_id].astype(np.float32), data.cam_xmat[cam_id].astype(np.float32))
    # looking down -z from z = 0.5: the box half-height 0.05 straddles the camera
    pos, mat, cam_pos, cam_mat = render._poses(scene, *args)
    rect = np.asarray(render_cull.geom_rects(pos, mat, scene.offset, render_cull.bound_half_extents(
        scene.geom_type, scene.size), cam_pos, cam_mat))
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, model.geom_bodyid[g]) for g in scene.geom_ids]
    assert np.all(np.isinf(rect[names.index("around")])) and rect[names.index("around")][0] < 0
    assert rect[names.index("behind")][0] > rect[names.index("behind")][1]  # empty: never hit
    assert np.all(np.isinf(rect[names.index("world")]))  # the infinite plane
    for height, width, tile, chunk in ((24, 24, 8, 1), (20, 36, 16, 3)):
        draw = functools.partial(render.render, scene, fovy=fovy, height=height, width=width)
        dense = jax.tree.map(np.asarray, jax.jit(draw)(*args))
        culled = jax.tree.map(np.asarray, jax.jit(functools.partial(draw, tile=tile, chunk=chunk))(*args))
        _assert_identical(culled, dense)
        assert len(np.unique(dense.geom_id)) >= 3


def test_bad_tile_or_chunk_is_refused():
    _, scene, _ = _libero()
    with pytest.raises(ValueError, match="tile and chunk must be positive"):
        render.make_renderer(scene, "agentview", height=32, width=32, tile=0)
    with pytest.raises(ValueError, match="tile and chunk must be positive"):
        render.make_renderer(scene, "agentview", height=32, width=32, tile=8, chunk=0)
