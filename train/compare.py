"""The paper's three comparisons, each over several seeds, as one table of means and spreads.

    python -m train.compare --size small --seeds 0,1,2 --out runs/compare       # one GPU, hours
    python -m train.compare --size tiny --seeds 0 --out /tmp/compare              # CPU smoke run

1. DLB (linear, direct, all) vs teacher forcing: long-horizon LPIPS / FID / FVD / FloLPIPS on
   LIBERO-Original and LIBERO-Mixed.
2. Style augmentation vs none: the same metrics on LIBERO-Mixed.
3. GRPO inside the Sword world model vs inside a WoVR-config world model (teacher forcing +
   context noise, no augmentation): policy success in the simulator over GRPO steps.

Every run is ``train.pipeline`` in ``<out>/<run>/seed<k>`` (resumable, so an interrupted
comparison continues); the table goes to ``<out>/comparison.md`` and ``<out>/comparison.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

import numpy as np

METRICS = ("lpips", "fid", "fvd", "flolpips")


def runs_for(size: str) -> dict[str, tuple[str, list[str]]]:
    """Run name -> (config name, extra overrides)."""
    prefix = "" if size == "tiny" else f"{size}-"
    return {
        "sword": (f"cache_ablation:{prefix}linear-direct-all", []),
        "teacher_forcing": (f"cache_ablation:{prefix}tf", []),
        "no_augmentation": (f"cache_ablation:{prefix}linear-direct-all", ["--augment.enabled=false"]),
        "wovr": (f"cache_ablation:{prefix}wovr", []),
    }


COMPARISONS = (
    ("DLB vs teacher forcing", "sword", "teacher_forcing", ("original", "mixed")),
    ("style augmentation vs none", "sword", "no_augmentation", ("mixed",)),
    ("GRPO in Sword vs in WoVR", "sword", "wovr", ()),
)


def _mean_std(values: list[float]) -> dict[str, float]:
    arr = np.asarray(values, np.float64)
    return {"mean": float(arr.mean()), "std": float(arr.std(ddof=1)) if arr.size > 1 else 0.0, "n": int(arr.size)}


def aggregate(results: dict[str, list[dict]]) -> dict:
    """``{run: [results.json per seed]}`` -> per run: metric means/spreads per split, success curve."""
    table = {}
    for run, per_seed in results.items():
        entry: dict = {"metrics": {}, "success": {}}
        for split in ("original", "mixed"):
            for metric in METRICS:
                values = [next(iter(r["stages"]["evaluate"]["metrics"][split].values()))[metric]
                          for r in per_seed if split in r["stages"].get("evaluate", {}).get("metrics", {})]
                if values:
                    entry["metrics"][f"{split}/{metric}"] = _mean_std(values)
        points: dict[str, list[float]] = {}
        for r in per_seed:
            for label, value in r["stages"].get("policy", {}).get("success", {}).items():
                points.setdefault(label, []).append(value)
        entry["success"] = {label: _mean_std(v) for label, v in points.items()}
        table[run] = entry
    return table


def to_markdown(table: dict, seeds: Sequence[int]) -> str:
    lines = [f"# Sword comparisons ({len(seeds)} seeds: {', '.join(map(str, seeds))}; mean ± std)", ""]
    for title, ours, baseline, splits in COMPARISONS:
        lines += [f"## {title}", ""]
        if splits:
            keys = [f"{s}/{m}" for s in splits for m in METRICS]
            lines += ["| run | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
            for run in (ours, baseline):
                cells = [f"{table[run]['metrics'][k]['mean']:.4g} ± {table[run]['metrics'][k]['std']:.2g}"
                         if k in table.get(run, {}).get("metrics", {}) else "" for k in keys]
                lines.append(f"| {run} | " + " | ".join(cells) + " |")
        else:
            labels = sorted({l for run in (ours, baseline) for l in table.get(run, {}).get("success", {})},
                            key=lambda l: int(l.rsplit(" ", 1)[-1]))
            lines += ["| run | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
            for run in (ours, baseline):
                success = table.get(run, {}).get("success", {})
                lines.append(f"| {run} | " + " | ".join(
                    f"{success[l]['mean']:.3f} ± {success[l]['std']:.2g}" if l in success else "" for l in labels) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--out", default="runs/compare")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    from train import pipeline

    results: dict[str, list[dict]] = {}
    for run, (config, extra) in runs_for(args.size).items():
        for seed in seeds:
            workdir = os.path.join(args.out, run, f"seed{seed}")
            pipeline.main(["--config", config, f"--seed={seed}", f"--workdir={workdir}", *extra])
            with open(os.path.join(workdir, "results.json")) as f:
                results.setdefault(run, []).append(json.load(f))
    table = aggregate(results)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "comparison.json"), "w") as f:
        json.dump({"seeds": seeds, "size": args.size, "runs": table}, f, indent=1)
    with open(os.path.join(args.out, "comparison.md"), "w") as f:
        f.write(to_markdown(table, seeds))
    print(to_markdown(table, seeds))
    return table


if __name__ == "__main__":
    main()
