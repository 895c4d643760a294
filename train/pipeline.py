"""The main job: the whole Sword method on one config, each stage resumable.

    python -m train.pipeline                                   # tiny default config, CPU, minutes
    python -m train.pipeline --config sword:small --workdir runs/small
    python -m train.pipeline --config cache_ablation:wovr --workdir runs/wovr --vae.checkpoint=Wan2.2_VAE.safetensors

Stages (each writes ``<workdir>/stages/<name>.json`` and is skipped when already done):
expert data (train + held-out) -> VAE (trained, or official Wan 2.2 weights) -> latents (with
styled copies) -> light rollout decoder (with ``rl.imagined.decoder=light``) -> world model (DLB or the configured variant) -> state probe -> reward model ->
long-horizon evaluation on LIBERO-Original / LIBERO-Mixed (pixel metrics, and action following
read by the probe and the reward model) -> supervised policy -> GRPO inside the world model
with policy evaluation in the simulator -> report. ``--stop-after STAGE`` ends a run early (the
finished stages stay, so a later run continues from there). Writes ``report.md`` and ``results.json``.
``--parallel 2`` runs each stage in its own process, two at a time, each as soon as the stages it
reads are done: the VAE trains while the policy is cloned and rolled out, the success detector
while the world model trains (the same results: a stage reads only the stages it needs).
``--adopt DONOR`` takes over another work dir's finished stages where the config sections they read agree, so
that a second world model (another training rule, e.g. ``--cache.enabled=false``) trains on the first's data, VAE
and latents: ``python -m train.pipeline --config sword:small --cache.enabled=false --workdir runs/tf --adopt
runs/small --only world_model``.
"""

from __future__ import annotations

import sys
from collections.abc import Collection, Sequence

import configs
from sim import pipeline_stages
from sword_jax.cli import UsageError
from train import distributed


def main(argv: Sequence[str] | None = None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    names = [s.name for s in pipeline_stages.STAGES]
    parser = configs.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--restart", action="store_true", help="discard finished stages of this work dir")
    parser.add_argument("--only", default="", help="comma-separated stages to run now (the rest are left for a later "
                                                   "run; refused if one of them needs a stage that has not run)")
    parser.add_argument("--parallel", type=int, default=0, metavar="N",
                        help="run each stage in its own process, up to N at a time, a stage as soon as the stages "
                             "it needs are done (the VAE trains while the policy is cloned and rolled out); "
                             "logs in <workdir>/logs/<stage>.log. 0 (default): one after another, in this process")
    parser.add_argument("--stop-after", default="", choices=["", *names],
                        help="end after this stage (finished stages are kept; a later run continues)")
    parser.add_argument("--skip", default="",
                        help="comma-separated stages to leave out of this run (e.g. probe,evaluate when only the "
                             "policy is wanted); a later stage that needs one of them fails naming it")
    parser.add_argument("--adopt", default="", metavar="DONOR",
                        help="another pipeline work dir whose finished stages this one takes over where the config "
                             "sections they read agree (data, VAE, latents, policy data, supervised policy, detector: "
                             "sword_jax.pipeline.compare.SHAREABLE), e.g. a second world model on the first's latents")
    cfg, rest = configs.from_argv(argv)
    args = parser.parse_args(rest)
    skip = {s for s in args.skip.split(",") if s}
    unknown = skip - set(names)
    if unknown:
        raise UsageError(f"--skip: unknown stage(s) {', '.join(sorted(unknown))}; stages: "
                         f"{', '.join(names)}")
    if args.parallel < 0:
        raise UsageError(f"--parallel must be >= 0, got {args.parallel}")
    if args.parallel and cfg.mesh.distributed:
        raise UsageError("--parallel runs stages as separate processes on one host; a multi-process job "
                         "(mesh.distributed) runs its stages one after another")
    if not args.parallel:
        distributed.initialize(cfg.mesh)  # once for every stage (the stages leave process setup to main)
    # what the report names as the config: its experiment:variant and the dotted overrides given
    name = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--config"),
                next((a.split("=", 1)[1] for a in argv if a.startswith("--config=")), configs.DEFAULT))
    overrides = [a for a in argv if a.startswith("--") and a.split("=", 1)[0][2:].split(".")[0]
                 in cfg.__dataclass_fields__ and "=" in a and not a.startswith("--workdir")]
    only = set(args.only.split(",")) if args.only else None
    if only and only - set(names):
        raise UsageError(f"--only: unknown stage(s) {', '.join(sorted(only - set(names)))}")
    launch = pipeline_stages.stage_launcher(argv, cfg.workdir) if args.parallel else None
    return run(cfg, stop_after=args.stop_after, skip=skip, only=only, restart=args.restart, cfg_name=name,
               overrides=overrides, launch=launch, max_running=args.parallel, adopt=args.adopt)


def run(cfg, *, stop_after: str = "", skip: Collection[str] = (), only: set[str] | None = None,
        restart: bool = False, cfg_name: str = configs.DEFAULT, overrides: Sequence[str] = (),
        launch=None, max_running: int = 2, adopt: str = "") -> dict:
    """:func:`sim.pipeline_stages.run_pipeline`: runs the stages in ``cfg.workdir``, returns every stage's results."""
    return pipeline_stages.run_pipeline(cfg, stop_after=stop_after, skip=skip, only=only, restart=restart,
                                        cfg_name=cfg_name, overrides=overrides, launch=launch,
                                        max_running=max_running, adopt=adopt)


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
