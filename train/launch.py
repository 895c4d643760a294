"""Runs a trainer as one process per GPU on one host, the processes joined by ``jax.distributed``.

Usage::

    python -m train.launch --processes 4 -- python -m train.train_world_model --config sword:small \\
        --mesh.distributed=true --workdir runs/wm
    python -m train.launch --processes 2 --cpu-devices 2 --log-dir logs -- python -m train.train_world_model \\
        --config sword:tiny --synthetic --mesh.distributed=true --workdir runs/wm-tiny

Rank ``i`` gets ``JAX_COORDINATOR_ADDRESS`` (127.0.0.1 and a free port), ``JAX_NUM_PROCESSES``,
``JAX_PROCESS_ID=i`` and ``CUDA_VISIBLE_DEVICES`` = the ``i``-th of ``--gpus`` (default: the first
``--processes`` GPUs this process sees); ``--cpu-devices K`` runs each rank on ``K`` CPU devices
instead. NVLink multicast stays off in every rank. Each rank's output lines come out prefixed
``[rank i]`` (and go to ``--log-dir``/rank<i>.log too). The exit status is 0 when every rank exited 0.

When a rank fails (a non-zero status, or killed), the others get SIGTERM and, after ``--grace``
seconds (default 10), SIGKILL: the launcher exits within ``--grace`` + 2 s of the failure, non-zero,
naming the rank that failed first. Rerunning the same command resumes from the last checkpoint. The
body is :func:`sword_jax.pipeline.launch.launch`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from sword_jax.cli import ArgumentParser, UsageError
from sword_jax.pipeline import launch as launcher

# The entry points that join a jax.distributed job (their main calls train.distributed.initialize).
JOINING = ("train.grpo", "train.pipeline", "train.train_light_decoder", "train.train_vae", "train.train_world_model")


def _parse(argv: Sequence[str]):
    argv = list(argv)
    split = argv.index("--") if "--" in argv else len(argv)
    own, command = argv[:split], argv[split + 1:]
    parser = ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, required=True, help="processes (ranks) to start, one per GPU")
    parser.add_argument("--gpus", type=launcher.parse_gpus, default=None,
                        help="comma-separated GPU of each rank (default: the first --processes GPUs visible)")
    parser.add_argument("--cpu-devices", type=int, default=None,
                        help="run each rank on this many CPU devices instead of one GPU (gloo collectives)")
    parser.add_argument("--log-dir", default=None, help="also write each rank's output to DIR/rank<i>.log")
    parser.add_argument("--grace", type=float, default=launcher.DEFAULT_GRACE_S,
                        help="seconds from SIGTERM to SIGKILL when a rank fails (default %(default)s)")
    parser.add_argument("--port", type=int, default=None, help="coordinator port on 127.0.0.1 (default: a free one)")
    args, unknown = parser.parse_known_args(own)
    if unknown and command:
        raise UsageError(f"unrecognized arguments before --: {' '.join(unknown)} (see --help)")
    if not command:
        raise UsageError("give the command after --, e.g. python -m train.launch --processes 4 -- "
                         "python -m train.train_world_model ... --mesh.distributed=true")
    if args.processes < 1 or (args.cpu_devices is not None and args.cpu_devices < 1) or args.grace < 0:
        raise UsageError("--processes and --cpu-devices must be >= 1 and --grace >= 0")
    module = command[command.index("-m") + 1] if "-m" in command[:-1] else ""
    if module.startswith("train.") and (module not in JOINING or "--mesh.distributed=true" not in command):
        # otherwise each rank would train alone in the same work dir
        raise UsageError(f"{module} does not join one multi-process job: run one of {', '.join(JOINING)} "
                         "with --mesh.distributed=true")
    gpus = args.gpus
    if gpus is not None and len(gpus) < args.processes:
        raise UsageError(f"--gpus names {len(gpus)} GPUs for {args.processes} processes")
    return args, command, gpus


def main(argv: Sequence[str] | None = None) -> int:
    """Launches the ranks and waits for them; returns the job's exit status."""
    args, command, gpus = _parse(sys.argv[1:] if argv is None else argv)
    result = launcher.launch(command, args.processes, gpus=gpus, cpu_devices=args.cpu_devices,
                             log_dir=args.log_dir, grace_s=args.grace, port=args.port)
    return result.returncode


if __name__ == "__main__":
    from sword_jax import cli

    # ``--debug`` is the launcher's only before ``--``; after it, it belongs to the command
    full = sys.argv[1:]
    cut = full.index("--") if "--" in full else len(full)
    cli.run(lambda own: main([*own, *full[cut:]]), full[:cut])
