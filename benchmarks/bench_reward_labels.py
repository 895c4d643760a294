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

With ``--policy``, the same question on the policy's own states (GRPO rewards the detector on those,
not on the expert's): the policy acts (sampled at ``--temperature``, for a fixed number of steps,
going on after success, as the pipeline's ``policy_data`` stage records it) from ``--policy-per-task``
training and ``--policy-heldout-per-task`` held-out initial states per task (the first held-out states,
where the held-out expert episodes start too). The state-labelled detector trained on the experts alone and
one trained on the experts plus the policy's training episodes (the reward-model stage's mix: one
episode set, frames drawn alike) are scored on the held-out policy and expert episodes, under the
imagined-success rule for ``rl.imagined.success_frames`` k in (1, 2, 4, 8), with the separation
P(fires | real success) - P(fires | real failure). All episodes are then rendered at ``data.image_size``
(the detector resizes them to ``rl.detector_image_size``) and are ``episode_steps`` long, as the pipeline's
data stages make them (unless ``--resolution`` / ``--steps`` say otherwise).
Results go under ``policy_episodes``. Dotted config overrides (``--section.key=value``) apply to every
detector, e.g. ``--rl.reward_model.image_size=128`` (write those runs elsewhere with ``--out``).

  python -m benchmarks.bench_reward_labels                  # 10 tasks, ~6 min on 2 cores
  python -m benchmarks.bench_reward_labels --policy policy.npz --temperature 0.5     # ~21 min on 2 cores
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import jax
import numpy as np

import configs
from benchmarks.common import merge_results, print_table, record
from sword_jax import cli
from sword_jax.rl import data as rl_data
from sword_jax.rl.reward_model import as_reward_model, build_detector, detector_report, score_episodes, train_detector
from sword_jax.rng import stream_key, stream_rng

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "policy", "reward_labels.json")
SUCCESS_FRAMES = (1, 2, 4, 8)


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
        gen = datagen.GenDataConfig(out=paths[name], tasks=tasks, backend="cpu", resolution=resolution,
                                    wrist_camera=False, overwrite=True, renderer="jax", **spec)
        if not written_with(gen):
            datagen.generate(gen, progress=False, workers=workers)
    return paths


def written_with(gen) -> bool:
    """Whether ``gen.out`` exists and was generated with ``gen``'s settings (another size or length is redone)."""
    from sim.datagen import dataset_info
    from sim.dataset import read_info

    if not os.path.exists(gen.out):
        return False
    wanted = json.loads(json.dumps(dataset_info(gen, None).env_args["env_kwargs"]))
    return read_info(gen.out).env_args.get("env_kwargs") == wanted


def generate_policy(out_dir: str, cfg, rl, policy_path: str, tasks: tuple[int, ...], per_task: int,
                    heldout_per_task: int, resolution: int, steps: int) -> dict:
    """The policy's episodes (always redone): ``per_task`` from the first training initial states of each
    task and ``heldout_per_task`` from the first held-out ones, ``steps`` actions each, sampled at
    ``rl.grpo.temperature``; ``{name: summary of sim.policy_rollouts.write_policy_episodes}``."""
    from sim.datagen import GenDataConfig
    from sim.policy_rollouts import write_policy_episodes
    from sword_jax.rl.env_rollout import make_act_fns
    from sword_jax.rl.params_io import load_params
    from sword_jax.rl.policy import build_policy

    graphdef, params = build_policy(rl, seed=cfg.seed)
    params, _ = load_params(policy_path, params, kind="policy")
    act = make_act_fns(graphdef, rl)
    summaries = {}
    for name, split, episodes in (("policy_train", "train", per_task), ("policy_heldout", "heldout", heldout_per_task)):
        gen = GenDataConfig(out=os.path.join(out_dir, f"{name}.hdf5"), tasks=tasks, episodes=episodes, backend="cpu",
                            resolution=resolution, max_steps=steps, stop_at_success=False, wrist_camera=False,
                            overwrite=True, renderer="jax", init_split=split, init_start=0,
                            init_seed=cfg.sim.init_seed)
        t0 = time.perf_counter()
        summaries[name] = write_policy_episodes(gen.out, lambda: act, params, rl, gen,
                                                key=stream_key(jax.random.key(cfg.seed), f"bench/{name}"))
        summaries[name]["seconds"] = round(time.perf_counter() - t0, 1)
        print(name, json.dumps(summaries[name]), flush=True)
    return summaries


def train_scorer(rl, train: rl_data.EpisodeSet, train_labels: np.ndarray):
    """The detector trained on ``train`` (class-balanced frames, as the reward-model stage draws them), as a
    jitted frame scorer."""
    graphdef, params = build_detector(rl, seed=0)

    def batch_at(step: int) -> dict:
        return rl_data.sample_reward_batch(train, train_labels, rl.reward_model.batch_size,
                                           stream_rng(0, "reward/batches", step))

    state, _ = train_detector(graphdef, params, rl, batch_at, key=jax.random.key(0), log=lambda line: None)
    return jax.jit(as_reward_model(graphdef, state.params).score)


def rule_reports(scores: np.ndarray, episodes: rl_data.EpisodeSet, threshold: float,
                 success_frames: tuple[int, ...] = SUCCESS_FRAMES) -> dict[str, dict]:
    """``{str(k): detector_report under the k-consecutive-frames rule, plus separation}``: separation is
    P(fires | real success) - P(fires | real failure), None where either group is empty."""
    out = {}
    for k in success_frames:
        report = detector_report(scores, episodes, threshold, success_frames=k)
        missing = report["misses"] is None or report["fires_on_failed"] is None
        report["separation"] = None if missing else 1.0 - report["misses"] - report["fires_on_failed"]
        out[str(k)] = report
    return out


def main(argv=None) -> dict:
    from sim.data_stages import episode_steps
    from sim.dataset import read_dataset

    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--tasks", default="0,1,2,3,4,5,6,7,8,9")
    parser.add_argument("--per-task", type=int, default=10)
    parser.add_argument("--resolution", type=int, default=None,
                        help="default 64; with --policy the config's data.image_size (what the pipeline renders)")
    parser.add_argument("--steps", type=int, default=None,
                        help="default 129; with --policy the pipeline's fixed episode length (episode_steps)")
    parser.add_argument("--detector-steps", type=int, default=None, help="default: the config's rl.reward_model.steps")
    parser.add_argument("--policy", default=None,
                        help="a policy .npz (the config's rl policy): also score the detector on its episodes")
    parser.add_argument("--policy-per-task", type=int, default=20,
                        help="policy episodes per task (train split) the second detector trains on")
    parser.add_argument("--policy-heldout-per-task", type=int, default=5, help="held-out policy episodes per task")
    parser.add_argument("--temperature", type=float, default=None, help="default: the config's rl.grpo.temperature")
    parser.add_argument("--data-dir", default="runs/bench_reward_labels")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", default=OUT)
    args, overrides = parser.parse_known_args(argv)
    cfg = configs.apply_overrides(configs.get(args.config), overrides).validate()  # e.g. --rl.reward_model.image_size=128
    rl = cfg.rl if args.detector_steps is None else dataclasses.replace(
        cfg.rl, reward_model=dataclasses.replace(cfg.rl.reward_model, steps=args.detector_steps))
    if args.temperature is not None:
        rl = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, temperature=args.temperature))
    resolution = args.resolution or (cfg.data.image_size if args.policy else 64)
    steps = args.steps or (episode_steps(cfg) if args.policy else 129)
    tasks = tuple(int(t) for t in args.tasks.split(","))
    os.makedirs(args.data_dir, exist_ok=True)
    t0 = time.perf_counter()
    paths = generate(args.data_dir, tasks, args.per_task, resolution, steps, args.workers)
    gen_s = time.perf_counter() - t0
    heldout = rl_data.load_episodes([paths["heldout"]], read=read_dataset, stop_at_success=False)
    results = {"command": "python -m benchmarks.bench_reward_labels " + " ".join(argv or []), "config": args.config,
               "tasks": list(tasks), "per_task": args.per_task, "resolution": resolution,
               "detector_steps": rl.reward_model.steps, "threshold": rl.success_threshold,
               "generate_s": round(gen_s, 1), "heldout_episodes": heldout.num_episodes, "labels": {}}
    scorers = {}
    for labels in ("tail", "state"):
        t0 = time.perf_counter()
        train = rl_data.load_episodes([paths["fixed"], paths["demos"]], read=read_dataset,
                                      stop_at_success=labels == "tail")
        train_labels = rl_data.success_labels(train, rl.reward_model.positive_tail, labels)
        scorers[labels] = train_scorer(rl, train, train_labels)
        scores = score_episodes(scorers[labels], heldout.frames)
        report = detector_report(scores, heldout, rl.success_threshold)
        report["train_positive_frames"] = int((train_labels == 1).sum())
        report["seconds"] = round(time.perf_counter() - t0, 1)
        results["labels"][labels] = report
        print(labels, json.dumps(report), flush=True)
    if args.policy:
        del train, train_labels
        results["policy_episodes"] = on_policy(args, cfg, rl, tasks, resolution, steps, paths, heldout,
                                               scorers["state"])
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print("wrote", args.out)
    if args.out == OUT:
        state, tail = results["labels"]["state"], results["labels"]["tail"]
        entries = {"reward_detector_fires_on_failed_small": record(
            "reward_detector_fires_on_failed_small", state["fires_on_failed"], None,
            tail_labels=tail["fires_on_failed"], fires_early={"state": state["fires_early"], "tail": tail["fires_early"]},
            frame_precision={"state": state["frame_precision"], "tail": tail["frame_precision"]},
            frame_recall={"state": state["frame_recall"], "tail": tail["frame_recall"]},
            heldout_episodes=results["heldout_episodes"], resolution=results["resolution"],
            note="share of held-out failed episodes (noisy expert) in which the success detector fires on some "
                 "frame, i.e. an imagined rollout would count a false success; value = rl.reward_model.labels=state, "
                 "tail_labels = the earlier labels (frames before the first success). Data: "
                 "benchmarks/results/policy/reward_labels.json")}
        if args.policy:
            entries["reward_detector_on_policy_small"] = policy_record(results["policy_episodes"])
        merge_results(entries)
    return results


def on_policy(args, cfg, rl, tasks, resolution: int, steps: int, paths: dict, expert_heldout: rl_data.EpisodeSet,
              experts_scorer) -> dict:
    """The ``policy_episodes`` results: the policy's episodes, and both detectors on held-out policy and
    expert episodes under each k-frame rule."""
    from sim.dataset import read_dataset

    t0 = time.perf_counter()
    made = generate_policy(args.data_dir, cfg, rl, args.policy, tasks, args.policy_per_task,
                           args.policy_heldout_per_task, resolution, steps)
    out = {"policy": args.policy, "temperature": rl.grpo.temperature, "resolution": resolution, "steps": steps,
           "per_task": args.policy_per_task, "heldout_per_task": args.policy_heldout_per_task,
           "generate_s": round(time.perf_counter() - t0, 1), "success_frames": list(SUCCESS_FRAMES),
           "episodes": {name: {k: v for k, v in summary.items() if k != "path"} for name, summary in made.items()},
           "detectors": {}}
    policy_heldout = rl_data.load_episodes([made["policy_heldout"]["path"]], read=read_dataset, stop_at_success=False)
    t0 = time.perf_counter()
    # the reward-model stage's mix: expert files and the policy's rollouts read into one episode set
    train = rl_data.load_episodes([paths["fixed"], paths["demos"], made["policy_train"]["path"]], read=read_dataset,
                                  stop_at_success=False)
    train_labels = rl_data.success_labels(train, rl.reward_model.positive_tail, "state")
    mixed_scorer = train_scorer(rl, train, train_labels)
    mixed = {"train_episodes": train.num_episodes, "train_positive_frames": int((train_labels == 1).sum()),
             "seconds": round(time.perf_counter() - t0, 1)}
    del train, train_labels
    rows = []
    for name, scorer, extra in (("experts", experts_scorer, {}), ("experts_and_policy", mixed_scorer, mixed)):
        entry = dict(extra)
        for split, episodes in (("policy_heldout", policy_heldout), ("expert_heldout", expert_heldout)):
            entry[split] = rule_reports(score_episodes(scorer, episodes.frames), episodes, rl.success_threshold)
            rows += [{"detector": name, "scored_on": split, "k": k, **entry[split][k]} for k in entry[split]]
        out["detectors"][name] = entry
    print_table(rows, ["detector", "scored_on", "k", "episodes_succeeded", "episodes_failed", "fires_on_failed",
                       "misses", "frame_precision", "frame_recall", "separation"])
    return out


def policy_record(policy: dict) -> dict:
    """The latest.json entry: held-out policy episodes on which the detector trained with policy rollouts
    fires though the policy failed (k = 1)."""
    held = {name: policy["detectors"][name]["policy_heldout"] for name in ("experts", "experts_and_policy")}
    pick = lambda metric: {name: {k: r[metric] for k, r in by_k.items()} for name, by_k in held.items()}  # noqa: E731
    return record("reward_detector_on_policy_small", held["experts_and_policy"]["1"]["fires_on_failed"], None,
                  fires_on_failed=pick("fires_on_failed"), misses=pick("misses"),
                  frame_precision=pick("frame_precision"), frame_recall=pick("frame_recall"),
                  separation=pick("separation"), temperature=policy["temperature"], policy=policy["policy"],
                  resolution=policy["resolution"], steps=policy["steps"],
                  heldout_episodes=policy["episodes"]["policy_heldout"]["episodes"],
                  note="share of held-out failed episodes of the policy (its own real episodes, sampled) in which "
                       "the state-labelled detector trained on experts plus the policy's rollouts fires (k = 1: "
                       "one frame >= rl.success_threshold); by detector (experts alone / with policy rollouts) and "
                       "k (rl.imagined.success_frames) beside. Data: benchmarks/results/policy/reward_labels.json")


if __name__ == "__main__":
    cli.run(main)
