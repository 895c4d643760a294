"""How much of the policy's real success survives when what it sees is degraded, as a learned simulator's frames
may be: blurred, dimmer or brighter, noisy.

GRPO in the world model has the policy act on the world model's frames, and its imagined actions succeed in
reality far less often than the same policy's actions on real frames (docs/RESULTS.md, "Frames or reward").
Either the policy misreads frames that differ from the real ones, or the world model drifts from where the
actions lead. This benchmark measures the first kind of fragility without a world model. The policy runs on
MJX from the tasks' fixed evaluation states, and each episode's observed frames go through one view
(:data:`VIEWS`, :func:`degrade`) before the policy reads them. The physics and the success are untouched.

The mode is the one GRPO in the world model trains: sampled at ``rl.grpo.temperature``, the policy's "missing
proprio" input, ``rl.imagined.execute_steps`` actions a decision, here from rest to the episode limit. The
config's defaults are T 1.0 and whole chunks; the GRPO recipe's runs pass the overrides below. Every view's
episodes run in one compiled rollout: a view's parameters travel with its start states (:class:`ViewedEnv`)::

    python -m benchmarks.bench_policy_view --config sword:small --policy runs/p/policy_d50.npz \\
        --episodes-per-task 50 --out runs/view --rl.grpo.temperature=0.5 --rl.imagined.execute_steps=4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax import cli

# view: (Gaussian blur sigma in pixels of the environment's frames, brightness gain, noise std in 0-255 levels)
VIEWS: dict[str, tuple[float, float, float]] = {
    "real": (0.0, 1.0, 0.0), "blur_1px": (1.0, 1.0, 0.0), "blur_2px": (2.0, 1.0, 0.0),
    "dim_20pct": (0.0, 0.8, 0.0), "bright_20pct": (0.0, 1.2, 0.0), "noise_8": (0.0, 1.0, 8.0)}
VIEW_COLUMNS = 3
TAPS = 13  # the blur kernel's width: +-6 pixels, 3 sigma of the widest view


def blur_weights(sigma: jax.Array) -> jax.Array:
    """``[n, TAPS]`` normalised Gaussian taps per row; sigma 0 is the identity (one tap)."""
    offsets = jnp.arange(TAPS, dtype=jnp.float32) - TAPS // 2
    safe = jnp.maximum(sigma[:, None], 1e-3)
    identity = (offsets[None] == 0).astype(jnp.float32)
    weights = jnp.where(sigma[:, None] > 0, jnp.exp(-0.5 * (offsets[None] / safe) ** 2), identity)
    return weights / jnp.sum(weights, axis=1, keepdims=True)


def degrade(frames: jax.Array, view: jax.Array, key: jax.Array) -> jax.Array:
    """``frames [n, H, W, 3]`` uint8 seen through each row's ``view [n, 3]`` (:data:`VIEWS`' columns): a separable
    Gaussian blur (edges repeated), the brightness gain, Gaussian noise; rounded and clipped back to uint8."""
    x = frames.astype(jnp.float32)
    n, h, w = x.shape[:3]
    taps = blur_weights(view[:, 0])[:, :, None, None, None]  # (n, TAPS, 1, 1, 1)
    pad = TAPS // 2
    rows = jnp.pad(x, ((0, 0), (pad, pad), (0, 0), (0, 0)), mode="edge")
    x = sum(taps[:, k] * rows[:, k:k + h] for k in range(TAPS))
    cols = jnp.pad(x, ((0, 0), (0, 0), (pad, pad), (0, 0)), mode="edge")
    x = sum(taps[:, k] * cols[:, :, k:k + w] for k in range(TAPS))
    x = x * view[:, 1, None, None, None] + view[:, 2, None, None, None] * jax.random.normal(key, x.shape)
    return jnp.clip(jnp.round(x), 0, 255).astype(jnp.uint8)


class ViewedEnv:
    """A pure JAX environment (``reset(starts) -> (state, obs)``, ``step(state, actions) -> (state, obs,
    success)``) whose observed frames each episode sees through its own view: ``reset`` takes the inner
    environment's starts with the view's :data:`VIEW_COLUMNS` parameters appended as the last columns."""

    def __init__(self, env: Any, *, seed: int = 0):
        self.env, self.key = env, jax.random.key(seed)

    def reset(self, starts: jax.Array) -> tuple[Any, dict[str, jax.Array]]:
        if starts.ndim != 2 or starts.shape[1] <= VIEW_COLUMNS:
            raise ValueError(f"ViewedEnv.reset: starts must be [n, k + {VIEW_COLUMNS}] (the environment's starts, "
                             f"then the view), got {starts.shape}")
        view = starts[:, -VIEW_COLUMNS:].astype(jnp.float32)
        state, obs = self.env.reset(starts[:, :-VIEW_COLUMNS])
        count = jnp.zeros((), jnp.int32)
        return (state, view, count), self._seen(obs, view, count)

    def step(self, state: Any, actions: jax.Array) -> tuple[Any, dict[str, jax.Array], jax.Array]:
        inner, view, count = state
        inner, obs, success = self.env.step(inner, actions)
        count = count + 1
        return (inner, view, count), self._seen(obs, view, count), success

    def _seen(self, obs: dict[str, jax.Array], view: jax.Array, count: jax.Array) -> dict[str, jax.Array]:
        return dict(obs, frames=degrade(obs["frames"], view, jax.random.fold_in(self.key, count)))


def with_views(starts: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """Every start once per view, view after view: ``[len(names) x n, k + 3]``."""
    unknown = [v for v in names if v not in VIEWS]
    if unknown or not names:
        raise ValueError(f"views must name some of {', '.join(VIEWS)}, got {list(names)}")
    starts = np.asarray(starts, np.float32)
    return np.concatenate([np.concatenate([starts, np.tile(np.asarray(VIEWS[v], np.float32), (len(starts), 1))], 1)
                           for v in names])


def main(argv: Sequence[str] | None = None) -> dict:
    import configs

    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, rest = configs.from_argv(argv, default="sword:small")
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, help="the policy to evaluate (.npz)")
    parser.add_argument("--episodes-per-task", type=int, default=50)
    parser.add_argument("--views", default=",".join(VIEWS), help=f"comma list of {', '.join(VIEWS)}")
    parser.add_argument("--out", required=True, help="folder for view_results.json")
    args = parser.parse_args(rest)
    views = [v for v in args.views.split(",") if v]
    try:
        with_views(np.zeros((1, 1)), views)  # refuses unknown views before anything is built
    except ValueError as err:
        raise SystemExit(f"bench_policy_view: --{err}") from None
    if args.episodes_per_task < 1:
        raise SystemExit("bench_policy_view: --episodes-per-task must be >= 1")

    from sim import tasks as sim_tasks
    from sim.mjx_batch import MjxEpisodes, episode_starts
    from sword_jax.rl.jax_env_grpo import EnvGRPO
    from sword_jax.rl.params_io import load_params_npz
    from sword_jax.rl.policy import build_policy, tokenize_instructions
    from sword_jax.rl.policy_success import success_summary

    # the learned simulator's execution: sampled, its actions a decision, no ensembling (from rest, to the limit)
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=cfg.rl.imagined_actions_per_decision,
                                                             action_ensemble=False))
    graphdef, params = build_policy(rl, seed=cfg.seed)
    params = load_params_npz(args.policy, params)
    episodes = sim_tasks.evaluation_episodes(list(cfg.sim.tasks), args.episodes_per_task)
    qpos, text = episode_starts(episodes)
    tasks = [t for t, _ in episodes]
    tokens = tokenize_instructions(text, rl.policy.max_instruction_bytes)
    runner = EnvGRPO(graphdef, rl, ViewedEnv(MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution), seed=cfg.seed),
                     max_steps=cfg.sim.max_steps, starts_at=None, eval_starts=with_views(qpos, views),
                     eval_tokens=np.tile(tokens, (len(views), 1)), eval_tasks=tasks * len(views),
                     key=jax.random.key(cfg.seed))
    start = time.time()
    success, _ = runner.run_episodes(params, greedy=False, ensemble=False, proprio=False, key=jax.random.key(cfg.seed))
    seconds = time.time() - start
    n = len(episodes)
    results = {"policy": args.policy, "config": cfg.name, "argv": argv,
               "device": str(jax.devices()[0].device_kind),
               "mode": f"sampled at T {rl.grpo.temperature}, proprio missing, {rl.env.execute_steps} "
                       f"actions a decision, {cfg.sim.max_steps} actions from rest",
               "seconds_all_views_compile_included": round(seconds, 1), "views": {}}
    for i, view in enumerate(views):
        summary = success_summary(success[i * n:(i + 1) * n], tasks, 0.0)
        results["views"][view] = dict(summary, parameters=dict(zip(("blur_sigma_px", "gain", "noise_std"), VIEWS[view])))
        print(f"[view] {view:<13} success {summary['mean']:.3f} [{summary['ci95'][0]:.3f}, {summary['ci95'][1]:.3f}] "
              f"({summary['episodes']} episodes)", flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "view_results.json"), "w") as f:
        json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    cli.run(main)
