"""Pure-JAX ray-cast renderer for MuJoCo scenes of primitive geoms: RGB, depth, segmentation.

One camera ray per pixel is intersected analytically with every visible primitive geom
(plane, sphere, capsule, ellipsoid, cylinder, box; a mesh geom is stood in for by its
bounding box) in the geom's local frame, the nearest hit wins, and the pixel is shaded from
the geom's colour (its material's colour where it has one) and surface normal with the
model's directional lights, headlight and ambient (optionally a hard shadow ray). Every
input is a JAX array (``geom_xpos``/``geom_xmat`` and the camera pose), everything about the
model is a static constant, so ``render`` runs under ``jit`` and ``vmap`` on any backend and takes the
poses of MJX's ``Data`` or, as numpy arrays, of MuJoCo's C-engine ``MjData`` alike.

Why this design (measured with ``benchmarks/render_speed.py`` on the LIBERO scene, 85 drawn
geoms, 16 envs, agentview, shadows off, on a 2-core CPU under a load of about 17 (other
processes), so absolute figures are pessimistic; ms per frame per env):

    resolution   this renderer (RGB+depth+seg)   mjx.ray (depth+id only)   mujoco.Renderer (RGB)
        64                  23                            151                        62
       128                 402                            957                       128

  * ``mjx.ray`` is 2-6x slower here, returns only distance and geom id (normals, colours
    and classes still need a per-geom pass like this one) and crashes on models with no
    ``<material>`` (issue 6). So it was not used.
  * A first dense version of this renderer materialised (geoms, pixels, 3) arrays; the
    current one scans over the geoms of each type keeping a running nearest hit, which is
    2-6x faster on CPU (identical output) and needs O(pixels) memory per env, so thousands
    of envs fit on one accelerator.
  * Static geometry once: the geoms that never move (27 of the 85 here: table, walls, fixtures,
    the robot's base) are intersected once per batch for a fixed camera (``render_batch(static_camera=
    True)``) or once per renderer (``make_renderer(model=...)``), and each frame tests only the moving
    ones, continuing from those hits; ties go to the same geom either way, so the frames are the
    same up to float rounding (LIBERO rollouts, 32-128 px: geom ids, classes and colours identical,
    depth within 4e-6 m). Side by side on this CPU (16 envs, ``benchmarks/render_speed.py``): 1.46x at 64 px,
    1.32x at 128 px.
  * Rays stay in the camera's frame, where their directions are per-pixel constants shared by
    every pose, and each geom's rotation absorbs the camera's; 3x3 rotations are broadcast
    multiply-adds. A per-geom ``(rays, 3) @ (3, 3)`` product, vmapped, became a batched dot that XLA's
    GPU backend runs as its own kernel, writing and re-reading the rotated rays once per geom: removing
    it took the LIBERO scene at 128 px from 20,125 to 111,600 frames/s on one H100 (batch 4096, with
    the static split below) and 27.4 to 9.9 ms per frame on the 2-core CPU (16 envs); the same frames.
  * Tile culling (``sim/render_cull.py``, on by default: ``tile=8``): each camera ray tests only the
    geoms whose projected bounding box covers its 8x8-pixel tile, with work in proportion to the
    overlapping (tile, geom) pairs (about 2% of them on the LIBERO agentview). The same frames (depth
    within float rounding). One H100, batch 4096, 128 px, LIBERO states (``bench_sim``, 2026-11-26):
    359k vs 173k frames/s without it; on this 2-core CPU 3-9x.
  * Shading is written per vector component (``render_hits._dot3``): a GPU profile found every
    ``sum(-1)``/``norm``/``argmax`` over an axis of 3 ending a fusion and writing a whole (batch,
    pixels, 3) array, 16 such kernels after the intersections; bit-identical frames.
  * ``mujoco.Renderer`` (OpenGL via EGL) cannot run under ``jit`` on the accelerator; on an
    idle CPU it takes ~1.8 ms per 128x128 frame (issue 6), so CPU data generation uses it
    where a GL context exists (``train.gen_data --renderer auto``, via ``sim/render_gl``)
    and it is the reference the tests compare against. On 9 LIBERO states (tasks 0/4/7,
    start, mid-grasp, step 60) at 64 and 128 px, segmentation classes agree on >= 99.9% of
    pixels (agentview and eye_in_hand), geom ids on >= 99.6%, and where both see the same
    geom the depth error is 0 mm median, < 0.75 mm at the 99th percentile (the rest are
    silhouette pixels); RGB differs by 6-22/255 on average (MuJoCo adds specular light).

Conventions: image row 0 is the top (as ``mujoco.Renderer`` returns it); depth is the
distance along the camera's viewing axis in metres (as MuJoCo's depth buffer, linearised),
``far`` where nothing is hit; ``geom_id`` is the MuJoCo geom id, -1 for background;
``seg`` is the class map of ``RenderScene.class_names`` (0 = background).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jaxtyping import Array, Float, Int, UInt8

from sim import render_cull
from sim.render_classes import segmentation_classes
from sim.render_hits import (_BOX, _HIT, _MESH, _SUPPORTED, _dot3, _local_normal, _rotate_rows, hit_order,
                             ranks_of_type)
from sim.render_hits import camera_dirs as _camera_dirs

_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], np.float32)


class Frame(NamedTuple):
    """One rendered camera image (leading batch axes allowed when vmapped)."""

    rgb: UInt8[Array, "h w 3"]
    depth: Float[Array, "h w"]
    geom_id: Int[Array, "h w"]
    seg: Int[Array, "h w"]


@dataclasses.dataclass(frozen=True, eq=False)
class RenderScene:
    """Static description of what to draw, built once from an ``MjModel`` (hash = identity).

    Attributes:
      geom_ids: model geom ids drawn, (n,), sorted.
      geom_type: their MuJoCo geom types (meshes replaced by boxes), (n,).
      size: intersection sizes, (n, 3) (box half sizes; radius/half-length; plane extent).
      offset: local-frame centre offset (mesh bounding boxes; zero otherwise), (n, 3).
      rgb: base colour in [0, 1], (n, 3).
      geom_class: class id of every model geom (ngeom,); class_names: names of class ids.
      cameras: camera name -> (camera id, vertical field of view in degrees).
      light_dirs: unit vectors towards each directional light (world frame), (L, 3);
        light_diffuse: their diffuse intensities (L,); ambient: ambient intensity;
        headlight: diffuse intensity of MuJoCo's headlight (along the view ray).
      background: RGB in [0, 1] where nothing is hit; far: depth there (metres).
      static: drawn geoms that never move (their body and its ancestors have no joint and are not
        mocap), (n,) bool; static_cameras: names of cameras that never move (fixed mode on such a
        body). A batch seen by a static camera shares the static geoms' nearest hits, which
        ``render_batch`` computes once instead of once per frame (the same output up to float rounding).
    """

    geom_ids: np.ndarray
    geom_type: np.ndarray
    size: np.ndarray
    offset: np.ndarray
    rgb: np.ndarray
    geom_class: np.ndarray
    class_names: tuple[str, ...]
    cameras: dict[str, tuple[int, float]]
    light_dirs: np.ndarray
    light_diffuse: np.ndarray
    ambient: float = 0.35
    headlight: float = 0.0
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # MuJoCo with no skybox
    far: float = 10.0
    static: np.ndarray | None = None  # None: treat every geom as moving
    static_cameras: frozenset[str] = frozenset()


def _geom_rgba(model: mujoco.MjModel, geom: int) -> np.ndarray:
    rgba = np.asarray(model.geom_rgba[geom], np.float32)
    matid = int(model.geom_matid[geom])
    # MuJoCo draws the material colour unless the geom's own rgba was set explicitly.
    if matid >= 0 and np.allclose(rgba, _DEFAULT_RGBA):
        rgba = np.asarray(model.mat_rgba[matid], np.float32)
    return rgba


def _static_bodies(model: mujoco.MjModel) -> np.ndarray:
    """(nbody,) bool: bodies fixed in the world (no joint and no mocap on them or any ancestor)."""
    static = np.zeros(model.nbody, bool)
    static[0] = True
    for body in range(1, model.nbody):  # parents come before their children in MuJoCo's order
        parent = int(model.body_parentid[body])
        static[body] = static[parent] and model.body_jntnum[body] == 0 and model.body_mocapid[body] < 0
    return static


def build_scene(
    model: mujoco.MjModel,
    *,
    geomgroups: tuple[int, ...] = (0, 1, 2),
    class_overrides: dict[str, str] | None = None,
    light_dir: tuple[float, float, float] | None = None,
    far: float = 10.0,
) -> RenderScene:
    """Collects the visible geoms of ``model`` (those MuJoCo's renderer shows by default).

    Args:
      model: the compiled MuJoCo model.
      geomgroups: geom groups drawn (MuJoCo's default visual option shows 0, 1 and 2).
      class_overrides: body name -> class name, passed to ``segmentation_classes``.
      light_dir: a single directional light (direction towards it, world frame) replacing
        the model's lights and headlight; default: the model's lights, as MuJoCo draws them
        (directional and spot lights by their static direction, diffuse only, plus the
        headlight and ambient terms; no textures or specular highlights).
      far: depth reported where a ray hits nothing (metres).

    Returns:
      The static ``RenderScene``.

    Raises:
      ValueError: if no geom is visible or a visible geom has an unsupported type.
    """
    if far <= 0:
        raise ValueError(f"far must be positive, got {far}")
    ids, types, sizes, offsets, colours = [], [], [], [], []
    for geom in range(model.ngeom):
        if int(model.geom_group[geom]) not in geomgroups:
            continue
        rgba = _geom_rgba(model, geom)
        if rgba[3] <= 0.0:
            continue
        gtype = int(model.geom_type[geom])
        if gtype not in _SUPPORTED:
            name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
            raise ValueError(
                f"geom {geom} ({name!r}) has type {mujoco.mjtGeom(gtype).name}, which the "
                "JAX renderer does not draw (planes, spheres, capsules, ellipsoids, "
                "cylinders, boxes and meshes-as-boxes only); put it in a hidden geom group"
            )
        size = np.asarray(model.geom_size[geom], np.float32)
        offset = np.zeros(3, np.float32)
        if gtype == _MESH:  # stand-in: the mesh's local bounding box
            aabb = np.asarray(model.geom_aabb[geom], np.float32)
            offset, size, gtype = aabb[:3], aabb[3:], _BOX
        ids.append(geom)
        types.append(gtype)
        sizes.append(size)
        offsets.append(offset)
        colours.append(rgba[:3])
    if not ids:
        raise ValueError(f"no geom of the model is visible in geom groups {geomgroups}")
    geom_class, class_names = segmentation_classes(model, overrides=class_overrides)
    cameras, static_cameras = {}, set()
    static_body = _static_bodies(model)
    for cam in range(model.ncam):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, cam) or f"camera{cam}"
        cameras[name] = (cam, float(model.cam_fovy[cam]))
        if static_body[model.cam_bodyid[cam]] and int(model.cam_mode[cam]) == int(mujoco.mjtCamLight.mjCAMLIGHT_FIXED):
            static_cameras.add(name)
    if light_dir is not None or model.nlight == 0:
        light = np.asarray(light_dir if light_dir is not None else (0.3, -0.4, 1.0), np.float32)
        light_dirs = (light / np.linalg.norm(light))[None, :]
        light_diffuse = np.array([0.65], np.float32)
        ambient, headlight = 0.35, 0.0
    else:
        towards = -np.asarray(model.light_dir, np.float32)  # world-body lights: static
        light_dirs = towards / np.linalg.norm(towards, axis=-1, keepdims=True)
        light_diffuse = np.asarray(model.light_diffuse, np.float32).mean(-1)
        active = bool(model.vis.headlight.active)
        ambient = float(np.mean(model.light_ambient.sum(0)) + active * np.mean(model.vis.headlight.ambient))
        headlight = float(active * np.mean(model.vis.headlight.diffuse))
    return RenderScene(
        geom_ids=np.asarray(ids, np.int32),
        geom_type=np.asarray(types, np.int32),
        size=np.stack(sizes).astype(np.float32),
        offset=np.stack(offsets).astype(np.float32),
        rgb=np.stack(colours).astype(np.float32),
        geom_class=geom_class,
        class_names=class_names,
        cameras=cameras,
        light_dirs=light_dirs,
        light_diffuse=light_diffuse,
        ambient=ambient,
        headlight=headlight,
        far=float(far),
        static=static_body[model.geom_bodyid[np.asarray(ids)]],
        static_cameras=frozenset(static_cameras),
    )




def _hit_order(scene: RenderScene) -> np.ndarray:
    """Drawn-geom indices in the order ``_nearest_hits`` tests them (:func:`sim.render_hits.hit_order`)."""
    return hit_order(scene.geom_type)


def _nearest_ranked(scene: RenderScene, pos, mat, origins, dirs, *, which: np.ndarray | None = None, start=None,
                    unroll: int | bool = 1, dir_frame=None):
    """Nearest hit of rays (r, 3) from origins (r|1, 3) over the drawn geoms ``which`` selects (bool (n,);
    ``None``: all), as (t (r,), rank (r,)): the ray parameter (+inf on a miss) and the winner's rank
    in :func:`_hit_order` (n on a miss). ``start``: a (t, rank) pair to continue from, e.g. the nearest
    hits of the other geoms; the result is the same as testing all of them at once.

    ``dir_frame``: a rotation (3, 3) the directions are given in (world directions ``dirs @ dir_frame.T``),
    e.g. a camera's frame, where a camera's ray directions are the same constants for every pose; each
    geom's rotation then absorbs it (one 3x3 product per geom, not per ray), so a batch of frames reads
    no per-frame direction array.

    A ``lax.scan`` over the geoms of each type keeps a running (t, rank) minimum, so the
    memory is O(rays) rather than O(geoms * rays) and each step stays in cache. ``unroll`` geoms per
    scan step (``True``: all of a type in one step) let XLA fuse their tests into one pass over the
    rays instead of reading and writing the running minimum once per geom; the result is the same.
    """
    order = _hit_order(scene)
    if start is None:
        best_t = jnp.full(dirs.shape[:1], jnp.inf, jnp.float32)
        best_r = jnp.full(dirs.shape[:1], len(order), jnp.int32)
    else:
        best_t, best_r = start
    for gtype, hit in _HIT.items():
        ranks, idx = ranks_of_type(order, scene.geom_type, gtype, which)
        if ranks.size == 0:
            continue
        dir_mat = mat[idx] if dir_frame is None else jnp.einsum("ji,njk->nik", dir_frame, mat[idx])

        def step(carry, geom, hit=hit):
            best_t, best_r = carry
            rank, geom_pos, geom_mat, dir_mat, size, offset = geom
            # Local frame: p_local = R^T (p - x) - offset, written row-wise as (p - x) R.
            local_o = _rotate_rows(origins - geom_pos, geom_mat) - offset
            local_d = _rotate_rows(dirs, dir_mat)
            t = hit(local_o, local_d, size)
            # Ties go to the lower rank, so the winner does not depend on which geoms were tested first.
            closer = (t < best_t) | ((t == best_t) & (rank < best_r) & jnp.isfinite(t))
            return (jnp.where(closer, t, best_t), jnp.where(closer, rank, best_r)), None

        geoms = (jnp.asarray(ranks, jnp.int32), pos[idx], mat[idx], dir_mat, jnp.asarray(scene.size[idx]),
                 jnp.asarray(scene.offset[idx]))
        (best_t, best_r), _ = jax.lax.scan(step, (best_t, best_r), geoms, unroll=unroll)
    return best_t, best_r


def _nearest_hits(scene: RenderScene, pos, mat, origins, dirs, *, start=None, which: np.ndarray | None = None,
                  unroll: int | bool = 1, dir_frame=None):
    """Nearest hit of rays (r, 3) from origins (r|1, 3) over the drawn geoms (``which``/``start``/``dir_frame``:
    see :func:`_nearest_ranked`).

    Returns:
      (t (r,) ray parameter of the nearest hit, +inf on a miss; index (r,) into the
      scene's drawn-geom arrays, 0 on a miss).
    """
    best_t, best_r = _nearest_ranked(scene, pos, mat, origins, dirs, which=which, start=start, unroll=unroll,
                                     dir_frame=dir_frame)
    return best_t, _geom_of_rank(scene, best_r)


def _geom_of_rank(scene: RenderScene, rank):
    """Drawn-geom index of each rank in :func:`_hit_order` (0 for the miss rank n)."""
    return jnp.asarray(np.append(_hit_order(scene), 0), jnp.int32)[rank]


def render(
    scene: RenderScene,
    geom_xpos: Float[Array, "ngeom 3"],
    geom_xmat: Float[Array, "ngeom 3 3"],
    cam_pos: Float[Array, "3"],
    cam_mat: Float[Array, "3 3"],
    *,
    fovy: float,
    height: int,
    width: int,
    shadows: bool = False,
    static_hits: tuple[Any, Any] | None = None,
    unroll: int | bool = 1,
    tile: int | None = None,
    chunk: int = 16,
) -> Frame:
    """Renders one camera view of one state (vmap for batches).

    Args:
      scene: static scene from ``build_scene``.
      geom_xpos: world positions of all model geoms, (ngeom, 3).
      geom_xmat: world orientations of all model geoms, (ngeom, 3, 3) or (ngeom, 9).
      cam_pos: camera position, (3,). cam_mat: camera orientation (columns: right, up,
        backward, as MuJoCo's ``cam_xmat``), (3, 3) or (9,).
      fovy: vertical field of view in degrees. height, width: image size in pixels.
      shadows: cast a shadow ray per pixel towards the light (about twice the cost).
      static_hits: the nearest hits of the scene's static geoms from this camera
        (:func:`static_nearest`, the same for every state a static camera sees); only the moving
        geoms are then tested per frame. The output is that of testing them all, up to float
        rounding (another XLA program computes the static hits).
      unroll: geoms tested per step of the per-type scans (``True``: all of a type at once); the same
        frames, another schedule (see ``_nearest_ranked``).
      tile: cull by ``tile x tile`` pixel tiles: each camera ray tests only the geoms whose projected
        bounding box covers its tile (``sim/render_cull.py``; the same frames). ``None``: every ray tests
        every geom. chunk: tiles per step of the culled loop.

    Returns:
      ``Frame`` with rgb (h, w, 3) uint8, depth (h, w) float32 metres, geom_id (h, w)
      int32 (-1 = background) and seg (h, w) int32 class ids.

    Raises:
      ValueError: poses whose shapes do not fit the scene's model (checked at trace time).
    """
    ngeom = len(scene.geom_class)
    if np.shape(geom_xpos) != (ngeom, 3) or np.size(geom_xmat) != ngeom * 9:
        raise ValueError(
            f"geom poses must be ({ngeom}, 3) and ({ngeom}, 3, 3) for this scene's model, got "
            f"{np.shape(geom_xpos)} and {np.shape(geom_xmat)} (vmap over batch axes)"
        )
    if np.size(cam_pos) != 3 or np.size(cam_mat) != 9:
        raise ValueError(f"camera pose must be (3,) and (3, 3), got {np.shape(cam_pos)} and {np.shape(cam_mat)}")
    ids = scene.geom_ids
    pos, mat, cam_pos, cam_mat = _poses(scene, geom_xpos, geom_xmat, cam_pos, cam_mat)
    cam_dirs = jnp.asarray(_camera_dirs(fovy, height, width))  # the same constants for every pose
    if tile is not None:
        depth, rank = render_cull.nearest_culled(
            scene.geom_type, scene.size, scene.offset, pos, mat, cam_pos, cam_mat, fovy=fovy, height=height,
            width=width, tile=tile, chunk=chunk, start=static_hits,
            which=None if static_hits is None else ~np.asarray(scene.static, bool))
        nearest = _geom_of_rank(scene, rank)
    elif static_hits is None:
        depth, nearest = _nearest_hits(scene, pos, mat, cam_pos[None, :], cam_dirs, unroll=unroll, dir_frame=cam_mat)
    else:
        depth, nearest = _nearest_hits(scene, pos, mat, cam_pos[None, :], cam_dirs, start=static_hits,
                                       which=~np.asarray(scene.static, bool), unroll=unroll, dir_frame=cam_mat)
    dirs = _rotate_rows(cam_dirs, cam_mat.T)
    hit = jnp.isfinite(depth)
    depth = jnp.where(hit, depth, jnp.float32(scene.far))

    # Normal of the winning geom only, from the hit point in its local frame.
    hit_mat = mat[nearest]  # (R, 3, 3)
    points = cam_pos[None, :] + depth[:, None] * dirs
    p_local = _rotate_rows(points - pos[nearest], hit_mat) - jnp.asarray(scene.offset)[nearest]
    n_local = _local_normal(
        jnp.asarray(scene.geom_type)[nearest], p_local, jnp.asarray(scene.size)[nearest]
    )
    normal = _rotate_rows(n_local, jnp.swapaxes(hit_mat, -1, -2))
    # Per-component dot products (``_dot3``), not sums over the last axis: on a GPU each such reduction
    # wrote a whole (batch, pixels, 3) array; without them the shading fuses (sim/render_hits.py).
    view = dirs / jnp.sqrt(_dot3(dirs, dirs))[:, None]
    normal = jnp.where(_dot3(normal, view)[:, None] > 0, -normal, normal)

    lights = [jnp.maximum(_dot3(normal, jnp.asarray(light)), 0.0) for light in scene.light_dirs]  # L x (R,)
    if shadows:  # hard shadows from the strongest light
        strongest = int(np.argmax(scene.light_diffuse))
        light = jnp.asarray(scene.light_dirs[strongest])
        starts = points + normal * jnp.float32(1e-3)
        t_shadow, _ = _nearest_hits(scene, pos, mat, starts, jnp.broadcast_to(light, dirs.shape))
        lights[strongest] = jnp.where(jnp.isfinite(t_shadow), 0.0, lights[strongest])
    base = jnp.asarray(scene.rgb)[nearest]
    facing = jnp.maximum(-_dot3(normal, view), 0.0)
    shade = (jnp.float32(scene.ambient) + sum(lambert * jnp.float32(diffuse)
                                             for lambert, diffuse in zip(lights, scene.light_diffuse))
             + jnp.float32(scene.headlight) * facing)
    colour = jnp.where(hit[:, None], base * shade[:, None], jnp.asarray(scene.background, jnp.float32))
    rgb = jnp.round(jnp.clip(colour, 0.0, 1.0) * 255.0).astype(jnp.uint8)

    geom_id = jnp.where(hit, jnp.asarray(ids)[nearest], -1)
    seg = jnp.where(hit, jnp.asarray(scene.geom_class)[jnp.maximum(geom_id, 0)], 0)
    return Frame(
        rgb=rgb.reshape(height, width, 3),
        depth=depth.reshape(height, width),
        geom_id=geom_id.reshape(height, width).astype(jnp.int32),
        seg=seg.reshape(height, width).astype(jnp.int32),
    )


def _poses(scene: RenderScene, geom_xpos, geom_xmat, cam_pos, cam_mat):
    """The drawn geoms' poses (n, 3), (n, 3, 3) and the camera's (3,), (3, 3), as float32."""
    ids = scene.geom_ids
    pos = jnp.asarray(geom_xpos, jnp.float32)[ids]
    mat = jnp.asarray(geom_xmat, jnp.float32).reshape(-1, 3, 3)[ids]
    return pos, mat, jnp.asarray(cam_pos, jnp.float32).reshape(3), jnp.asarray(cam_mat, jnp.float32).reshape(3, 3)


def _view(scene: RenderScene, geom_xpos, geom_xmat, cam_pos, cam_mat, *, fovy: float, height: int, width: int):
    """The drawn geoms' poses (n, 3), (n, 3, 3), the camera position (3,) and one world ray direction per
    pixel (R, 3)."""
    pos, mat, cam_pos, cam_mat = _poses(scene, geom_xpos, geom_xmat, cam_pos, cam_mat)
    return pos, mat, cam_pos, _rotate_rows(jnp.asarray(_camera_dirs(fovy, height, width)), cam_mat.T)


def static_nearest(scene: RenderScene, geom_xpos, geom_xmat, cam_pos, cam_mat, *, fovy: float, height: int,
                   width: int) -> tuple[Any, Any]:
    """The nearest hits of the scene's static geoms, one per pixel, as ``render(static_hits=...)`` takes
    them: valid for every state seen by the same static camera (the static geoms and the camera do not
    move), so a batch computes them once.

    Raises:
      ValueError: a scene without static-geom information (built before it existed).
    """
    if scene.static is None:
        raise ValueError("static_nearest: this RenderScene does not say which geoms are static (rebuild it "
                         "with build_scene)")
    pos, mat, cam_pos, cam_mat = _poses(scene, geom_xpos, geom_xmat, cam_pos, cam_mat)
    return _nearest_ranked(scene, pos, mat, cam_pos[None, :], jnp.asarray(_camera_dirs(fovy, height, width)),
                           which=np.asarray(scene.static, bool), dir_frame=cam_mat)


def camera_pose(data: Any, camera_id: int) -> tuple[Any, Any]:
    """(cam_xpos (3,), cam_xmat (3, 3)) of an ``mjx.Data`` or a ``mujoco.MjData``."""
    return data.cam_xpos[camera_id], data.cam_xmat[camera_id].reshape(3, 3)


def static_hits_of_model(scene: RenderScene, model: mujoco.MjModel, camera: str, *, height: int,
                         width: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``static_nearest`` for ``camera`` from the model's own static poses (MuJoCo's forward kinematics
    at ``qpos0``: static geoms and fixed cameras sit where the model puts them in every state), as
    constants a per-state renderer closes over; ``None`` if the camera moves or nothing is static."""
    if camera not in scene.static_cameras or scene.static is None or not np.any(scene.static):
        return None
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_camlight(model, data)
    cam_id, fovy = scene.cameras[camera]
    t, rank = static_nearest(scene, data.geom_xpos.astype(np.float32), data.geom_xmat.astype(np.float32),
                             data.cam_xpos[cam_id].astype(np.float32), data.cam_xmat[cam_id].astype(np.float32),
                             fovy=fovy, height=height, width=width)
    return np.asarray(t), np.asarray(rank)


def make_renderer(
    scene: RenderScene,
    camera: str,
    *,
    height: int,
    width: int,
    shadows: bool = False,
    model: mujoco.MjModel | None = None,
    unroll: int | bool = 1,
    tile: int | None = None,
    chunk: int = 16,
) -> Callable[[Any], Frame]:
    """A pure ``data -> Frame`` function for one camera (jit/vmap it over ``mjx.Data``).

    Args:
      scene: from ``build_scene``. camera: camera name in the model.
      height, width: image size. shadows: see ``render``.
      model: the scene's ``MjModel``; with it, a fixed camera's static-geom hits are computed once,
        here (:func:`static_hits_of_model`), and each frame tests only the moving geoms. The frames
        are those of testing every geom up to float rounding (MJX's float32 kinematics place the
        static geoms within 5e-8 m of MuJoCo's, from which the hits are computed).
      unroll, tile, chunk: see ``render``.

    Raises:
      KeyError: unknown camera. ValueError: non-positive image size, tile or chunk.
    """
    if camera not in scene.cameras:
        raise KeyError(f"camera {camera!r} not in the model; cameras: {sorted(scene.cameras)}")
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {height}x{width}")
    if (tile is not None and tile <= 0) or chunk <= 0:
        raise ValueError(f"tile and chunk must be positive, got tile {tile} and chunk {chunk}")
    cam_id, fovy = scene.cameras[camera]
    static = static_hits_of_model(scene, model, camera, height=height, width=width) if model is not None else None

    def render_data(data: Any) -> Frame:
        cam_pos, cam_mat = camera_pose(data, cam_id)
        return render(
            scene, data.geom_xpos, data.geom_xmat, cam_pos, cam_mat,
            fovy=fovy, height=height, width=width, shadows=shadows,
            static_hits=None if static is None else (jnp.asarray(static[0]), jnp.asarray(static[1])), unroll=unroll,
            tile=tile, chunk=chunk,
        )

    return render_data


@functools.partial(jax.jit, static_argnames=("scene", "fovy", "height", "width", "shadows", "static_camera", "tile"))
def render_batch(
    scene: RenderScene,
    geom_xpos: Float[Array, "b ngeom 3"],
    geom_xmat: Float[Array, "b ngeom 9"],
    cam_pos: Float[Array, "b 3"],
    cam_mat: Float[Array, "b 9"],
    *,
    fovy: float,
    height: int,
    width: int,
    shadows: bool = False,
    static_camera: bool = False,
    tile: int | None = 8,
) -> Frame:
    """Jitted, vmapped ``render`` over a leading batch axis (numpy or JAX inputs).

    ``static_camera``: the camera is one of ``scene.static_cameras`` (the same pose in every frame), so
    the static geoms' nearest hits are computed once, from the first frame, and each frame tests only
    the moving geoms (:func:`static_nearest`; the same output up to float rounding). ``tile``: tile culling
    (see ``render``; ``None`` tests every geom for every ray)."""
    fn = functools.partial(render, scene, fovy=fovy, height=height, width=width, shadows=shadows, tile=tile)
    if not (static_camera and scene.static is not None and np.any(scene.static)):
        return jax.vmap(fn)(geom_xpos, geom_xmat, cam_pos, cam_mat)
    shared = static_nearest(scene, geom_xpos[0], geom_xmat[0], cam_pos[0], cam_mat[0], fovy=fovy, height=height,
                            width=width)
    return jax.vmap(lambda *pose: fn(*pose, static_hits=shared))(geom_xpos, geom_xmat, cam_pos, cam_mat)


def render_mjdata(
    scene: RenderScene,
    datas: list[mujoco.MjData],
    camera: str,
    *,
    height: int,
    width: int,
    shadows: bool = False,
) -> Frame:
    """Renders C-engine states (after ``mj_forward``/``mj_step``) with the same JAX function.

    Returns numpy-convertible arrays with a leading axis of len(datas).
    """
    if camera not in scene.cameras:
        raise KeyError(f"camera {camera!r} not in the model; cameras: {sorted(scene.cameras)}")
    if not datas:
        raise ValueError("render_mjdata needs at least one MjData")
    cam_id, fovy = scene.cameras[camera]
    xpos = np.stack([d.geom_xpos for d in datas]).astype(np.float32)
    xmat = np.stack([d.geom_xmat for d in datas]).astype(np.float32)
    cpos = np.stack([d.cam_xpos[cam_id] for d in datas]).astype(np.float32)
    cmat = np.stack([d.cam_xmat[cam_id] for d in datas]).astype(np.float32)
    return render_batch(
        scene, xpos, xmat, cpos, cmat, fovy=fovy, height=height, width=width, shadows=shadows,
        static_camera=camera in scene.static_cameras,
    )


def make_obs_renderer(
    scene: RenderScene,
    cameras: tuple[str, ...] = ("agentview",),
    *,
    height: int,
    width: int,
    depth: bool = False,
    seg: bool = False,
) -> Callable[[Any], dict[str, Any]]:
    """An env observation hook ``data -> {"<camera>_rgb": ..., ...}`` (``sim.load(renderer=...)``).

    With an ``mjx.Data`` it is pure JAX (traced into the env's jitted step); with a
    ``mujoco.MjData`` (the C backend) it calls a jitted single-frame render and returns numpy.

    Args:
      scene: from ``build_scene``. cameras: camera names. height, width: image size.
      depth, seg: also return ``<camera>_depth`` (h, w) float32 and ``<camera>_seg`` (h, w) int32.

    Raises:
      KeyError: an unknown camera.
    """
    renderers = {cam: make_renderer(scene, cam, height=height, width=width) for cam in cameras}

    def images(frames: dict[str, Frame]) -> dict[str, Any]:
        out = {}
        for cam, frame in frames.items():
            out[f"{cam}_rgb"] = frame.rgb
            if depth:
                out[f"{cam}_depth"] = frame.depth
            if seg:
                out[f"{cam}_seg"] = frame.seg
        return out

    def obs_renderer(data: Any) -> dict[str, Any]:
        if isinstance(data, mujoco.MjData):
            frames = {cam: jax.tree.map(lambda x: np.asarray(x[0]),
                                        render_mjdata(scene, [data], cam, height=height, width=width))
                      for cam in cameras}
            return images(frames)
        return images({cam: fn(data) for cam, fn in renderers.items()})

    return obs_renderer
