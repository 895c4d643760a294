"""The paper's three comparisons, each over several seeds, in (run, seed) slices merged into one table.

    python -m train.compare --size small --runs sword --seeds 0               # one slice
    python -m train.compare --size small --runs sword,wovr --seeds 1          # two slices, same shared stages
    python -m train.compare --size small --runs sword,teacher_forcing,no_augmentation --seeds 0,1,2 \
        --no-policy --parallel 2 --slices-at-once 4   # shared stages once, then 9 slices, 4 side by side on one GPU
    python -m train.compare merge benchmarks/results/compare/small            # table from the slices there
    python -m train.compare --size tiny --seeds 0 --out /tmp/compare --results /tmp/compare/slices  # CPU smoke
    python -m train.compare --size small --runs sword --seeds 0 --trainer.steps=2000   # overrides: every run
    python -m train.compare --size small --runs sword,wovr,ground_truth --seeds 1 --shared-seed slice \
        --no-evaluate --slices-at-once 3   # comparison 3, one seed with its own shared stages

1. DLB (linear, direct, all) vs teacher forcing: long-horizon LPIPS / FID / FVD / FloLPIPS on
   LIBERO-Original and LIBERO-Mixed.
2. Style augmentation vs none: the same metrics on LIBERO-Mixed.
3. GRPO inside the Sword world model vs inside a WoVR-config world model (teacher forcing +
   context noise, no augmentation): real-environment success of the policy over GRPO steps, with
   GRPO against the MuJoCo environments themselves from the same supervised policy (run
   ``ground_truth``: no world model) as the upper reference.

A slice is one run at one seed: ``train.pipeline`` in ``<out>/<run>/seed<k>`` (resumable), then
one small file ``<results>/<run>_seed<k>.json`` (default ``benchmarks/results/compare/<size>/``):
metrics with per-horizon curves, the GRPO success curve (comparison-3 runs), the command, device,
stage times, code version and hashes of the shared inputs. ``merge DIR`` builds
``comparison.md``/``comparison.json`` in DIR from whatever slice files are there, with ``n`` per cell.

What the slices share. The seeds vary what is compared: world-model training (initialisation,
batch order, DLB reads) and GRPO. Stages that do not depend on the compared choice -- expert data
and held-out episodes, the VAE, the encoded latents (per augmentation setting), the light rollout
decoder (with ``rl.imagined.decoder=light``), the state probe, the reward model and the supervised
policy -- are built once in ``<out>/shared/<run>`` at
``--shared-seed`` (default 0), whatever the slice's seed, and adopted by the slice. They are meant
to be deterministic functions of the config and that seed, so that a slice run later on a fresh
machine rebuilds the same inputs; every slice file records their hashes (``sword_jax.pipeline.inputs``),
and ``merge`` refuses slices whose hashes disagree. ``--no-share`` makes every stage of every slice
from the slice's own seed.

``--shared-seed slice`` builds the shared stages once per seed, at that seed (in
``<out>/shared-seed<k>/``), and every run of the seed adopts them: each seed is then a whole,
independent replicate of the pipeline, its runs still paired. A comparison whose seeds run as separate
jobs (GPU runs need not rebuild bit-identical VAEs) is replicated this way, one seed per job;
``merge`` checks the hashes among the slices of each shared seed.
"""

from __future__ import annotations

import json
import os
import shlex
import sys
import time
from collections.abc import Sequence

from sword_jax.cli import ArgumentParser, StopRequested, UsageError, not_dotted_overrides
from sword_jax.pipeline.compare import (GROUND_TRUTH, GROUND_TRUTH_STAGES, SHAREABLE, SLICE_FORMAT, adopt_stages,
                                        finish, load_slices, merge, runs_for)
from sword_jax.pipeline import launch as launcher
from sword_jax.pipeline.inputs import REPO, code_version, device_info, shared_hashes
from sword_jax.pipeline.slices import (EVALUATION_ONLY, SLICES_AT_ONCE_ENV, needs_policy, parse_runs, parse_seeds,
                                       parse_shared_seed, run_slices_side_by_side, shared_dir_of, shared_seed_of,
                                       slice_command, slice_record)
from sword_jax.atomic_write import write_json_atomic
from sword_jax.pipeline.stages import Context, Stage, check_workdir_config, run_stages, run_stages_parallel

def _stage_names(run: str, *, policy: bool = True, evaluate: bool = True) -> list[str]:
    """The pipeline stages a slice of ``run`` goes through (up to the evaluation outside comparison 3, or
    without ``policy``; without ``evaluate``, comparison 3's GRPO stages without the world-model
    evaluation, its probe and the report)."""
    from sim import pipeline_stages

    if run == GROUND_TRUTH:
        return list(GROUND_TRUTH_STAGES)
    names = [stage.name for stage in pipeline_stages.STAGES]
    if not evaluate:
        return [n for n in names if n not in EVALUATION_ONLY]
    return names if needs_policy(run) and policy else names[:names.index("evaluate") + 1]


def _run_config(run: str, size: str, seed: int, workdir: str,
                overrides: Sequence[str]) -> tuple[str, "configs.ExperimentConfig", list[str]]:
    """``(config name, typed config, its dotted overrides)`` of ``run`` at ``seed`` in ``workdir``."""
    import configs

    config, extra = runs_for(size)[run]
    dotted = [f"--seed={seed}", *extra, *overrides]
    cfg, _ = configs.from_argv(["--config", config, f"--workdir={workdir}", *dotted])
    return config, cfg, dotted


def ground_truth_stages() -> list:
    """The ``ground_truth`` run's stages: the pipeline's data and supervised policy (shared), then GRPO
    against the MuJoCo environments from that policy (:func:`sim.policy_stages.grpo_in_ground_truth`)."""
    from sim import pipeline_stages, policy_stages

    by_name = {stage.name: stage for stage in pipeline_stages.STAGES}
    return [by_name["data"], by_name["sft_policy"],
            Stage("policy", lambda ctx: policy_stages.grpo_in_ground_truth(ctx),
                  "GRPO against the MuJoCo environments (no world model): comparison 3's upper reference",
                  needs=("data", "sft_policy"))]


def build_shared(run: str, size: str, *, out: str, shared_seed: int, overrides: Sequence[str],
                 policy: bool = True, parallel: int = 0, evaluate: bool = True) -> tuple[str, dict, list[str]]:
    """Builds (or finds) the shared stages ``run`` needs in ``<out>/shared/<run>`` at ``shared_seed``.

    Stages another run's shared dir has already made with equal config sections are adopted, not
    rebuilt. ``parallel`` > 0 runs them as ``train.pipeline --parallel`` does (each in its own
    process, that many at a time). Returns ``(shared dir, its config as a dict, stages built by this call)``.
    """
    import glob

    from configs.cli import to_dict
    from sim import pipeline_stages

    shared_dir = shared_dir_of(out, run, shared_seed)
    config, cfg, dotted = _run_config(run, size, shared_seed, shared_dir, overrides)
    check_workdir_config(cfg, shared_dir)
    wanted = [name for name in _stage_names(run, policy=policy, evaluate=evaluate) if name in SHAREABLE]
    for other in sorted(glob.glob(os.path.join(os.path.dirname(shared_dir), "*", "config.json"))):
        donor = os.path.dirname(other)
        if os.path.abspath(donor) != os.path.abspath(shared_dir):
            with open(other) as f:
                adopt_stages(shared_dir, donor, cfg, json.load(f), wanted)
    stages = [s for s in pipeline_stages.STAGES if s.name in wanted]
    done = {s.name for s in stages if os.path.exists(os.path.join(shared_dir, "stages", f"{s.name}.json"))}
    ctx = Context(cfg=cfg, workdir=shared_dir, cfg_name=config, overrides=dotted)
    if parallel:
        left_out = [s.name for s in pipeline_stages.STAGES if s.name not in wanted]
        launch = pipeline_stages.stage_launcher(["--config", config, f"--workdir={shared_dir}", *dotted,
                                                 *(["--skip", ",".join(left_out)] if left_out else [])], shared_dir)
        run_stages_parallel(stages, ctx, launch, max_running=parallel)
    else:
        run_stages(stages, ctx)
    return shared_dir, to_dict(cfg), [s.name for s in stages if s.name not in done]


def run_slice(run: str, seed: int, *, size: str, out: str, shared_seed: int, share: bool,
              overrides: Sequence[str], policy: bool = True, parallel: int = 0, evaluate: bool = True) -> dict:
    """Runs one (run, seed) slice (building the shared stages first where missing); returns its record.

    ``policy=False`` stops a comparison-3 run after its evaluation (no supervised policy, no GRPO): a
    slice for comparisons 1 and 2 only, recorded as such. ``evaluate=False`` leaves out the
    world-model evaluation (and its probe and the report): a comparison-3 slice that only trains
    GRPO and measures real success, recorded as such. ``parallel`` > 0: stages in their own
    processes, that many side by side (``train.pipeline --parallel``); the same results. The
    ``ground_truth`` run adopts the data and supervised policy and runs GRPO against MuJoCo in this
    process (one stage; ``parallel`` does not apply to it)."""
    from sim import pipeline_stages

    started = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    start = time.perf_counter()
    workdir = os.path.join(out, run, f"seed{seed}")
    config, cfg, dotted = _run_config(run, size, seed, workdir, overrides)
    shared: dict = {"seed": seed, "workdir": None, "built_here": [], "adopted": []}
    if share:
        shared_dir, shared_cfg, built = build_shared(run, size, out=out, shared_seed=shared_seed, overrides=overrides,
                                                     policy=policy, parallel=parallel, evaluate=evaluate)
        adopted = adopt_stages(workdir, shared_dir, cfg, shared_cfg)
        shared.update(seed=shared_seed, workdir=shared_dir, built_here=built, adopted=adopted)
    shared_seconds = time.perf_counter() - start
    last = _stage_names(run, policy=policy, evaluate=evaluate)[-1]
    skip = () if evaluate else tuple(n for n in EVALUATION_ONLY if n != "report")  # report: after `last`
    if run == GROUND_TRUTH:
        check_workdir_config(cfg, workdir)
        stages = run_stages(ground_truth_stages(), Context(
            cfg=cfg, workdir=workdir, cfg_name=config, overrides=dotted))
    else:
        launch = None
        if parallel:
            argv = ["--config", config, f"--workdir={workdir}", *dotted, "--stop-after", last,
                    *(["--skip", ",".join(skip)] if skip else [])]
            launch = pipeline_stages.stage_launcher(argv, workdir)
        stages = pipeline_stages.run_pipeline(cfg, stop_after=last, skip=skip, cfg_name=config, overrides=dotted,
                                              launch=launch, max_running=max(parallel, 1))
    slice_seconds = time.perf_counter() - start - shared_seconds
    hash_start = time.perf_counter()
    # the slices of one --out hash each shared file once between them (the later ones read the cache)
    shared["hashes"] = shared_hashes(cfg, stages, cache_dir=os.path.join(out, "hash_cache") if share else None)
    shared["stage_seconds"] = {name: stages[name].get("seconds") for name in shared["adopted"]}
    own = {name: r.get("seconds") for name, r in stages.items() if name not in shared["adopted"]}
    return {
        "format": SLICE_FORMAT, "size": size, "config": config, "overrides": list(overrides), "started": started,
        **slice_record(run, seed, stages, workdir),
        "stage_seconds": own, "shared": shared, "device": device_info(), "code": code_version(),
        "policy_stages": policy or not needs_policy(run), "evaluated": evaluate,
        "wall_seconds": {"shared": round(shared_seconds, 1), "slice": round(slice_seconds, 1),
                         "hashing": round(time.perf_counter() - hash_start, 1)},
    }


def launch_slice(argv: Sequence[str], log_path: str, env: dict):
    """Starts ``python -m train.compare ARGV`` (one slice) with its output in ``log_path``."""
    import subprocess

    with open(log_path, "w") as log:
        return subprocess.Popen([sys.executable, "-m", "train.compare", *argv], stdout=log,
                                stderr=subprocess.STDOUT, env=env)


def merge_main(argv: Sequence[str]) -> dict:
    parser = ArgumentParser(prog="python -m train.compare merge",
                            description="comparison.md/.json from the slice files in DIR, with n per cell")
    parser.add_argument("dir", help="a folder of slice files, e.g. benchmarks/results/compare/small")
    parser.add_argument("--allow-mismatch", action="store_true",
                        help="write the table even if slices' shared-input hashes differ (flagged at the top)")
    args = parser.parse_args(argv)
    table = merge(args.dir, allow_mismatch=args.allow_mismatch)
    print(f"[compare] wrote {os.path.join(args.dir, 'comparison.md')} from {len(load_slices(args.dir))} slices")
    return table


def main(argv: Sequence[str] | None = None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["merge"]:
        return merge_main(argv[1:])
    parser = ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False,
                            epilog="`merge DIR` builds the table from slice files. Any other --SECTION.KEY=VALUE "
                                   "is a config override applied to every run.")
    parser.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds; one slice per run and seed")
    parser.add_argument("--runs", default="", help=f"comma-separated runs (default: all of {', '.join(runs_for('tiny'))})")
    parser.add_argument("--out", default="runs/compare", help="work dirs: <out>/<run>/seed<k>, <out>/shared/<run>")
    parser.add_argument("--results", default="", help="slice files and table (default benchmarks/results/compare/<size>)")
    parser.add_argument("--shared-seed", type=parse_shared_seed, default=0,
                        help="seed of the shared stages (data, VAE, ...); 'slice': each seed's own, built at that "
                             "seed (each seed a whole replicate of the pipeline, its runs still paired)")
    parser.add_argument("--no-share", action="store_true", help="make every stage of every slice from its own seed")
    parser.add_argument("--parallel", type=int, default=0, metavar="N",
                        help="stages in their own processes, N side by side where their inputs allow "
                             "(train.pipeline --parallel); 0: one after another in this process")
    parser.add_argument("--slices-at-once", type=int, default=1, metavar="N",
                        help="build every run's shared stages first, then run the slices as child processes, N "
                             "side by side on the same device (a small model leaves most of a large GPU idle); "
                             "each child's output goes to <out>/logs/<run>_seed<k>.log")
    parser.add_argument("--gpus", type=launcher.parse_gpus, default=[], metavar="0,1,2,3",
                        help="the slices one per GPU of this list, side by side (--slices-at-once: their number)")
    parser.add_argument("--no-evaluate", action="store_true",
                        help="comparison 3 only (sword, wovr): leave out the world-model evaluation, its probe and "
                             "the report; the slice trains GRPO and measures real success. Write these slices to "
                             "their own --results folder (the comparison-1 files of the same run and seed live "
                             "elsewhere)")
    parser.add_argument("--no-policy", action="store_true",
                        help="stop every slice after its world-model evaluation (comparisons 1 and 2 only: no "
                             "supervised policy, no GRPO)")
    args, overrides = parser.parse_known_args(argv)
    bad = not_dotted_overrides(overrides)
    if bad:
        raise UsageError(f"not a dotted config override (--section.key=value): {' '.join(bad)}")
    if args.parallel < 0:
        raise UsageError(f"--parallel must be >= 0, got {args.parallel}")
    if args.slices_at_once < 1:
        raise UsageError(f"--slices-at-once must be >= 1, got {args.slices_at_once}")
    if args.gpus and not any(a == "--slices-at-once" or a.startswith("--slices-at-once=") for a in argv):
        args.slices_at_once = len(args.gpus)
    seeds, runs = parse_seeds(args.seeds), parse_runs(args.runs, args.size, policy=not args.no_policy)
    if args.no_evaluate and (args.no_policy or not all(needs_policy(r) for r in runs)):
        raise UsageError("--no-evaluate is for comparison-3 slices (runs sword, wovr, ground_truth, with their policy "
                         f"stages): got --runs {','.join(runs)}" + (" with --no-policy" if args.no_policy else ""))
    if args.no_policy and GROUND_TRUTH in runs:
        raise UsageError(f"--runs {GROUND_TRUTH} is GRPO against the environments (comparison 3's reference): it "
                         "cannot run with --no-policy")
    results_dir = args.results or os.path.join(REPO, "benchmarks", "results", "compare", args.size)
    os.makedirs(results_dir, exist_ok=True)
    invocation = shlex.join(["python", "-m", "train.compare", *argv])
    if args.slices_at_once > 1 and len(seeds) * len(runs) > 1:
        try:
            run_slices_side_by_side(argv, runs, seeds, args, overrides, build=build_shared, launch=launch_slice)
        except (RuntimeError, StopRequested):
            if load_slices(results_dir):  # the slices that finished still make a table
                merge(results_dir, allow_mismatch=True)
            raise
        return finish(results_dir)
    at_once = int(os.environ.get(SLICES_AT_ONCE_ENV, "1"))
    for seed in seeds:
        for run in runs:
            shared_seed = shared_seed_of(args.shared_seed, seed)
            record = run_slice(run, seed, size=args.size, out=args.out, shared_seed=shared_seed,
                               share=not args.no_share, overrides=overrides, policy=not args.no_policy,
                               parallel=args.parallel, evaluate=not args.no_evaluate)
            record["command"] = slice_command(run, seed, size=args.size, shared_seed=shared_seed,
                                              share=not args.no_share, overrides=overrides, policy=not args.no_policy,
                                              evaluate=not args.no_evaluate)
            record["invocation"] = invocation
            record["slices_at_once"] = at_once
            path = os.path.join(results_dir, f"{run}_seed{seed}.json")
            write_json_atomic(path, record, sort_keys=True)
            wall = record["wall_seconds"]
            print(f"[compare] slice {run} seed {seed}: {wall['shared']:.0f} s shared stages + {wall['slice']:.0f} s "
                  f"slice -> {path}")
            if at_once == 1:
                merge(results_dir, allow_mismatch=True)  # after every slice: a run stopped early leaves a table
    if at_once > 1:  # a child of --slices-at-once: its parent merges once every slice is done (one writer)
        return {}
    return finish(results_dir)


if __name__ == "__main__":
    from sword_jax.cli import run

    run(main)
