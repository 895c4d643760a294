"""Imagined frames per second inside a real GRPO step of ``sword:small``, before and after, side by side.

Each case builds the step ``python -m train.grpo --simulator world_model`` runs, through the same functions:
:func:`sword_jax.pipeline.grpo.setup_from_weights` (GRPO's simulator builder at ``rl.imagined.sim_precision``,
the success detector as reward model, keyframe start states encoded by the VAE) and
:func:`sword_jax.pipeline.grpo.grpo_step` (the compiled, donated ``make_grpo_step``: ``rollout_batch x
group_size`` imagined rollouts, then the policy update), from random weights (world model, VAE, light decoder,
policy, detector: the speed does not depend on them; nothing is read from disk or downloaded) and keyframes of
random episodes. The cases:

* ``before``: ``rl.imagined.sim_precision=float32`` with the VAE's decoder (the exact float32 decode);
* ``fast``: ``sim_precision=fast`` with the VAE's decoder;
* ``light``: ``rl.imagined.decoder=light`` (the light decoder at ``rl.image_size``, ``sim_precision=fast``).

Per case the first ``--warmup`` steps (the first compiles) are left out and the next ``--steps`` are timed one
at a time by GRPO's own clock (:class:`sword_jax.rl.grpo_loop.StepTimes`: the step's start states made and
placed, the step, its metrics read back), which also counts the imagined frames as a GRPO run's
``step_times.jsonl`` does: frames per chunk x trajectories x the chunks each trajectory actually rolled (the
step's ``mean_chunks``). Every case starts from the same start states and keys (``--seed``). Peak memory is the
process's running maximum, so the cases run light, fast, before: the order in which their memory should rise.

The defaults are the project's GRPO runs' settings (``DEFAULTS``: 32 start states x 8, 4 minibatches of
microbatch 8, 4 executed actions per chunk, 12 chunks); ``--rollout-batch`` / ``--group-size`` or any
``--section.key=value`` override them. ``--cases`` picks some of the cases, ``--results`` where they merge::

    python -m benchmarks.bench_grpo_step          # one GPU: the three cases, merged into benchmarks/results/latest.json
    python -m benchmarks.bench_grpo_step --tiny   # CPU smoke run on sword:tiny shapes (nothing merged)

``grpo_imagined_frames_per_s_small``'s value is the light case's frames/s (the fastest case's when it did not
run); each case's figures and the ratios to ``before`` are kept beside it.
"""

from __future__ import annotations

import statistics
import sys
import time

import jax
import numpy as np
from flax import nnx

import configs
from benchmarks import common
from sword_jax import cli
from sword_jax.load import experiment_vae, experiment_world_model
from sword_jax.pipeline.grpo import grpo_step, setup_from_weights
from sword_jax.pipeline.light_decoder import light_geometry
from sword_jax.rl.data import EpisodeSet
from sword_jax.rl.grpo_loop import StepTimes
from sword_jax.rl.policy import build_policy
from sword_jax.rl.reward_model import build_detector
from sword_jax.vae import light_decoder as light

KEY = "grpo_imagined_frames_per_s_small"
# the project's GRPO runs (benchmarks/results: bench_policy grpo-seeds, the comparisons' --rl.imagined.* settings)
DEFAULTS = ("--rl.grpo.rollout_batch=32", "--rl.grpo.group_size=8", "--rl.grpo.minibatches=4",
            "--rl.grpo.update_microbatch=8", "--rl.imagined.execute_steps=4", "--rl.imagined.max_chunks=12")
# the same structure at sword:tiny's size: several minibatches and microbatches, chunks shorter than rl.chunk_len
TINY_DEFAULTS = ("--rl.grpo.rollout_batch=2", "--rl.grpo.group_size=4", "--rl.grpo.minibatches=2",
                 "--rl.grpo.update_microbatch=2", "--rl.imagined.execute_steps=4", "--rl.imagined.max_chunks=2")
# case -> (rl.imagined.sim_precision, rl.imagined.decoder); run in this order (peak memory rising)
CASES = {"light": ("fast", "light"), "fast": ("fast", "full"), "before": ("float32", "full")}


def random_episodes(cfg, *, episodes: int = 4) -> EpisodeSet:
    """Episodes of uniform random frames, actions and proprio at the world model's frame size, whole length:
    what the keyframe start states are cut from (their content does not change the step's work)."""
    rng = np.random.default_rng(cfg.seed)
    length, size = cfg.data.episode_frames, cfg.data.image_size
    return EpisodeSet(
        frames=rng.integers(0, 256, (episodes, length, size, size, 3), dtype=np.uint8),
        actions=rng.uniform(-1.0, 1.0, (episodes, length, cfg.model.action_dim)).astype(np.float32),
        proprio=rng.normal(size=(episodes, length, max(8, cfg.rl.proprio_dim))).astype(np.float32),
        lengths=np.full((episodes,), length, np.int32), success=np.zeros((episodes,), bool),
        instructions=tuple(f"pick up the black bowl and place it on plate {i}" for i in range(episodes)))


def random_weights(cfg) -> dict:
    """Fresh weights of every model a GRPO run in the world model reads (seed ``cfg.seed``), in the layout the
    run's loaders give: ``(graphdef, state)`` each."""
    latent_size, frame_size = light_geometry(cfg)
    light_decoder = nnx.split(light.create_light_decoder(
        cfg.light_decoder, z_dim=cfg.vae.z_dim, scale=frame_size // latent_size,
        temporal_factor=cfg.vae.temporal_factor, key=jax.random.key(cfg.seed)))
    return {"world_model": experiment_world_model(cfg, None), "vae": experiment_vae(cfg),
            "detector": build_detector(cfg.rl, seed=cfg.seed), "light_decoder": light_decoder}


def case_config(cfg, case: str):
    """``cfg`` with the case's simulator precision and decoder, validated as a command line's would be."""
    precision, decoder = CASES[case]
    return configs.apply_overrides(cfg, [f"--rl.imagined.sim_precision={precision}",
                                         f"--rl.imagined.decoder={decoder}"]).validate()


def run_case(cfg, case: str, weights: dict, episodes: EpisodeSet, *, warmup: int, steps: int) -> dict:
    """Times GRPO steps of one case (module docstring); returns its row with the per-step figures."""
    cfg = case_config(cfg, case)
    rl = cfg.rl
    t0 = time.perf_counter()
    setup = setup_from_weights(cfg, rl, episodes, world_model=weights["world_model"], vae=weights["vae"],
                               detector=weights["detector"],
                               light_decoder=weights["light_decoder"] if rl.imagined.decoder == "light" else None)
    graphdef, params = build_policy(rl, seed=cfg.seed)  # fresh per case: the step donates its state
    run = grpo_step(cfg, rl, graphdef, params, setup, max_traces=1)  # a retrace would be timed: refused
    build_s = time.perf_counter() - t0
    frames_per_chunk, frame_size = run.frames_per_chunk, run.sim.frame_size
    times = StepTimes(None, rl.imagined_starts_per_step * rl.grpo.group_size * frames_per_chunk)
    state, warm_s, timed = run.state, [], []
    for index in range(warmup + steps):
        times.restart()
        state, metrics = run.step(state, run.place(run.batch_at(index)), run.key)
        metrics = jax.device_get(metrics)  # blocks on the step, as the loop's read of its metrics does
        # chunks rolled by every trajectory, the oversampled groups the update leaves out included
        chunks = float(metrics.get("mean_chunks_sampled", metrics["mean_chunks"]))
        row = times.add(index + 1, chunks)
        if index < warmup:
            warm_s.append(row["step_s"])
        else:
            timed.append(dict(row, mean_chunks=chunks, loss=float(metrics["loss"])))
    del state, run, setup
    trajectories = rl.imagined_starts_per_step * rl.grpo.group_size  # rolled out (rl.imagined.oversample included)
    return {"case": case, "precision": rl.imagined.sim_precision, "decoder": rl.imagined.decoder,
            "frame_size": frame_size,
            "step_s": statistics.median(r["step_s"] for r in timed),
            "imagined_frames_per_step": statistics.median(r["imagined_frames"] for r in timed),
            "imagined_frames_per_s": statistics.median(r["imagined_frames_per_s"] for r in timed),
            "frames_per_chunk": frames_per_chunk, "trajectories": trajectories,
            "mean_chunks": statistics.median(r["mean_chunks"] for r in timed), "max_chunks": rl.imagined.max_chunks,
            # what the scan computes whether or not a trajectory ended (StepTimes counts only the rolled chunks)
            "frames_computed_per_step": trajectories * frames_per_chunk * rl.imagined.max_chunks,
            "warmup_s": warm_s, "build_s": build_s, "steps": timed, "peak_gb": common.peak_memory_gb()}


def summary(rows: list[dict], cfg, *, warmup: int, steps: int) -> dict:
    """The ``grpo_imagined_frames_per_s_small`` entry: the light case's frames/s (else the fastest case's),
    every case's figures and their ratios to ``before``."""
    by_case = {r["case"]: r for r in rows}
    headline = by_case.get("light") or max(rows, key=lambda r: r["imagined_frames_per_s"])
    before = by_case.get("before")

    def over_before(case):
        if before is None or case not in by_case:
            return None
        return by_case[case]["imagined_frames_per_s"] / before["imagined_frames_per_s"]

    grpo = cfg.rl.grpo
    return common.record(
        KEY, headline["imagined_frames_per_s"], None,
        value_is=f"imagined frames/s inside a GRPO step, case {headline['case']}",
        note=(f"{cfg.name} DiT dim {cfg.model.dim} x {cfg.model.num_layers} layers, {cfg.data.image_size} px "
              f"frames, random weights; GRPO's step (rollouts + update) of {grpo.rollout_batch} x "
              f"{grpo.group_size} trajectories, frames counted as step_times.jsonl counts them"),
        config=cfg.name, rollout_batch=grpo.rollout_batch, group_size=grpo.group_size,
        trajectories=headline["trajectories"], minibatches=grpo.minibatches,
        update_microbatch=grpo.update_microbatch, execute_steps=cfg.rl.imagined.execute_steps,
        max_chunks=cfg.rl.imagined.max_chunks, sample_steps=cfg.flow.sample_steps, seed=cfg.seed,
        warmup_steps=warmup, timed_steps=steps,
        ratios={"fast_over_before": over_before("fast"), "light_over_before": over_before("light")},
        cases={r["case"]: {k: v for k, v in r.items() if k != "case"} for r in rows})


def main(argv=None) -> dict:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="CPU smoke run on sword:tiny (nothing merged)")
    parser.add_argument("--config", default=None, help="experiment config (default sword:small, tiny with --tiny)")
    parser.add_argument("--rollout-batch", type=int, default=None, help="rl.grpo.rollout_batch (start states)")
    parser.add_argument("--group-size", type=int, default=None, help="rl.grpo.group_size (trajectories per start)")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--warmup", type=int, default=1, help="steps left out per case (the first compiles)")
    parser.add_argument("--steps", type=int, default=3, help="timed steps per case")
    parser.add_argument("--results", default=None,
                        help=f"merge into this file (default {common.RESULTS}; with --tiny nothing unless given)")
    argv = sys.argv[1:] if argv is None else list(argv)
    tiny = "--tiny" in argv
    cfg, rest = configs.from_argv([*(TINY_DEFAULTS if tiny else DEFAULTS), *argv],
                                  default="sword:tiny" if tiny else "sword:small")
    args = parser.parse_args(rest)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = sorted(set(cases) - set(CASES))
    if unknown or not cases:
        parser.error(f"--cases: unknown case(s) {unknown or cases}: choose from {', '.join(CASES)}")
    if args.warmup < 1 or args.steps < 1:
        parser.error(f"--warmup and --steps must be at least 1 (the first step compiles), got {args.warmup}, "
                     f"{args.steps}")
    sizes = [f"--rl.grpo.{key}={value}" for key, value in (("rollout_batch", args.rollout_batch),
                                                           ("group_size", args.group_size)) if value is not None]
    cfg = configs.apply_overrides(cfg, sizes).validate()

    weights, episodes = random_weights(cfg), random_episodes(cfg)
    print(f"{common.device_name()}: {cfg.name}, GRPO step of {cfg.rl.grpo.rollout_batch} x {cfg.rl.grpo.group_size} "
          f"trajectories, {cfg.rl.imagined.max_chunks} chunks, {args.warmup} warm-up + {args.steps} timed steps per "
          "case", flush=True)
    rows = []
    for case in (c for c in CASES if c in cases):  # the fixed order: peak memory rising
        t0 = time.perf_counter()
        try:
            rows.append(run_case(cfg, case, weights, episodes, warmup=args.warmup, steps=args.steps))
        except Exception as err:  # noqa: BLE001 - out of memory: report it, keep the other cases
            if not common.is_oom(err):
                raise
            print(f"{case}: out of memory ({str(err).splitlines()[0][:160]})")
            continue
        print(f"{case}: {time.perf_counter() - t0:.1f} s with compilation", flush=True)
    if not rows:
        raise SystemExit("bench_grpo_step: no case ran; nothing recorded")
    order = {c: i for i, c in enumerate(("before", "fast", "light"))}
    rows.sort(key=lambda r: order[r["case"]])
    common.print_table(rows, ["case", "precision", "decoder", "frame_size", "step_s", "imagined_frames_per_step",
                              "imagined_frames_per_s", "mean_chunks", "trajectories", "frames_per_chunk",
                              "build_s", "peak_gb"])
    entry = summary(rows, cfg, warmup=args.warmup, steps=args.steps)
    print("ratios to before (frames/s):", entry["ratios"])
    if args.results or not tiny:
        print("merged into", common.merge_results({KEY: entry}, args.results or common.RESULTS))
    return {"rows": rows, "entry": entry, "config": cfg}


if __name__ == "__main__":
    cli.run(main)
