"""Accuracy of the proprio that imagined rollouts dead-reckon from actions (rl.imagined.proprio=reckoned).

Runs the noisy expert (DART noise 0.1, fixed length, C engine) from ``--per-task`` train-split
initial states of each task, fits the per-axis gains (:func:`sword_jax.rl.proprio_reckoning.fit_gains`)
on every other episode and measures, on the rest, the error of the reckoned proprio against the
engine's after h actions (windows starting every 8 steps): position (cm), rotation (degrees),
finger (mm), for the fitted and the unfitted (gain 1) convention, and for holding the start
proprio. Writes ``benchmarks/results/policy/proprio_reckoning.json``. CPU only (C engine).

  python -m benchmarks.bench_proprio_reckoning            # 10 tasks x 3 episodes x 128 steps
"""

from __future__ import annotations

import json
import os
import time

import jax.numpy as jnp
import numpy as np

from sword_jax import cli
from sword_jax.rl.policy import axis_angle_to_matrix
from sword_jax.rl.proprio_reckoning import ReckoningConfig, fit_gains, reckon

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "policy", "proprio_reckoning.json")
HORIZONS = (4, 8, 16, 32, 64, 127)


def expert_episodes(tasks, per_task: int, steps: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``[(proprio [steps + 1, 8], executed actions [steps, 7])]`` of noisy-expert C-engine episodes."""
    from sim import config as sim_config, expert, tasks as sim_tasks
    from sim import env as sim_env

    episodes = []
    for task in tasks:
        env = sim_env.make_env(sim_config.SimConfig(backend="cpu"), task)
        for i, qpos in enumerate(sim_tasks.split_init_states(task, "train", per_task)):
            out = expert.rollout_cpu(env, qpos, cfg=expert.ExpertConfig(noise=0.1), rng=np.random.default_rng(i),
                                     record=True, stop_at_success=False, max_steps=steps)
            episodes.append((np.stack([np.asarray(s.obs["proprio"]) for s in out["states"]]), out["executed"]))
            del out  # the recorded MjData states are large
    return episodes


def _degrees_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r = np.swapaxes(np.asarray(axis_angle_to_matrix(jnp.asarray(a))), -1, -2) @ np.asarray(
        axis_angle_to_matrix(jnp.asarray(b)))
    return np.degrees(np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def errors(episodes, cfg: ReckoningConfig, horizons=HORIZONS) -> dict[int, dict[str, float]]:
    """Per horizon: mean position / rotation / finger error of the reckoned proprio, windows every 8 steps."""
    out = {}
    for h in horizons:
        starts, actions, targets = zip(*[(p[s], a[s:s + h], p[s + h]) for p, a in episodes
                                         for s in range(0, len(a) - h + 1, 8)])
        pred = np.asarray(reckon(jnp.asarray(np.stack(starts)), jnp.asarray(np.stack(actions)), cfg))[:, -1]
        true = np.stack(targets)
        pos = np.linalg.norm(pred[:, :3] - true[:, :3], axis=-1)
        out[h] = {"pos_cm_mean": 100 * float(pos.mean()), "pos_cm_p90": 100 * float(np.percentile(pos, 90)),
                  "rot_deg_mean": float(_degrees_between(pred[:, 3:6], true[:, 3:6]).mean()),
                  "finger_mm_mean": 1000 * float(np.abs(pred[:, 6] - true[:, 6]).mean()), "windows": len(true)}
    return out


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-task", type=int, default=3, help="train-split initial states per task")
    parser.add_argument("--steps", type=int, default=128, help="actions per episode")
    parser.add_argument("--out", default=OUT)
    args = parser.parse_args(argv)
    start = time.perf_counter()
    episodes = expert_episodes(range(10), args.per_task, args.steps)
    fit, held = episodes[0::2], episodes[1::2]
    gains = fit_gains(np.stack([p[:-1] for p, _ in fit]), np.stack([a for _, a in fit]))
    hold = {h: 100 * float(np.mean([np.linalg.norm(p[s + h, :3] - p[s, :3]) for p, a in held
                                     for s in range(0, len(a) - h + 1, 8)])) for h in (8, 32)}
    result = {"fitted": errors(held, gains), "unfitted": errors(held, ReckoningConfig()), "hold_start_pos_cm": hold,
              "gains": {"pos": gains.pos_gain, "rot": gains.rot_gain},
              "setup": f"{len(episodes)} noisy-expert (noise 0.1) C-engine episodes of {args.steps} steps, "
                       f"{args.per_task} train init states x 10 tasks; gains fitted on {len(fit)}, errors on the "
                       f"other {len(held)}; windows start every 8 steps"}
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    for name in ("fitted", "unfitted"):
        print(name, {h: (round(v["pos_cm_mean"], 2), round(v["rot_deg_mean"], 2)) for h, v in result[name].items()})
    print(f"gains pos {gains.pos_gain} rot {gains.rot_gain}; hold {hold}; {time.perf_counter() - start:.0f} s -> {args.out}")


if __name__ == "__main__":
    cli.run(main)
