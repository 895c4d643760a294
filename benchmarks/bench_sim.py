"""Sim benchmark: env-steps/s and the scripted expert's success per task.

GPU (default): the MJX backend, ``jit(vmap(step))`` over ``--batch`` worlds (and each of
``--batch-sweep``), with the agentview camera's RGB, depth and segmentation rendered at
``--resolution`` by ``sim/render.py`` inside the same jit; beside it, physics alone and the
renderer alone at the same batch. Then the vmapped expert's success per task over ``lax.scan``
rollouts (``--no-expert`` skips it). Key: ``mjx_env_steps_per_s_128px`` (the best batch).

``--tiny`` (CPU): MuJoCo's C engine (the CPU backend): env-steps/s of one env, and the
expert's success on each task's fixed initial states (all 50 with ``--episodes 50``).

    python -m benchmarks.bench_sim --tiny --episodes 50
    python -m benchmarks.bench_sim --batch 4096 --resolution 128
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks import common
from sword_jax import cli


def expert_success_cpu(episodes: int, task_ids: list[int], noise: float, **sim_overrides
                       ) -> tuple[dict[int, float], float]:
    """Success rate per task on the C backend and the env-steps/s it ran at (``SimConfig`` overrides)."""
    from sim import expert
    from sim.config import SimConfig
    from sim.env import CpuEnv

    rates, steps, seconds = {}, 0, 0.0
    for task_id in task_ids:
        env = CpuEnv(SimConfig(**sim_overrides), task_id)
        rng = np.random.default_rng(task_id)
        wins = 0
        for i in range(episodes):
            start = time.perf_counter()
            out = expert.rollout_cpu(env, env.init_states[i], cfg=expert.ExpertConfig(noise=noise), rng=rng)
            seconds += time.perf_counter() - start
            steps += out["steps"] + env.config.settle_steps
            wins += out["success"]
        rates[task_id] = wins / episodes
        print(f"task {task_id}: expert success {wins}/{episodes}", flush=True)
    return rates, steps / max(seconds, 1e-9)


def mjx_throughput(batch: int, resolution: int, steps: int, *, render: bool = True, render_alone: bool = True,
                   render_variants: bool = True, renderer_options: dict | None = None,
                   tile_variants: tuple[tuple[int, int], ...] = (), **sim_overrides) -> dict[str, float]:
    """Vmapped, jitted MJX env-steps/s, with the agentview camera rendered (RGB + depth + segmentation).

    Returns ``env_steps_per_s`` (physics + render in one jit when ``render``) and, to show where the
    time goes, ``physics_steps_per_s`` (the same env without a renderer) and ``render_frames_per_s``
    (the renderer alone on the batch's states), all at this batch. Beside the last, timed in turn on
    the same states: ``render_frames_per_s_every_geom``, the renderer without the static-geometry
    split (every geom tested in every frame), and their ratio ``render_static_split_speedup``; and
    ``render_frames_per_s_unroll_1`` / ``_4`` / ``_all`` with each geom type's scan testing 1 / 4 geoms a
    step / all at once (fewer passes over the rays' running minimum; the default is 4 on a GPU, 1
    elsewhere: ``sim.env.camera_renderer``). ``render_alone=False`` skips the renderer-alone
    figures, ``render_variants=False`` the variants beside them (five more compilations and
    timings per batch size). ``renderer_options``: ``camera_renderer`` keywords for the env's renderer
    (e.g. ``tile``, ``chunk``). ``tile_variants``: (tile, chunk) pairs, each timed renderer-alone as
    ``render_frames_per_s_tile{tile}_chunk{chunk}`` (tile culling, ``sim/render_cull.py``), with
    ``render_frames_per_s_dense`` (no culling) and ``env_steps_per_s_dense`` (the env-step figure without
    culling) beside them. ``sim_overrides``: ``SimConfig`` fields.
    """
    import jax
    import jax.numpy as jnp

    from brax.envs.wrappers import training

    import sim
    from sim.env import camera_renderer

    def steps_per_s(renderer) -> tuple[float, object]:
        env = training.wrap(sim.load("libero_spatial", backend="mjx", renderer=renderer, **sim_overrides),
                            episode_length=220)
        keys = jax.random.split(jax.random.PRNGKey(0), batch)  # brax's wrappers take raw keys
        state = jax.jit(env.reset)(keys)
        step = jax.jit(env.step)
        actions = jax.random.uniform(jax.random.key(1), (batch, 7), jnp.float32, -0.3, 0.3)
        state = common.block(step(state, actions))
        start = time.perf_counter()
        for _ in range(steps):
            state = step(state, actions)
        common.block(state.obs)
        return batch * steps / (time.perf_counter() - start), state

    out = {}
    renderer = None
    if render:
        mj_model = sim.load("libero_spatial").mj_model

        def renderer_with(**options):
            return camera_renderer(mj_model, resolution=resolution, depth_and_seg=True,
                                   **{**(renderer_options or {}), **options})

        renderer = renderer_with()
        out["env_steps_per_s"], _ = steps_per_s(renderer)
        if tile_variants:  # the env-step figure without culling, side by side
            out["env_steps_per_s_dense"], _ = steps_per_s(renderer_with(tile=None))
    out["physics_steps_per_s"], state = steps_per_s(None)
    if render and render_alone:
        def frames_per_s(draw_one) -> float:
            draw = jax.jit(jax.vmap(draw_one))
            frames = common.block(draw(state.data))
            for key in ("agentview_rgb", "agentview_depth", "agentview_seg"):
                if key not in frames:
                    raise RuntimeError(f"renderer output lacks {key}")
            start = time.perf_counter()
            for _ in range(steps):
                frames = draw(state.data)
            common.block(frames)
            return batch * steps / (time.perf_counter() - start)

        out["render_frames_per_s"] = frames_per_s(renderer)
        if tile_variants:
            out["render_frames_per_s_dense"] = frames_per_s(renderer_with(tile=None))
        for tile, chunk in tile_variants:
            out[f"render_frames_per_s_tile{tile}_chunk{chunk}"] = frames_per_s(renderer_with(tile=tile, chunk=chunk))
        if not render_variants:
            return out
        out["render_frames_per_s_every_geom"] = frames_per_s(renderer_with(static_split=False))
        out["render_static_split_speedup"] = out["render_frames_per_s"] / out["render_frames_per_s_every_geom"]
        for name, unroll in (("1", 1), ("4", 4), ("all", True)):
            out[f"render_frames_per_s_unroll_{name}"] = frames_per_s(renderer_with(unroll=unroll))
    elif not render:
        out["env_steps_per_s"] = out["physics_steps_per_s"]
    return out


def batch_layout(batch: int, resolution: int, steps: int) -> dict[str, float]:
    """Env-steps/s of the raw MJX env step (no episode wrappers) vmapped with the batch axis first (as
    brax's ``VmapWrapper``) and last (``in_axes=-1, out_axes=-1``: every state leaf stored batch-
    innermost between steps), physics alone and with the agentview camera rendered (RGB + depth + seg).
    XLA lays out each program's intermediates itself; this measures whether the state's layout between
    steps pays."""
    import jax
    import jax.numpy as jnp

    import sim
    from sim.env import camera_renderer

    out = {}
    for name, renderer in (("physics", None), ("rendered", "camera")):
        if renderer is not None:
            renderer = camera_renderer(sim.load("libero_spatial").mj_model, resolution=resolution, depth_and_seg=True)
        env = sim.load("libero_spatial", backend="mjx", renderer=renderer)
        keys = jax.random.split(jax.random.key(0), batch)
        first = jax.jit(jax.vmap(env.reset))(keys)
        actions = jax.random.uniform(jax.random.key(1), (batch, 7), jnp.float32, -0.3, 0.3)
        for axis in (0, -1):
            state = first if axis == 0 else jax.tree.map(lambda x: jnp.moveaxis(x, 0, -1), first)
            act = actions if axis == 0 else actions.T
            step = jax.jit(jax.vmap(env.step, in_axes=axis, out_axes=axis))
            state = common.block(step(state, act))
            start = time.perf_counter()
            for _ in range(steps):
                state = step(state, act)
            common.block(state.obs)
            out[f"{name}_steps_per_s_batch_{'first' if axis == 0 else 'last'}"] = batch * steps / (
                time.perf_counter() - start)
        out[f"{name}_batch_last_vs_first"] = out[f"{name}_steps_per_s_batch_last"] / out[f"{name}_steps_per_s_batch_first"]
        print(f"batch layout, {name}: " + ", ".join(f"{k} {v:.4g}" for k, v in out.items() if k.startswith(name)),
              flush=True)
    return out


def expert_success_mjx(episodes: int, task_ids: list[int], horizon: int, **sim_overrides) -> dict[int, float]:
    """Vmapped expert rollouts (one ``lax.scan`` in one jit) on MJX from each task's first
    ``episodes`` fixed initial states. The tasks share one model, so all run as one batch."""
    import jax
    import jax.numpy as jnp

    import sim
    from sim import expert, tasks

    env = sim.load("libero_spatial", backend="mjx", **sim_overrides)
    qpos = np.concatenate([tasks.fixed_init_states(t)[:episodes] for t in task_ids])
    rollout = jax.jit(lambda qpos, key: expert.rollout_mjx(env, qpos, key, horizon)[0])
    solved = np.asarray(rollout(jnp.asarray(qpos, jnp.float32), jax.random.key(0))).reshape(len(task_ids), episodes)
    rates = {task_id: float(solved[i].mean()) for i, task_id in enumerate(task_ids)}
    for task_id, rate in rates.items():
        print(f"task {task_id}: MJX expert success {rate:.3f}", flush=True)
    return rates


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true", help="CPU: C-backend figures only")
    parser.add_argument("--episodes", type=int, default=None, help="init states per task for the expert (<= 50)")
    parser.add_argument("--tasks", type=str, default="0,1,2,3,4,5,6,7,8,9")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--no-expert", action="store_true", help="skip the MJX expert rollouts (throughput only)")
    parser.add_argument("--no-render-variants", action="store_true",
                        help="time the renderer alone in its default form only (no static-split / unroll variants)")
    parser.add_argument("--tile", default="default",
                        help="the env renderer's tile culling: a tile side in pixels, 'none' for every geom in every "
                             "frame, or 'default' (sim.env.camera_renderer's)")
    parser.add_argument("--chunk", type=int, default=None, help="tiles per step of the culled loop (with --tile)")
    parser.add_argument("--tile-variants", default="",
                        help="renderer-alone timings of tile culling, TILE:CHUNK,... (e.g. 8:16,16:16), beside no culling")
    parser.add_argument("--batch-layout", action="store_true",
                        help="also time the raw env step vmapped batch-first vs batch-last at --batch")
    parser.add_argument("--batch-sweep", default="", help="more batch sizes for the MJX throughput, e.g. 4096,8192")
    parser.add_argument("--noise", type=float, default=0.0)
    parser.add_argument("--horizon", type=int, default=220, help="MJX expert rollout steps")
    parser.add_argument("--solver-variants", default="",
                        help="constraint-solver settings to compare with the default, ITER,LS;ITER,LS (e.g. 4,4): "
                             "MJX env-steps/s at --batch and the expert's success on both engines for each")
    args = parser.parse_args(argv)
    task_ids = [int(t) for t in args.tasks.split(",")]
    episodes = args.episodes if args.episodes is not None else (5 if args.tiny else 50)
    if not 1 <= episodes <= 50:
        raise SystemExit(f"--episodes must be in 1..50, got {episodes}")
    renderer_options = {}
    if args.tile != "default":
        renderer_options["tile"] = None if args.tile == "none" else int(args.tile)
    if args.chunk is not None:
        renderer_options["chunk"] = args.chunk
    tile_variants = tuple(tuple(int(v) for v in pair.split(":")) for pair in args.tile_variants.split(",") if pair)
    if any(len(pair) != 2 or min(pair) <= 0 for pair in tile_variants):
        raise SystemExit(f"--tile-variants wants positive TILE:CHUNK pairs, got {args.tile_variants!r}")
    entries, rows = {}, []
    rates, cpu_sps = expert_success_cpu(episodes, task_ids, args.noise)
    rows.append({"figure": "cpu_env_steps_per_s (C engine, 1 thread, expert)", "value": cpu_sps})
    for task_id, rate in rates.items():
        rows.append({"figure": f"expert success task {task_id} (C, {episodes} init states)", "value": rate})
    # The C-engine expert's records stand for all 50 fixed states of all 10 tasks; a throughput run with a
    # few episodes prints its figures but does not replace them.
    if episodes == 50 and sorted(task_ids) == list(range(10)):
        entries["cpu_env_steps_per_s"] = common.record("cpu_env_steps_per_s", cpu_sps, None, backend="cpu")
        entries["sim_expert_success_min"] = common.record(
            "sim_expert_success_min", min(rates.values()), 0.9, backend="cpu", episodes_per_task=episodes,
            per_task={str(k): v for k, v in rates.items()}, noise=args.noise)
    else:
        print(f"C-engine expert: {episodes} episodes of tasks {task_ids} (not all 50 states of all 10 tasks): "
              "printed, not recorded", flush=True)
    if not args.tiny:
        key = f"mjx_env_steps_per_s_{args.resolution}px"
        sweep = []
        for batch in sorted({args.batch, *(int(b) for b in args.batch_sweep.split(",") if b)}):
            try:
                figures = mjx_throughput(batch, args.resolution, args.steps,
                                         render_variants=not args.no_render_variants,
                                         renderer_options=renderer_options, tile_variants=tile_variants)
            except Exception as err:  # noqa: BLE001 - out of memory at a large batch: report and go on
                print(f"batch {batch}: failed ({type(err).__name__}: {str(err)[:160]})", flush=True)
                continue
            sweep.append({"batch": batch, **figures})
            for name, value in figures.items():
                rows.append({"figure": f"{name} (batch {batch}, {args.resolution}px RGB + depth + seg)", "value": value})
            print(f"batch {batch}: " + ", ".join(f"{k} {v:.4g}" for k, v in figures.items()), flush=True)
        if not sweep:
            raise SystemExit("bench_sim: every MJX batch size failed")
        best = max(sweep, key=lambda r: r["env_steps_per_s"])
        entries[key] = common.record(key, best["env_steps_per_s"], 20000, batch=best["batch"], rendered=True,
                                     outputs="agentview RGB + depth + segmentation", sweep=sweep,
                                     renderer_options=renderer_options or "default")
        at_batch = next((r for r in sweep if r["batch"] == args.batch and "render_frames_per_s_dense" in r), None)
        if at_batch is not None:  # culled vs every geom, side by side in this run
            cull_key = f"sim.render_cull_{args.resolution}px"
            entries[cull_key] = (
                common.record(cull_key, at_batch["render_frames_per_s"] / at_batch["render_frames_per_s_dense"],
                              None, batch=args.batch, renderer_options=renderer_options or "default",
                              env_steps_per_s=at_batch["env_steps_per_s"],
                              env_steps_per_s_dense=at_batch["env_steps_per_s_dense"],
                              env_step_speedup=at_batch["env_steps_per_s"] / at_batch["env_steps_per_s_dense"],
                              **{k: v for k, v in at_batch.items() if k.startswith("render_frames_per_s")}))
        common.merge_results(entries)  # keep the throughput even if the MJX expert run below is cut short
    if args.batch_layout and not args.tiny:
        layout = batch_layout(args.batch, args.resolution, args.steps)
        for name, value in layout.items():
            rows.append({"figure": f"{name} (batch {args.batch})", "value": value})
        entries["sim.mjx_batch_layout"] = common.record("sim.mjx_batch_layout", layout["rendered_batch_last_vs_first"],
                                                        None, batch=args.batch, **layout)
        common.merge_results(entries)
    if not args.tiny and not args.no_expert:
        mjx_rates = expert_success_mjx(episodes, task_ids, args.horizon)
        for task_id, rate in mjx_rates.items():
            rows.append({"figure": f"expert success task {task_id} (MJX)", "value": rate})
        entries["sim_expert_success_min_mjx"] = common.record(
            "sim_expert_success_min_mjx", min(mjx_rates.values()), 0.9, per_task={str(k): v for k, v in mjx_rates.items()})
    if args.solver_variants and not args.tiny:
        entries["sim_solver_variants"] = solver_variants(args, episodes, task_ids, sweep, rows)
    common.print_table(rows, ["figure", "value"])
    print("wrote", common.merge_results(entries))


def solver_variants(args, episodes: int, task_ids: list[int], sweep: list[dict], rows: list[dict]) -> dict:
    """The solver lever, side by side with the default run above: per ``ITER,LS`` setting, MJX
    env-steps/s (with the renderer) and physics-only at ``--batch``, and the scripted expert's lowest
    per-task success on the C engine and (unless ``--no-expert``) on MJX, over the same initial states."""
    from sim.config import SimConfig

    default = SimConfig()
    base = next((r for r in sweep if r["batch"] == args.batch), None)
    # MJX runs at sim.mjx_solver_iterations/mjx_ls_iterations, the C engine at sim.solver_iterations/ls_iterations.
    variants = [{"solver_iterations": default.mjx_solver_iterations, "ls_iterations": default.mjx_ls_iterations,
                 "env_steps_per_s": base and base["env_steps_per_s"],
                 "physics_steps_per_s": base and base["physics_steps_per_s"]}]
    for spec in args.solver_variants.split(";"):
        try:
            iterations, ls_iterations = (int(x) for x in spec.split(","))
        except ValueError:
            raise SystemExit(f"--solver-variants: expected ITER,LS;ITER,LS, got {spec!r}") from None
        cpu_overrides = {"solver_iterations": iterations, "ls_iterations": ls_iterations}
        mjx_overrides = {"mjx_solver_iterations": iterations, "mjx_ls_iterations": ls_iterations}
        SimConfig(**cpu_overrides, **mjx_overrides).validate()
        row = {**cpu_overrides, **mjx_throughput(args.batch, args.resolution, args.steps, render_alone=False,
                                                 **mjx_overrides)}
        cpu_rates, _ = expert_success_cpu(episodes, task_ids, args.noise, **cpu_overrides)
        row["expert_success_min_cpu"] = min(cpu_rates.values())
        if not args.no_expert:
            row["expert_success_min_mjx"] = min(expert_success_mjx(episodes, task_ids, args.horizon,
                                                                   **mjx_overrides).values())
        variants.append(row)
        print(f"solver {iterations},{ls_iterations}: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()), flush=True)
        for name, value in row.items():
            rows.append({"figure": f"solver {iterations},{ls_iterations}: {name} (batch {args.batch})", "value": value})
    best = max(variants[1:], key=lambda r: r["env_steps_per_s"])
    return common.record("sim_solver_variants", best["env_steps_per_s"], 20000, batch=args.batch,
                         resolution=args.resolution, episodes_per_task=episodes, variants=variants,
                         note="first row: the default MJX settings, measured above in the same run; each variant sets both engines")


if __name__ == "__main__":
    cli.run(main)
