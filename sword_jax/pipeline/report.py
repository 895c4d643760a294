"""The pipeline's closing report: ``report.md`` (+ ``report.html``) and ``results.json`` in the work dir."""

from __future__ import annotations

import html
import os
import shutil

from configs.cli import to_dict
from sword_jax.atomic_write import write_json_atomic
from sword_jax.pipeline.stages import Context


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "" if value is None else str(value)


def _measured_segments(final: dict) -> str:
    """The world model's last measurement of fixed segments (``trainer.eval_every``) as a sentence, or ""."""
    if "eval_train_loss" not in final:
        return ""
    splits = [s for s in ("heldout", "policy", "trainpolicy", "train") if f"eval_{s}_loss" in final]
    names = {"heldout": "held-out", "policy": "held-out policy rollouts", "trainpolicy": "training policy rollouts",
             "train": "training"}
    text = " On fixed segments at the end, flow loss " + " against ".join(
        f"{_fmt(final[f'eval_{s}_loss'])} {names[s]}" for s in splits)
    steps = sorted(int(k.rsplit("_", 1)[1]) for k in final if k.startswith("eval_train_sample_error_"))
    for n in steps:
        text += f"; the sampler's error at {n} Euler steps " + " against ".join(
            f"{_fmt(final[f'eval_{s}_sample_error_{n}'])} {names[s]}" for s in splits)
    detail = sorted(int(k.rsplit("_", 1)[1]) for k in final if k.startswith("eval_train_sample_detail_"))
    for n in detail:  # below 1: the samples are smoother than the data (the mean of futures the model cannot tell)
        text += f"; the samples' detail over the data's at {n} Euler steps " + " against ".join(
            f"{_fmt(final[f'eval_{s}_sample_detail_{n}'])} {names[s]}" for s in splits
            if f"eval_{s}_sample_detail_{n}" in final)
    other = sorted(int(k.rsplit("_", 1)[1]) for k in final if k.startswith("eval_train_other_actions_error_"))
    for n in other:  # the same call under other segments' actions: how much the actions decide
        text += f"; under other segments' actions at {n} Euler steps " + " against ".join(
            f"{_fmt(final[f'eval_{s}_other_actions_error_{n}'])} {names[s]}" for s in splits
            if f"eval_{s}_other_actions_error_{n}" in final)
    return text + "."


def _metric_tables(eval_metrics: dict) -> list[str]:
    lines = []
    for split, per_model in eval_metrics.items():
        metrics = sorted({m for r in per_model.values() for m in r})
        lines += [f"**{split}**", "", "| model | " + " | ".join(metrics) + " |",
                  "|---|" + "---|" * len(metrics)]
        for model, values in per_model.items():
            lines.append(f"| {model} | " + " | ".join(_fmt(values.get(m)) for m in metrics) + " |")
        lines.append("")
    return lines


def write(ctx: Context) -> dict:
    """Writes the report from every finished stage's results; returns the paths."""
    cfg, results = ctx.cfg, ctx.results
    lines = [f"# Sword pipeline report: {cfg.name}", ""]
    lines.append(f"Config `{ctx.cfg_name}`" + (f" with overrides `{' '.join(ctx.overrides)}`" if ctx.overrides else "")
                 + f"; seed {cfg.seed}; DiT dim {cfg.model.dim} x {cfg.model.num_layers} layers; "
                 f"frames {cfg.data.image_size}x{cfg.data.image_size}, {cfg.data.episode_frames} per episode; "
                 f"DLB {'on (' + cfg.cache.schedule + ', ' + cfg.cache.replacement + ', ' + cfg.cache.scope + ')' if cfg.cache.enabled else 'off'}; "
                 f"style augmentation {'on' if cfg.augment.enabled else 'off'}.")
    lines.append("")
    lines += ["## Stages", "", "| stage | seconds | key results |", "|---|---|---|"]
    for name, res in results.items():
        summary = {k: v for k, v in res.items() if k != "seconds" and not isinstance(v, (dict, list))}
        lines.append(f"| {name} | {_fmt(res.get('seconds'))} | "
                     + ", ".join(f"{k}={_fmt(v)}" for k, v in list(summary.items())[:6]) + " |")
    lines.append("")
    data = results.get("data", {})
    if data:
        lines += ["## Data", "", f"Expert episodes: {data.get('train', {}).get('episodes')} for training, "
                  f"{data.get('heldout', {}).get('episodes')} held out "
                  f"(expert success: train {_fmt(data.get('train', {}).get('success_rate'))}, "
                  f"held-out {_fmt(data.get('heldout', {}).get('success_rate'))}).", ""]
    vae = results.get("vae", {})
    if vae:
        lines += ["## VAE", "", f"Loss {_fmt(vae.get('first_loss'))} -> {_fmt(vae.get('final_loss'))} "
                  f"over {vae.get('steps')} steps" + (f" (official weights: {vae['source']})" if vae.get("source") else "") + ".", ""]
    light = results.get("light_decoder", {})
    if light.get("eval"):
        ev = light["eval"]
        strip = os.path.relpath(light["strip"], ctx.workdir) if light.get("strip") else None
        lines += ["## Light rollout decoder", "", f"Distilled from the VAE at {light.get('frame_size')} px over "
                  f"{light.get('steps')} steps ({_fmt(light.get('params'))} parameters); on held clips, L1 to the VAE's "
                  f"frames {_fmt(ev.get('init_l1'))} -> {_fmt(ev.get('final_l1'))}, PSNR {_fmt(ev.get('init_psnr'))} -> "
                  f"{_fmt(ev.get('final_psnr'))} dB." + (f" Frames: [{strip}]({strip})." if strip else ""), ""]
    wm = results.get("world_model", {})
    if wm:
        final = wm.get("final_metrics", {})
        lines += ["## World model", "", f"Flow-matching loss {_fmt(wm.get('first_loss'))} -> {_fmt(final.get('loss'))} "
                  f"over {wm.get('final_step')} steps; DLB read probability at the end {_fmt(final.get('read_prob'))}, "
                  f"cache filled {_fmt(final.get('cache_filled'))}." + _measured_segments(final), ""]
    evaluation = results.get("evaluate", {})
    if evaluation:
        lines += ["## Long-horizon evaluation (LIBERO-Original / LIBERO-Mixed)", "",
                  "Full evaluation report with plots, strips and videos: [eval/report.md](eval/report.md).", ""]
        lines += _metric_tables(evaluation.get("metrics", {}))
    policy = results.get("policy", {})
    if policy:
        lines += ["## Policy post-training", ""]
        for key in ("reward_model", "sft", "grpo"):
            if key in policy:
                lines.append(f"- {key}: " + ", ".join(f"{k}={_fmt(v)}" for k, v in policy[key].items()
                                                       if not isinstance(v, (dict, list))))
        curve = policy.get("success_curve_png")
        if curve and os.path.exists(curve):
            rel = os.path.relpath(curve, ctx.workdir)
            lines += ["", f"![policy success in the simulator]({rel})"]
        if "success" in policy:
            lines += ["", "| point | success (simulator) |", "|---|---|"]
            for label, value in policy["success"].items():
                lines.append(f"| {label} | {_fmt(value)} |")
        lines.append("")
    report_md = os.path.join(ctx.workdir, "report.md")
    with open(report_md, "w") as f:
        f.write("\n".join(lines) + "\n")
    with open(os.path.join(ctx.workdir, "report.html"), "w") as f:
        f.write("<html><body><pre style='font-family:monospace'>" + html.escape("\n".join(lines)) + "</pre></body></html>")
    results_json = os.path.join(ctx.workdir, "results.json")
    write_json_atomic(results_json, {"config": to_dict(cfg), "config_name": ctx.cfg_name, "stages": results},
                      sort_keys=True)
    if evaluation.get("report") and os.path.exists(os.path.join(ctx.workdir, "eval")):
        shutil.copyfile(os.path.join(ctx.workdir, "eval", "results.json"), os.path.join(ctx.workdir, "eval_results.json")) \
            if os.path.exists(os.path.join(ctx.workdir, "eval", "results.json")) else None
    return {"report": report_md, "results": results_json}
