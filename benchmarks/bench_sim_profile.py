"""Where an MJX physics step's time goes, stage by stage, on the LIBERO-Spatial-like scene.

    python -m benchmarks.bench_sim_profile --batch 4096     # one GPU
    python -m benchmarks.bench_sim_profile --tiny           # CPU check: batch 2, no results file

The batch of worlds is reset and stepped with random actions for ``--warmup`` control steps (so
objects rest and contacts exist). Then every stage of ``mjx.step`` (``fwd_position``'s kinematics
... constraint assembly, ``fwd_velocity``, ``fwd_actuation``, ``fwd_acceleration``, the
constraint solver, the integrator) is jitted and vmapped alone and timed on the states the stages
before it produced. Beside them, in the same run: the env's whole physics step (``sim.env.mjx_step``:
MJX's forward stages with box-box contacts at the C engine's midpoints, and the implicit update as the
C engine does it; the stages' sum less what XLA fuses across them), MJX's own ``mjx.step`` (what those
corrections cost), and the env's step with fewer solver (line-search) iterations, for the cost side
of the solver lever (whether the expert still succeeds is ``bench_sim``'s and the C-engine
comparison's question, not this file's). An env-step is ``substeps`` physics steps.

The renderer, on the same states (agentview, ``--resolution`` px, with the static-geometry split
the env uses): the poses, the moving geoms' intersection by geom type (each type's scan alone, its rays
the camera-frame constants ``render`` uses), and the whole frame; what is left of the whole is the
nearest-geom normal, shading and the RGB / depth / segmentation outputs (less what XLA fuses across
stages: at tiny batches, where each separate jit's overhead dominates, the remainder can come out
negative).

Records ``sim.mjx_physics_profile_<batch>`` in ``benchmarks/results/latest.json``: microseconds per
world per physics step for each stage, the whole step, and the solver variants; and
``sim.render_profile_<resolution>px_<batch>``: microseconds per frame for each renderer stage.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.abspath(os.path.join(os.path.dirname(__file__), "..")))

from benchmarks import common  # noqa: E402
from sword_jax import cli  # noqa: E402

# mjx.step for this scene's implicitfast integrator, in its order (mujoco/mjx/_src/forward.py).
STAGES = ("kinematics", "com_pos", "camlight", "tendon", "crb", "tendon_armature", "factor_m", "collision",
          "make_constraint", "transmission", "sensor_pos", "fwd_velocity", "sensor_vel", "fwd_actuation",
          "fwd_acceleration", "solve", "sensor_acc", "implicit")


def _timed(fn, arg, repeats: int) -> tuple[float, object]:
    import jax

    out = jax.block_until_ready(fn(arg))  # compile
    start = time.perf_counter()
    for _ in range(repeats):
        out = fn(arg)
    jax.block_until_ready(out)
    return (time.perf_counter() - start) / repeats, out


def profile(batch: int, *, warmup: int, repeats: int, solver_variants: tuple[tuple[int, int], ...],
            resolution: int = 128) -> dict:
    """Microseconds per world per physics step: per stage, the whole step, and ``(iterations,
    ls_iterations)`` solver variants; plus the scene's contact and constraint counts."""
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    import sim
    from sim.env import mjx_step

    env = sim.load("libero_spatial", backend="mjx")
    keys = jax.random.split(jax.random.key(0), batch)
    state = jax.jit(jax.vmap(env.reset))(keys)
    step = jax.jit(jax.vmap(env.step))
    actions = jax.random.uniform(jax.random.key(1), (batch, 7), jnp.float32, -0.3, 0.3)
    for _ in range(warmup):
        state = step(state, actions)
    data = jax.block_until_ready(state.data)
    model = env.mjx_model
    per = 1e6 / batch
    stages, d = {}, data
    for name in STAGES:
        fn = getattr(mjx, name)
        seconds, d = _timed(jax.jit(jax.vmap(lambda x, fn=fn: fn(model, x))), d, repeats)
        stages[name] = seconds * per
    whole, _ = _timed(jax.jit(jax.vmap(lambda x: mjx_step(model, x))), data, repeats)
    plain, _ = _timed(jax.jit(jax.vmap(lambda x: mjx.step(model, x))), data, repeats)
    variants = {}
    for iterations, ls_iterations in solver_variants:
        m = model.replace(opt=model.opt.replace(iterations=iterations, ls_iterations=ls_iterations))
        seconds, _ = _timed(jax.jit(jax.vmap(lambda x, m=m: mjx_step(m, x))), data, repeats)
        variants[f"iterations {iterations}, ls_iterations {ls_iterations}"] = seconds * per
    return {"render_us": render_profile(data, env.mj_model, resolution=resolution, repeats=repeats),
            "stages_us": stages, "stage_sum_us": sum(stages.values()), "step_us": whole * per, "mjx_step_us": plain * per,
            "solver_variants_step_us": variants, "substeps": env.substeps,
            "solver": {"iterations": int(model.opt.iterations), "ls_iterations": int(model.opt.ls_iterations)},
            "ncon": int(data._impl.contact.dist.shape[-1]) if hasattr(data, "_impl") else None,
            "nefc": int(data._impl.efc_J.shape[-2]) if hasattr(data, "_impl") else None}


def render_profile(data, mj_model, *, resolution: int, repeats: int) -> dict:
    """Microseconds per frame of the renderer's stages on a batch of ``mjx.Data`` (agentview)."""
    import jax
    import mujoco
    import numpy as np

    from sim import render

    scene = render.build_scene(mj_model)
    cam_id, fovy = scene.cameras["agentview"]
    batch = data.qpos.shape[0]
    per = 1e6 / batch
    geom_xpos, geom_xmat = data.geom_xpos, data.geom_xmat
    cam_pos, cam_mat = data.cam_xpos[:, cam_id], data.cam_xmat[:, cam_id]
    poses = jax.jit(jax.vmap(lambda p, m, cp, cm: render._poses(scene, p, m, cp, cm)))
    seconds, (pos, mat, origin, frame) = _timed(lambda a: poses(*a), (geom_xpos, geom_xmat, cam_pos, cam_mat), repeats)
    out = {"poses": seconds * per}
    dirs = jax.numpy.asarray(render._camera_dirs(fovy, resolution, resolution))  # camera frame, as render() uses them
    moving = ~np.asarray(scene.static, bool) if scene.static is not None else np.ones(len(scene.geom_ids), bool)
    for gtype in render._HIT:
        which = moving & (scene.geom_type == gtype)
        if not which.any():
            continue
        hits = jax.jit(jax.vmap(lambda p, m, o, f, which=which: render._nearest_ranked(
            scene, p, m, o[None, :], dirs, which=which, dir_frame=f)))
        seconds, _ = _timed(lambda a, hits=hits: hits(*a), (pos, mat, origin, frame), repeats)
        name = mujoco.mjtGeom(gtype).name.removeprefix("mjGEOM_").lower()
        out[f"hit {name} x{int(which.sum())}"] = seconds * per
    whole = jax.jit(jax.vmap(render.make_renderer(scene, "agentview", height=resolution, width=resolution,
                                                  model=mj_model)))
    seconds, _ = _timed(whole, data, repeats)
    out["whole frame"] = seconds * per
    out["rest (normal, shading, outputs)"] = out["whole frame"] - sum(v for k, v in out.items() if k != "whole frame")
    return out


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--warmup", type=int, default=5, help="control steps before timing")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--resolution", type=int, default=128, help="renderer profile image size")
    parser.add_argument("--tiny", action="store_true", help="CPU check: batch 2, 1 repeat, no results file")
    args = parser.parse_args(argv)
    if args.tiny:
        args.batch, args.warmup, args.repeats = 2, 1, 1
    if args.batch < 1 or args.repeats < 1 or args.warmup < 0:
        raise SystemExit("--batch and --repeats must be >= 1, --warmup >= 0")
    if args.tiny:
        args.resolution = 32
    out = profile(args.batch, warmup=args.warmup, repeats=args.repeats, resolution=args.resolution,
                  solver_variants=((6, 8), (4, 4), (2, 4)) if not args.tiny else ((2, 4),))
    rows = [{"stage": k, "us_per_world_step": v, "share": v / out["stage_sum_us"]} for k, v in out["stages_us"].items()]
    rows.append({"stage": "sum of stages", "us_per_world_step": out["stage_sum_us"], "share": 1.0})
    rows.append({"stage": "sim.env.mjx_step (one jit)", "us_per_world_step": out["step_us"], "share": out["step_us"] / out["stage_sum_us"]})
    rows.append({"stage": "mjx.step (MJX's own implicit; one jit)", "us_per_world_step": out["mjx_step_us"],
                 "share": out["mjx_step_us"] / out["stage_sum_us"]})
    for name, value in out["solver_variants_step_us"].items():
        rows.append({"stage": f"sim.env.mjx_step, {name}", "us_per_world_step": value, "share": value / out["stage_sum_us"]})
    common.print_table(rows, ["stage", "us_per_world_step", "share"])
    frame = out["render_us"]["whole frame"]
    common.print_table([{"renderer stage": k, "us_per_frame": v, "share": v / frame} for k, v in out["render_us"].items()],
                       ["renderer stage", "us_per_frame", "share"])
    print(f"substeps per env-step {out['substeps']}; contacts {out['ncon']}, constraint rows {out['nefc']}; "
          f"physics-only env-steps/s implied by the step: {1e6 / (out['step_us'] * out['substeps']):.0f}", flush=True)
    if not args.tiny:
        key = f"sim.mjx_physics_profile_{args.batch}"
        render_key = f"sim.render_profile_{args.resolution}px_{args.batch}"
        print("wrote", common.merge_results({
            key: common.record(key, out["step_us"], None, batch=args.batch, **{
                k: v for k, v in out.items() if k not in ("step_us", "render_us")}),
            render_key: common.record(render_key, frame, None, batch=args.batch, resolution=args.resolution,
                                      camera="agentview", stages_us=out["render_us"])}))


if __name__ == "__main__":
    cli.run(main)
