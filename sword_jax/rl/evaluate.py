"""Ground-truth evaluation of the policy in the MuJoCo LIBERO-Spatial environments, and the curve.

Success per task over the tasks' fixed initial states (50 in the paper), on MuJoCo's C engine
(``sim.gym_env.LiberoSpatialGymEnv``). All episodes advance in lockstep so the policy runs as one
batched, jitted call per action chunk; the policy acts greedily (argmax bins) and each chunk's 8
actions are executed open-loop (action chunking). :class:`SuccessCurve` appends one point per
evaluation to ``success_curve.json`` and redraws ``success_curve.png``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.rl.config import RLConfig
from sword_jax.rl.policy import greedy_chunk, resize_frames, tokenize_instructions, tokens_to_actions


def make_act_fn(graphdef: nnx.GraphDef, cfg: RLConfig):
    """Jitted ``act(params, frames uint8 [n,H,W,3], tokens [n,L], proprio [n,P]) -> actions [n,T,A]``."""

    @jax.jit
    def act(params, frames, tokens, proprio):
        logits = nnx.merge(graphdef, params)(resize_frames(frames, cfg.image_size), tokens, proprio)
        return tokens_to_actions(greedy_chunk(logits), cfg.action_bins)

    return act


def evaluate_in_sim(
    graphdef: nnx.GraphDef,
    params: nnx.State,
    cfg: RLConfig,
    *,
    tasks: Sequence[int],
    episodes_per_task: int,
    resolution: int,
    max_steps: int = 220,
    env_factory: Any = None,
    renderer: str = "jax",
) -> dict[str, Any]:
    """Runs the policy from each task's first ``episodes_per_task`` fixed initial states.

    Args:
      graphdef / params: the split policy.
      cfg: RL config (chunk length, proprio size, image size, bins).
      tasks: task ids (0-9).
      episodes_per_task: initial states per task (<= 50).
      resolution: rendered frame size of the environment.
      max_steps: environment step limit (LIBERO-Spatial: 220).
      env_factory: ``(task_id) -> gymnasium.Env`` override (default: the sim's C-backend env).
      renderer: the env's frame renderer: "jax" (default) looks like the data ``train.gen_data`` makes
        with the JAX renderer, so the policy sees no renderer shift; "gl" is MuJoCo's OpenGL renderer.

    Returns:
      ``{"per_task": {task: success rate}, "mean": float, "episodes": int}``.
    """
    if env_factory is None:
        from sim.gym_env import LiberoSpatialGymEnv

        def env_factory(task_id):
            return LiberoSpatialGymEnv(task_id=task_id, resolution=resolution, image_obs=True, max_steps=max_steps,
                                       renderer=renderer)

    act = make_act_fn(graphdef, cfg)
    envs, task_of, obs = [], [], []
    for task in tasks:
        for i in range(episodes_per_task):
            env = env_factory(task)
            o, info = env.reset(options={"init_state_id": i})
            envs.append(env)
            task_of.append(task)
            obs.append(o)
    n = len(envs)
    language = [getattr(env, "language", None) or env.unwrapped.language for env in envs]
    tokens = jnp.asarray(tokenize_instructions(language, cfg.max_instruction_bytes))
    done = np.zeros(n, bool)
    success = np.zeros(n, bool)
    step = 0
    while not done.all() and step < max_steps:
        frames = np.stack([o["agentview_rgb"] for o in obs])
        proprio = np.stack([o["proprio"][: cfg.proprio_dim] for o in obs]).astype(np.float32)
        chunk = np.asarray(act(params, jnp.asarray(frames), tokens, jnp.asarray(proprio)))
        for t in range(cfg.chunk_len):
            for k in np.flatnonzero(~done):
                o, _, terminated, truncated, _ = envs[k].step(chunk[k, t])
                obs[k] = o
                if terminated:
                    success[k] = True
                if terminated or truncated:
                    done[k] = True
            step += 1
            if done.all() or step >= max_steps:
                break
    for env in envs:
        env.close()
    per_task = {str(t): float(np.mean(success[np.asarray(task_of) == t])) for t in tasks}
    return {"per_task": per_task, "mean": float(np.mean(success)), "episodes": n}


class SuccessCurve:
    """Success-rate curve over training steps, as ``<dir>/success_curve.json`` + ``.png``."""

    def __init__(self, directory: str, label: str = "GRPO in the learned simulator"):
        self.dir, self.label = directory, label
        self.path = os.path.join(directory, "success_curve.json")
        os.makedirs(directory, exist_ok=True)
        self.points: list[dict[str, Any]] = []
        if os.path.exists(self.path):
            with open(self.path) as f:
                self.points = json.load(f)["points"]

    def add(self, step: int, result: dict[str, Any], **extra: Any) -> None:
        self.points = [p for p in self.points if p["step"] != step] + [dict(step=int(step), **result, **extra)]
        self.points.sort(key=lambda p: p["step"])
        tmp = self.path + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"label": self.label, "points": self.points}, f, indent=1)
        os.replace(tmp, self.path)
        self._plot()

    def _plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        steps = [p["step"] for p in self.points]
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.plot(steps, [p["mean"] for p in self.points], "o-", color="k", lw=2, label="mean")
        tasks = sorted({t for p in self.points for t in p["per_task"]}, key=lambda t: (not t.isdigit(), t.zfill(4)))
        for t in tasks:
            ax.plot(steps, [p["per_task"].get(t, np.nan) for p in self.points], lw=0.8, alpha=0.6, label=f"task {t}")
        ax.set_xlabel("GRPO step")
        ax.set_ylabel("success rate (MuJoCo, ground truth)")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(self.label)
        ax.legend(fontsize=6, ncol=2)
        fig.tight_layout()
        fig.savefig(os.path.join(self.dir, "success_curve.png"), dpi=120)
        plt.close(fig)
