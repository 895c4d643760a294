"""Behaviour cloning (SFT) of the VLA policy on expert demonstrations: the GRPO starting point.

:func:`run_sft_policy` is what ``python -m train.train_policy`` and the pipeline's supervised-policy
stage run. Writes ``<workdir>/rl/policy_sft`` (orbax) and, with ``eval_episodes``, the ground-truth
success in the MuJoCo sim. The train state is checkpointed to ``<workdir>/rl/sft_checkpoints`` and a
rerun resumes from there.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence

import numpy as np

from sim.dataset import read_dataset
from sword_jax import sharding as shd
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import save_params
from sword_jax.rl.policy import build_policy
from sword_jax.rl.policy_success import evaluate_in_sim
from sword_jax.rl.sft import train_sft


def run_sft_policy(cfg, demos: Sequence[str], *, eval_episodes: int = 0, eval_workers: int = 0,
                   renderer: str = "jax", holdout: float = 0.1) -> dict:
    """Behaviour-clones (or resumes) the policy on ``demos`` in ``<cfg.workdir>/rl``; with ``eval_episodes``
    per task, measures its success in the simulator. Returns the summary (also in ``sft_result.json``)."""
    demos, rl = list(demos), cfg.rl
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    episodes = rl_data.successful(rl_data.load_episodes(demos, read=read_dataset))
    episodes = rl_data.EpisodeSet(episodes.frames, episodes.actions, episodes.proprio[..., : rl.proprio_dim],
                                  episodes.lengths, episodes.success, episodes.instructions)
    train_eps, held_out = rl_data.split_holdout(episodes, holdout, rng)
    train_eps = rl_data.per_task_subset(train_eps, rl.sft.episodes_per_task, rng)
    print(f"train_policy: {train_eps.num_episodes} demonstrations ({0 if held_out is None else held_out.num_episodes}"
          f" held out), {len(set(train_eps.instructions))} instructions")
    graphdef, params = build_policy(rl, seed=cfg.seed)
    start = time.time()
    params, history = train_sft(graphdef, params, rl, train_eps, held_out, seed=cfg.seed,
                                log=lambda m: print(m, flush=True),
                                checkpoint_dir=os.path.join(workdir, "sft_checkpoints"), mesh=shd.make_mesh(cfg.mesh),
                                rules=cfg.mesh.rules)
    path = os.path.join(workdir, "policy_sft")
    save_params(path, params, rl, kind="policy", step=rl.sft.steps)
    result = {"steps": rl.sft.steps, "demos": train_eps.num_episodes, "path": path,
              "final_loss": history[-1]["loss"], "seconds": round(time.time() - start, 1),
              "heldout_loss": history[-1].get("heldout_loss"), "heldout_token_accuracy":
              history[-1].get("heldout_token_accuracy")}
    if eval_episodes:
        from sim.lockstep import lockstep_evaluation

        result["eval"] = evaluate_in_sim(graphdef, params, rl, **lockstep_evaluation(
            cfg.sim.tasks, eval_episodes, resolution=cfg.sim.resolution, max_steps=cfg.sim.max_steps,
            renderer=renderer, workers=eval_workers))
        print("ground-truth success:", json.dumps(result["eval"]))
    with open(os.path.join(workdir, "sft_result.json"), "w") as f:
        json.dump(dict(result, history=history), f, indent=1)
    return result
