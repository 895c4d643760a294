"""Renderer speed on the LIBERO scene: JAX ray caster vs mjx.ray (depth only) vs mujoco.Renderer.

Prints ms per frame per env for a batch of envs at the given resolutions and merges the
figures into benchmarks/results/latest.json under ``sim.render.*``.

  python benchmarks/render_speed.py --tiny            # CPU check: 2 envs, 32 px
  python benchmarks/render_speed.py --envs 16 --res 64 128
"""

from __future__ import annotations

import argparse
import datetime
import json
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

RESULTS = os.path.join(os.path.dirname(__file__), "results", "latest.json")

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
    parser = argparse.ArgumentParser(description=__doc__)
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
    rows = {}
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

    print(f"device: {device}, envs: {args.envs}, geoms drawn: {len(scene.geom_ids)}")
    print(f"{'res':>5} {'jax rgb+depth+seg':>18} {'mjx.ray depth':>14} {'mujoco.Renderer rgb':>20}  (ms/frame/env)")
    for res, (a, b, c) in rows.items():
        print(f"{res:>5} {a * 1e3:>18.3f} {b * 1e3:>14.3f} {c * 1e3:>20.3f}")
    if args.no_write:
        return
    results = json.load(open(RESULTS)) if os.path.exists(RESULTS) else {}
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")
    cmd = "python benchmarks/render_speed.py " + " ".join(argv or sys.argv[1:])
    for res, (a, b, c) in rows.items():
        for name, val in (("jax", a), ("mjx_ray_depth", b), ("mujoco_gl", c)):
            results[f"sim.render.{args.scene}.{name}_ms_per_frame_{res}px_{args.envs}env"] = {
                "value": round(val * 1e3, 4), "target": None, "device": device, "date": date, "command": cmd,
            }
    os.makedirs(os.path.dirname(RESULTS), exist_ok=True)
    with open(RESULTS, "w") as f:
        json.dump(results, f, indent=2, sort_keys=True)


if __name__ == "__main__":
    main()
