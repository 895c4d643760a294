"""Long-horizon evaluation of world-model checkpoints on LIBERO-Original / LIBERO-Mixed.

:func:`run_evaluation` is what ``python -m train.evaluate_world_model`` and the pipeline's evaluation
stage run (their command line and docstring say what is scored). For every held-out episode and model:
encode the first frame and the first context chunk, roll the world model out with the ground-truth
actions for ``eval.horizon_frames`` frames (cut to the longest ``1 + context + predict * n`` that fits),
decode, and score against ground truth, overall and against horizon; the report goes to ``inputs.out``.
Episodes are LIBERO-layout HDF5 (read with :mod:`sim.dataset`, the true state with
:mod:`sim.probe_targets`) or ``.npz``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Mapping

import jax
import numpy as np

from configs.base import ExperimentConfig
from sword_jax import sharding as shd
from sword_jax.evaluation.harness import evaluate_videos, rollout_videos
from sword_jax.evaluation.horizon import per_frame_curve
from sword_jax.evaluation.report import write_report
from sword_jax.evaluation.vae_floor import vae_floor
from sword_jax.load import experiment_vae, experiment_world_model
from sword_jax.metrics.suite import MetricSuite
from sword_jax.rng import stream_key, stream_seed


def effective_horizon(cfg: ExperimentConfig, available: int) -> tuple[int, int, int]:
    """``(frames, k, p)``: the longest ``1 + 4k + 4pn <= min(horizon, available)`` rollout."""
    tf = cfg.vae.temporal_factor  # frames per latent
    k, p = cfg.data.context_frames // tf, cfg.data.predict_frames // tf
    limit = min(cfg.eval.horizon_frames, available)
    n = (limit - 1 - tf * k) // (tf * p)
    if n < 1:
        raise SystemExit(f"evaluate: {limit} frames cannot hold 1 + {tf * k} context + {tf * p} predicted frames")
    return 1 + tf * k + tf * p * n, k, p


def synthetic_split(cfg: ExperimentConfig, split: str, *, seed: int) -> dict[str, np.ndarray]:
    """Smooth textures that pan with the first action dimension; the mixed split is re-styled."""
    rng = np.random.default_rng(seed)
    e, t, size = cfg.eval.num_episodes, cfg.data.episode_frames, cfg.data.image_size
    coarse = rng.random((e, size // 4, size // 4, 3)).astype(np.float32)
    base = np.kron(coarse, np.ones((1, 4, 4, 1), np.float32))
    actions = rng.uniform(-1, 1, (e, t, cfg.model.action_dim)).astype(np.float32)
    offsets = np.cumsum(np.round(actions[..., 0] * 2).astype(int), axis=1)
    frames = np.stack([np.stack([np.roll(base[i], offsets[i, j], axis=1) for j in range(t)]) for i in range(e)])
    if split == "mixed":  # style shift: hue rotation + contrast change, same motion
        frames = np.clip(0.2 + 0.7 * frames[..., [2, 0, 1]], 0, 1)
    return {"frames": frames.astype(np.float32), "actions": actions}


def load_split(path: str, num_episodes: int) -> dict[str, np.ndarray]:
    """Held-out episodes from HDF5 (LIBERO layout) or npz; frames in [0, 1]; the true state
    (``targets``, see :mod:`sword_jax.evaluation.probe`) and ``rewards`` where the file has them."""
    truth = {}
    if path.endswith(".npz"):
        data = np.load(path)
        frames, actions = data["frames"][:num_episodes], data["actions"][:num_episodes]
        truth = {k: data[k][:num_episodes] for k in ("targets", "rewards") if k in data.files}
    else:
        from sim.dataset import read_dataset

        _, episodes = read_dataset(path)
        length = min(len(ep.actions) for ep in episodes[:num_episodes])
        frames = np.stack([ep.agentview_rgb[:length] for ep in episodes[:num_episodes]])
        actions = np.stack([ep.actions[:length] for ep in episodes[:num_episodes]])
        from sim.probe_targets import episode_targets

        truth = {"targets": np.stack([episode_targets(ep)[:length] for ep in episodes[:num_episodes]]),
                 "rewards": np.stack([ep.rewards[:length] for ep in episodes[:num_episodes]])}
    frames = frames.astype(np.float32) / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float32)
    return {"frames": frames, "actions": actions.astype(np.float32), **truth}


def model_config(cfg: ExperimentConfig, workdir: str | None) -> ExperimentConfig:
    """The config a world-model workdir was trained with (its ``config.json``: model, flow, cache,
    trainer sections), so checkpoints of different configs can be compared side by side."""
    path = os.path.join(workdir, "config.json") if workdir else ""
    if not path or not os.path.exists(path):
        return cfg
    with open(path) as f:
        saved = json.load(f)
    sections = {}
    for name in ("model", "flow", "cache", "trainer"):
        section = getattr(cfg, name)
        names = {field.name for field in dataclasses.fields(section)}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in saved.get(name, {}).items() if k in names}
        sections[name] = dataclasses.replace(section, **values)
    return dataclasses.replace(cfg, **sections)


def _fidelity(cfg: ExperimentConfig, probe_path: str, reward_path: str):
    """The action-following scorer from a probe file and / or a reward-model checkpoint (or None)."""
    if not probe_path and not reward_path:
        return None
    from sword_jax.evaluation.probe import FidelityScorer

    success_score = None
    if reward_path:
        import jax.numpy as jnp

        from sword_jax.rl.reward_model import as_reward_model, load_detector

        graphdef, params = load_detector(reward_path, cfg.rl, seed=cfg.seed)
        score = jax.jit(as_reward_model(graphdef, params).score)

        def score_frames(frames):
            return np.concatenate([np.asarray(score(jnp.asarray(frames[i:i + 256]))) for i in range(0, len(frames), 256)])

        success_score = score_frames

    kwargs = {"success_score": success_score, "success_threshold": cfg.rl.success_threshold}
    return FidelityScorer.from_probe_file(probe_path, **kwargs) if probe_path else FidelityScorer(**kwargs)


def fidelity_notes(results) -> list[str]:
    """One line per split and model: the action-following metrics, early vs late in the horizon."""
    lines = []
    for split, per_model in results.models.items():
        for model, result in per_model.items():
            parts = []
            for name in ("probe_ee_cm", "probe_bowl_cm", "probe_gripper_agree", "reward_agree"):
                if name in result.curves:
                    quarters = np.array_split(np.asarray(result.curves[name]["mean"]), 4)
                    parts.append(f"{name} " + " / ".join(f"{q.mean():.3g}" for q in quarters if q.size))
            floor = [f"{k} {v:.3g}" for k, v in result.overall.items() if k.startswith(("probe_floor", "reward_"))
                     and k != "reward_agree"]
            if parts:
                lines.append(f"Action following, {split} / {model} (4 horizon quarters): " + "; ".join(parts)
                             + (f"; overall {', '.join(floor)}" if floor else "") + ".")
    return lines


def add_latent_errors(results, latent: dict, *, given_frames: int, horizon: int) -> None:
    """Adds ``latent_mse`` / ``latent_mse_hold`` (overall and per frame, bootstrap intervals) to every
    model's results (see :func:`sword_jax.evaluation.harness.latent_errors`)."""
    for model, per_split in latent.items():
        for split, errors in per_split.items():
            result = results.models[split][model]
            for name, values in errors.items():
                values = values[:, : horizon - given_frames]
                result.curves[name] = per_frame_curve(values, frame_offset=given_frames).to_dict()
                result.overall[name] = float(values.mean())


def latent_notes(results) -> list[str]:
    """One line per split and model: the world model's latent error against holding the context still."""
    lines = []
    for split, per_model in results.models.items():
        for model, result in per_model.items():
            if "latent_mse" in result.overall:
                ratio = result.overall["latent_mse"] / max(result.overall["latent_mse_hold"], 1e-12)
                lines.append(f"Latent error ({split}, {model}): MSE {result.overall['latent_mse']:.4g} against the "
                             f"encoded ground truth, {ratio:.2f}x that of holding the last context latent still "
                             f"({result.overall['latent_mse_hold']:.4g}); free of the VAE's reconstruction error.")
    return lines


@dataclasses.dataclass(frozen=True)
class EvalInputs:
    """What :func:`run_evaluation` evaluates and where the report goes (the command line's flags, typed)."""

    models: Mapping[str, str] = dataclasses.field(default_factory=dict)  # name -> world-model workdir
    episodes: Mapping[str, str] = dataclasses.field(default_factory=dict)  # split -> HDF5 / npz path
    out: str = ""  # report directory (default: eval.report_dir, else <workdir>/eval)
    vae_checkpoint: str = ""  # empty: a randomly initialised VAE (the report says so)
    synthetic: bool = False  # synthetic splits, and a random-init world model when ``models`` is empty
    metrics: tuple[str, ...] = ()  # subset of ALL_METRICS (default: eval.metrics)
    probe: str = ""  # train.train_probe's probe.npz
    reward_model: str = ""  # train.train_reward's reward_model dir


def run_evaluation(cfg: ExperimentConfig, inputs: EvalInputs) -> dict:
    """Rolls every model out on every split, scores and writes the report; returns
    ``{"report": path of report.md, "out": the report directory}``."""
    start = time.time()
    splits = {}
    if inputs.synthetic:
        splits = {s: synthetic_split(cfg, s, seed=stream_seed(cfg.seed, f"evaluate/synthetic/{s}"))
                  for s in cfg.eval.splits}
    for split, path in inputs.episodes.items():
        splits[split] = load_split(path, cfg.eval.num_episodes)
    if not splits:
        raise SystemExit("evaluate: give --episodes SPLIT=PATH (or --synthetic)")
    models = dict(inputs.models) or ({"random-init": None} if inputs.synthetic else {})
    if not models:
        raise SystemExit("evaluate: give --model NAME=WORKDIR (or --synthetic for a random-init smoke run)")
    available = min(s["frames"].shape[1] for s in splits.values())
    horizon, k, p = effective_horizon(cfg, available)
    given = 1 + cfg.vae.temporal_factor * k  # the first frame and the context frames
    notes = [f"Horizon: {horizon} frames (first frame + {given - 1} context frames given, {horizon - given} predicted; "
             f"metrics over the predicted frames {given}..{horizon - 1}), {cfg.eval.num_episodes} episodes per split, "
             f"{cfg.flow.sample_steps} Euler steps per chunk."]
    if not inputs.vae_checkpoint:
        notes.append("VAE: random initialisation (no --vae-checkpoint): decoded frames are not meaningful.")
    # replicated over the mesh the world models are placed on (one jitted rollout reads both)
    vae_graphdef, vae_state = experiment_vae(cfg, inputs.vae_checkpoint, mesh=shd.make_mesh(cfg.mesh))
    gt = {s: v["frames"][:, :horizon] for s, v in splits.items()}
    predictions: dict[str, dict[str, np.ndarray]] = {}
    latent: dict[str, dict[str, dict[str, np.ndarray]]] = {}  # model -> split -> latent_errors()
    for name, workdir in models.items():
        if workdir is None:
            notes.append(f"Model '{name}': randomly initialised world model (pipeline smoke run).")
        model_cfg = model_config(cfg, workdir)
        wm_graphdef, wm_state = experiment_world_model(model_cfg, workdir)
        predictions[name], latent[name] = {}, {}
        for split, episodes in splits.items():
            t0 = time.time()
            predictions[name][split], latent[name][split] = rollout_videos(
                wm_graphdef, wm_state, vae_graphdef, vae_state, episodes["frames"][:, :horizon],
                episodes["actions"][:, :horizon], key=stream_key(jax.random.key(cfg.seed), f"evaluate/rollout/{split}"),
                flow_cfg=model_cfg.flow, num_context=k, num_future=p, with_latent_error=True)
            print(f"[evaluate] rolled out {name} on {split}: {gt[split].shape[0]} episodes x {horizon} frames "
                  f"in {time.time() - t0:.1f} s", flush=True)
    rollout_s = time.time() - start  # data, models and rollouts
    suite = MetricSuite(cfg.eval, metrics=inputs.metrics or cfg.eval.metrics)
    truth = {s: {key: v[key][:, :horizon] for key in ("targets", "rewards") if key in v} for s, v in splits.items()}
    results = evaluate_videos(suite, gt, predictions, given_frames=given, horizon_window=cfg.eval.horizon_window,
                              settings={"horizon": horizon, "given_frames": given, "config": cfg.name,
                                        "probe": inputs.probe, "reward_model": inputs.reward_model},
                              fidelity=_fidelity(cfg, inputs.probe, inputs.reward_model), truth_by_split=truth)
    add_latent_errors(results, latent, given_frames=given, horizon=horizon)
    notes += fidelity_notes(results) + latent_notes(results)
    metrics_s = time.time() - start - rollout_s
    results.vae_floor, floor_s = vae_floor(cfg.eval, suite.metrics, vae_graphdef, vae_state, gt, num_context=k,
                                           num_future=p, given_frames=given)
    results.settings["episodes"] = {s: int(v.shape[0]) for s, v in gt.items()}
    results.timing = {"rollout_s": rollout_s, "metrics_s": metrics_s,
                      **{f"of_which_{name}_s": sec for name, sec in suite.seconds.items()},
                      "vae_floor_s": floor_s, "total_s": time.time() - start}  # write_report adds report_s
    videos = {s: {"ground truth": gt[s][: cfg.eval.report_videos],
                  **{m: predictions[m][s][: cfg.eval.report_videos] for m in predictions}} for s in gt}
    out = inputs.out or cfg.eval.report_dir or os.path.join(cfg.workdir, "eval")
    path = write_report(out, results, videos, title=f"World-model evaluation: {cfg.name}", notes=notes,
                        max_episodes=cfg.eval.report_videos)
    print(f"[evaluate] report written to {path} ({time.time() - start:.1f} s)", flush=True)
    return {"report": path, "out": out}
