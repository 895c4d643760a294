"""The main job: the whole Sword method on one config, each stage resumable.

    python -m train.pipeline                                   # tiny default config, CPU, minutes
    python -m train.pipeline --config sword:small --workdir runs/small
    python -m train.pipeline --config cache_ablation:wovr --workdir runs/wovr --vae.checkpoint=Wan2.2_VAE.safetensors

Stages (each writes ``<workdir>/stages/<name>.json`` and is skipped when already done):
expert data (train + held-out) -> VAE (trained, or official Wan 2.2 weights) -> latents (with
styled copies) -> world model (DLB or the configured variant) -> state probe -> reward model ->
long-horizon evaluation on LIBERO-Original / LIBERO-Mixed (pixel metrics, and action following
read by the probe and the reward model) -> supervised policy -> GRPO inside the world model
with policy evaluation in the simulator -> report. ``--stop-after STAGE`` ends a run early (the
finished stages stay, so a later run continues from there). Writes ``report.md`` and ``results.json``.
``--parallel 2`` runs each stage in its own process, two at a time, each as soon as the stages it
reads are done: the VAE trains while the policy is cloned and rolled out, the success detector
while the world model trains (the same results: a stage reads only the stages it needs).
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from collections.abc import Collection, Sequence

import configs
from sword_jax.cli import UsageError
from sword_jax.pipeline.stages import (Context, Stage, check_order, check_workdir_config, run_stages,
                                       run_stages_parallel, without_flags)
from train import distributed


def stage_data(ctx: Context) -> dict:
    from train import pipeline_data

    return pipeline_data.generate_expert_data(ctx)


def stage_vae(ctx: Context) -> dict:
    from sim import vae_training

    workdir = ctx.stage_dir("vae_run")
    summary = vae_training.run_vae(ctx.cfg_in(workdir), [ctx.results["data"]["train"]["path"]])
    summary["path"] = os.path.join(workdir, "vae")
    return summary


def stage_latents(ctx: Context) -> dict:
    from train import pipeline_data

    return pipeline_data.encode_training_latents(ctx)


def stage_world_model(ctx: Context) -> dict:
    from sword_jax.pipeline import world_model

    workdir = ctx.stage_dir("world_model")
    data = dataclasses.replace(ctx.cfg.data, path=ctx.results["latents"]["path"])
    summary = world_model.run_world_model(ctx.cfg_in(workdir, data=data))
    return {"workdir": workdir, "final_step": summary["step"], "final_metrics": summary["metrics"],
            "first_loss": _first_logged(os.path.join(workdir, "metrics.jsonl"), "loss")}


def stage_probe(ctx: Context) -> dict:
    from sim import probe_training

    return probe_training.run_probe(ctx.cfg, [ctx.results["data"]["train"]["path"]], ctx.stage_dir("probe"),
                                    probe_training.probe_config(ctx.cfg))


def stage_evaluate(ctx: Context) -> dict:
    from sim import world_model_eval
    from train import pipeline_data

    splits = pipeline_data.write_eval_splits(ctx)
    inputs = world_model_eval.EvalInputs(
        models={ctx.cfg.name: ctx.results["world_model"]["workdir"]}, episodes=splits, out=ctx.stage_dir("eval"),
        vae_checkpoint=ctx.results["vae"]["path"],
        probe=ctx.results.get("probe", {}).get("path") or "",  # skipped stages: none
        reward_model=ctx.results.get("reward_model", {}).get("path") or "")
    summary = world_model_eval.run_evaluation(ctx.cfg, inputs)
    return {"report": summary["report"], "splits": splits, "metrics": pipeline_data.read_eval_results(summary["out"])}


def stage_reward_model(ctx: Context) -> dict:
    from train import pipeline_policy

    return pipeline_policy.reward_model(ctx)


def stage_sft_policy(ctx: Context) -> dict:
    from train import pipeline_policy

    return pipeline_policy.sft_policy(ctx)


def stage_policy(ctx: Context) -> dict:
    from train import pipeline_policy

    return pipeline_policy.grpo_in_world_model(ctx)


def stage_report(ctx: Context) -> dict:
    from sword_jax.pipeline import report

    return report.write(ctx)


def stage_policy_data(ctx: Context) -> dict:
    from train import pipeline_data

    return pipeline_data.generate_policy_rollouts(ctx)


STAGES = [
    Stage("data", stage_data, "expert demonstrations (train + held-out) in LIBERO's HDF5 layout"),
    # The supervised policy needs only the demonstrations; it comes early so that its own rollouts
    # (successes and failures, data.policy_rollouts_per_task) can join the world model's training data.
    Stage("sft_policy", stage_sft_policy, "the supervised (behaviour-cloned) VLA policy", needs=("data",)),
    Stage("policy_data", stage_policy_data, "the supervised policy's own rollouts for the world model (if enabled)",
          needs=("data", "sft_policy")),
    Stage("vae", stage_vae, "the video VAE (trained from scratch, or official Wan 2.2 weights)", needs=("data",)),
    Stage("latents", stage_latents, "encode training episodes and their styled copies to latents",
          needs=("data", "policy_data", "vae")),
    Stage("world_model", stage_world_model, "train the world model (DLB or the configured variant)",
          needs=("latents",)),
    Stage("probe", stage_probe, "the state probe (frames -> end effector, gripper, bowl) that scores action following",
          needs=("data",)),
    # Before evaluation: the success detector also scores imagined vs real rollouts there.
    Stage("reward_model", stage_reward_model, "the success detector that rewards imagined rollouts",
          needs=("data", "policy_data")),
    Stage("evaluate", stage_evaluate, "long-horizon rollouts vs ground truth on LIBERO-Original / LIBERO-Mixed",
          needs=("data", "vae", "world_model", "probe", "reward_model")),
    Stage("policy", stage_policy, "GRPO inside the world model, policy success in the simulator over steps",
          needs=("data", "sft_policy", "vae", "world_model", "reward_model")),
    Stage("report", stage_report, "report.md and results.json",
          needs=("data", "sft_policy", "policy_data", "vae", "latents", "world_model", "probe", "reward_model",
                 "evaluate", "policy")),
]
check_order(STAGES)


def _first_logged(path: str, key: str):
    import json

    if not os.path.exists(path):
        return None
    with open(path) as f:
        for line in f:
            row = json.loads(line)
            if key in row:
                return row[key]
    return None


def main(argv: Sequence[str] | None = None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = configs.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--restart", action="store_true", help="discard finished stages of this work dir")
    parser.add_argument("--only", default="", help="comma-separated stages to run now (the rest are left for a later "
                                                   "run; refused if one of them needs a stage that has not run)")
    parser.add_argument("--parallel", type=int, default=0, metavar="N",
                        help="run each stage in its own process, up to N at a time, a stage as soon as the stages "
                             "it needs are done (the VAE trains while the policy is cloned and rolled out); "
                             "logs in <workdir>/logs/<stage>.log. 0 (default): one after another, in this process")
    parser.add_argument("--stop-after", default="", choices=["", *(s.name for s in STAGES)],
                        help="end after this stage (finished stages are kept; a later run continues)")
    parser.add_argument("--skip", default="",
                        help="comma-separated stages to leave out of this run (e.g. probe,evaluate when only the "
                             "policy is wanted); a later stage that needs one of them fails naming it")
    cfg, rest = configs.from_argv(argv)
    args = parser.parse_args(rest)
    skip = {s for s in args.skip.split(",") if s}
    unknown = skip - {s.name for s in STAGES}
    if unknown:
        raise UsageError(f"--skip: unknown stage(s) {', '.join(sorted(unknown))}; stages: "
                         f"{', '.join(s.name for s in STAGES)}")
    if args.parallel < 0:
        raise UsageError(f"--parallel must be >= 0, got {args.parallel}")
    if args.parallel and cfg.mesh.distributed:
        raise UsageError("--parallel runs stages as separate processes on one host; a multi-process job "
                         "(mesh.distributed) runs its stages one after another")
    if not args.parallel:
        distributed.initialize(cfg.mesh)  # once for every stage (their entry points' run() leave process setup to main)
    # what the report names as the config: its experiment:variant and the dotted overrides given
    name = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--config"),
                next((a.split("=", 1)[1] for a in argv if a.startswith("--config=")), configs.DEFAULT))
    overrides = [a for a in argv if a.startswith("--") and a.split("=", 1)[0][2:].split(".")[0]
                 in cfg.__dataclass_fields__ and "=" in a and not a.startswith("--workdir")]
    only = set(args.only.split(",")) if args.only else None
    if only and only - {s.name for s in STAGES}:
        raise UsageError(f"--only: unknown stage(s) {', '.join(sorted(only - {s.name for s in STAGES}))}")
    launch = stage_launcher(argv, cfg.workdir) if args.parallel else None
    return run(cfg, stop_after=args.stop_after, skip=skip, only=only, restart=args.restart, cfg_name=name,
               overrides=overrides, launch=launch, max_running=args.parallel)


def stage_launcher(argv: Sequence[str], workdir: str):
    """``launch(stage) -> Popen`` for ``--parallel``: this command again with ``--only STAGE`` (its
    output to ``<workdir>/logs/<stage>.log``). Each process is its own JAX runtime, so a GPU is shared
    by allocating on demand (``XLA_PYTHON_CLIENT_PREALLOCATE=false`` unless set) instead of each
    process reserving 75% of it."""
    base = without_flags(argv, {"--parallel": True, "--only": True, "--restart": False})

    def launch(stage: Stage) -> subprocess.Popen:
        os.makedirs(os.path.join(workdir, "logs"), exist_ok=True)
        env = dict(os.environ)
        env.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
        with open(os.path.join(workdir, "logs", f"{stage.name}.log"), "w") as log:
            return subprocess.Popen([sys.executable, "-m", "train.pipeline", *base, "--only", stage.name],
                                    stdout=log, stderr=subprocess.STDOUT, env=env)

    return launch


def run(cfg, *, stop_after: str = "", skip: Collection[str] = (), only: set[str] | None = None,
        restart: bool = False, cfg_name: str = configs.DEFAULT, overrides: Sequence[str] = (),
        launch=None, max_running: int = 2) -> dict:
    """Runs the stages in ``cfg.workdir`` (finished ones are skipped); returns every stage's results.

    Args:
      cfg: the experiment config.
      stop_after: the last stage to run (empty: all).
      skip: stages left out of this run.
      only: the stages to run now (others are left for later; refused if one of these needs one of
        them); ``None``: all.
      launch: ``launch(stage) -> subprocess.Popen`` (:func:`stage_launcher`): run each stage in its own
        process, ``max_running`` at a time, as soon as its needs are done
        (:func:`train.run_stages_parallel`); ``None``: in this process, in order.
      restart: discard the work dir's finished stages first.
      cfg_name, overrides: the ``experiment:variant`` and dotted overrides the config came from, for the report.
    """
    workdir = cfg.workdir
    if restart and os.path.isdir(os.path.join(workdir, "stages")):
        import shutil

        shutil.rmtree(workdir)
    check_workdir_config(cfg, workdir)
    ctx = Context(cfg=cfg, workdir=workdir, cfg_name=cfg_name, overrides=list(overrides))
    start = time.perf_counter()
    stages = STAGES
    if stop_after:
        stages = STAGES[:[s.name for s in STAGES].index(stop_after) + 1]
    if skip:
        stages = [s for s in stages if s.name not in skip]
    if launch is not None:
        if only is not None:
            raise ValueError("run: give either only or launch (each launched process runs one stage with --only)")
        results = run_stages_parallel(stages, ctx, launch, max_running=max_running)
    else:
        results = run_stages(stages, ctx, only=only)
    if stages is STAGES:
        print(f"[pipeline] {cfg.name}: all stages done in {time.perf_counter() - start:.1f} s; "
              f"report: {os.path.join(workdir, 'report.md')}")
    else:
        print(f"[pipeline] {cfg.name}: stages up to {stop_after} done in {time.perf_counter() - start:.1f} s")
    return results


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
