"""Runs every GPU benchmark, one subprocess each (with a time limit), then refreshes the README table.

    python -m benchmarks.run_all                     # all
    python -m benchmarks.run_all --only dit,vae      # a subset

Each benchmark merges its own keys into ``benchmarks/results/latest.json``; a failing or timed-out
benchmark is reported and the others still run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

BENCHMARKS = {
    "dit": ["benchmarks.bench_dit_train", "--sweep", "8x96xdots,12x64xdots,8x128xdots", "--iters", "6"],
    "dlb": ["benchmarks.bench_dlb"],
    "vae": ["benchmarks.bench_vae"],
    "rollout": ["benchmarks.bench_imagined_rollout"],
    "sim": ["benchmarks.bench_sim", "--episodes", "5"],
    "render": ["benchmarks.render_speed", "--envs", "256", "--res", "64", "128"],
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default=",".join(BENCHMARKS))
    parser.add_argument("--timeout", type=int, default=300, help="seconds per benchmark")
    args = parser.parse_args()
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
    main()
