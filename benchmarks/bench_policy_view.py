"""How much of the policy's real success survives when what it sees is degraded, as a learned simulator's frames
may be: blurred, dimmer or brighter, noisy, or round-tripped through the causal video VAE that decodes the world
model's frames.

GRPO in the world model has the policy act on the world model's frames, and its imagined actions succeed in
reality far less often than the same policy's actions on real frames (docs/RESULTS.md, "Frames or reward").
Either the policy misreads frames that differ from the real ones, or the world model drifts from where the
actions lead. This benchmark measures the first kind of fragility without a world model. The policy runs on
MJX from the tasks' fixed evaluation states, and each episode's observed frames go through one view
(:data:`VIEWS`, :func:`degrade`) before the policy reads them. The physics and the success are untouched.

The view ``vae`` encodes each real frame with a trained VAE (``--vae``, the checkpoint ``train.grpo --vae`` takes)
and decodes it back (:func:`vae_round_trip`): the policy's success there is the most any world model decoding
through that VAE can give it, whatever its dynamics. The run also reports how far the round trip moves the start
frames (mean absolute error and mean brightness shift per colour channel, :func:`round_trip_error`). The round
trip runs on the frames the policy reads, for every episode of a rollout batch that holds a ``vae`` episode, and is
kept only where the view asks for it; views listed next to ``vae`` may share its batches and pay for it too.

The view ``lag_1`` shows the policy, at each decision, the frame of the decision before: what a world model that
does not move the scene, or shows it a decision late, costs the policy in real success.

The mode is the one GRPO in the world model trains: sampled at ``rl.grpo.temperature``, the policy's "missing
proprio" input, ``rl.imagined.execute_steps`` actions a decision, here from rest to the episode limit. The
config's defaults are T 1.0 and whole chunks; the GRPO recipe's runs pass the overrides below. Every view's
episodes run in one compiled rollout: a view's parameters travel with its start states (:class:`ViewedEnv`)::

    python -m benchmarks.bench_policy_view --config sword:small --policy runs/p/policy_d50.npz \\
        --episodes-per-task 50 --out runs/view --rl.grpo.temperature=0.5 --rl.imagined.execute_steps=4

    python -m benchmarks.bench_policy_view --config sword:small --policy runs/p/policy_d50.npz \\
        --views real,lag_1,vae --vae runs/p/vae_run/vae --episodes-per-task 50 --out runs/view_vae \\
        --rl.grpo.temperature=0.5 --rl.imagined.execute_steps=4
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, UInt8

from benchmarks import common
from sword_jax import cli

# view: (Gaussian blur sigma in pixels of the environment's frames, brightness gain, noise std in 0-255 levels,
# 1 to round-trip the frame through the VAE, 1 to show the frame of the decision before)
VIEWS: dict[str, tuple[float, float, float, float, float]] = {
    "real": (0.0, 1.0, 0.0, 0.0, 0.0), "blur_1px": (1.0, 1.0, 0.0, 0.0, 0.0), "blur_2px": (2.0, 1.0, 0.0, 0.0, 0.0),
    "dim_20pct": (0.0, 0.8, 0.0, 0.0, 0.0), "bright_20pct": (0.0, 1.2, 0.0, 0.0, 0.0),
    "noise_8": (0.0, 1.0, 8.0, 0.0, 0.0), "vae": (0.0, 1.0, 0.0, 1.0, 0.0), "lag_1": (0.0, 1.0, 0.0, 0.0, 1.0)}
VIEW_COLUMNS = 5
PARAMETER_NAMES = ("blur_sigma_px", "gain", "noise_std", "vae_round_trip", "lag_decisions")
CHANNELS = ("r", "g", "b")
RoundTrip = Callable[[UInt8[Array, "n h w 3"]], UInt8[Array, "n h w 3"]]
TAPS = 13  # the blur kernel's width: +-6 pixels, 3 sigma of the widest view


def blur_weights(sigma: jax.Array) -> jax.Array:
    """``[n, TAPS]`` normalised Gaussian taps per row; sigma 0 is the identity (one tap)."""
    offsets = jnp.arange(TAPS, dtype=jnp.float32) - TAPS // 2
    safe = jnp.maximum(sigma[:, None], 1e-3)
    identity = (offsets[None] == 0).astype(jnp.float32)
    weights = jnp.where(sigma[:, None] > 0, jnp.exp(-0.5 * (offsets[None] / safe) ** 2), identity)
    return weights / jnp.sum(weights, axis=1, keepdims=True)


def degrade(frames: jax.Array, view: jax.Array, key: jax.Array) -> jax.Array:
    """``frames [n, H, W, 3]`` uint8 seen through each row's ``view [n, VIEW_COLUMNS]`` (:data:`VIEWS`' columns): a
    separable Gaussian blur (edges repeated), the brightness gain, Gaussian noise; rounded and clipped back to uint8.
    The last two columns (the VAE round trip, the lag) are :class:`ViewedEnv`'s."""
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


def in_levels(unit_round_trip: Callable[[jax.Array], jax.Array]) -> RoundTrip:
    """A round trip of frames in [0, 1] as one of uint8 frames: the levels scaled to [0, 1], round-tripped,
    rounded back to uint8."""

    def round_trip(frames: UInt8[Array, "n h w 3"]) -> UInt8[Array, "n h w 3"]:
        out = unit_round_trip(frames.astype(jnp.float32) / jnp.float32(255.0))
        return jnp.clip(jnp.round(out * jnp.float32(255.0)), 0, 255).astype(jnp.uint8)

    return round_trip


def still_round_trip(codec: Callable[[jax.Array], jax.Array], frames_per_latent: int) -> RoundTrip:
    """:func:`sword_jax.rl.world_model_sim.still_round_trip` of uint8 frames (:func:`in_levels`): each frame held
    still for ``1 + frames_per_latent`` frames, passed through ``codec`` (video in [-1, 1] -> the same), the last
    frame kept."""
    from sword_jax.rl import world_model_sim

    return in_levels(world_model_sim.still_round_trip(codec, frames_per_latent))


def vae_round_trip(vae_graphdef: Any, vae_state: Any) -> RoundTrip:
    """:func:`sword_jax.rl.world_model_sim.vae_round_trip` of uint8 frames: encoded as a still keyframe is encoded
    for the world model, decoded (clamped); the round trip GRPO's closed-loop record measures too
    (``closed_loop_frame_error_vae_k``, there through the simulator's VAE as it decodes, in [0, 1])."""
    from sword_jax.rl import world_model_sim

    return in_levels(world_model_sim.vae_round_trip(vae_graphdef, vae_state))


def round_trip_error(real: np.ndarray, seen: np.ndarray) -> dict[str, Any]:
    """How far ``seen`` (uint8 ``[n, H, W, 3]``) is from ``real``, in 0-255 levels, per colour channel and over
    all: the mean absolute error and the mean signed shift (``seen - real``: positive is brighter)."""
    diff = np.asarray(seen, np.float64) - np.asarray(real, np.float64)

    def per_channel(values: np.ndarray) -> dict[str, float]:
        return dict(zip(CHANNELS, values.mean(axis=(0, 1, 2)).round(3).tolist()), all=round(float(values.mean()), 3))

    return {"frames": len(diff), "mean_abs_error": per_channel(np.abs(diff)), "mean_shift": per_channel(diff)}


def start_frames(env: Any, round_trip: RoundTrip, starts: np.ndarray, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """``(real, round-tripped)`` uint8 frames at ``env``'s reset from ``starts``, in slices of ``batch`` (the last
    padded by repeating starts, so one shape compiles)."""
    @jax.jit
    def reset_and_round_trip(some_starts: jax.Array) -> tuple[jax.Array, jax.Array]:
        frames = env.reset(some_starts)[1]["frames"]
        return frames, round_trip(frames)

    real, seen = [], []
    for lo in range(0, len(starts), batch):
        idx = np.arange(lo, lo + batch) % len(starts)
        frames, trip = jax.device_get(reset_and_round_trip(jnp.asarray(starts[idx])))
        keep = min(batch, len(starts) - lo)
        real.append(frames[:keep])
        seen.append(trip[:keep])
    return np.concatenate(real), np.concatenate(seen)


class ViewedEnv:
    """A pure JAX environment (``reset(starts) -> (state, obs)``, ``step(state, actions) -> (state, obs,
    success)``) whose observed frames each episode sees through its own view: ``reset`` takes the inner
    environment's starts with the view's :data:`VIEW_COLUMNS` parameters appended as the last columns.

    ``round_trip`` (e.g. :func:`vae_round_trip`) replaces the frames of the rows whose VAE column is 1. It
    runs only on the frames the policy reads (at reset and after every ``every`` actions, a decision's) and only
    for a batch that holds such a row, on the whole batch, selected per row. Without it that column is not read
    and nothing of it is compiled.

    A row whose lag column is 1 reads, at each decision, the frame it would have read at the decision before
    (at the first decision the start frame again): a simulator that shows the scene a decision late."""

    def __init__(self, env: Any, *, seed: int = 0, round_trip: RoundTrip | None = None, every: int = 1):
        if every < 1:
            raise ValueError(f"ViewedEnv: every must be >= 1 (actions a decision), got {every}")
        self.env, self.key, self.round_trip, self.every = env, jax.random.key(seed), round_trip, every

    def reset(self, starts: jax.Array) -> tuple[Any, dict[str, jax.Array]]:
        if starts.ndim != 2 or starts.shape[1] <= VIEW_COLUMNS:
            raise ValueError(f"ViewedEnv.reset: starts must be [n, k + {VIEW_COLUMNS}] (the environment's starts, "
                             f"then the view), got {starts.shape}")
        view = starts[:, -VIEW_COLUMNS:].astype(jnp.float32)
        state, obs = self.env.reset(starts[:, :-VIEW_COLUMNS])
        count = jnp.zeros((), jnp.int32)
        frames = self._seen(obs, view, count)
        return (state, view, count, frames), dict(obs, frames=frames)

    def step(self, state: Any, actions: jax.Array) -> tuple[Any, dict[str, jax.Array], jax.Array]:
        inner, view, count, held = state
        inner, obs, success = self.env.step(inner, actions)
        count = count + 1
        frames = self._seen(obs, view, count)
        read = count % self.every == 0  # a decision's end: the policy reads this frame
        lagged = read & (view[:, 4] > 0)
        shown = jnp.where(lagged[:, None, None, None], held, frames)
        held = jnp.where(read, frames, held)
        return (inner, view, count, held), dict(obs, frames=shown), success

    def _seen(self, obs: dict[str, jax.Array], view: jax.Array, count: jax.Array) -> jax.Array:
        frames = degrade(obs["frames"], view, jax.random.fold_in(self.key, count))
        if self.round_trip is not None:
            flagged = view[:, 3] > 0
            frames = jax.lax.cond(
                jnp.any(flagged) & (count % self.every == 0),
                lambda f: jnp.where(flagged[:, None, None, None], self.round_trip(f), f), lambda f: f, frames)
        return frames


def with_views(starts: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """Every start once per view, view after view: ``[len(names) x n, k + VIEW_COLUMNS]``."""
    unknown = [v for v in names if v not in VIEWS]
    if unknown or not names:
        raise ValueError(f"views must name some of {', '.join(VIEWS)}, got {list(names)}")
    starts = np.asarray(starts, np.float32)
    return np.concatenate([np.concatenate([starts, np.tile(np.asarray(VIEWS[v], np.float32), (len(starts), 1))], 1)
                           for v in names])


def policy_parser(doc: str, *, episodes_per_task: int, views: Sequence[str], results: str) -> cli.ArgumentParser:
    """The flags of a benchmark of the policy's views: ``--policy``, ``--episodes-per-task``, ``--views`` (a comma
    list of ``views``, all by default) and ``--out`` (the folder of the file ``results``)."""
    parser = cli.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, help="the policy (.npz)")
    parser.add_argument("--episodes-per-task", type=int, default=episodes_per_task)
    parser.add_argument("--views", default=",".join(views), help=f"comma list of {', '.join(views)}")
    parser.add_argument("--out", required=True, help=f"folder for {results}")
    return parser


def main(argv: Sequence[str] | None = None) -> dict:
    import configs

    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, rest = configs.from_argv(argv, default="sword:small")
    parser = policy_parser(__doc__, episodes_per_task=50, views=tuple(VIEWS), results="view_results.json")
    parser.add_argument("--vae", default="", help="VAE checkpoint directory (train_vae; a pipeline's vae_run/vae), "
                        "read by the view vae")
    args = parser.parse_args(rest)
    views = [v for v in args.views.split(",") if v]
    try:
        with_views(np.zeros((1, 1)), views)  # refuses unknown views before anything is built
    except ValueError as err:
        raise SystemExit(f"bench_policy_view: --{err}") from None
    if args.episodes_per_task < 1:
        raise SystemExit("bench_policy_view: --episodes-per-task must be >= 1")
    if "vae" in views and not args.vae:
        raise SystemExit("bench_policy_view: the view vae round-trips frames through a trained VAE; give its "
                         "checkpoint with --vae (e.g. runs/<pipeline>/vae_run/vae)")

    from sim import tasks as sim_tasks
    from sim.mjx_batch import MjxEpisodes, episode_starts
    from sword_jax.load import experiment_vae
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
    env = MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution)
    round_trip = vae_round_trip(*experiment_vae(cfg, args.vae)) if "vae" in views else None
    runner = EnvGRPO(graphdef, rl, ViewedEnv(env, seed=cfg.seed, round_trip=round_trip, every=rl.env.execute_steps),
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
        results["views"][view] = dict(summary, parameters=dict(zip(PARAMETER_NAMES, VIEWS[view])))
        print(f"[view] {view:<13} success {common.interval_text(summary)} "
              f"({summary['episodes']} episodes)", flush=True)
    if round_trip is not None:
        error = round_trip_error(*start_frames(env, round_trip, qpos, runner.batch))
        results["vae_round_trip"] = dict(error, vae=args.vae)
        print(f"[view] vae round trip of the {error['frames']} start frames, in 0-255 levels (r g b all): "
              f"|error| {' '.join(f'{v:.2f}' for v in error['mean_abs_error'].values())}, "
              f"shift {' '.join(f'{v:+.2f}' for v in error['mean_shift'].values())}", flush=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "view_results.json"), "w") as f:
        json.dump(results, f, indent=1)
    return results


if __name__ == "__main__":
    cli.run(main)
