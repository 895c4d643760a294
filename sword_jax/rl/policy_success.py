"""Ground-truth evaluation of the policy in the MuJoCo LIBERO-Spatial environments, and the curve.

Success per task over the tasks' fixed evaluation initial states (50 per task in the paper and
LIBERO; demonstrations come from other initial states), on MuJoCo's C engine. The caller passes
the episodes and the environments' factory (``sim.lockstep.lockstep_evaluation`` builds both;
the library does not import ``sim``). All episodes run in lockstep (optionally over worker
processes) so the policy runs as one batched, jitted call per decision; the policy acts greedily
(argmax bins) and re-plans every ``rl.env.execute_steps`` actions (or ensembles,
``rl.env.action_ensemble``). Results carry a 95% Wilson interval. :class:`SuccessCurve` appends one point per evaluation to
``success_curve.json`` and redraws ``success_curve.png``.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from flax import nnx

from sword_jax.atomic_write import write_json_atomic
from sword_jax.rl.config import RLConfig
from sword_jax.rl.env_rollout import make_act_fns, outcomes_text, run_policy, wilson_interval


def evaluate_in_sim(
    graphdef: nnx.GraphDef,
    params: nnx.State,
    cfg: RLConfig,
    *,
    episodes: Sequence[tuple[int, Any]] | None = None,
    envs_factory: Callable[[Sequence[tuple[int, Any]]], Any] | None = None,
    max_steps: int = 220,
    act: Any = None,
    proprio: str = "true",
    reckoning: Any = None,
    trace: Any = None,
    greedy: bool = True,
    key: jax.Array | None = None,
) -> dict[str, Any]:
    """Runs the policy greedily (or sampled) from each evaluation episode's initial state.

    ``sim.lockstep.lockstep_evaluation(tasks, episodes_per_task, resolution=..., max_steps=...,
    renderer=..., workers=...)`` gives ``episodes``, ``envs_factory`` and ``max_steps`` for MuJoCo's
    LIBERO-Spatial tasks.

    Args:
      graphdef / params: the split policy.
      cfg: RL config (chunking, re-planning, proprio size, image size, bins).
      episodes: ``(task, initial qpos)`` per episode, e.g. each task's first fixed evaluation
        initial states (``sim.tasks.evaluation_episodes``).
      envs_factory: ``(episodes) -> envs`` with the lockstep protocol of
        :mod:`~sword_jax.rl.env_rollout` (e.g. ``sim.lockstep.LockstepEnvs``; its renderer "jax"
        looks like the data the pipeline makes, so the policy sees no renderer shift).
      max_steps: environment step limit (LIBERO-Spatial: 220).
      act: a :func:`~sword_jax.rl.env_rollout.make_act_fns` result to reuse (one compile per process).
      proprio / reckoning: the policy's proprio input mode (:func:`~sword_jax.rl.env_rollout.run_policy`).
      trace: a :class:`sword_jax.rl.sim_agreement.EpisodeTrace` recording the episodes (for a replay
        in the learned simulator).
      greedy: argmax actions (the policy's success). ``False`` samples at ``rl.grpo.temperature``:
        the stochastic policy GRPO trains, whose success its rollouts estimate on training states.
      key: sampling randomness when not greedy (default ``key(0)``).

    Returns:
      ``{"per_task": {task: rate}, "mean", "episodes", "successes", "ci95": [lo, hi], "seconds"}``.

    Raises:
      ValueError: ``episodes`` or ``envs_factory`` missing (the library does not import ``sim``).
    """
    if not episodes or envs_factory is None:
        missing = " and ".join(n for n, v in (("episodes", episodes), ("envs_factory", envs_factory)) if not v)
        raise ValueError(f"evaluate_in_sim needs {missing}: pass episodes=[(task, qpos), ...] and "
                         "envs_factory=(episodes) -> envs, e.g. **sim.lockstep.lockstep_evaluation(tasks, "
                         "episodes_per_task, resolution=...)")
    act = act or make_act_fns(graphdef, cfg)
    start = time.time()
    envs = envs_factory(episodes)
    try:
        rollout = run_policy(act, params, envs, cfg, key=jax.random.key(0) if key is None else key, greedy=greedy,
                             max_steps=max_steps, record=False, proprio=proprio, reckoning=reckoning, trace=trace)
    finally:
        envs.close()
    return success_summary(np.asarray(rollout.success), [t for t, _ in episodes], time.time() - start)


def success_summary(success: np.ndarray, task_of: Sequence[int], seconds: float) -> dict[str, Any]:
    """``{"per_task": {task: rate}, "mean", "episodes", "successes", "ci95": [lo, hi], "seconds", "outcomes"}`` of
    episode outcomes ``success [E]`` whose tasks are ``task_of [E]`` (tasks in first-seen order, 95% Wilson interval;
    ``outcomes``: each episode's, :func:`~sword_jax.rl.env_rollout.outcomes_text`, which pairs the gains between
    two evaluations of one run, :func:`~sword_jax.rl.env_rollout.gain_interval`)."""
    success, task_of = np.asarray(success, bool), np.asarray(task_of)
    tasks = dict.fromkeys(int(t) for t in task_of)
    wins = int(success.sum())
    return {"per_task": {str(t): float(np.mean(success[task_of == t])) for t in tasks}, "mean": float(np.mean(success)),
            "episodes": int(success.size), "successes": wins, "ci95": list(wilson_interval(wins, int(success.size))),
            "seconds": round(seconds, 1), "outcomes": outcomes_text(success)}


class SuccessCurve:
    """Success-rate curve over training steps, as ``<dir>/success_curve.json`` + ``.png`` (``writes=False``: kept
    in memory only, e.g. on the processes of a multi-process job other than process 0)."""

    def __init__(self, directory: str, label: str = "GRPO in the learned simulator", *, writes: bool = True):
        self.dir, self.label, self.writes = directory, label, writes
        self.path = os.path.join(directory, "success_curve.json")
        os.makedirs(directory, exist_ok=True)
        self.points: list[dict[str, Any]] = []
        if os.path.exists(self.path):
            with open(self.path) as f:
                self.points = json.load(f)["points"]

    def add(self, step: int, result: dict[str, Any], **extra: Any) -> None:
        self.points = [p for p in self.points if p["step"] != step] + [dict(step=int(step), **result, **extra)]
        self.points.sort(key=lambda p: p["step"])
        self._write()

    def drop_after(self, step: int) -> None:
        """Forgets the points after ``step`` (evaluations a killed run made after its last checkpoint)."""
        kept = [p for p in self.points if p["step"] <= step]
        if len(kept) != len(self.points):
            self.points = kept
            self._write()

    def _write(self) -> None:
        if not self.writes:
            return
        write_json_atomic(self.path, {"label": self.label, "points": self.points})
        self._plot()

    def _plot(self) -> None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        steps = [p["step"] for p in self.points]
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.plot(steps, [p["mean"] for p in self.points], "o-", color="k", lw=2, label="mean")
        for extra, colour in (("train_mode", "tab:red"), ("proprio_masked", "tab:blue")):
            marked = [p for p in self.points if isinstance(p.get(extra), dict)]
            if marked:
                label = f"mean, proprio {marked[0][extra].get('proprio', 'masked')}"
                ax.plot([p["step"] for p in marked], [p[extra]["mean"] for p in marked], "s--", color=colour, lw=1.5,
                        label=label)
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
