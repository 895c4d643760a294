"""The evaluation report: metric table, metric-vs-horizon plots, ground truth next to predictions.

Writes into ``out_dir``: ``report.md`` and ``report.html`` (same content; the HTML embeds the
images and GIFs by relative path), ``results.json``, ``plots/<split>_<metric>.png``,
``strips/<split>_ep<i>.png`` (rows: ground truth then each model, columns: sampled frames) and
``videos/<split>_ep<i>.gif`` (ground truth and every model side by side, all frames).
"""

from __future__ import annotations

import html
import json
import os
from typing import Sequence

import numpy as np
from jaxtyping import Float

from sword_jax.evaluation.results import EvalResults
from sword_jax.metrics.suite import LOWER_IS_BETTER

_LABEL = {"lpips": "LPIPS", "flolpips": "FloLPIPS", "psnr": "PSNR (dB)", "ssim": "SSIM", "fid": "FID", "fvd": "FVD"}


def _u8(frames: np.ndarray, *, min_side: int = 96) -> np.ndarray:
    """uint8 frames, small ones upscaled (nearest) so that the shorter side is at least ``min_side``."""
    frames = np.clip(np.rint(np.asarray(frames, np.float32) * 255.0), 0, 255).astype(np.uint8)
    factor = max(1, -(-min_side // min(frames.shape[-3:-1])))
    if factor > 1:
        frames = np.repeat(np.repeat(frames, factor, axis=-3), factor, axis=-2)
    return frames


def _label_bar(text: str, width: int, height: int = 12) -> np.ndarray:
    """A dark bar with the label drawn by OpenCV (no font files needed)."""
    import cv2

    bar = np.full((height, width, 3), 32, np.uint8)
    cv2.putText(bar, text[: max(1, width // 6)], (2, height - 3), cv2.FONT_HERSHEY_PLAIN, 0.7, (255, 255, 255), 1)
    return bar


def side_by_side(videos: dict[str, Float[np.ndarray, "t h w 3"]], *, gap: int = 2) -> np.ndarray:
    """Frames of several same-shaped videos placed left to right with a label above each, uint8."""
    panels = []
    for name, video in videos.items():
        frames = _u8(video)
        bar = np.broadcast_to(_label_bar(name, frames.shape[2]), (frames.shape[0],) + _label_bar(name, frames.shape[2]).shape)
        panels.append(np.concatenate([bar, frames], axis=1))
        panels.append(np.full(panels[-1].shape[:2] + (gap, 3), 255, np.uint8))
    return np.concatenate(panels[:-1], axis=2)


def write_strip(path: str, videos: dict[str, np.ndarray], *, columns: int = 8) -> None:
    """A PNG grid: one row per video (ground truth first), ``columns`` evenly spaced frames."""
    from PIL import Image

    num_frames = next(iter(videos.values())).shape[0]
    picks = np.unique(np.linspace(0, num_frames - 1, min(columns, num_frames)).round().astype(int))
    rows = []
    for name, video in videos.items():
        frames = _u8(video[picks])
        row = np.concatenate(list(frames), axis=1)
        rows.append(np.concatenate([_label_bar(f"{name}", row.shape[1]), row], axis=0))
    Image.fromarray(np.concatenate(rows, axis=0)).save(path)


def write_gif(path: str, videos: dict[str, np.ndarray], *, fps: int = 8) -> None:
    """An animated GIF of the videos side by side."""
    from PIL import Image

    frames = side_by_side(videos)
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)


def plot_curves(path: str, split: str, metric: str, curves: dict[str, dict], *, floor: dict | None = None) -> None:
    """One PNG: ``metric`` against horizon for every model, shaded with its bootstrap interval over
    episodes (the standard error where a curve has none), and the VAE's reconstruction ``floor`` dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.4), dpi=110)
    for model, curve in curves.items():
        frames, mean, err = (np.asarray(curve[k], np.float64) for k in ("frames", "mean", "stderr"))
        ax.plot(frames, mean, marker="o" if len(frames) < 20 else None, ms=3, label=model)
        if curve.get("ci_low") is not None:
            ax.fill_between(frames, curve["ci_low"], curve["ci_high"], alpha=0.2)
        elif np.any(err > 0):
            ax.fill_between(frames, mean - err, mean + err, alpha=0.2)
    if floor is not None:
        ax.plot(floor["frames"], floor["mean"], ls="--", color="0.4", lw=1.2, label="VAE floor (encode-decode)")
        if floor.get("ci_low") is not None:
            ax.fill_between(floor["frames"], floor["ci_low"], floor["ci_high"], color="0.4", alpha=0.12)
    arrow = "lower is better" if LOWER_IS_BETTER[metric] else "higher is better"
    level = next((c["ci_level"] for c in curves.values() if c.get("ci_level")), None)
    shade = f"; shaded: {level:.0%} bootstrap interval over episodes" if level else ""
    ax.set(xlabel=f"horizon (frame index; frame 0 = given first frame){shade}", ylabel=_LABEL.get(metric, metric),
           title=f"{split}: {_LABEL.get(metric, metric)} ({arrow})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _number(value: float) -> str:
    return f"{value:.4f}" if abs(value) < 100 else f"{value:.1f}"


def _cell(result, metric: str) -> str:
    """The overall value, with its bootstrap interval over episodes where the metric has one."""
    value = result.overall.get(metric, float("nan"))
    interval = result.curves.get(metric, {}).get("overall_ci")
    return _number(value) + (f" [{_number(interval[0])}, {_number(interval[1])}]" if interval else "")


def _table(results: EvalResults, split: str) -> list[list[str]]:
    metrics = [m for m in results.metrics if any(m in r.overall for r in results.models[split].values())]
    header = ["model"] + [f"{_LABEL[m]} {'↓' if LOWER_IS_BETTER[m] else '↑'}" for m in metrics]
    rows = [header]
    best = {}
    for m in metrics:
        values = [r.overall[m] for r in results.models[split].values() if m in r.overall]
        best[m] = min(values) if LOWER_IS_BETTER[m] else max(values)
    for model, r in results.models[split].items():
        cells = [model]
        for m in metrics:
            text = _cell(r, m)
            cells.append(f"**{text}**" if r.overall.get(m) == best[m] and len(results.models[split]) > 1 else text)
        rows.append(cells)
    floor = results.vae_floor.get(split)
    if floor is not None:
        rows.append(["VAE floor (encode-decode of ground truth)"]
                    + [_cell(floor, m) if m in floor.overall else "–" for m in metrics])
    return rows


def floor_lines(results: EvalResults) -> list[str]:
    """One line per split: the VAE's reconstruction floor, so world-model error reads apart from VAE error."""
    lines = []
    for split, floor in results.vae_floor.items():
        parts = [f"{_LABEL.get(m, m)} {_cell(floor, m)}" for m in floor.overall]
        lines.append(f"VAE reconstruction floor on {split} (encode-decode of the ground truth, the scored frames; "
                     f"95% bootstrap interval over episodes): " + ", ".join(parts) + ".")
    return lines


def _md_table(rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    lines += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    return "\n".join(lines)


def _html_table(rows: list[list[str]]) -> str:
    def cell(text, tag):
        bold = text.startswith("**")
        text = html.escape(text.strip("*"))
        return f"<{tag}>{'<b>' + text + '</b>' if bold else text}</{tag}>"

    out = ["<table>", "<tr>" + "".join(cell(c, "th") for c in rows[0]) + "</tr>"]
    out += ["<tr>" + "".join(cell(c, "td") for c in r) + "</tr>" for r in rows[1:]]
    return "\n".join(out + ["</table>"])


def write_report(out_dir: str, results: EvalResults, videos: dict[str, dict[str, np.ndarray]], *,
                 title: str = "World-model evaluation", notes: Sequence[str] = (), max_episodes: int = 2) -> str:
    """Writes the report files; returns the path of ``report.md``.

    Args:
      out_dir: output directory (created).
      results: metrics per split and model (see :mod:`sword_jax.evaluation.results`).
      videos: ``{split: {"ground truth": [B, T, H, W, 3], model: [B, T, H, W, 3], ...}}`` in [0, 1].
      title: report heading.
      notes: extra lines shown at the top (settings, caveats).
      max_episodes: episodes shown as strips and GIFs per split.
    """
    import time

    start = time.perf_counter()
    for sub in ("plots", "strips", "videos"):
        os.makedirs(os.path.join(out_dir, sub), exist_ok=True)
    md = [f"# {title}", ""]
    body_html = [f"<h1>{html.escape(title)}</h1>"]
    caveats = list(notes) + floor_lines(results)
    if any(c.get("ci_low") is not None for per in results.models.values() for r in per.values() for c in r.curves.values()):
        caveats.append("Intervals (tables, shaded curves) are 95% percentile bootstrap intervals of the mean over "
                       "episodes; FID/FVD windows have none.")
    if results.random_weight_networks:
        caveats.insert(0, "**Random-weight metric networks** (no published weights found) for: "
                       + ", ".join(results.random_weight_networks)
                       + ". Their numbers only compare models within this report; they are NOT comparable to published values.")
    for line in caveats:
        md.append(f"- {line}")
        body_html.append(f"<p>{html.escape(line.replace('**', ''))}</p>")
    md.append("")
    for split in results.models:
        md += [f"## {split}", "", _md_table(_table(results, split)), ""]
        body_html += [f"<h2>{html.escape(split)}</h2>", _html_table(_table(results, split))]
        for metric in results.metrics:
            curves = {m: r.curves[metric] for m, r in results.models[split].items() if metric in r.curves}
            if not curves:
                continue
            rel = f"plots/{split}_{metric}.png"
            floor = results.vae_floor.get(split)
            plot_curves(os.path.join(out_dir, rel), split, metric, curves,
                        floor=floor.curves.get(metric) if floor is not None else None)
            md.append(f"![{split} {metric}]({rel})")
            body_html.append(f'<img src="{rel}" alt="{split} {metric}">')
        md.append("")
        split_videos = videos.get(split, {})
        if split_videos:
            count = min(max_episodes, next(iter(split_videos.values())).shape[0])
            for ep in range(count):
                per_ep = {name: v[ep] for name, v in split_videos.items()}
                strip, gif = f"strips/{split}_ep{ep}.png", f"videos/{split}_ep{ep}.gif"
                write_strip(os.path.join(out_dir, strip), per_ep)
                write_gif(os.path.join(out_dir, gif), per_ep)
                md += [f"Episode {ep}: ground truth (top) and predictions", "", f"![strip]({strip})", "",
                       f"![video]({gif})", ""]
                body_html += [f"<h3>Episode {ep}</h3>", f'<img src="{strip}"><br><img src="{gif}">']
    report_s = time.perf_counter() - start
    if results.timing:
        results.timing["report_s"] = report_s
        results.timing["total_s"] = results.timing.get("total_s", 0.0) + report_s
        parts = ", ".join(f"{k[:-2].replace('_', ' ')} {v:.1f} s" for k, v in results.timing.items() if k != "total_s")
        line = f"Evaluation time: {results.timing['total_s']:.1f} s ({parts})."
        md += [line, ""]
        body_html.append(f"<p>{html.escape(line)}</p>")
    with open(os.path.join(out_dir, "results.json"), "w") as f:
        json.dump(results.to_dict(), f, indent=1)
    md_path = os.path.join(out_dir, "report.md")
    with open(md_path, "w") as f:
        f.write("\n".join(md) + "\n")
    style = "body{font-family:sans-serif;max-width:1100px;margin:auto}table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:4px 8px}"
    with open(os.path.join(out_dir, "report.html"), "w") as f:
        f.write(f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
                f"<style>{style}</style></head><body>\n" + "\n".join(body_html) + "\n</body></html>\n")
    return md_path
