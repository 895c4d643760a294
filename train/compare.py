"""The paper's three comparisons, each over several seeds, as one table of means and spreads.

    python -m train.compare --size small --seeds 0,1,2 --out runs/compare       # one GPU, hours
    python -m train.compare --size tiny --seeds 0 --out /tmp/compare              # CPU smoke run
    python -m train.compare --size small --trainer.steps=2000                     # overrides apply to every run

1. DLB (linear, direct, all) vs teacher forcing: long-horizon LPIPS / FID / FVD / FloLPIPS on
   LIBERO-Original and LIBERO-Mixed.
2. Style augmentation vs none: the same metrics on LIBERO-Mixed.
3. GRPO inside the Sword world model vs inside a WoVR-config world model (teacher forcing +
   context noise, no augmentation): policy success in the simulator over GRPO steps.

Every run is ``train.pipeline`` in ``<out>/<run>/seed<k>`` (resumable, so an interrupted
comparison continues); the table goes to ``<out>/comparison.md`` and ``<out>/comparison.json``.

What the runs share. The seeds vary what is compared: world-model training (initialisation, batch
order, DLB reads) and GRPO. Stages that do not depend on the compared choice are made once, by the
first run at the first seed, and adopted by the others when their config sections agree: expert
data and held-out episodes (so every run is scored on the same episodes), the VAE, the encoded
latents (per augmentation setting), the reward model and the supervised policy. Runs outside
comparison 3 stop after the evaluation. ``--no-share`` makes every run from scratch.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence

import numpy as np

from sword_jax.cli import ArgumentParser, UsageError

METRICS = ("lpips", "fid", "fvd", "flolpips", "psnr", "ssim")  # psnr / ssim need no network weights


def runs_for(size: str) -> dict[str, tuple[str, list[str]]]:
    """Run name -> (config name, extra overrides)."""
    prefix = "" if size == "tiny" else f"{size}-"
    return {
        "sword": (f"cache_ablation:{prefix}linear-direct-all", []),
        "teacher_forcing": (f"cache_ablation:{prefix}tf", []),
        "no_augmentation": (f"cache_ablation:{prefix}linear-direct-all", ["--augment.enabled=false"]),
        "wovr": (f"cache_ablation:{prefix}wovr", []),
    }


# Stage -> the config sections its result depends on (beyond the seed, which only the first seed's run uses).
SHAREABLE = {
    "data": ("sim", "data", "eval"),
    "vae": ("sim", "data", "vae"),
    "latents": ("sim", "data", "vae", "augment"),
    "reward_model": ("sim", "data", "rl"),
    "sft_policy": ("sim", "data", "rl"),
}


def adopt_stages(workdir: str, donor: str, cfg, donor_cfg, stages: Sequence[str] = tuple(SHAREABLE)) -> list[str]:
    """Copies the donor run's finished-stage records into ``workdir`` where the config sections agree.

    The records point at the donor's files, so nothing is copied but the small JSON markers. A stage
    ``workdir`` has already finished is left alone. Returns the stages adopted.
    """
    import shutil

    from configs.cli import to_dict

    mine, theirs = to_dict(cfg), to_dict(donor_cfg)
    adopted = []
    os.makedirs(os.path.join(workdir, "stages"), exist_ok=True)
    for stage in stages:
        source = os.path.join(donor, "stages", f"{stage}.json")
        target = os.path.join(workdir, "stages", f"{stage}.json")
        if os.path.exists(target) or not os.path.exists(source):
            continue
        if any(mine[section] != theirs[section] for section in SHAREABLE[stage]):
            continue
        shutil.copyfile(source, target)
        adopted.append(stage)
    return adopted


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


def _cell(entry: dict, seeds: int, fmt: str) -> str:
    text = fmt.format(entry["mean"])
    if entry["n"] > 1:
        text += f" ± {entry['std']:.2g}"
    return text if entry["n"] >= seeds else f"{text} (n={entry['n']})"


def to_markdown(table: dict, seeds: Sequence[int]) -> str:
    lines = [f"# Sword comparisons ({len(seeds)} seeds: {', '.join(map(str, seeds))}; mean ± std over the seeds "
             "finished, with n where fewer than all finished)", ""]
    for title, ours, baseline, splits in COMPARISONS:
        lines += [f"## {title}", ""]
        if splits:
            keys = [f"{s}/{m}" for s in splits for m in METRICS]
            lines += ["| run | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
            for run in (ours, baseline):
                cells = [_cell(table[run]["metrics"][k], len(seeds), "{:.4g}")
                         if k in table.get(run, {}).get("metrics", {}) else "" for k in keys]
                lines.append(f"| {run} | " + " | ".join(cells) + " |")
        else:
            labels = sorted({l for run in (ours, baseline) for l in table.get(run, {}).get("success", {})},
                            key=lambda l: int(l.rsplit(" ", 1)[-1]))
            lines += ["| run | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
            for run in (ours, baseline):
                success = table.get(run, {}).get("success", {})
                lines.append(f"| {run} | " + " | ".join(
                    _cell(success[l], len(seeds), "{:.3f}") if l in success else "" for l in labels) + " |")
        lines.append("")
    return "\n".join(lines)


def write_tables(out: str, results: dict[str, list[dict]], seeds: Sequence[int], **extra) -> dict:
    """Writes ``comparison.{json,md}`` for the runs finished so far (rewritten after every run)."""
    table = aggregate(results)
    os.makedirs(out, exist_ok=True)
    finished = {run: len(per_seed) for run, per_seed in results.items()}
    with open(os.path.join(out, "comparison.json"), "w") as f:
        json.dump({"seeds": list(seeds), "finished_seeds_per_run": finished, **extra, "runs": table}, f, indent=1)
    with open(os.path.join(out, "comparison.md"), "w") as f:
        f.write(to_markdown(table, seeds))
    return table


def _needs_policy(run: str) -> bool:
    return any(run in (ours, baseline) for _, ours, baseline, splits in COMPARISONS if not splits)


def main(argv: Sequence[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__.splitlines()[0],
                            epilog="Any other --SECTION.KEY=VALUE is a config override applied to every run.")
    parser.add_argument("--size", default="small", choices=("tiny", "small", "paper"))
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--out", default="runs/compare")
    parser.add_argument("--no-share", action="store_true", help="make every stage of every run from scratch")
    parser.add_argument("--runs", default="", help="comma-separated subset of runs (default: all four)")
    # Anything else is a dotted config override applied to every run, e.g. --trainer.steps=2000.
    args, overrides = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    bad = [a for a in overrides if not (a.startswith("--") and "." in a.split("=", 1)[0] and "=" in a)]
    if bad:
        raise UsageError(f"not a dotted config override (--section.key=value): {bad}")
    seeds = [int(s) for s in args.seeds.split(",")]
    import time

    import configs
    from train import pipeline

    runs = runs_for(args.size)
    if args.runs:
        missing = sorted(set(args.runs.split(",")) - set(runs))
        if missing:
            raise UsageError(f"unknown runs {missing}; known: {sorted(runs)}")
        runs = {name: runs[name] for name in args.runs.split(",")}
    results: dict[str, list[dict]] = {}
    timings: dict[str, list[float]] = {}
    donors: list[tuple[str, object]] = []  # (workdir, config) of finished runs, first seed first
    for seed in seeds:
        for run, (config, extra) in runs.items():
            workdir = os.path.join(args.out, run, f"seed{seed}")
            argv_run = ["--config", config, f"--seed={seed}", f"--workdir={workdir}", *extra, *overrides]
            cfg, _ = configs.from_argv(argv_run)
            if not args.no_share:
                for donor, donor_cfg in donors:
                    adopted = adopt_stages(workdir, donor, cfg, donor_cfg)
                    if adopted:
                        print(f"[compare] {run} seed {seed}: adopts {', '.join(adopted)} from {donor}")
            start = time.perf_counter()
            stages = pipeline.main(argv_run + ([] if _needs_policy(run) else ["--stop-after", "evaluate"]))
            timings.setdefault(run, []).append(time.perf_counter() - start)
            donors.append((workdir, cfg))
            results.setdefault(run, []).append({"stages": stages})
            table = write_tables(args.out, results, seeds, size=args.size, overrides=overrides, timings=timings)
    print(to_markdown(table, seeds))
    return table


if __name__ == "__main__":
    from sword_jax.cli import run

    run(main)
