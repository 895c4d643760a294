"""GRPO post-training of the VLA policy inside the learned simulator, evaluated in MuJoCo.

    # the real thing: world model + VAE + SFT policy + reward model, keyframes from demos
    python -m train.grpo --config sword:small --simulator world_model --demos demos.hdf5 \
        --world-model runs/sword-small --vae runs/sword-small/vae --policy runs/sword-small/rl/policy_sft \
        --reward runs/sword-small/rl/reward_model [--rl.grpo.steps=200 --rl.grpo.eval_every=20]
    # the ground truth: GRPO in the MuJoCo environments themselves (reward = true success)
    python -m train.grpo --config sword:small --simulator env --policy runs/sword-small/rl/policy_sft \
        [--env-workers 14] [--rl.grpo.steps=100]
    # smoke run: the analytic toy simulator (no checkpoints needed)
    python -m train.grpo --config sword:tiny --simulator toy --rl.grpo.steps=4

Each step samples ``rl.grpo.rollout_batch`` keyframe start states, G = ``rl.grpo.group_size`` imagined
trajectories each, and applies the GRPO update (one jitted, donated step). With ``--simulator env``
the start states are training-split initial states (never the 50 evaluation states), the
trajectories run in MuJoCo's C engine (``sim.lockstep``), and the same ``grpo_update`` trains on
them: this validates the update independently of any world model. Every ``rl.grpo.eval_every``
steps (and at step 0) the policy is evaluated in the ground-truth MuJoCo envs (world_model mode)
or by greedy imagined rollouts (toy mode); the curve goes to ``<workdir>/success_curve.{json,png}``.
The GRPO state is checkpointed at each evaluation and the run resumes from it exactly (killed and
rerun = bit-identical, curve included; :mod:`sword_jax.rl.grpo_loop`); a work dir holding another run's
checkpoint is refused, naming the config keys that differ. A non-finite loss stops the run.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Sequence

import configs
from sim import grpo_env
from sim.dataset import read_dataset
from sim.lockstep import lockstep_evaluation
from sword_jax.pipeline.grpo import GRPOInputs, run_in_learned_simulator, toy_setup, world_model_setup
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import load_params
from sword_jax.rl.policy import build_policy
from train.distributed import ENTRY_MAX_TRACES

SIMULATORS = ("world_model", "env", "toy")


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--simulator", choices=SIMULATORS, default="world_model")
    parser.add_argument("--env-workers", type=int, default=0, help="C-engine processes (--simulator env, evaluation)")
    parser.add_argument("--renderer", choices=("jax", "gl"), default="jax",
                        help="frames of the C-engine episodes: the renderer the demonstrations were made with")
    parser.add_argument("--demos", action="append", default=[], help="demos whose frames are the start keyframes")
    parser.add_argument("--world-model", default="", help="world-model workdir (train_world_model)")
    parser.add_argument("--vae", default="", help="VAE checkpoint directory (train_vae)")
    parser.add_argument("--policy", default="", help="SFT policy: a train_policy checkpoint or an .npz of benchmarks.bench_policy; empty = from scratch")
    parser.add_argument("--reward", default="", help="reward model checkpoint (train_reward)")
    parser.add_argument("--latents", default="", help="the world model's training latents (.npz; rl.refresh needs them)")
    parser.add_argument("--eval-episodes", type=int, default=0, help="override rl.grpo.eval_episodes_per_task")
    args = parser.parse_args(rest)
    inputs = GRPOInputs(demos=tuple(args.demos), world_model=args.world_model, vae=args.vae, policy=args.policy,
                        reward=args.reward, latents=args.latents)
    return run(cfg, inputs, simulator=args.simulator, env_workers=args.env_workers, renderer=args.renderer,
               eval_episodes=args.eval_episodes)


def run(cfg, inputs: GRPOInputs, *, simulator: str = "world_model", env_workers: int = 0, renderer: str = "jax",
        eval_episodes: int = 0) -> dict:
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
        if rl.env.starts == "keyframes" and not inputs.demos:
            raise SystemExit("train.grpo --simulator env --rl.env.starts=keyframes needs --demos (the rollouts start "
                             "from their recorded states)")
    elif not (inputs.world_model and inputs.reward and inputs.demos):
        raise SystemExit("train.grpo --simulator world_model needs --world-model, --reward and --demos (see --help)")
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
                                       episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task)
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
            from sword_jax.load import experiment_vae

            if not inputs.latents:
                raise SystemExit("train.grpo --rl.refresh.every > 0 needs --latents (the world model's training latents)")
            return run_refreshed_in_mjx(cfg, rl, graphdef, params, workdir, setup, vae=experiment_vae(cfg, inputs.vae),
                                        latents=inputs.latents,
                                        episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task,
                                        max_traces=ENTRY_MAX_TRACES)
        env_eval = lockstep_evaluation(cfg.sim.tasks, eval_episodes or rl.grpo.eval_episodes_per_task,
                                       resolution=cfg.sim.resolution, max_steps=cfg.sim.max_steps, renderer=renderer,
                                       workers=env_workers)
    return run_in_learned_simulator(cfg, rl, graphdef, params, workdir, setup, simulator=simulator,
                                    env_eval=env_eval, max_traces=ENTRY_MAX_TRACES)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
