"""Every video metric of the paper on (ground truth, prediction) video batches.

:class:`MetricSuite` takes the metric networks (weights per :mod:`sword_jax.metrics.networks`) and
their jitted forwards from :mod:`sword_jax.metrics.compiled`, which builds and compiles each once per
process (every suite, every evaluation stage in one process shares them), and computes:

  * per frame: LPIPS (v0.1, [-1, 1] convention on [0, 1] frames via ``normalize``), PSNR, SSIM;
  * per frame transition: FloLPIPS (Farneback flow, see :mod:`sword_jax.metrics.flolpips`);
  * per set: FID (pool3 of every frame, unbiased covariance as pytorch-fid) and FVD (I3D logits of
    non-overlapping ``fvd_clip_frames`` clips after the common FVD resize/crop, unbiased covariance
    as common_metrics_on_video_quality's styleganv method).

Videos are host arrays ``[B, T, H, W, 3]`` in [0, 1]. Everything computed from the ground truth alone
(its optical flow, Inception and I3D features) can be computed once with :meth:`MetricSuite.reference`
and shared by every prediction scored against it; :attr:`MetricSuite.seconds` accumulates the wall time
per metric.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import time

import jax
import numpy as np
from jaxtyping import Float

from sword_jax.metrics import compiled
from sword_jax.metrics.config import ALL_METRICS, EvalConfig
from sword_jax.metrics.flolpips import farneback_flows, flolpips_video
from sword_jax.metrics.frechet import frechet_distance_from_features
from sword_jax.metrics.image_quality import psnr, ssim
from sword_jax.metrics.networks import MetricNetwork
from sword_jax.metrics.preprocess import check_range

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
      inception, i3d: the prediction's features (``[B, T, 2048]`` per frame; ``[B, T // clip, 400]`` per
        clip), where FID / FVD were computed, for horizon curves without a second forward pass.
    """

    per_frame: dict[str, np.ndarray]
    overall: dict[str, float]
    inception: np.ndarray | None = None
    i3d: np.ndarray | None = None


@dataclasses.dataclass
class Reference:
    """What the metrics need from a ground-truth video batch alone, computed once per batch.

    Attributes:
      video: the ground truth ``[B, T, H, W, 3]`` float32 in [0, 1].
      flows: per video, Farneback flow between consecutive frames ``[T-1, H, W, 2]`` (FloLPIPS).
      inception: pool3 features ``[B, T, 2048]`` (FID).
      i3d: I3D logits per non-overlapping clip ``[B, T // clip, 400]`` (FVD).
    """

    video: np.ndarray
    flows: list[np.ndarray] | None = None
    inception: np.ndarray | None = None
    i3d: np.ndarray | None = None


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
        self.seconds: collections.Counter = collections.Counter()  # wall time per metric, accumulated

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

    def reference(self, gt: Float[np.ndarray, "b t h w 3"]) -> Reference:
        """The ground truth's flows and features for the configured metrics (pass to :meth:`evaluate`).

        Raises:
          ValueError: not ``[B, T, H, W, 3]``, NaN/Inf, values outside [0, 1].
        """
        gt = np.asarray(gt, np.float32)
        if gt.ndim != 5 or gt.shape[-1] != 3:
            raise ValueError(f"ground truth must be [B, T, H, W, 3], got {gt.shape}")
        check_range(gt, 0.0, 1.0, "ground-truth video")
        ref = Reference(gt)
        b, t = gt.shape[:2]
        if "flolpips" in self.metrics and t >= 2:
            with self._timed("flolpips"):
                ref.flows = farneback_flows(list(gt))
        if "fid" in self.metrics:
            with self._timed("fid"):
                ref.inception = self.inception_features(gt.reshape(b * t, *gt.shape[2:])).reshape(b, t, -1)
        if "fvd" in self.metrics and t >= self.config.fvd_clip_frames:
            with self._timed("fvd"):
                ref.i3d = self.i3d_features(gt).reshape(b, t // self.config.fvd_clip_frames, -1)
        return ref

    @contextlib.contextmanager
    def _timed(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - start

    def evaluate(self, gt: Float[np.ndarray, "b t h w 3"], pred: Float[np.ndarray, "b t h w 3"], *,
                 reference: Reference | None = None) -> VideoMetrics:
        """Every configured metric of ``pred`` against ``gt``.

        Args:
          gt, pred: videos in [0, 1], same shape.
          reference: :meth:`reference` of ``gt``, where several predictions are scored against it.

        Raises:
          ValueError: shape mismatch, NaN/Inf, values outside [0, 1], a reference of another video.
        """
        gt, pred = np.asarray(gt, np.float32), np.asarray(pred, np.float32)
        if gt.shape != pred.shape or gt.ndim != 5 or gt.shape[-1] != 3:
            raise ValueError(f"gt {gt.shape} and pred {pred.shape} must both be [B, T, H, W, 3]")
        check_range(pred, 0.0, 1.0, "predicted video")
        if reference is None:
            reference = self.reference(gt)
        elif reference.video.shape != gt.shape or not (reference.video is gt or np.array_equal(reference.video, gt)):
            raise ValueError("reference was computed from another ground-truth video")
        b, t = gt.shape[:2]
        frames_gt, frames_pred = gt.reshape(b * t, *gt.shape[2:]), pred.reshape(b * t, *pred.shape[2:])
        per_frame: dict[str, np.ndarray] = {}
        batch = self.config.metric_batch_size
        if "lpips" in self.metrics:
            with self._timed("lpips"):
                per_frame["lpips"] = _batched(self._lpips, (frames_gt, frames_pred), batch).reshape(b, t)
        if "psnr" in self.metrics:
            with self._timed("psnr"):
                per_frame["psnr"] = _batched(self._psnr, (frames_pred, frames_gt), batch).reshape(b, t)
        if "ssim" in self.metrics:
            with self._timed("ssim"):
                per_frame["ssim"] = _batched(self._ssim, (frames_pred, frames_gt), batch).reshape(b, t)
        if "flolpips" in self.metrics and t >= 2:
            with self._timed("flolpips"):
                lpips_net = self.networks["flolpips"].module
                dis_flows = farneback_flows(list(pred))
                per_frame["flolpips"] = np.stack(
                    [flolpips_video(lpips_net, g, p, score_fn=self._flow_weighted, ref_flow=rf, dis_flow=df)
                     for g, p, rf, df in zip(gt, pred, reference.flows, dis_flows)]
                )
        overall = {name: float(values.mean()) for name, values in per_frame.items()}
        inception = i3d = None
        if "fid" in self.metrics:
            with self._timed("fid"):
                inception = self.inception_features(frames_pred).reshape(b, t, -1)
                overall["fid"] = frechet_distance_from_features(inception.reshape(b * t, -1),
                                                                reference.inception.reshape(b * t, -1))
        if "fvd" in self.metrics:
            with self._timed("fvd"):
                i3d = self.i3d_features(pred).reshape(b, t // self.config.fvd_clip_frames, -1)
                overall["fvd"] = frechet_distance_from_features(i3d.reshape(-1, i3d.shape[-1]),
                                                                reference.i3d.reshape(-1, reference.i3d.shape[-1]))
        return VideoMetrics(per_frame, overall, inception, i3d)
