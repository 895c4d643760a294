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
    # one process per device, data parallel (toy, or world_model without replays: --rl.imagined.eval_replay_episodes=0)
    python -m train.launch --processes 2 -- python -m train.grpo ... --mesh.distributed=true

Each step samples ``rl.grpo.rollout_batch`` keyframe start states, G = ``rl.grpo.group_size`` imagined
trajectories each, and applies the GRPO update (one jitted, donated step); with ``rl.imagined.oversample=k``
it samples k times as many and updates on ``rollout_batch`` groups of them, the mixed-outcome ones first.
With ``--simulator env`` the start states are training-split initial states (never the 50 evaluation states), the
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
import sys
from collections.abc import Sequence

import configs
from sim.grpo_training import SIMULATORS, run_grpo
from sword_jax.pipeline.grpo import GRPOInputs
from train import distributed


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
    parser.add_argument("--light-decoder", default="",
                        help="the light rollout decoder (train_light_decoder; rl.imagined.decoder=light needs it)")
    parser.add_argument("--eval-episodes", type=int, default=0, help="override rl.grpo.eval_episodes_per_task")
    args = parser.parse_args(rest)
    distributed.initialize(cfg.mesh)
    inputs = GRPOInputs(demos=tuple(args.demos), world_model=args.world_model, vae=args.vae, policy=args.policy,
                        reward=args.reward, latents=args.latents, light_decoder=args.light_decoder)
    return run(cfg, inputs, simulator=args.simulator, env_workers=args.env_workers, renderer=args.renderer,
               eval_episodes=args.eval_episodes)


def run(cfg, inputs: GRPOInputs, *, simulator: str = "world_model", env_workers: int = 0, renderer: str = "jax",
        eval_episodes: int = 0) -> dict:
    """:func:`sim.grpo_training.run_grpo`."""
    return run_grpo(cfg, inputs, simulator=simulator, env_workers=env_workers, renderer=renderer,
                    eval_episodes=eval_episodes)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
