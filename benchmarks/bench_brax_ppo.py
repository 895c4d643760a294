"""brax PPO's env steps per second against the ground-truth MJX env and inside the learned simulator.

One brax PPO call (``examples/brax_ppo.py``'s ``train``: brax's vision networks, its training wrappers,
``--num-envs`` envs, ``--unroll-length`` steps per env per iteration) runs against each env in turn, the
env object being the only difference. The figure per env is brax's own ``training/sps`` of the iterations
after the first (the first includes compilation), their median; the wall time of the whole call is kept
beside it. Keys: ``brax_ppo_env_steps_per_s_mjx`` and ``brax_ppo_env_steps_per_s_learned``.

``mjx``: LIBERO-Spatial task ``--task`` on MJX with the agentview camera at ``--resolution``; a step is one
7-D action. ``learned``: ``sword_jax.make_env`` over the world model of ``--run`` (a pipeline work dir;
without it the examples' tiny model, trained first for a few steps); a step is one chunk of actions, so
its frames per step are the world model's frames per chunk.

    python -m benchmarks.bench_brax_ppo --envs mjx,learned --num-envs 256 --iterations 4
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys

from benchmarks import common
from sword_jax import cli

EXAMPLES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples")


def _examples():
    if EXAMPLES not in sys.path:
        sys.path.insert(0, EXAMPLES)
    import brax_ppo

    return brax_ppo


def steady_steps_per_s(iterations: list[dict]) -> float:
    """The median of brax's ``training/sps`` over the iterations after the first (which compiles).

    Raises:
      ValueError: with fewer than two iterations there is no iteration free of compilation.
    """
    if len(iterations) < 2:
        raise ValueError(f"need at least 2 PPO iterations to time one without compilation, got {len(iterations)}")
    return statistics.median(item["steps_per_s"] for item in iterations[1:])


def make_env(name: str, args: argparse.Namespace):
    brax_ppo = _examples()
    if name == "mjx":
        return brax_ppo.mjx_env(task=args.task, resolution=args.resolution), args.episode_length_mjx
    if name == "learned":
        return brax_ppo.learned_env(args.run, workdir=args.workdir, train_steps=args.train_steps,
                                    episode_length=args.episode_length_learned, seed=args.seed), \
            args.episode_length_learned
    raise ValueError(f"unknown env {name!r}: choose from mjx, learned")


def main(argv=None) -> dict:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", default="mjx,learned", help="comma-separated: mjx, learned")
    parser.add_argument("--run", help="learned: a pipeline work dir (default: the examples' tiny model)")
    parser.add_argument("--workdir", default="runs/bench-brax-ppo-tiny", help="where the tiny model goes")
    parser.add_argument("--train-steps", type=int, default=10)
    parser.add_argument("--task", type=int, default=0)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--num-envs", type=int, default=256)
    parser.add_argument("--unroll-length", type=int, default=8)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--episode-length-mjx", type=int, default=220)
    parser.add_argument("--episode-length-learned", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-record", action="store_true", help="print only; leave latest.json alone")
    args = parser.parse_args(argv)
    names = [n.strip() for n in args.envs.split(",") if n.strip()]
    unknown = sorted(set(names) - {"mjx", "learned"})
    if unknown or not names:
        parser.error(f"--envs: unknown env(s) {unknown or names}: choose from mjx, learned")
    if args.iterations < 2:
        parser.error(f"--iterations must be at least 2 (the first includes compilation), got {args.iterations}")

    brax_ppo = _examples()
    rows, entries = [], {}
    for name in names:
        env, episode_length = make_env(name, args)
        result = brax_ppo.train(env, num_envs=args.num_envs, unroll_length=args.unroll_length,
                                iterations=args.iterations, episode_length=episode_length, seed=args.seed)
        sps = steady_steps_per_s(result["iterations"])
        row = {"env": name, "env_steps_per_s": round(sps, 1), "num_envs": args.num_envs,
               "unroll_length": args.unroll_length, "iterations": args.iterations,
               "wall_s": round(result["seconds"], 1), "action_size": env.action_size}
        if name == "mjx":
            row.update(task=args.task, resolution=args.resolution)
        else:
            row.update(run=args.run or "tiny (examples/_tiny_run.py)")
        rows.append(row)
        key = f"brax_ppo_env_steps_per_s_{name}"
        entries[key] = common.record(key, sps, None, **{k: v for k, v in row.items() if k != "env_steps_per_s"})
    common.print_table(rows, list(rows[0]))
    if not args.no_record:
        print("wrote", common.merge_results(entries))
    return {"rows": rows, "entries": entries}


if __name__ == "__main__":
    cli.run(main)
