"""Runs every GPU benchmark, one subprocess each (with a time limit), then refreshes the README table.

    python -m benchmarks.run_all                     # all
    python -m benchmarks.run_all --only dit,vae      # a subset

Each benchmark merges its own keys into ``benchmarks/results/latest.json``; a failing or timed-out
benchmark is reported and the others still run.
"""

from __future__ import annotations

import subprocess
import sys
import time

from sword_jax import cli

BENCHMARKS = {
    "dit": ["benchmarks.bench_dit_train", "--layers", "8", "--batch", "96", "--remat", "dots", "--levers",
            "--skip-small", "--iters", "5"],
    # The full 30-layer model needs more than 80 GB at any batch worth timing: one H200.
    "dit_full": ["benchmarks.bench_dit_train", "--layers", "30", "--batch", "16", "--remat", "dots", "--sweep",
                 "30x24xdots,30x64xfull", "--skip-small", "--iters", "4"],
    "dlb": ["benchmarks.bench_dlb"],
    "vae": ["benchmarks.bench_vae", "--batch", "1,4", "--iters", "5", "--forms", "conv3d/repeat,conv3d/subpixel"],
    "rollout": ["benchmarks.bench_imagined_rollout", "--layers", "30", "--skip-small"],
    "rollout_width": ["benchmarks.bench_imagined_rollout"],
    "grpo_step": ["benchmarks.bench_grpo_step"],  # sword:small's GRPO step: before / fast / light decoder
    "sim": ["benchmarks.bench_sim", "--episodes", "5"],
    "render": ["benchmarks.render_speed", "--envs", "256", "--res", "64", "128"],
}


def main(argv: list[str] | None = None) -> None:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(BENCHMARKS))
    parser.add_argument("--timeout", type=int, default=600, help="seconds per benchmark")
    args = parser.parse_args(argv)
    for name in args.only.split(","):
        start = time.time()
        print(f"=== {name}", flush=True)
        try:
            code = subprocess.run([sys.executable, "-m", *BENCHMARKS[name]], timeout=args.timeout).returncode
        except subprocess.TimeoutExpired:
            code = "timeout"
        print(f"=== {name}: exit {code} after {time.time() - start:.0f} s", flush=True)
    subprocess.run([sys.executable, "-m", "benchmarks.report"])


if __name__ == "__main__":
    cli.run(main)
