"""GRPO post-training of the VLA policy inside the learned simulator (or the MuJoCo environments, or the
analytic toy simulator), evaluated in MuJoCo.

:func:`run_grpo` is what ``python -m train.grpo`` and the pipeline's GRPO stages run: it builds the
policy, loads its checkpoint and dispatches to :mod:`sim.grpo_env` (``simulator="env"``),
:mod:`sim.grpo_refresh` (``rl.refresh.every``) or :func:`sword_jax.pipeline.grpo.run_in_learned_simulator`.
In a job of several processes (``--mesh.distributed=true``) the toy simulator and the world model (without
replays) run data parallel; what has not run over processes yet is refused (:func:`refuse_several_processes`).
"""

from __future__ import annotations

import dataclasses
import os

import jax

from sim import grpo_env
from sim.dataset import read_dataset
from sim.lockstep import lockstep_evaluation
from sword_jax.pipeline.grpo import GRPOInputs, run_in_learned_simulator, toy_setup, world_model_setup
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import load_params
from sword_jax.rl.policy import build_policy
from sword_jax.tracing import ENTRY_MAX_TRACES

SIMULATORS = ("world_model", "env", "toy")


def run_grpo(cfg, inputs: GRPOInputs, *, simulator: str = "world_model", env_workers: int = 0,
             renderer: str = "jax", eval_episodes: int = 0) -> dict:
    """GRPO in ``simulator`` (``world_model``, ``env`` or ``toy``), resuming from ``<cfg.workdir>/rl/grpo``.

    ``eval_episodes`` (per task) overrides ``rl.grpo.eval_episodes_per_task``; ``env_workers`` are the C-engine
    processes of the evaluations (and of the episodes with ``simulator="env"``). Returns
    ``{"curve": evaluation points, "workdir", "history": per-step metrics of the whole run}`` (the history
    is also written to ``<workdir>/train_history.jsonl``).
    """
    if simulator not in SIMULATORS:
        raise ValueError(f"train.grpo: simulator {simulator!r} is none of {SIMULATORS}")
    rl = cfg.rl
    if simulator == "toy":
        rl = dataclasses.replace(rl, proprio_dim=max(rl.proprio_dim, 2))
    elif simulator == "env":
        if rl.imagined.oversample > 1:
            raise SystemExit("train.grpo --simulator env: rl.imagined.oversample is dynamic sampling in the learned "
                             "simulator; in the ground-truth environments it is rl.grpo.max_sample_rounds (mjx backend)")
        if rl.env.starts == "keyframes" and not inputs.demos:
            raise SystemExit("train.grpo --simulator env --rl.env.starts=keyframes needs --demos (the rollouts start "
                             "from their recorded states)")
    elif not (inputs.world_model and inputs.reward and inputs.demos):
        raise SystemExit("train.grpo --simulator world_model needs --world-model, --reward and --demos (see --help)")
    if rl.value.episodes and simulator != "env":
        raise SystemExit(f"train.grpo --simulator {simulator}: rl.value (a fitted value closing short rollouts) runs in "
                         "ground-truth GRPO on MJX only (--simulator env --rl.env.backend=mjx); set "
                         "--rl.value.episodes=0")
    if jax.process_count() > 1:
        refuse_several_processes(rl, simulator)
    workdir = os.path.join(cfg.workdir, "rl", "grpo")
    os.makedirs(workdir, exist_ok=True)

    graphdef, params = build_policy(rl, seed=cfg.seed)
    if inputs.policy:  # an orbax directory (train_policy) or an .npz file (benchmarks.bench_policy)
        params, _ = load_params(inputs.policy, params, kind="policy")
    if simulator == "env":
        if rl.env.proprio == "reckoned" and not inputs.demos:
            raise SystemExit("train.grpo --simulator env --rl.env.proprio=reckoned needs --demos (the reckoning's "
                             "gains are fitted to them)")
        reckoning = keyframes = None
        if rl.env.proprio == "reckoned" or rl.env.starts == "keyframes":
            demos = rl_data.load_episodes(inputs.demos, read=read_dataset)
            reckoning = grpo_env.sim_reckoning(demos) if rl.env.proprio == "reckoned" else None
            keyframes = demos if rl.env.starts == "keyframes" else None
        if rl.env.backend == "mjx":
            return grpo_env.run_in_mjx(cfg, rl, graphdef, params, workdir,
                                       episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task,
                                       keyframes=keyframes)
        return grpo_env.run_in_env(cfg, rl, graphdef, params, workdir,
                                   episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task,
                                   workers=env_workers, renderer=renderer, reckoning=reckoning, keyframes=keyframes,
                                   max_traces=ENTRY_MAX_TRACES)
    if simulator == "toy":
        setup, env_eval = toy_setup(cfg, rl), None
    else:
        demos = rl_data.load_episodes(inputs.demos, read=read_dataset)
        reckoning = grpo_env.sim_reckoning(demos) if rl.imagined.proprio == "reckoned" else None
        setup = world_model_setup(cfg, rl, inputs, demos, reckoning=reckoning)
        if rl.refresh.every:
            from sim.grpo_refresh import run_refreshed_in_mjx
            from sword_jax import sharding as shd
            from sword_jax.load import experiment_vae, experiment_world_model

            if not inputs.latents:
                raise SystemExit("train.grpo --rl.refresh.every > 0 needs --latents (the world model's training latents)")
            mesh = shd.make_mesh(cfg.mesh)  # the VAE beside the world model
            return run_refreshed_in_mjx(cfg, rl, graphdef, params, workdir, setup,
                                        vae=experiment_vae(cfg, inputs.vae, mesh=mesh),
                                        world_model=experiment_world_model(cfg, inputs.world_model),
                                        latents=inputs.latents,
                                        episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task,
                                        max_traces=ENTRY_MAX_TRACES)
        if rl.env.backend == "mjx":  # the evaluation (and with a reward paid by execution, the reward) on MJX
            from sim.grpo_refresh import mjx_evaluation

            if rl.imagined.executes and setup.env_starts is None:
                raise SystemExit(f"train.grpo --rl.imagined.reward={rl.imagined.reward} resets MJX to the keyframes' "
                                 f"recorded states: the demonstrations {', '.join(inputs.demos)} hold no 'states'")
            env, evaluate_real = mjx_evaluation(cfg, rl, graphdef, params, workdir,
                                                episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task)
            return run_in_learned_simulator(cfg, rl, graphdef, params, workdir, setup, simulator=simulator,
                                            env_eval=None, max_traces=ENTRY_MAX_TRACES, env=env,
                                            evaluate_real=evaluate_real)
        env_eval = lockstep_evaluation(cfg.sim.tasks, eval_episodes or rl.grpo.eval_episodes_per_task,
                                       resolution=cfg.sim.resolution, max_steps=cfg.sim.max_steps, renderer=renderer,
                                       workers=env_workers)
    return run_in_learned_simulator(cfg, rl, graphdef, params, workdir, setup, simulator=simulator,
                                    env_eval=env_eval, max_traces=ENTRY_MAX_TRACES)


def refuse_several_processes(rl, simulator: str) -> None:
    """Refuses, in one line naming the setting, what a job of several processes does not run yet (it would
    otherwise duplicate work on every process or wait on a collective that never comes).

    Raises:
      SystemExit: ``--simulator env`` (C-engine and MJX rollouts), ``rl.refresh.every > 0``, or in the world
        model ``rl.imagined.eval_replay_episodes > 0``, ``rl.imagined.decoder=light`` or
        ``rl.imagined.proprio=reckoned`` (the replays of real episodes, the light decoder's placement and the
        proprio reckoning have not been run over processes).
    """
    drop = "run it in one process (drop --mesh.distributed=true)"
    if simulator == "env":
        raise SystemExit(f"train.grpo --simulator env does not run in several processes yet (its C-engine / MJX "
                         f"rollouts are not split over them): {drop}")
    if rl.refresh.every:
        raise SystemExit(f"train.grpo --rl.refresh.every={rl.refresh.every} does not run in several processes yet: "
                         f"pass --rl.refresh.every=0 or {drop}")
    if simulator == "world_model" and rl.imagined.eval_replay_episodes:
        raise SystemExit(f"train.grpo --rl.imagined.eval_replay_episodes={rl.imagined.eval_replay_episodes} does not "
                         f"run in several processes yet: pass --rl.imagined.eval_replay_episodes=0 or {drop}")
    if simulator == "world_model" and rl.imagined.decoder == "light":
        raise SystemExit(f"train.grpo --rl.imagined.decoder=light does not run in several processes yet: {drop}")
    if simulator == "world_model" and rl.imagined.proprio == "reckoned":
        raise SystemExit(f"train.grpo --rl.imagined.proprio=reckoned does not run in several processes yet: {drop}")
