"""Behaviour cloning (SFT) of the VLA policy on expert demonstrations: the GRPO starting point.

    python -m train.train_policy --config sword:small --demos demos.hdf5 [--rl.sft_steps=2000]
        [--rl.sft_episodes_per_task=10] [--workdir DIR] [--eval-episodes 10]

The knobs that set how good the starting policy is: ``rl.sft_steps`` and
``rl.sft_episodes_per_task`` (demonstrations per instruction). Writes ``<workdir>/policy_sft``
(orbax) and, with ``--eval-episodes``, the ground-truth success in the MuJoCo sim.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence

import jax
import numpy as np

import configs
from sword_jax.rl import data as rl_data
from sword_jax.rl.evaluate import evaluate_in_sim
from sword_jax.rl.params_io import save_params
from sword_jax.rl.policy import build_policy
from sword_jax.rl.sft import make_sft_step


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demos", action="append", required=True, help="LIBERO-layout HDF5 demos (repeatable)")
    parser.add_argument("--eval-episodes", type=int, default=0, help="fixed initial states per task to evaluate on")
    args = parser.parse_args(rest)
    rl = cfg.rl
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    episodes = rl_data.per_task_subset(rl_data.load_episodes(args.demos), rl.sft_episodes_per_task, rng)
    episodes = rl_data.EpisodeSet(episodes.frames, episodes.actions, episodes.proprio[..., : rl.proprio_dim],
                                  episodes.lengths, episodes.success, episodes.instructions)
    print(f"train_policy: {episodes.num_episodes} demonstrations, {len(set(episodes.instructions))} instructions")
    graphdef, params = build_policy(rl, seed=cfg.seed)
    init, step = make_sft_step(graphdef, rl)
    state = init(params)
    key = jax.random.key(cfg.seed)
    start, metrics = time.time(), {}
    for i in range(rl.sft_steps):
        batch = rl_data.sample_bc_batch(episodes, rl.sft_batch_size, rl.chunk_len, rl.max_instruction_bytes, rng)
        state, metrics = step(state, batch, key)
        if (i + 1) % max(rl.sft_steps // 10, 1) == 0 or i + 1 == rl.sft_steps:
            loss = float(metrics["loss"])
            if not np.isfinite(loss):
                raise SystemExit(f"train_policy: non-finite loss at step {i + 1}")
            eta = (time.time() - start) / (i + 1) * (rl.sft_steps - i - 1)
            print(f"sft step {i + 1}/{rl.sft_steps} loss {loss:.4f} "
                  f"token_acc {float(metrics['token_accuracy']):.3f} eta {eta:.0f}s", flush=True)
    path = os.path.join(workdir, "policy_sft")
    save_params(path, state.params, rl, kind="policy", step=int(state.step))
    result = {"steps": rl.sft_steps, "demos": episodes.num_episodes, "path": path,
              "final_loss": float(metrics["loss"]) if metrics else None}
    if args.eval_episodes:
        result["eval"] = evaluate_in_sim(graphdef, state.params, rl, tasks=cfg.sim.tasks,
                                         episodes_per_task=args.eval_episodes, resolution=cfg.sim.resolution,
                                         max_steps=cfg.sim.max_steps)
        print("ground-truth success:", json.dumps(result["eval"]))
    with open(os.path.join(workdir, "sft_result.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    from sword_jax.cli import run

    run(main)
