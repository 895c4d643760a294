"""The main job's stages: the whole Sword method on one config, each stage resumable.

:func:`run_pipeline` is what ``python -m train.pipeline`` runs (its docstring lists the stages) and what
``train.compare`` runs for each slice. Each stage writes ``<workdir>/stages/<name>.json`` and is skipped
when already done; a stage calls the orchestration function of its part (``sim.vae_training.run_vae``,
``sword_jax.pipeline.world_model.run_world_model``, ...) with the pipeline's typed config, never an
entry point. With ``launch`` (:func:`stage_launcher`) each stage runs in its own process,
``python -m train.pipeline ... --only STAGE``, as soon as the stages it reads are done.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from collections.abc import Collection, Sequence

from configs import DEFAULT
from sword_jax.pipeline.stages import (Context, Stage, check_order, check_workdir_config, run_stages,
                                       run_stages_parallel, without_flags)


def stage_data(ctx: Context) -> dict:
    from sim import data_stages

    return data_stages.generate_expert_data(ctx)


def stage_vae(ctx: Context) -> dict:
    from sim import vae_training

    workdir = ctx.stage_dir("vae_run")
    summary = vae_training.run_vae(ctx.cfg_in(workdir), [ctx.results["data"]["train"]["path"]])
    summary["path"] = os.path.join(workdir, "vae")
    return summary


def stage_latents(ctx: Context) -> dict:
    from sim import data_stages

    return data_stages.encode_training_latents(ctx)


def stage_light_decoder(ctx: Context) -> dict:
    """The light rollout decoder, distilled from the VAE on the world model's training latents, when GRPO's
    imagined frames come from it (``rl.imagined.decoder=light``); else nothing to do."""
    if ctx.cfg.rl.imagined.decoder != "light":
        return {"path": "", "skipped": f"rl.imagined.decoder={ctx.cfg.rl.imagined.decoder}"}
    from sword_jax.pipeline import light_decoder

    workdir = ctx.stage_dir("light_decoder")
    return light_decoder.run_light_decoder(ctx.cfg_in(workdir), vae=ctx.results["vae"]["path"],
                                           latents=ctx.results["latents"]["path"])


def stage_world_model(ctx: Context) -> dict:
    from sword_jax.pipeline import world_model

    workdir = ctx.stage_dir("world_model")
    latents = ctx.results["latents"]
    data = dataclasses.replace(ctx.cfg.data, path=latents["path"],
                               heldout_path=ctx.cfg.data.heldout_path or latents.get("heldout_path", ""))
    summary = world_model.run_world_model(ctx.cfg_in(workdir, data=data))
    return {"workdir": workdir, "final_step": summary["step"], "final_metrics": summary["metrics"],
            "first_loss": _first_logged(os.path.join(workdir, "metrics.jsonl"), "loss")}


def stage_probe(ctx: Context) -> dict:
    from sim import probe_training

    return probe_training.run_probe(ctx.cfg, [ctx.results["data"]["train"]["path"]], ctx.stage_dir("probe"),
                                    probe_training.probe_config(ctx.cfg))


def stage_evaluate(ctx: Context) -> dict:
    from sim import world_model_eval
    from sim import data_stages

    splits = data_stages.write_eval_splits(ctx)
    inputs = world_model_eval.EvalInputs(
        models={ctx.cfg.name: ctx.results["world_model"]["workdir"]}, episodes=splits, out=ctx.stage_dir("eval"),
        vae_checkpoint=ctx.results["vae"]["path"],
        probe=ctx.results.get("probe", {}).get("path") or "",  # skipped stages: none
        reward_model=ctx.results.get("reward_model", {}).get("path") or "")
    summary = world_model_eval.run_evaluation(ctx.cfg, inputs)
    return {"report": summary["report"], "splits": splits, "metrics": data_stages.read_eval_results(summary["out"])}


def stage_reward_model(ctx: Context) -> dict:
    from sim import policy_stages

    return policy_stages.reward_model(ctx)


def stage_sft_policy(ctx: Context) -> dict:
    from sim import policy_stages

    return policy_stages.sft_policy(ctx)


def stage_policy(ctx: Context) -> dict:
    from sim import policy_stages

    return policy_stages.grpo_in_world_model(ctx)


def stage_report(ctx: Context) -> dict:
    from sword_jax.pipeline import report

    return report.write(ctx)


def stage_policy_data(ctx: Context) -> dict:
    from sim import data_stages

    return data_stages.generate_policy_rollouts(ctx)


STAGES = [
    Stage("data", stage_data, "expert demonstrations (train + held-out) in LIBERO's HDF5 layout"),
    # The supervised policy needs only the demonstrations; it comes early so that its own rollouts
    # (successes and failures, data.policy_rollouts_per_task) can join the world model's training data.
    Stage("sft_policy", stage_sft_policy, "the supervised (behaviour-cloned) VLA policy", needs=("data",)),
    Stage("policy_data", stage_policy_data, "the supervised policy's own rollouts for the world model (if enabled)",
          needs=("data", "sft_policy")),
    Stage("vae", stage_vae, "the video VAE (trained from scratch; or vae.checkpoint: official Wan 2.2 weights, a "
                            "trained VAE)", needs=("data",)),
    Stage("latents", stage_latents, "encode training episodes and their styled copies to latents",
          needs=("data", "policy_data", "vae")),
    Stage("light_decoder", stage_light_decoder,
          "distil the light rollout decoder from the VAE (with rl.imagined.decoder=light)", needs=("vae", "latents")),
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
          needs=("data", "sft_policy", "vae", "light_decoder", "world_model", "reward_model")),
    Stage("report", stage_report, "report.md and results.json",
          needs=("data", "sft_policy", "policy_data", "vae", "latents", "light_decoder", "world_model", "probe",
                 "reward_model", "evaluate", "policy")),
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


def _donor_config(donor: str, workdir: str) -> dict:
    """The config a donor work dir (``--adopt``) was made with, or a :class:`UsageError` naming the problem."""
    import json

    from sword_jax.cli import UsageError

    if os.path.abspath(donor) == os.path.abspath(workdir):
        raise UsageError(f"--adopt {donor}: that is this run's own work dir")
    path = os.path.join(donor, "config.json")
    if not os.path.isfile(path):
        raise UsageError(f"--adopt {donor}: no config.json there (not a train.pipeline work dir)")
    try:
        with open(path) as f:
            return json.load(f)
    except ValueError as error:
        raise UsageError(f"--adopt {donor}: its config.json is not JSON ({error})") from None


def run_pipeline(cfg, *, stop_after: str = "", skip: Collection[str] = (), only: set[str] | None = None,
                 restart: bool = False, cfg_name: str = DEFAULT, overrides: Sequence[str] = (),
                 launch=None, max_running: int = 2, adopt: str = "") -> dict:
    """Runs the stages in ``cfg.workdir`` (finished ones are skipped); returns every stage's results.

    Args:
      cfg: the experiment config.
      stop_after: the last stage to run (empty: all).
      skip: stages left out of this run.
      only: the stages to run now (others are left for later; refused if one of these needs one of
        them); ``None``: all.
      launch: ``launch(stage) -> subprocess.Popen`` (:func:`stage_launcher`): run each stage in its own
        process, ``max_running`` at a time, as soon as its needs are done
        (:func:`sword_jax.pipeline.stages.run_stages_parallel`); ``None``: in this process, in order.
      restart: discard the work dir's finished stages first.
      cfg_name, overrides: the ``experiment:variant`` and dotted overrides the config came from, for the report.
      adopt: a donor pipeline work dir: its finished stages whose config sections agree with ``cfg``'s
        (:func:`sword_jax.pipeline.compare.adopt_stages`) count as this work dir's, their files left where they are.
    """
    workdir = cfg.workdir
    donor_cfg = _donor_config(adopt, workdir) if adopt else None  # refused before anything is touched
    if restart and os.path.isdir(os.path.join(workdir, "stages")):
        import shutil

        shutil.rmtree(workdir)
    check_workdir_config(cfg, workdir)
    if adopt:
        from sword_jax.pipeline.compare import adopt_stages

        adopted = adopt_stages(workdir, adopt, cfg, donor_cfg)
        print(f"[pipeline] adopted from {adopt}: {', '.join(adopted) or 'no stage (none finished there with this config)'}")
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
