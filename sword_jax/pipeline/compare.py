"""The comparison's data: the runs, their aggregation over seeds, the markdown and JSON tables, the figures,
and the checks that paired slices share their inputs (``python -m train.compare`` runs the slices,
:mod:`sword_jax.pipeline.slices` describes them; its docstring says what the three comparisons are).

A slice record is plain JSON (``SLICE_FORMAT``); everything here reads such records and the stage
results they came from, never a log.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence

import numpy as np

from sword_jax.metrics.config import EvalConfig
from sword_jax.world_model.config import DataConfig


# psnr / ssim need no network weights; latent_mse is the world model's error before decoding (no VAE
# error in it), probe_ee_cm the state probe's end-effector error on predicted frames (action following)
METRICS = ("lpips", "fid", "fvd", "flolpips", "psnr", "ssim", "latent_mse", "probe_ee_cm", "probe_gripper_agree",
           "reward_agree")
HIGHER_IS_BETTER = frozenset({"psnr", "ssim", "probe_gripper_agree", "reward_agree"})
SLICE_FORMAT = "sword-compare-slice/1"


def runs_for(size: str) -> dict[str, tuple[str, list[str]]]:
    """Run name -> (config name, extra overrides)."""
    prefix = "" if size == "tiny" else f"{size}-"
    return {
        "sword": (f"cache_ablation:{prefix}linear-direct-all", []),
        "teacher_forcing": (f"cache_ablation:{prefix}tf", []),
        "no_augmentation": (f"cache_ablation:{prefix}linear-direct-all", ["--augment.enabled=false"]),
        "wovr": (f"cache_ablation:{prefix}wovr", []),
        # comparison 3's upper reference: GRPO against the MuJoCo environments, from the same supervised policy
        "ground_truth": (f"cache_ablation:{prefix}linear-direct-all", []),
    }


GROUND_TRUTH = "ground_truth"
GROUND_TRUTH_STAGES = ("data", "sft_policy", "policy")  # the policy stage runs GRPO in MuJoCo, not a world model


# Stage -> the config sections its result depends on (beyond the seed, which is --shared-seed for all).
SHAREABLE = {
    "data": ("sim", "data", "eval"),
    "vae": ("sim", "data", "vae", "eval"),
    "latents": ("sim", "data", "vae", "augment", "rl", "eval"),  # rl: the policy's rollouts join the data
    "light_decoder": ("sim", "data", "vae", "augment", "rl", "light_decoder", "eval"),  # distilled on those latents
    "policy_data": ("sim", "data", "rl"),
    "probe": ("sim", "data"),  # the state probe that scores action following, where the pipeline has one
    "reward_model": ("sim", "data", "rl"),
    "sft_policy": ("sim", "data", "rl"),
}
# Settings of those sections that change no result (how the work is spread over processes).
NO_RESULT_KEYS = {"data": DataConfig.result_free_fields}
# What a stage reads of the eval section, the rest being how the evaluation scores: the data stage the held-out
# episodes' count, length and splits; the VAE the LPIPS network of its perceptual loss, and so the stages made from
# the VAE (the latents it encodes, the light decoder distilled from it).
EVAL_READ = {"data": EvalConfig.data_fields, "vae": EvalConfig.perceptual_fields,
             "latents": EvalConfig.perceptual_fields, "light_decoder": EvalConfig.perceptual_fields}


def adopt_stages(workdir: str, donor: str, cfg, donor_cfg, stages: Sequence[str] = tuple(SHAREABLE)) -> list[str]:
    """Copies the donor run's finished-stage records into ``workdir`` where the config sections agree.

    The records point at the donor's files, so nothing is copied but the small JSON markers. A stage
    ``workdir`` has already finished is left alone. ``cfg``/``donor_cfg`` are configs or their
    ``to_dict`` form (a work dir's ``config.json``). Returns the stages adopted.
    """
    import shutil

    from configs.cli import to_dict

    mine = cfg if isinstance(cfg, dict) else to_dict(cfg)
    theirs = donor_cfg if isinstance(donor_cfg, dict) else to_dict(donor_cfg)
    adopted = []
    os.makedirs(os.path.join(workdir, "stages"), exist_ok=True)
    for stage in stages:
        source = os.path.join(donor, "stages", f"{stage}.json")
        target = os.path.join(workdir, "stages", f"{stage}.json")
        if os.path.exists(target) or not os.path.exists(source):
            continue
        if any(_result_settings(mine, section, stage) != _result_settings(theirs, section, stage)
               for section in SHAREABLE[stage]):
            continue
        shutil.copyfile(source, target)
        adopted.append(stage)
    return adopted


def _result_settings(cfg_dict: dict, section: str, stage: str) -> dict:
    """``cfg_dict``'s ``section`` less :data:`NO_RESULT_KEYS` (absent from configs saved before they existed); of the
    eval section only what ``stage`` reads (:data:`EVAL_READ`)."""
    settings = cfg_dict[section]
    if section == "eval":
        return {k: v for k, v in settings.items() if k in EVAL_READ.get(stage, ())}
    return {k: v for k, v in settings.items() if k not in NO_RESULT_KEYS.get(section, ())}


COMPARISONS = (
    ("DLB vs teacher forcing", "sword", "teacher_forcing", ("original", "mixed")),
    ("style augmentation vs none", "sword", "no_augmentation", ("mixed",)),
    ("GRPO in Sword vs in WoVR", "sword", "wovr", ()),
)


# ---- the table: means and spreads over seeds, n per cell ----

def _mean_std(values: list[float]) -> dict[str, float]:
    arr = np.asarray(values, np.float64)
    return {"mean": float(arr.mean()), "std": float(arr.std(ddof=1)) if arr.size > 1 else 0.0, "n": int(arr.size)}


def aggregate(results: dict[str, list[dict]]) -> dict:
    """``{run: [slice record per seed]}`` -> per run: metric means/spreads per split, success curve.

    A record needs ``metrics`` (``{split: {metric: value}}``) and ``success`` (``{label: value}``).
    """
    table = {}
    for run, per_seed in results.items():
        entry: dict = {"metrics": {}, "success": {}}
        for split in ("original", "mixed"):
            for metric in METRICS:
                values = [r["metrics"][split][metric] for r in per_seed
                          if metric in r.get("metrics", {}).get(split, {})]
                if values:
                    entry["metrics"][f"{split}/{metric}"] = _mean_std(values)
        points: dict[str, list[float]] = {}
        for r in per_seed:
            for label, value in r.get("success", {}).items():
                points.setdefault(label, []).append(value)
        entry["success"] = {label: _mean_std(v) for label, v in points.items()}
        table[run] = entry
    return table


def paired(results: dict[str, list[dict]], ours: str, baseline: str, splits: Sequence[str]) -> dict:
    """Per metric, ``ours - baseline`` at every seed both runs finished (the slices share their inputs,
    so a seed's two runs differ only in the compared choice and the seed's own draws): the differences,
    their mean, and at how many seeds ``ours`` was better (lower, or higher for :data:`HIGHER_IS_BETTER`)."""
    by_seed = {run: {r["seed"]: r for r in results.get(run, [])} for run in (ours, baseline)}
    seeds = sorted(set(by_seed[ours]) & set(by_seed[baseline]))
    out = {}
    for split in splits:
        for metric in METRICS:
            pairs = [(seed, by_seed[ours][seed]["metrics"].get(split, {}).get(metric),
                      by_seed[baseline][seed]["metrics"].get(split, {}).get(metric)) for seed in seeds]
            pairs = [(seed, a, b) for seed, a, b in pairs if a is not None and b is not None]
            if not pairs:
                continue
            diffs = [a - b for _, a, b in pairs]
            sign = 1.0 if metric in HIGHER_IS_BETTER else -1.0
            out[f"{split}/{metric}"] = {"seeds": [seed for seed, _, _ in pairs], "diffs": diffs,
                                        "mean": float(np.mean(diffs)), "ours_better": sum(sign * d > 0 for d in diffs),
                                        "n": len(diffs)}
    return out


def _cell(entry: dict, fmt: str) -> str:
    text = fmt.format(entry["mean"])
    if entry["n"] > 1:
        text += f" ± {entry['std']:.2g}"
    return f"{text} (n={entry['n']})"


def to_markdown(table: dict, seeds: Sequence[int], *, mismatches: dict | None = None,
                slices: Sequence[dict] = (), pairs: dict | None = None) -> str:
    lines = []
    if mismatches:
        lines += ["> **WARNING: the slices below were not made from the same shared inputs** (data, VAE, latents,",
                  "> reward model or supervised policy differ), so their runs are not paired comparisons:", ">"]
        for key, groups in mismatches.items():
            lines.append(f"> - `{key}`: " + "; ".join(f"{digest[:12]} in {', '.join(names)}"
                                                      for digest, names in groups.items()))
        lines.append("")
    differing = override_differences(slices)
    if differing:
        lines += ["> **Note: the slices were run with different overrides** (each slice's `command` has them all):", ">"]
        lines += [f"> - `{o}` in {', '.join(names)} only" for o, names in differing.items()]
        lines.append("")
    lines += [f"# Sword comparisons (seeds {', '.join(map(str, seeds))}; mean ± std over the seeds finished, "
              "n = seeds in the cell)", ""]
    for title, ours, baseline, splits in COMPARISONS:
        lines += [f"## {title}", ""]
        if splits:
            keys = [f"{s}/{m}" for s in splits for m in METRICS
                    if any(f"{s}/{m}" in table.get(run, {}).get("metrics", {}) for run in (ours, baseline))]
            if not keys:
                lines += [f"No evaluated slices of `{ours}` or `{baseline}` here.", ""]
                continue
            lines += ["| run | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
            for run in (ours, baseline):
                cells = [_cell(table[run]["metrics"][k], "{:.4g}")
                         if k in table.get(run, {}).get("metrics", {}) else "" for k in keys]
                lines.append(f"| {run} | " + " | ".join(cells) + " |")
            floors = [s["vae_floor"] for s in slices if s.get("vae_floor")]
            if floors:  # the shared VAE's encode-decode of each slice's ground truth, scored like a prediction
                cells = []
                for k in keys:
                    split, metric = k.split("/")
                    values = [f[split][metric] for f in floors if metric in f.get(split, {})]
                    cells.append(f"{np.mean(values):.4g}" if values else "")
                lines.append("| VAE floor (mean over slices) | " + " | ".join(cells) + " |")
            diffs = (pairs or {}).get(f"{ours} vs {baseline}", {})
            if diffs:
                lines += ["", f"Paired by seed, `{ours}` minus `{baseline}` (better: lower, except "
                          f"{', '.join(sorted(HIGHER_IS_BETTER))}):", "",
                          "| metric | per seed | mean | `" + ours + "` better at |", "|---|---|---|---|"]
                for key, d in diffs.items():
                    per_seed = ", ".join(f"{v:+.4g} (s{seed})" for seed, v in zip(d["seeds"], d["diffs"]))
                    lines.append(f"| {key} | {per_seed} | {d['mean']:+.4g} | {d['ours_better']}/{d['n']} seeds |")
        else:
            shown = [run for run in (ours, baseline, GROUND_TRUTH) if run in (ours, baseline) or run in table]
            labels = sorted({l for run in shown for l in table.get(run, {}).get("success", {})}, key=_step)
            if not labels:
                lines += [f"No GRPO slices of `{ours}` or `{baseline}` here.", ""]
                continue
            lines += ["Real-environment success of the policy (greedy, MuJoCo) at each GRPO step:", "",
                      "| run | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
            for run in shown:
                success = table.get(run, {}).get("success", {})
                name = f"{run} (GRPO in MuJoCo: reference)" if run == GROUND_TRUTH else run
                lines.append(f"| {name} | " + " | ".join(
                    _cell(success[l], "{:.3f}") if l in success else "" for l in labels) + " |")
            gains = (pairs or {}).get(f"{ours} vs {baseline}", {})
            if gains:
                runs = [r for r in (ours, baseline, GROUND_TRUTH) if any(g is not None for g in gains.get(r, []))]
                lines += ["", "GRPO gain (last evaluation minus step 0; 95% Newcombe interval) by seed:", "",
                          "| seed | " + " | ".join(runs) + f" | `{ours}` - `{baseline}` |", "|---|" + "---|" * (len(runs) + 1)]
                for i, seed in enumerate(gains["seeds"]):
                    cells = []
                    for run in runs:
                        gain, ci = gains[run][i], gains["gain_ci95"][run][i]
                        cells.append("" if gain is None else f"{gain:+.3f}" + (f" [{ci[0]:+.3f}, {ci[1]:+.3f}]" if ci else ""))
                    lines.append(f"| {seed} | " + " | ".join(cells) + f" | {gains['diffs'][i]:+.3f} |")
                lines += ["", f"`{ours}` gained more than `{baseline}` at {gains['ours_better']}/{gains['n']} seeds "
                          f"(mean difference {gains['mean']:+.3f})."]
            lines += replay_lines([s for s in slices if s["run"] in (ours, baseline)])
            lines += exploitation_lines([s for s in slices if s["run"] in (ours, baseline)])
        lines.append("")
    if slices:
        lines += ["## Slices", "", "| run | seed | device | seconds (shared stages built here + slice) | slices at once "
                  "| commit | data | VAE |", "|---|---|---|---|---|---|---|---|"]
        for s in slices:
            wall = s.get("wall_seconds", {})
            commit = (s.get("code", {}).get("commit") or "?")[:10] + ("+" if s.get("code", {}).get("dirty") else "")
            lines.append(f"| {s['run']} | {s['seed']} | {s.get('device', {}).get('kind', '?')} | "
                         f"{wall.get('shared', 0):.0f} + {wall.get('slice', 0):.0f} | {s.get('slices_at_once', 1)} | "
                         f"{commit} | {s.get('shared', {}).get('hashes', {}).get('data', '?')[:12]} | "
                         f"{s.get('shared', {}).get('hashes', {}).get('vae', '?')[:12]} |")
        lines.append("")
    return "\n".join(lines)


def replay_lines(slices: Sequence[dict], horizon: str = "48") -> list[str]:
    """Markdown: can each learned simulator tell the supervised policy's real successes from its real
    failures? From the replay at the first GRPO evaluation (the same real episodes for every run of a
    seed): imagined success of real successes / real failures by action ``horizon`` and over the whole
    replay, the separation (the difference of the two) by ``horizon`` with its 95% bootstrap interval
    (:func:`sword_jax.rl.sim_agreement.separation`), how often another noise draw changes the verdict,
    and per seed the paired difference of two runs' separations."""
    from sword_jax.rl.sim_agreement import separation

    rows, diffs = [], []
    by_seed: dict[int, list[tuple[dict, dict]]] = {}
    for s in slices:
        replay = (s.get("success_curve") or [{}])[0].get("replay") or {}
        if replay.get("imagined_success_by_horizon"):
            by_seed.setdefault(s["seed"], []).append((s, replay))
    for seed, members in sorted(by_seed.items()):
        flags = [tuple(r.get("real_success_flags") or ()) for _, r in members]
        paired = len(set(flags)) == 1 and flags[0] and all(r.get("imagined_first_success") for _, r in members)
        seps = None
        if paired and 0 < sum(flags[0]) < len(flags[0]):
            seps = separation(np.asarray(flags[0]), [r["imagined_first_success"] for _, r in members], int(horizon))
        for i, (s, replay) in enumerate(members):
            by_h = replay["imagined_success_by_horizon"]
            cells = [f"{by_h[h]['real_success']['rate']:.2f} / {by_h[h]['real_failure']['rate']:.2f} "
                     f"(of {by_h[h]['real_success']['of']} / {by_h[h]['real_failure']['of']})" if h in by_h else ""
                     for h in (horizon, "all")]
            if seps:
                sep = seps["per_simulator"][i]
                cells.append(f"{sep['separation']:+.2f} [{sep['ci95'][0]:+.2f}, {sep['ci95'][1]:+.2f}]")
            else:
                cells.append("")
            rows.append(f"| {s['run']} | {seed} | " + " | ".join(cells) +
                        f" | {replay.get('resample_disagreement', {}).get('rate', float('nan')):.2f} |")
        if seps and "difference" in seps:
            d = seps["difference"]
            diffs.append(f"- seed {seed}: `{members[1][0]['run']}` minus `{members[0][0]['run']}` separation by action "
                         f"{horizon}: {d['separation']:+.2f} [{d['ci95'][0]:+.2f}, {d['ci95'][1]:+.2f}] (paired bootstrap "
                         "over the same episodes)")
    if not rows:
        return []
    return ["", "Replay of the supervised policy's real evaluation episodes in each learned simulator (step 0): "
            "imagined success of real successes / real failures, and their difference (separation: 0 = the "
            "verdict ignores the actions):", "",
            f"| run | seed | by action {horizon} | whole replay | separation by action {horizon} (95%) | "
            "another noise draw disagrees |", "|---|---|---|---|---|---|", *rows, *([""] + diffs if diffs else [])]


def exploitation_lines(slices: Sequence[dict], horizon: str = "48") -> list[str]:
    """Markdown: did GRPO learn to fool its simulator? Per world-model slice, from the replays at its
    first and last GRPO evaluations (each replays that step's policy's own real episodes): the share of
    real failures the simulator calls successes by action ``horizon`` (false success), of real successes
    it calls successes, and the real success rate (greedy, all evaluation episodes), first -> last.
    False success rising while real success falls is the signature of exploitation."""
    rows, fooled, fell, n = [], 0, 0, 0
    for s in sorted(slices, key=lambda s: (s["run"], s["seed"])):
        curve = [c for c in s.get("success_curve") or []
                 if (c.get("replay") or {}).get("imagined_success_by_horizon", {}).get(horizon)]
        if len(curve) < 2:
            continue
        first, last = curve[0], curve[-1]
        rate = lambda c, kind: c["replay"]["imagined_success_by_horizon"][horizon][kind]["rate"]  # noqa: E731
        n += 1
        fooled += rate(last, "real_failure") > rate(first, "real_failure")
        fell += last["mean"] < first["mean"]
        training = s.get("policy", {}).get("grpo", {}).get("training_success") or {}
        rows.append(f"| {s['run']} | {s['seed']} | {first.get('step', 0)} -> {last.get('step', '?')} | "
                    + (f"{training['first']:.2f} -> {training['last']:.2f} | " if training else "| ")
                    + f"{rate(first, 'real_failure'):.2f} -> {rate(last, 'real_failure'):.2f} | "
                    f"{rate(first, 'real_success'):.2f} -> {rate(last, 'real_success'):.2f} | "
                    f"{first['mean']:.3f} -> {last['mean']:.3f} |")
    if not rows:
        return []
    return ["", "Did GRPO learn to fool its simulator? Its imagined training rollouts' success (first -> last 10 "
            "steps; from the GRPO log beside the slice where the slice predates recording it), and the replay at "
            f"each evaluation of that step's policy's own real episodes, first -> last evaluation: imagined "
            f"success by action {horizon} of real failures (false success) and of real successes, and real "
            "success:", "",
            f"| run | seed | GRPO steps | imagined training rollouts | false success by action {horizon} | "
            "imagined success of real successes | real success |", "|---|---|---|---|---|---|---|", *rows, "",
            f"False success rose at {fooled}/{n} slices; real success fell at {fell}/{n}."]


def override_differences(slices: Sequence[dict]) -> dict[str, list[str]]:
    """Overrides that some slices ran with and others did not: ``{override: [slice files with it]}``."""
    sets = {s.get("file", f"{s['run']}_seed{s['seed']}"): set(s.get("overrides", [])) for s in slices}
    every = set.intersection(*sets.values()) if sets else set()
    out: dict[str, list[str]] = {}
    for name, overrides in sets.items():
        for o in sorted(overrides - every):
            out.setdefault(o, []).append(name)
    return out


def write_tables(out: str, results: dict[str, list[dict]], seeds: Sequence[int], *, mismatches: dict | None = None,
                 slices: Sequence[dict] = (), **extra) -> dict:
    """Writes ``comparison.{json,md}`` in ``out`` for the runs finished so far."""
    table = aggregate(results)
    pairs = {f"{ours} vs {baseline}": paired(results, ours, baseline, splits) if splits
             else paired_gains(results, ours, baseline) for _, ours, baseline, splits in COMPARISONS}
    os.makedirs(out, exist_ok=True)
    finished = {run: len(per_seed) for run, per_seed in results.items()}
    with open(os.path.join(out, "comparison.json"), "w") as f:
        json.dump({"seeds": list(seeds), "finished_seeds_per_run": finished, **extra,
                   "shared_input_mismatches": mismatches or {}, "runs": table, "paired": pairs}, f, indent=1)
    with open(os.path.join(out, "comparison.md"), "w") as f:
        f.write(to_markdown(table, seeds, mismatches=mismatches, slices=slices, pairs=pairs))
    return table


# ---- merging slice files ----

def load_slices(directory: str) -> list[dict]:
    """Every slice record in ``directory`` (``*.json`` in the slice format), ordered by run and seed."""
    slices = []
    for name in sorted(os.listdir(directory)) if os.path.isdir(directory) else []:
        if not name.endswith(".json"):
            continue
        with open(os.path.join(directory, name)) as f:
            record = json.load(f)
        if isinstance(record, dict) and record.get("format") == SLICE_FORMAT:
            slices.append({**record, "file": name})
    order = list(runs_for("tiny"))
    return sorted(slices, key=lambda s: (order.index(s["run"]) if s["run"] in order else len(order), s["seed"]))


def _hashes_by_shared_seed(slices: Sequence[dict]) -> dict[int, dict[str, dict[str, list[str]]]]:
    """Per shared seed, each shared-input key's hashes and the slice files holding them:
    ``{shared seed: {key: {hash: [files]}}}`` (slices of different shared seeds are different
    replicates, so their hashes are never compared)."""
    out: dict[int, dict[str, dict[str, list[str]]]] = {}
    for s in slices:
        seen = out.setdefault(int(s.get("shared", {}).get("seed") or 0), {})
        for key, digest in s.get("shared", {}).get("hashes", {}).items():
            seen.setdefault(key, {}).setdefault(digest, []).append(s["file"])
    return out


def hash_mismatches(slices: Sequence[dict]) -> dict[str, dict[str, list[str]]]:
    """Shared-input keys whose hash differs between slices made from the same shared seed:
    ``{key: {hash: [slice files]}}`` (the key names the shared seed where the slices have several)."""
    per_seed = _hashes_by_shared_seed(slices)
    return {key if len(per_seed) == 1 else f"{key} (shared seed {seed})": by_digest
            for seed, seen in sorted(per_seed.items()) for key, by_digest in seen.items() if len(by_digest) > 1}


def agreed_hashes(slices: Sequence[dict]) -> dict:
    """The shared-input hashes the slices agree on; per shared seed (``{"shared seed K": {...}}``) where
    the slices have several."""
    per_seed = {seed: {key: next(iter(by_digest)) for key, by_digest in seen.items() if len(by_digest) == 1}
                for seed, seen in _hashes_by_shared_seed(slices).items()}
    if len(per_seed) == 1:
        return next(iter(per_seed.values()))
    return {f"shared seed {seed}": entries for seed, entries in sorted(per_seed.items())}


def _step(label: str) -> int:
    return int(label.rsplit(" ", 1)[-1])


def gain_of(record: dict) -> float | None:
    """Real success at the last GRPO evaluation minus at the first (step 0), or ``None`` without two."""
    success = record.get("success", {})
    if len(success) < 2:
        return None
    labels = sorted(success, key=_step)
    return success[labels[-1]] - success[labels[0]]


def gain_interval_of(record: dict) -> list[float] | None:
    """The 95% interval of :func:`gain_of` from the success curve's counts, where it has them (paired episode by
    episode where both points kept their outcomes, :func:`~sword_jax.rl.env_rollout.gain_interval`)."""
    from sword_jax.rl.env_rollout import gain_interval

    points = record.get("success_curve") or []
    if len(points) < 2 or not all("successes" in p and "episodes" in p for p in (points[0], points[-1])):
        return None
    first, last = points[0], points[-1]
    return [round(x, 4) for x in gain_interval(first, last)]


def paired_gains(results: dict[str, list[dict]], ours: str, baseline: str,
                 reference: str = GROUND_TRUTH) -> dict:
    """Comparison 3 by seed: each run's GRPO gain (last evaluation minus step 0, the same supervised
    policy at both runs' step 0) with its 95% interval, ``ours - baseline``, and at how many seeds
    ``ours`` gained more; the ``reference`` run's gains (GRPO in MuJoCo) where it ran at those seeds."""
    records = {run: {r["seed"]: r for r in results.get(run, [])} for run in (ours, baseline, reference)}
    by_seed = {run: {seed: gain_of(r) for seed, r in per_seed.items()} for run, per_seed in records.items()}
    seeds = sorted(s for s in set(by_seed[ours]) & set(by_seed[baseline])
                   if by_seed[ours][s] is not None and by_seed[baseline][s] is not None)
    if not seeds:
        return {}
    diffs = [by_seed[ours][s] - by_seed[baseline][s] for s in seeds]
    out = {"seeds": seeds, ours: [by_seed[ours][s] for s in seeds], baseline: [by_seed[baseline][s] for s in seeds],
           "diffs": diffs, "mean": float(np.mean(diffs)), "ours_better": sum(d > 0 for d in diffs), "n": len(diffs),
           "gain_ci95": {run: [gain_interval_of(records[run][s]) if s in records[run] else None for s in seeds]
                         for run in (ours, baseline, reference)}}
    out[reference] = [by_seed[reference].get(s) for s in seeds]
    return out


def plot_success_curves(slices: Sequence[dict], path: str,
                        runs: Sequence[str] = ("sword", "wovr", GROUND_TRUTH)) -> str | None:
    """Comparison 3: real success against GRPO steps, per run (mean over seeds, each seed a thin line,
    the first seed's 95% interval shaded) -> ``path`` (PNG); ``None`` when no slice has a curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per_run = {run: [s for s in slices if s["run"] == run and s.get("success_curve")] for run in runs}
    if not any(per_run.values()):
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    colours = {"sword": "tab:red", "wovr": "tab:blue", GROUND_TRUTH: "k"}
    for run, members in per_run.items():
        if not members:
            continue
        colour = colours.get(run, None)
        steps = [p["step"] for p in members[0]["success_curve"]]
        curves = [[p["mean"] for p in m["success_curve"]] for m in members
                  if [p["step"] for p in m["success_curve"]] == steps]
        for curve in curves if len(curves) > 1 else ():
            ax.plot(steps, curve, color=colour, lw=0.6, alpha=0.45)
        ci = [p.get("ci95") for p in members[0]["success_curve"]]
        if all(ci):
            ax.fill_between(steps, [c[0] for c in ci], [c[1] for c in ci], color=colour, alpha=0.12, lw=0)
        label = f"{run} (n={len(curves)})" + (": GRPO in MuJoCo, reference" if run == GROUND_TRUTH else "")
        ax.plot(steps, np.mean(curves, axis=0), color=colour, lw=2, marker="o", ls="--" if run == GROUND_TRUTH else "-",
                label=label)
    ax.set_xlabel("GRPO step")
    ax.set_ylabel("real-environment success")
    ax.set_title("GRPO in the Sword vs the WoVR world model")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


CURVE_METRICS = (("latent_mse", "latent MSE (no VAE error)"), ("lpips", "LPIPS"), ("probe_ee_cm", "end-effector error (cm)"))


def plot_horizon_curves(slices: Sequence[dict], path: str, *, runs: tuple[str, str] = ("sword", "teacher_forcing"),
                        splits: tuple[str, ...] = ("original", "mixed")) -> str | None:
    """Per-horizon curves of two runs (mean over their seeds, each seed a thin line) -> ``path`` (PNG).

    One panel per (split, metric in :data:`CURVE_METRICS`); the shaded band is the first seed's 95%
    interval over episodes. Returns ``path``, or ``None`` when neither run has curves.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    per_run = {run: [s for s in slices if s["run"] == run and s.get("curves")] for run in runs}
    if not any(per_run.values()):
        return None
    fig, axes = plt.subplots(len(splits), len(CURVE_METRICS), figsize=(5 * len(CURVE_METRICS), 3.6 * len(splits)),
                             squeeze=False)
    legend_drawn = False
    for row, split in enumerate(splits):
        for col, (metric, label) in enumerate(CURVE_METRICS):
            ax = axes[row][col]
            for colour, run in zip(("tab:red", "tab:blue"), runs):
                curves = [s["curves"][split][metric] for s in per_run[run]
                          if metric in s["curves"].get(split, {})]
                if not curves:
                    continue
                frames = np.asarray(curves[0]["frames"])
                means = np.stack([np.asarray(c["mean"]) for c in curves])
                for seed_curve in means if len(curves) > 1 else ():
                    ax.plot(frames, seed_curve, color=colour, lw=0.6, alpha=0.4)
                band = 1.96 * np.asarray(curves[0].get("stderr", np.zeros_like(frames)))
                ax.fill_between(frames, means[0] - band, means[0] + band, color=colour, alpha=0.15, lw=0)
                ax.plot(frames, means.mean(0), color=colour, lw=1.8, label=f"{run} (n={len(curves)})")
            if metric == "probe_ee_cm":
                floor = [s["curves"][split].get("probe_floor_ee_cm") for s in per_run[runs[0]]]
                if floor and floor[0]:
                    ax.plot(floor[0]["frames"], floor[0]["mean"], color="k", ls="--", lw=1, label="VAE floor")
            ax.set_title(f"{split}: {label}")
            ax.set_xlabel("frame (horizon)")
            ax.grid(alpha=0.3)
            if not legend_drawn and ax.get_legend_handles_labels()[0]:  # the first panel with curves names them
                ax.legend(fontsize=8)
                legend_drawn = True
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def merge(directory: str, *, allow_mismatch: bool = False) -> dict:
    """Builds ``comparison.{md,json}`` in ``directory`` from its slice files; returns the table.

    Refuses (``SystemExit``) slices whose shared-input hashes disagree unless ``allow_mismatch``,
    which writes the table with a warning at the top instead.
    """
    slices = load_slices(directory)
    if not slices:
        raise SystemExit(f"train.compare merge: no slice files ({SLICE_FORMAT}) in {directory}")
    sizes = sorted({s["size"] for s in slices})
    if len(sizes) > 1:
        raise SystemExit(f"train.compare merge: {directory} mixes slices of sizes {sizes}")
    mismatches = hash_mismatches(slices)
    if mismatches and not allow_mismatch:
        detail = "; ".join(f"{key}: " + " vs ".join(f"{d[:12]} ({', '.join(n)})" for d, n in groups.items())
                           for key, groups in mismatches.items())
        raise SystemExit(f"train.compare merge: slices in {directory} were made from different shared inputs "
                         f"({detail}); rerun them from the same config and --shared-seed, or pass --allow-mismatch "
                         "to write a table flagged as unpaired")
    results: dict[str, list[dict]] = {}
    for s in slices:
        results.setdefault(s["run"], []).append(s)
    seeds = sorted({s["seed"] for s in slices})
    agreed = agreed_hashes(slices)
    listing = [{"file": s["file"], "run": s["run"], "seed": s["seed"], "device": s.get("device", {}).get("kind"),
                "wall_seconds": s.get("wall_seconds"), "slices_at_once": s.get("slices_at_once", 1),
                "commit": s.get("code", {}).get("commit")} for s in slices]
    table = write_tables(directory, results, seeds, mismatches=mismatches, slices=slices, size=sizes[0],
                         shared_input_hashes=agreed, slice_files=listing)
    plot_horizon_curves(slices, os.path.join(directory, "dlb_vs_teacher_forcing.png"))
    if any(s["run"] == "no_augmentation" for s in slices):
        plot_horizon_curves(slices, os.path.join(directory, "augmentation_vs_none.png"),
                            runs=("sword", "no_augmentation"), splits=("mixed",))
    plot_success_curves(slices, os.path.join(directory, "grpo_sword_vs_wovr.png"))
    return table


def finish(results_dir: str) -> dict:
    """The last merge of a run of slices: the table (flagged where slices disagree on shared inputs), printed."""
    table = merge(results_dir, allow_mismatch=True)
    mismatches = hash_mismatches(load_slices(results_dir))
    if mismatches:
        print(f"[compare] WARNING: slices in {results_dir} disagree on shared inputs {sorted(mismatches)}; "
              "the table is flagged (see its top)", file=sys.stderr)
    with open(os.path.join(results_dir, "comparison.md")) as f:
        print(f.read())
    return table
