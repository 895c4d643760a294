"""Sim benchmark: env-steps/s and the scripted expert's success per task.

GPU (default): the MJX backend, ``jit(vmap(step))`` over ``--batch`` worlds, with the
agentview camera rendered at ``--resolution`` by ``sim/render.py`` inside the same jit (when
that module exists; else physics only, and the table says so), plus the vmapped expert's
success per task over ``lax.scan`` rollouts. Key: ``mjx_env_steps_per_s_128px``.

``--tiny`` (CPU): MuJoCo's C engine (the CPU backend): env-steps/s of one env, and the
expert's success on each task's fixed initial states (all 50 with ``--episodes 50``).

    python -m benchmarks.bench_sim --tiny --episodes 50
    python -m benchmarks.bench_sim --batch 4096 --resolution 128
"""

from __future__ import annotations

import argparse
import importlib.util
import time

import numpy as np

from benchmarks import common


def expert_success_cpu(episodes: int, task_ids: list[int], noise: float) -> tuple[dict[int, float], float]:
    """Success rate per task on the C backend and the env-steps/s it ran at."""
    from sim import expert
    from sim.config import SimConfig
    from sim.env import CpuEnv

    rates, steps, seconds = {}, 0, 0.0
    for task_id in task_ids:
        env = CpuEnv(SimConfig(), task_id)
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


def mjx_throughput(batch: int, resolution: int, steps: int) -> tuple[float, bool]:
    """Vmapped, jitted MJX env-steps/s with agentview rendering (if ``sim/render.py`` exists)."""
    import jax
    import jax.numpy as jnp

    import sim
    from sim import wrappers

    has_renderer = importlib.util.find_spec("sim.render") is not None
    renderer = None
    if has_renderer:
        from sim.env import camera_renderer

        renderer = camera_renderer(sim.load("libero_spatial").mj_model, resolution=resolution)
    env = wrappers.wrap_for_training(sim.load("libero_spatial", backend="mjx", renderer=renderer), 220)
    keys = jax.random.split(jax.random.key(0), batch)
    state = jax.jit(env.reset)(keys)
    step = jax.jit(env.step)
    actions = jax.random.uniform(jax.random.key(1), (batch, 7), jnp.float32, -0.3, 0.3)
    state = common.block(step(state, actions))
    start = time.perf_counter()
    for _ in range(steps):
        state = step(state, actions)
    common.block(state.obs)
    return batch * steps / (time.perf_counter() - start), has_renderer


def expert_success_mjx(episodes: int, task_ids: list[int], horizon: int) -> dict[int, float]:
    """Vmapped expert rollouts (one ``lax.scan`` in one jit) on MJX from each task's first
    ``episodes`` fixed initial states. The tasks share one model, so all run as one batch."""
    import jax
    import jax.numpy as jnp

    import sim
    from sim import expert, tasks

    env = sim.load("libero_spatial", backend="mjx")
    init_fn, act_fn = expert.jax_policy(env)
    qpos = np.concatenate([tasks.fixed_init_states(t)[:episodes] for t in task_ids])

    @jax.jit
    def rollout(qpos, key):
        state = jax.vmap(env.reset_to)(qpos)
        est = jax.vmap(init_fn)(state)

        def body(carry, key):
            state, est, solved = carry
            action, est = jax.vmap(act_fn)(state, est, jax.random.split(key, qpos.shape[0]))
            state = jax.vmap(env.step)(state, action)
            return (state, est, jnp.maximum(solved, state.done)), None

        (_, _, solved), _ = jax.lax.scan(body, (state, est, state.done), jax.random.split(key, horizon))
        return solved

    solved = np.asarray(rollout(jnp.asarray(qpos, jnp.float32), jax.random.key(0))).reshape(len(task_ids), episodes)
    rates = {task_id: float(solved[i].mean()) for i, task_id in enumerate(task_ids)}
    for task_id, rate in rates.items():
        print(f"task {task_id}: MJX expert success {rate:.3f}", flush=True)
    return rates


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true", help="CPU: C-backend figures only")
    parser.add_argument("--episodes", type=int, default=None, help="init states per task for the expert (<= 50)")
    parser.add_argument("--tasks", type=str, default="0,1,2,3,4,5,6,7,8,9")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--noise", type=float, default=0.0)
    parser.add_argument("--horizon", type=int, default=220, help="MJX expert rollout steps")
    args = parser.parse_args(argv)
    task_ids = [int(t) for t in args.tasks.split(",")]
    episodes = args.episodes if args.episodes is not None else (5 if args.tiny else 50)
    if not 1 <= episodes <= 50:
        raise SystemExit(f"--episodes must be in 1..50, got {episodes}")
    entries, rows = {}, []
    rates, cpu_sps = expert_success_cpu(episodes, task_ids, args.noise)
    rows.append({"figure": "cpu_env_steps_per_s (C engine, 1 thread, expert)", "value": cpu_sps})
    entries["cpu_env_steps_per_s"] = common.record("cpu_env_steps_per_s", cpu_sps, None, backend="cpu")
    for task_id, rate in rates.items():
        rows.append({"figure": f"expert success task {task_id} (C, {episodes} init states)", "value": rate})
    entries["sim_expert_success_min"] = common.record(
        "sim_expert_success_min", min(rates.values()), 0.9, backend="cpu", episodes_per_task=episodes,
        per_task={str(k): v for k, v in rates.items()}, noise=args.noise)
    if not args.tiny:
        sps, rendered = mjx_throughput(args.batch, args.resolution, args.steps)
        key = f"mjx_env_steps_per_s_{args.resolution}px"
        note = "physics + agentview render" if rendered else "physics only (sim/render.py missing)"
        rows.append({"figure": f"{key} (batch {args.batch}, {note})", "value": sps})
        entries[key] = common.record(key, sps, 20000, batch=args.batch, rendered=rendered)
        print(f"{key}: {sps:.0f} env-steps/s (batch {args.batch}, {note})", flush=True)
        common.merge_results(entries)  # keep the throughput even if the MJX expert run below is cut short
        mjx_rates = expert_success_mjx(episodes, task_ids, args.horizon)
        for task_id, rate in mjx_rates.items():
            rows.append({"figure": f"expert success task {task_id} (MJX)", "value": rate})
        entries["sim_expert_success_min_mjx"] = common.record(
            "sim_expert_success_min_mjx", min(mjx_rates.values()), 0.9, per_task={str(k): v for k, v in mjx_rates.items()})
    common.print_table(rows, ["figure", "value"])
    print("wrote", common.merge_results(entries))


if __name__ == "__main__":
    main()
