"""Renderer speed on the LIBERO scene: JAX ray caster vs mjx.ray (depth only) vs mujoco.Renderer.

Prints ms per frame per env for a batch of envs at the given resolutions and merges the
figures into benchmarks/results/latest.json under ``sim.render.*``. It also times ``render_batch``
with and without the static-geometry split (a fixed camera's static geoms intersected once per
batch; the same frames up to float rounding) side by side, recorded as the ratio ``sim.render.<scene>.static_split_speedup_*``.

  python benchmarks/render_speed.py --tiny            # CPU check: 2 envs, 32 px
  python benchmarks/render_speed.py --envs 16 --res 64 128
"""

from __future__ import annotations

import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..")))
from sim import render as R  # noqa: E402
from sword_jax import cli  # noqa: E402


# A 13-geom arm-on-a-table scene (the measured scale); a material so mjx.ray runs.
SCENE_XML = """
<mujoco>
  <asset><material name="m" rgba="0.7 0.7 0.7 1"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 0.1" rgba="0.3 0.3 0.3 1" material="m"/>
    <body name="table" pos="0 0 0.4"><geom type="box" size="0.5 0.6 0.02" rgba="0.6 0.4 0.2 1"/></body>
    <body name="robot_link0" pos="-0.4 0 0.42"><joint type="hinge" axis="0 0 1"/>
      <geom type="capsule" size="0.04 0.15" pos="0 0 0.15"/>
      <body name="robot_link1" pos="0 0 0.3"><joint type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.035"/>
        <body name="robot_link2" pos="0.25 0 0"><joint type="hinge" axis="1 0 0"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.15" size="0.03"/>
          <body name="robot_hand" pos="0 0 -0.15"><geom type="box" size="0.02 0.05 0.02"/>
            <geom type="box" size="0.01 0.005 0.03" pos="0 0.03 -0.04"/>
            <geom type="box" size="0.01 0.005 0.03" pos="0 -0.03 -0.04"/></body></body></body></body>
    <body name="bowl" pos="0.1 0.1 0.5"><freejoint/><geom type="cylinder" size="0.05 0.025" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0"/></body>
    <body name="ball" pos="-0.1 -0.15 0.5"><freejoint/><geom type="sphere" size="0.04" rgba="0.8 0.1 0.1 1"/></body>
    <body name="box" pos="0.15 -0.2 0.48"><freejoint/><geom type="box" size="0.03 0.04 0.01" rgba="0.1 0.7 0.1 1"/></body>
    <body name="cabinet" pos="0.35 0.35 0.52"><geom type="box" size="0.08 0.1 0.1" rgba="0.5 0.3 0.1 1"/></body>
    <camera name="agentview" pos="0.9 0 1.1" xyaxes="0 1 0 -0.6 0 0.8" fovy="45"/>
  </worldbody>
</mujoco>
"""


def _time(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    start = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(fn())
    return (time.perf_counter() - start) / repeats


def main(argv=None) -> None:
    parser = cli.ArgumentParser(description=__doc__)
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--res", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--scene", choices=("libero", "primitives"), default="libero")
    parser.add_argument("--tiny", action="store_true", help="2 envs at 32 px, no results file")
    parser.add_argument("--no-write", action="store_true")
    args = parser.parse_args(argv)
    if args.tiny:
        args.envs, args.res, args.repeats, args.no_write = 2, [32], 1, True

    rng = np.random.default_rng(0)
    if args.scene == "libero":
        from sim import scene as libero_scene
        from sim import tasks

        model = libero_scene.build_model()
        qpos = [tasks.fixed_init_states(k % 10)[k % 50] for k in range(args.envs)]
    else:
        model = mujoco.MjModel.from_xml_string(SCENE_XML)
        qpos = []
        for _ in range(args.envs):
            q = model.qpos0.copy()
            q[:3] = rng.uniform(-0.5, 0.5, 3)
            qpos.append(q)
    scene = R.build_scene(model)
    mx = mjx.put_model(model)
    datas = []
    for q in qpos:
        d = mujoco.MjData(model)
        d.qpos[:] = q
        mujoco.mj_forward(model, d)
        datas.append(d)
    # Poses from the C engine carried as a batched mjx.Data (MJX physics is not what is timed).
    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *[mjx.put_data(model, d) for d in datas])
    cam_id, fovy = scene.cameras["agentview"]
    device = jax.devices()[0].device_kind
    rows, splits = {}, {}
    for res in args.res:
        jax_fn = jax.jit(jax.vmap(R.make_renderer(scene, "agentview", height=res, width=res)))
        t_jax = _time(lambda: jax_fn(batch), args.repeats) / args.envs

        # mjx.ray: depth + geom id only, one ray per pixel, vmapped over pixels and envs.
        ys, xs = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
        tan = np.tan(np.deg2rad(fovy) / 2)
        cam_dirs = np.stack([((xs + .5) / res * 2 - 1) * tan, (1 - (ys + .5) / res * 2) * tan, -np.ones_like(xs, float)], -1)
        cam_dirs = jnp.asarray(cam_dirs.reshape(-1, 3), jnp.float32)

        def ray_one(d):
            dirs = cam_dirs @ d.cam_xmat[cam_id].T
            dirs = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
            return jax.vmap(lambda v: mjx.ray(mx, d, d.cam_xpos[cam_id], v))(dirs)

        ray_fn = jax.jit(jax.vmap(ray_one))
        t_ray = _time(lambda: ray_fn(batch), args.repeats) / args.envs

        t_gl = float("nan")
        try:
            gl = mujoco.Renderer(model, res, res)
            start = time.perf_counter()
            for _ in range(args.repeats):
                for d in datas:
                    gl.update_scene(d, "agentview")
                    gl.render()
            t_gl = (time.perf_counter() - start) / (args.repeats * args.envs)
            gl.close()
        except Exception as err:  # noqa: BLE001 - EGL may be missing on a host
            print(f"mujoco.Renderer unavailable: {err}")
        rows[res] = (t_jax, t_ray, t_gl)

        poses = [np.stack([getattr(d, name) for d in datas]).astype(np.float32) for name in ("geom_xpos", "geom_xmat")]
        cams = [np.stack([getattr(d, name)[cam_id] for d in datas]).astype(np.float32) for name in ("cam_xpos", "cam_xmat")]
        whole_s, split_s = (_time(lambda s=s: R.render_batch(scene, *poses, *cams, fovy=fovy, height=res, width=res,
                                                             static_camera=s, tile=None), args.repeats) / args.envs
                            for s in (False, True))
        splits[res] = (whole_s, split_s)

    print(f"device: {device}, envs: {args.envs}, geoms drawn: {len(scene.geom_ids)}")
    print(f"{'res':>5} {'jax rgb+depth+seg':>18} {'mjx.ray depth':>14} {'mujoco.Renderer rgb':>20}  (ms/frame/env)")
    for res, (a, b, c) in rows.items():
        print(f"{res:>5} {a * 1e3:>18.3f} {b * 1e3:>14.3f} {c * 1e3:>20.3f}")
    static = int(np.sum(scene.static)) if scene.static is not None else 0
    print(f"render_batch, agentview, every geom per frame vs the {static} static geoms once per batch "
          "(ms/frame/env, side by side):")
    for res, (whole_s, split_s) in splits.items():
        print(f"{res:>5} {whole_s * 1e3:>10.3f} {split_s * 1e3:>10.3f}   speedup {whole_s / split_s:.2f}x")
    if args.no_write:
        return
    from benchmarks import common

    entries = {}
    for res, (a, b, c) in rows.items() if jax.default_backend() != "cpu" else ():  # CPU: ratios only
        for name, val in (("jax", a), ("mjx_ray_depth", b), ("mujoco_gl", c)):
            entries[f"sim.render.{args.scene}.{name}_ms_per_frame_{res}px_{args.envs}env"] = common.record(
                "", round(val * 1e3, 4), None)
    for res, (whole_s, split_s) in splits.items():
        entries[f"sim.render.{args.scene}.static_split_speedup_{res}px_{args.envs}env"] = common.record(
            "", round(whole_s / split_s, 3), None, static_geoms=static, drawn_geoms=len(scene.geom_ids),
            note="render_batch with static_camera vs without, same poses; frames equal up to float rounding")
    common.merge_results(entries)


if __name__ == "__main__":
    cli.run(main)
