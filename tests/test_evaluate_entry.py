"""Smoke test of the evaluation entry point: tiny random world model, synthetic splits, report."""

import json
import os

import pytest

from train import evaluate


@pytest.mark.slow
def test_evaluate_entry_point_writes_report(tmp_path):
    out = tmp_path / "eval"
    path = evaluate.main([
        "--config", "sword:tiny", "--out", str(out), "--synthetic", "--metrics", "lpips,psnr,ssim",
        "--eval.allow_random_weights=true", "--eval.num_episodes=1", "--eval.horizon_frames=13",
        "--eval.report_videos=1",
    ])
    text = open(path).read()
    assert "random-init" in text and "Random-weight metric networks" in text and "VAE: random" in text
    results = json.load(open(out / "results.json"))
    assert set(results["models"]) == {"original", "mixed"}
    assert results["settings"]["horizon"] == 13
    assert os.path.getsize(out / "videos" / "original_ep0.gif") > 0


def test_effective_horizon_fits_rollout_layout():
    import configs

    cfg = configs.get("sword:tiny")
    assert evaluate.effective_horizon(cfg, 33) == (29, 1, 2)  # 1 + 4 + 8n <= 33
    with pytest.raises(SystemExit, match="cannot hold"):
        evaluate.effective_horizon(cfg, 9)
