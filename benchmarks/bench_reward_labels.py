"""What the success detector learns from each labelling (``rl.reward_model.labels``), against true success.

An imagined rollout succeeds at the first frame the detector scores >= ``rl.success_threshold``
(:func:`sword_jax.rl.rollout.chunk_outcome`), so a detector that fires before the bowl has landed
pays GRPO for bringing the bowl near the plate rather than onto it. This trains one detector per
labelling on the same episodes (C engine, ``--resolution`` px, jax renderer as the pipeline):
fixed-length expert episodes that keep moving after success and stop-at-success demonstrations,
both from the train split, DART noise ``sim.expert_noise`` on half of them, and scores each on
held-out fixed-length episodes (the held-out split; half of them with heavy noise, so some fail)
against the task's success predicate: frame precision/recall, and as the rollout rule reads them
(fires on failed episodes, fires more than one latent early, misses). Writes
``benchmarks/results/policy/reward_labels.json``. CPU only.

  python -m benchmarks.bench_reward_labels                  # 10 tasks, ~6 min on 2 cores
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax

import configs
from benchmarks.common import merge_results, record
from sword_jax import cli
from sword_jax.rl import data as rl_data
from sword_jax.rl.reward_model import as_reward_model, build_detector, detector_report, score_episodes, train_detector
from sword_jax.rng import stream_rng

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "policy", "reward_labels.json")


def generate(out_dir: str, tasks: tuple[int, ...], per_task: int, resolution: int, steps: int, workers: int) -> dict:
    """The three episode files (skipped where they exist): train fixed-length, demos, held-out."""
    from sim import datagen

    specs = {
        "fixed": dict(episodes=per_task, stop_at_success=False, init_split="train", init_start=0, noise=0.1,
                      noisy_share=0.5, seed=1, max_steps=steps),
        "demos": dict(episodes=per_task, stop_at_success=True, init_split="train", init_start=per_task, noise=0.1,
                      noisy_share=0.5, seed=2, max_steps=steps),
        "heldout": dict(episodes=max(per_task // 2, 2), stop_at_success=False, init_split="heldout", init_start=0,
                        noise=0.4, noisy_share=0.5, seed=3, max_steps=steps),
    }
    paths = {}
    for name, spec in specs.items():
        paths[name] = os.path.join(out_dir, f"{name}.hdf5")
        if not os.path.exists(paths[name]):
            datagen.generate(datagen.GenDataConfig(out=paths[name], tasks=tasks, backend="cpu", resolution=resolution,
                                                     wrist_camera=False, overwrite=True, renderer="jax", **spec),
                              progress=False, workers=workers)
    return paths


def main(argv=None) -> dict:
    from sim.dataset import read_dataset

    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--tasks", default="0,1,2,3,4,5,6,7,8,9")
    parser.add_argument("--per-task", type=int, default=10)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--steps", type=int, default=129)
    parser.add_argument("--detector-steps", type=int, default=None, help="default: the config's rl.reward_model.steps")
    parser.add_argument("--data-dir", default="runs/bench_reward_labels")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", default=OUT)
    args = parser.parse_args(argv)
    cfg = configs.get(args.config)
    rl = cfg.rl if args.detector_steps is None else dataclasses.replace(
        cfg.rl, reward_model=dataclasses.replace(cfg.rl.reward_model, steps=args.detector_steps))
    tasks = tuple(int(t) for t in args.tasks.split(","))
    os.makedirs(args.data_dir, exist_ok=True)
    t0 = time.perf_counter()
    paths = generate(args.data_dir, tasks, args.per_task, args.resolution, args.steps, args.workers)
    gen_s = time.perf_counter() - t0
    heldout = rl_data.load_episodes([paths["heldout"]], read=read_dataset, stop_at_success=False)
    results = {"command": "python -m benchmarks.bench_reward_labels " + " ".join(argv or []), "config": args.config,
               "tasks": list(tasks), "per_task": args.per_task, "resolution": args.resolution,
               "detector_steps": rl.reward_model.steps, "threshold": rl.success_threshold,
               "generate_s": round(gen_s, 1), "heldout_episodes": heldout.num_episodes, "labels": {}}
    for labels in ("tail", "state"):
        t0 = time.perf_counter()
        train = rl_data.load_episodes([paths["fixed"], paths["demos"]], read=read_dataset,
                                      stop_at_success=labels == "tail")
        train_labels = rl_data.success_labels(train, rl.reward_model.positive_tail, labels)
        graphdef, params = build_detector(rl, seed=0)

        def batch_at(step: int, train=train, train_labels=train_labels) -> dict:
            return rl_data.sample_reward_batch(train, train_labels, rl.reward_model.batch_size,
                                               stream_rng(0, "reward/batches", step))

        state, _ = train_detector(graphdef, params, rl, batch_at, key=jax.random.key(0), log=lambda line: None)
        scores = score_episodes(jax.jit(as_reward_model(graphdef, state.params).score), heldout.frames)
        report = detector_report(scores, heldout, rl.success_threshold)
        report["train_positive_frames"] = int((train_labels == 1).sum())
        report["seconds"] = round(time.perf_counter() - t0, 1)
        results["labels"][labels] = report
        print(labels, json.dumps(report), flush=True)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print("wrote", args.out)
    if args.out == OUT:
        state, tail = results["labels"]["state"], results["labels"]["tail"]
        merge_results({"reward_detector_fires_on_failed_small": record(
            "reward_detector_fires_on_failed_small", state["fires_on_failed"], None,
            tail_labels=tail["fires_on_failed"], fires_early={"state": state["fires_early"], "tail": tail["fires_early"]},
            frame_precision={"state": state["frame_precision"], "tail": tail["frame_precision"]},
            frame_recall={"state": state["frame_recall"], "tail": tail["frame_recall"]},
            heldout_episodes=results["heldout_episodes"],
            note="share of held-out failed episodes (noisy expert) in which the success detector fires on some "
                 "frame, i.e. an imagined rollout would count a false success; value = rl.reward_model.labels=state, "
                 "tail_labels = the earlier labels (frames before the first success). Data: "
                 "benchmarks/results/policy/reward_labels.json")})
    return results


if __name__ == "__main__":
    cli.run(main)
