"""The VAE's reconstruction floor in the evaluation: the rollout's decode path, in results.json and the report."""

import json

import jax
import numpy as np
import pytest

from sword_jax.evaluation.harness import evaluate_videos
from sword_jax.evaluation.report import write_report
from sword_jax.evaluation.vae_floor import reconstruct_videos, vae_floor
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.suite import MetricSuite
from sword_jax.vae import api as vae_api
from sword_jax.vae import tiny_config


def test_vae_floor_is_the_encode_decode_and_reaches_results_and_report(tmp_path):
    from flax import nnx

    cfg = tiny_config(z_dim=8)
    graphdef, state = nnx.split(vae_api.create_vae(cfg, key=jax.random.key(0)))
    rng = np.random.default_rng(0)
    gt = {"original": rng.random((3, 9, 16, 16, 3)).astype(np.float32)}
    gt["mixed"] = gt["original"][:, :, :, :, ::-1].copy()
    recon = reconstruct_videos(graphdef, state, gt["original"], num_context=1, num_future=2, batch=2)  # 2 + 1 padded
    eval_cfg = EvalConfig(allow_random_weights=True)
    floor, seconds = vae_floor(eval_cfg, ("psnr", "fvd"), graphdef, state, gt, num_context=1, num_future=2,
                               given_frames=5, batch=2)
    assert set(floor) == {"original", "mixed"} and set(floor["original"].overall) == {"psnr"} and seconds > 0
    expected = np.mean([[10 * np.log10(1 / np.mean((r[t] - g[t]) ** 2)) for t in range(5, 9)]
                        for r, g in zip(recon, gt["original"])])
    assert floor["original"].overall["psnr"] == pytest.approx(expected, rel=1e-4)
    # eval.floor_metrics chooses among the evaluation's metrics (small and paper add FVD/FloLPIPS)
    chosen, _ = vae_floor(EvalConfig(allow_random_weights=True, floor_metrics=("ssim", "psnr")), ("psnr", "lpips", "ssim"),
                          graphdef, state, {"original": gt["original"]}, num_context=1, num_future=2, given_frames=5)
    assert set(chosen["original"].overall) == {"psnr", "ssim"}
    assert chosen["original"].overall["psnr"] == pytest.approx(floor["original"].overall["psnr"], rel=1e-5)
    with pytest.raises(ValueError, match="eval.floor_metrics"):
        EvalConfig(floor_metrics=("psnr", "nope")).validate()

    suite = MetricSuite(eval_cfg, metrics=("psnr",))
    results = evaluate_videos(suite, gt, {"m": {s: np.clip(v + 0.2, 0, 1) for s, v in gt.items()}}, given_frames=5,
                              progress=lambda _: None)
    results.vae_floor, results.timing = floor, {"rollout_s": 1.0, "metrics_s": 2.0, "total_s": 3.0}
    md = open(write_report(str(tmp_path), results, {}, notes=[])).read()
    saved = json.load(open(tmp_path / "results.json"))
    for split in gt:
        entry = saved["vae_floor"][split]
        assert entry["overall"]["psnr"] == pytest.approx(floor[split].overall["psnr"])
        lo, hi = entry["curves"]["psnr"]["overall_ci"]
        assert lo <= entry["overall"]["psnr"] <= hi
        assert f"VAE reconstruction floor on {split}" in md
    assert "VAE floor (encode-decode of ground truth)" in md
    timing = saved["timing"]
    assert timing["report_s"] > 0 and timing["total_s"] == pytest.approx(3.0 + timing["report_s"], abs=0.02)


@pytest.mark.slow
def test_reconstruction_is_the_whole_sequence_encode_decode():
    from flax import nnx

    graphdef, state = nnx.split(vae_api.create_vae(tiny_config(z_dim=8), key=jax.random.key(0)))
    video = np.random.default_rng(0).random((3, 9, 16, 16, 3)).astype(np.float32)
    # Padded batches (2 + 1) and the chunked streaming decode equal one whole-sequence encode -> decode.
    recon = reconstruct_videos(graphdef, state, video, num_context=1, num_future=2, batch=2)
    direct = vae_api.decode(graphdef, state, vae_api.encode(graphdef, state, video * 2 - 1), clamp=True)
    np.testing.assert_allclose(recon, np.clip((np.asarray(direct) + 1) / 2, 0, 1), atol=2e-5)


@pytest.mark.slow
def test_tiny_evaluation_writes_floor_intervals_and_timing(tmp_path):
    from train import evaluate_world_model

    out = tmp_path / "eval"
    evaluate_world_model.main(["--config", "sword:tiny", "--out", str(out), "--synthetic", "--metrics", "lpips,psnr",
                               "--eval.num_episodes=3", "--eval.horizon_frames=13", "--eval.report_videos=1"])
    results = json.load(open(out / "results.json"))
    assert results["settings"]["episodes"] == {"original": 3, "mixed": 3}
    for split in ("original", "mixed"):
        assert set(results["vae_floor"][split]["overall"]) == {"lpips", "psnr"}
        curve = results["models"][split]["random-init"]["curves"]["lpips"]
        assert len(curve["ci_low"]) == len(curve["frames"]) == 8
    assert all(results["timing"][k] > 0 for k in ("rollout_s", "metrics_s", "vae_floor_s", "report_s", "total_s"))
