"""Behaviour cloning (SFT) of the VLA policy on expert demonstrations: the GRPO starting point.

:func:`run_sft_policy` is what ``python -m train.train_policy`` and the pipeline's supervised-policy
stage run (:func:`given_policy` instead, with ``rl.sft.init``). Writes ``<workdir>/rl/policy_sft`` (orbax)
and, with ``eval_episodes``, the ground-truth success in the MuJoCo sim. The train state is checkpointed to ``<workdir>/rl/sft_checkpoints`` and a
rerun resumes from there.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Sequence

import numpy as np

from sim.dataset import read_dataset
from sword_jax import sharding as shd
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import load_params, save_params
from sword_jax.rl.policy import build_policy
from sword_jax.rl.policy_success import evaluate_in_sim
from sword_jax.rl.sft import train_sft


def given_policy(cfg, source: str) -> dict:
    """The ``sft_policy`` stage with ``rl.sft.init``: copies the trained policy ``source`` (a
    ``train.train_policy`` checkpoint directory or ``.npz``) into ``<cfg.workdir>/rl`` and checks that it loads
    into ``cfg.rl``'s policy. Returns the stage's summary, ``path`` the copy (later stages read it, so the run
    does not depend on ``source`` staying where it is).

    Raises:
      FileNotFoundError: ``source`` does not exist.
      ValueError: it holds another kind of checkpoint or another architecture than ``cfg.rl`` builds.
    """
    if not os.path.exists(source):
        raise FileNotFoundError(f"rl.sft.init: no such policy {source!r} (a train_policy checkpoint directory or .npz)")
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    is_npz = source.endswith(".npz")
    path = os.path.abspath(os.path.join(workdir, "policy_given.npz" if is_npz else "policy_given"))
    tmp = path[: -len(".npz")] + ".tmp.npz" if is_npz else path + ".tmp"  # load_params tells formats by suffix
    shutil.rmtree(tmp, ignore_errors=True)
    if os.path.isfile(tmp):
        os.remove(tmp)
    (shutil.copyfile if is_npz else shutil.copytree)(source, tmp)
    try:
        _, params = build_policy(cfg.rl, seed=cfg.seed)
        load_params(tmp, params, kind="policy")
    except ValueError as err:  # CheckpointError (another config) included
        (os.remove if is_npz else shutil.rmtree)(tmp)
        raise ValueError(f"rl.sft.init: {source} does not load into this config's policy: {err}") from err
    if os.path.isdir(path):
        shutil.rmtree(path)
    os.replace(tmp, path)
    result = {"given": os.path.abspath(source), "path": path, "steps": 0, "demos": 0}
    with open(os.path.join(workdir, "sft_result.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(f"sft_policy: starting from the given policy {source}", flush=True)
    return result


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
