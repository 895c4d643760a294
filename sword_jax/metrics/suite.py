"""Every video metric of the paper on (ground truth, prediction) video batches.

:class:`MetricSuite` takes the metric networks (weights per :mod:`sword_jax.metrics.networks`) and
their jitted forwards from :mod:`sword_jax.metrics.compiled`, which builds and compiles each once per
process (every suite, every evaluation stage in one process shares them), and computes:

  * per frame: LPIPS (v0.1, [-1, 1] convention on [0, 1] frames via ``normalize``), PSNR, SSIM;
  * per frame transition: FloLPIPS (Farneback flow, see :mod:`sword_jax.metrics.flolpips`);
  * per set: FID (pool3 of every frame, unbiased covariance as pytorch-fid) and FVD (I3D logits of
    non-overlapping ``fvd_clip_frames`` clips after the common FVD resize/crop, unbiased covariance
    as common_metrics_on_video_quality's styleganv method).

Videos are host arrays ``[B, T, H, W, 3]`` in [0, 1].
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from jaxtyping import Float

from sword_jax.metrics import compiled
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.flolpips import flolpips_video
from sword_jax.metrics.frechet import frechet_distance_from_features
from sword_jax.metrics.image_quality import psnr, ssim
from sword_jax.metrics.networks import MetricNetwork
from sword_jax.metrics.preprocess import check_range

ALL_METRICS = ("lpips", "flolpips", "psnr", "ssim", "fid", "fvd")
LOWER_IS_BETTER = {"lpips": True, "flolpips": True, "psnr": False, "ssim": False, "fid": True, "fvd": True}

_psnr = jax.jit(psnr)
_ssim = jax.jit(ssim)
_batched = compiled.batched


@dataclasses.dataclass
class VideoMetrics:
    """Metrics of one prediction set against ground truth.

    Attributes:
      per_frame: ``{"lpips"|"psnr"|"ssim": [B, T], "flolpips": [B, T-1]}``.
      overall: scalar per metric (per-frame metrics averaged, FID/FVD over the whole set).
    """

    per_frame: dict[str, np.ndarray]
    overall: dict[str, float]


class MetricSuite:
    """The metric networks plus the code that turns videos into numbers.

    Args:
      config: eval config (weights, batch sizes, FVD clip length).
      metrics: which metrics to compute (subset of :data:`ALL_METRICS`); networks are only built
        for these.
    """

    def __init__(self, config: EvalConfig, metrics: tuple[str, ...] = ALL_METRICS):
        unknown = set(metrics) - set(ALL_METRICS)
        if unknown:
            raise ValueError(f"unknown metrics {sorted(unknown)}; known: {ALL_METRICS}")
        self.config, self.metrics = config, tuple(metrics)
        self.networks: dict[str, MetricNetwork] = {}
        if "lpips" in metrics:
            self.networks["lpips"] = compiled.network("lpips", config)
            self._lpips = compiled.forward("lpips", "distance01", config)
        if "flolpips" in metrics:  # FloLPIPS is defined on AlexNet LPIPS
            self.networks["flolpips"] = compiled.network("lpips", config, net="alex")
            self._flow_weighted = compiled.forward("lpips", "flow_weighted", config, net="alex")
        if "fid" in metrics:
            self.networks["fid"] = compiled.network("fid", config)
            self._inception = compiled.forward("fid", "pool3", config)
        if "fvd" in metrics:
            self.networks["fvd"] = compiled.network("fvd", config)
            self._i3d = compiled.forward("fvd", "logits", config)
        self._psnr, self._ssim = _psnr, _ssim

    @property
    def random_weight_networks(self) -> list[str]:
        """Metrics whose network has random (not published) weights; their numbers are not comparable."""
        return sorted(name for name, net in self.networks.items() if net.random_weights)

    def describe_weights(self) -> dict[str, str]:
        """Where each network's weights came from."""
        return {name: net.source for name, net in self.networks.items()}

    def inception_features(self, frames: Float[np.ndarray, "n h w 3"]) -> Float[np.ndarray, "n 2048"]:
        """pool3 features of [0, 1] frames."""
        return _batched(self._inception, (np.asarray(frames, np.float32),), self.config.metric_batch_size)

    def i3d_features(self, videos: Float[np.ndarray, "b t h w 3"]) -> Float[np.ndarray, "n 400"]:
        """I3D logits of every non-overlapping ``fvd_clip_frames`` clip of each [0, 1] video."""
        videos = np.asarray(videos, np.float32)
        clip = self.config.fvd_clip_frames
        b, t = videos.shape[:2]
        if t < clip:
            raise ValueError(f"FVD needs videos of at least eval.fvd_clip_frames={clip} frames, got {t}")
        n_clips = t // clip
        clips = videos[:, : n_clips * clip].reshape(b * n_clips, clip, *videos.shape[2:])
        return _batched(self._i3d, (clips,), max(1, self.config.metric_batch_size // 4))

    def evaluate(self, gt: Float[np.ndarray, "b t h w 3"], pred: Float[np.ndarray, "b t h w 3"]) -> VideoMetrics:
        """Every configured metric of ``pred`` against ``gt``.

        Raises:
          ValueError: shape mismatch, NaN/Inf, values outside [0, 1].
        """
        gt, pred = np.asarray(gt, np.float32), np.asarray(pred, np.float32)
        if gt.shape != pred.shape or gt.ndim != 5 or gt.shape[-1] != 3:
            raise ValueError(f"gt {gt.shape} and pred {pred.shape} must both be [B, T, H, W, 3]")
        check_range(gt, 0.0, 1.0, "ground-truth video")
        check_range(pred, 0.0, 1.0, "predicted video")
        b, t = gt.shape[:2]
        frames_gt, frames_pred = gt.reshape(b * t, *gt.shape[2:]), pred.reshape(b * t, *pred.shape[2:])
        per_frame: dict[str, np.ndarray] = {}
        batch = self.config.metric_batch_size
        if "lpips" in self.metrics:
            per_frame["lpips"] = _batched(self._lpips, (frames_gt, frames_pred), batch).reshape(b, t)
        if "psnr" in self.metrics:
            per_frame["psnr"] = _batched(self._psnr, (frames_pred, frames_gt), batch).reshape(b, t)
        if "ssim" in self.metrics:
            per_frame["ssim"] = _batched(self._ssim, (frames_pred, frames_gt), batch).reshape(b, t)
        if "flolpips" in self.metrics and t >= 2:
            lpips_net = self.networks["flolpips"].module
            per_frame["flolpips"] = np.stack(
                [flolpips_video(lpips_net, g, p, score_fn=self._flow_weighted) for g, p in zip(gt, pred)]
            )
        overall = {name: float(values.mean()) for name, values in per_frame.items()}
        if "fid" in self.metrics:
            overall["fid"] = frechet_distance_from_features(
                self.inception_features(frames_pred), self.inception_features(frames_gt)
            )
        if "fvd" in self.metrics:
            overall["fvd"] = frechet_distance_from_features(self.i3d_features(pred), self.i3d_features(gt))
        return VideoMetrics(per_frame, overall)
