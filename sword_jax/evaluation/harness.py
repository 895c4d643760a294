"""Long-horizon evaluation: roll world models out on held-out episodes and score them.

Two layers:
  * :func:`evaluate_videos` takes plain arrays -- ground-truth videos per split and each model's
    predicted videos -- and computes every metric overall and against horizon (frame 0, the given
    first frame, is excluded: it is conditioning, not prediction).
  * :func:`rollout_videos` produces a model's predicted videos: encode the first frame and the first
    context chunk with the VAE, roll the world model out in latent space with the ground-truth
    actions (:func:`sword_jax.world_model.rollout.rollout`, one scan in one jit), decode with the
    streaming VAE decoder, map [-1, 1] -> [0, 1].
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Float

from sword_jax.evaluation.horizon import Curve, horizon_windows, per_frame_curve
from sword_jax.evaluation.probe import FidelityScorer
from sword_jax.evaluation.results import EvalResults, ModelResult
from sword_jax.metrics.frechet import frechet_distance_from_features
from sword_jax.metrics.suite import MetricSuite, Reference

ProgressFn = Callable[[str], None]


def _window_curve(features_pred: list[np.ndarray], features_gt: list[np.ndarray], windows: list[tuple[int, int]]) -> Curve | None:
    frames, values = [], []
    for (lo, hi), fp, fg in zip(windows, features_pred, features_gt):
        if fp.shape[0] >= 2 and fg.shape[0] >= 2:
            frames.append((lo + hi - 1) / 2)
            values.append(frechet_distance_from_features(fp, fg))
    if not values:
        return None
    return Curve(np.asarray(frames), np.asarray(values), np.zeros(len(values)))


def evaluate_model(suite: MetricSuite, gt: Float[np.ndarray, "b t h w 3"], pred: Float[np.ndarray, "b t h w 3"], *,
                   horizon_window: int = 16, given_frames: int = 1, fidelity: FidelityScorer | None = None,
                   truth: dict[str, np.ndarray] | None = None, reference: Reference | None = None) -> ModelResult:
    """Every metric of one model's predictions against ground truth (frames ``given_frames``..T-1).

    Args:
      suite: the metric networks.
      gt, pred: videos in [0, 1].
      horizon_window: frames per window of the FID/FVD-vs-horizon curves.
      given_frames: leading frames that were conditioning, not prediction (the first frame and
        the context chunk); excluded from every metric. Curves count horizon from frame 0.
      fidelity: action-following probe / success detector (:mod:`sword_jax.evaluation.probe`).
      truth: per-episode ``targets [B, T, 7]`` / ``rewards [B, T]`` of the ground truth (optional).
      reference: ``suite.reference`` of the scored ground-truth frames (``gt[:, given_frames:]``), where
        several models are scored against the same ground truth (:func:`evaluate_videos`).
    """
    if not 0 <= given_frames < gt.shape[1] - 1:
        raise ValueError(f"given_frames={given_frames} leaves fewer than 2 of {gt.shape[1]} frames to score")
    gt = np.asarray(gt, np.float32)[:, given_frames:]
    pred = np.asarray(pred, np.float32)[:, given_frames:]
    reference = reference if reference is not None else suite.reference(gt)
    metrics = suite.evaluate(gt, pred, reference=reference)
    curves = {name: per_frame_curve(values, frame_offset=given_frames).to_dict() for name, values in metrics.per_frame.items()}
    t = gt.shape[1]
    if metrics.inception is not None:  # FID per horizon window, from the features FID was computed on
        windows = horizon_windows(t, min(horizon_window, t))
        feats_p, feats_g = metrics.inception, reference.inception
        curve = _window_curve([feats_p[:, lo:hi].reshape(-1, feats_p.shape[-1]) for lo, hi in windows],
                              [feats_g[:, lo:hi].reshape(-1, feats_g.shape[-1]) for lo, hi in windows], windows)
        if curve is not None:
            curves["fid"] = Curve(curve.frames + given_frames, curve.mean, curve.stderr).to_dict()
    if metrics.i3d is not None:  # FVD per clip: FVD's clips are the horizon's consecutive windows
        clip = suite.config.fvd_clip_frames
        windows = horizon_windows(t, clip)
        curve = _window_curve([metrics.i3d[:, i] for i in range(len(windows))],
                              [reference.i3d[:, i] for i in range(len(windows))], windows)
        if curve is not None:
            curves["fvd"] = Curve(curve.frames + given_frames, curve.mean, curve.stderr).to_dict()
    overall = dict(metrics.overall)
    if fidelity is not None:
        truth = {k: np.asarray(v)[:, given_frames:given_frames + t] for k, v in (truth or {}).items()}
        per_frame, scalars = fidelity.score(gt, pred, targets=truth.get("targets"), rewards=truth.get("rewards"))
        for name, values in per_frame.items():
            curves[name] = per_frame_curve(values, frame_offset=given_frames).to_dict()
            overall[name] = float(values.mean())
        overall.update(scalars)
    return ModelResult(overall, curves)


def evaluate_videos(suite: MetricSuite, gt_by_split: dict[str, np.ndarray],
                    predictions: dict[str, dict[str, np.ndarray]], *, horizon_window: int = 16,
                    given_frames: int = 1, settings: dict | None = None, progress: ProgressFn = print,
                    fidelity: FidelityScorer | None = None,
                    truth_by_split: dict[str, dict[str, np.ndarray]] | None = None) -> EvalResults:
    """Scores several models side by side on several splits.

    Args:
      suite: the metric networks.
      gt_by_split: ``{split: [B, T, H, W, 3]}`` ground-truth videos in [0, 1].
      predictions: ``{model: {split: [B, T, H, W, 3]}}`` predicted videos (same shapes).
      horizon_window: frames per FID window on the horizon curves.
      given_frames: leading conditioning frames excluded from the metrics (see :func:`evaluate_model`).
      settings: recorded in the results.
      progress: called with one line per (split, model).
      fidelity, truth_by_split: action-following metrics and ``{split: truth}`` (see :func:`evaluate_model`).

    Returns:
      Results for :func:`sword_jax.evaluation.report.write_report`.
    """
    models: dict[str, dict[str, ModelResult]] = {}
    for split, gt in gt_by_split.items():
        models[split] = {}
        if not 0 <= given_frames < gt.shape[1] - 1:
            raise ValueError(f"given_frames={given_frames} leaves fewer than 2 of {gt.shape[1]} frames to score")
        reference = suite.reference(np.asarray(gt, np.float32)[:, given_frames:])  # shared by every model
        for model, per_split in predictions.items():
            if split not in per_split:
                raise KeyError(f"model {model!r} has no predictions for split {split!r}")
            if per_split[split].shape != gt.shape:
                raise ValueError(f"{model}/{split}: predictions {per_split[split].shape} != ground truth {gt.shape}")
            models[split][model] = evaluate_model(suite, gt, per_split[split], horizon_window=horizon_window,
                                                  given_frames=given_frames, fidelity=fidelity,
                                                  truth=(truth_by_split or {}).get(split), reference=reference)
            summary = ", ".join(f"{k}={v:.4g}" for k, v in models[split][model].overall.items())
            progress(f"[evaluate] {split} / {model}: {summary}")
    return EvalResults(suite.metrics, models, suite.random_weight_networks, suite.describe_weights(), settings or {})


def rollout_videos(wm_graphdef: nnx.GraphDef, wm_state: Any, vae_graphdef: nnx.GraphDef, vae_state: Any,
                   frames: Float[np.ndarray, "b t h w 3"], actions: Float[np.ndarray, "b t a"], *, key: jax.Array,
                   flow_cfg, num_context: int = 1, num_future: int = 2, num_steps: int | None = None,
                   with_latent_error: bool = False) -> np.ndarray | tuple[np.ndarray, dict[str, np.ndarray]]:
    """Predicted videos of one world model from each episode's first frame and first context chunk.

    Args:
      wm_graphdef, wm_state: the world model (``state`` as :func:`rollout.rollout` takes it).
      vae_graphdef, vae_state: the video VAE.
      frames: ground-truth videos in [0, 1], ``T = 1 + 4k + 4pn`` frames (the horizon).
      actions: per-frame ground-truth actions, ``[B, T, a]``.
      key: sampling key.
      flow_cfg: :class:`FlowConfig` of the world model.
      num_context, num_future: latents of context / predicted per chunk (``k``, ``p``).
      num_steps: Euler steps per chunk (default from ``flow_cfg``).

      with_latent_error: also return the world model's error in latent space, free of the VAE's
        reconstruction error (:func:`latent_errors`).

    Returns:
      ``[B, T, H, W, 3]`` in [0, 1]: frame 0 and the context frames decoded from their latents,
      then the predicted frames; with ``with_latent_error``, also :func:`latent_errors`' dict.
    """
    from sword_jax.world_model import rollout as wm_rollout

    frames = np.asarray(frames, np.float32)
    b, t = frames.shape[:2]
    if actions.shape[:2] != (b, t):
        raise ValueError(f"actions {actions.shape} must be [B, T, a] matching frames {frames.shape}")
    wm_rollout.num_chunks_for(t, num_context, num_future)  # validates the horizon
    run = _rollout_fn(wm_graphdef, vae_graphdef, flow_cfg, num_context, num_future, num_steps)
    out, predicted, truth = run(wm_state, vae_state, jnp.asarray(frames), jnp.asarray(actions, jnp.float32), key)
    video = np.clip(np.asarray(out)[:, :t], 0.0, 1.0)
    if not with_latent_error:
        return video
    return video, latent_errors(np.asarray(predicted), np.asarray(truth), num_context=num_context)


def latent_errors(predicted: Float[np.ndarray, "b l h w c"], truth: Float[np.ndarray, "b L h w c"], *,
                  num_context: int) -> dict[str, np.ndarray]:
    """Per-frame mean squared error of predicted latents against the encoded ground truth.

    Pixel metrics include the VAE's reconstruction error (the "VAE floor"); where the VAE is lossy
    they measure the VAE, not the world model. Latents are compared before decoding, so this error
    is the world model's alone. ``latent_mse_hold`` is the same error for holding the last context
    latent still (a model that predicts no motion), the reference that says whether the model
    predicts motion at all.

    Args:
      predicted: ``[B, l, h, w, c]`` predicted latents (after the ``num_context`` given ones).
      truth: ``[B, L >= 1 + num_context + l, h, w, c]`` latents of the ground-truth video (``mu``).

    Returns:
      ``{"latent_mse", "latent_mse_hold"}``, each ``[B, 4 l]``: every predicted latent's error
      repeated over the 4 video frames it decodes to, so it lines up with the per-frame pixel metrics.
    """
    lead = 1 + num_context
    target = truth[:, lead: lead + predicted.shape[1]].astype(np.float32)
    if target.shape != predicted.shape:
        raise ValueError(f"latent_errors: predicted {predicted.shape} vs ground-truth latents {truth.shape} "
                         f"after {lead} given latents")
    hold = truth[:, lead - 1: lead].astype(np.float32)
    axes = (2, 3, 4)
    per_latent = {"latent_mse": np.mean((predicted.astype(np.float32) - target) ** 2, axis=axes),
                  "latent_mse_hold": np.mean((hold - target) ** 2, axis=axes)}
    return {name: np.repeat(values, 4, axis=1) for name, values in per_latent.items()}


@functools.lru_cache(maxsize=8)
def _rollout_fn(wm_graphdef, vae_graphdef, flow_cfg, num_context: int, num_future: int, num_steps: int | None):
    """One compiled encode -> rollout -> decode per (model graph, VAE graph, settings)."""
    from sword_jax.vae import api as vae_api
    from sword_jax.world_model import rollout as wm_rollout

    @jax.jit
    def run(wm_state, vae_state, video, acts, key):
        signed = video * jnp.float32(2) - jnp.float32(1)
        given = 1 + vae_api.factors(vae_graphdef, vae_state)[0] * num_context  # the first and the context frames
        video_out, predicted, _ = wm_rollout.rollout_video(
            wm_graphdef, wm_state, vae_graphdef, vae_state, signed[:, :given], acts, key=key,
            cfg=flow_cfg, num_future=num_future, num_steps=num_steps)
        # the ground truth's own latents (causal encoder: the given ones equal rollout_video's)
        truth = vae_api.encode(vae_graphdef, vae_state, signed, check_values=False)
        return (video_out + jnp.float32(1)) / jnp.float32(2), predicted, truth

    return run
