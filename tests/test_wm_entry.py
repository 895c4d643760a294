"""Entry point smoke test: train a few steps, resume exactly, stop cleanly on a non-finite loss."""

import glob
import json
import os

import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.world_model import data
from sword_jax import train_loop
from tests.support.world_model import MixerWorldModel
from sword_jax.pipeline import world_model as wm_run
from train import distributed, train_world_model

ARGS = ["--config", "sword:tiny", "--synthetic", "--model.num_layers=1", "--trainer.log_every=1",
        "--trainer.checkpoint_every=2", "--mesh.data=2", "--mesh.tensor=4"]  # the tiny batch of 2 splits over data


def _params_at(workdir, step):
    import orbax.checkpoint as ocp

    path = os.path.join(workdir, "checkpoints", str(step), "state")
    return ocp.StandardCheckpointer().restore(path)


@pytest.mark.slow
def test_train_resume_equals_uninterrupted(tmp_path, capsys):
    straight, split = str(tmp_path / "straight"), str(tmp_path / "split")
    out = train_world_model.main(ARGS + ["--workdir", straight, "--trainer.steps=4"])
    assert out["step"] == 4 and np.isfinite(out["metrics"]["loss"])
    train_world_model.main(ARGS + ["--workdir", split, "--trainer.steps=2"])
    resumed = train_world_model.main(ARGS + ["--workdir", split, "--trainer.steps=4"])
    assert resumed["step"] == 4
    printed = capsys.readouterr().out
    assert "latent cache:" in printed and "resumed from step 2" in printed and "ETA" in printed
    a, b = _params_at(straight, 4), _params_at(split, 4)
    for x, y in zip(_leaves(a), _leaves(b)):
        np.testing.assert_array_equal(x, y)
    assert np.asarray(b["cache"]["filled"]).any()
    rows = [json.loads(line) for line in open(os.path.join(split, "metrics.jsonl"))]
    assert [r["step"] for r in rows] == [1, 2, 3, 4]
    assert glob.glob(os.path.join(split, "tensorboard", "events.out.tfevents.*"))  # both runs wrote events
    with pytest.raises(SystemExit, match="another config"):
        train_world_model.main(ARGS + ["--workdir", split, "--trainer.steps=5", "--trainer.learning_rate=0.5"])


def _leaves(tree):
    import jax

    return [np.asarray(x) for x in jax.tree.leaves(tree)]


@pytest.mark.slow  # test_reliability checks the same stop in the default run, with a finite last checkpoint
def test_nonfinite_loss_stops_and_keeps_last_good_checkpoint(tmp_path):
    ds = data.synthetic_latent_dataset(8, 9, 2, 2, 48, seed=0)
    huge = ds.latents * np.float32(1e30)  # finite, but the squared error overflows
    path = str(tmp_path / "huge.npz")
    np.savez(path, latents=huge, actions=ds.actions)
    workdir = str(tmp_path / "run")
    args = [a for a in ARGS if a != "--synthetic"] + ["--workdir", workdir, "--trainer.steps=3", f"--data.path={path}"]
    with pytest.raises(train_loop.NonFiniteLoss, match="step 0"):
        train_world_model.main(args)
    assert not os.path.exists(os.path.join(workdir, "checkpoints", "2"))


def test_config_checks_name_the_same_differing_sections(tmp_path):
    """The work dir's config.json check and the checkpoint's run check share one diff (top-level sections)."""
    saved = {"data": {"image_size": 32}, "model": {"depth": 2}, "trainer": {"steps": 4}, "workdir": "a", "mesh": {}}
    wm_run._check_config_matches(str(tmp_path), saved)  # first use: stored
    current = {**saved, "data": {"image_size": 64}, "model": {"depth": 3}, "trainer": {"steps": 9}, "workdir": "b"}
    assert train_loop.differing_keys(saved, current) == ["data", "model", "trainer", "workdir"]
    # the work dir check ignores resumable trainer keys (steps) and the work dir itself
    with pytest.raises(SystemExit, match=r"sections differ: \['data', 'model'\]"):
        wm_run._check_config_matches(str(tmp_path), current)
    with pytest.raises(ValueError, match=r"differs in \['data', 'model', 'trainer', 'workdir'\]"):
        train_loop._check_same_run("x", str(tmp_path), saved, current)
    train_loop._check_same_run("x", str(tmp_path), saved, dict(saved))  # the same run passes


def test_a_step_that_retraces_past_the_entry_bound_stops_the_run(tmp_path, monkeypatch):
    """Latents of another dtype every step make the step trace again; the trace past
    ``ENTRY_MAX_TRACES`` stops the run naming the step (unguarded, it would recompile every step)."""
    dtypes = (np.float32, np.float16, jnp.bfloat16)[:distributed.ENTRY_MAX_TRACES + 1]
    assert len(dtypes) == distributed.ENTRY_MAX_TRACES + 1
    batch_at = data.SegmentLoader.host_batch_at

    def drifting_batch_at(loader, step):
        batch = batch_at(loader, step)
        return {**batch, "latents": batch["latents"].astype(dtypes[step % len(dtypes)])}

    monkeypatch.setattr(data.SegmentLoader, "host_batch_at", drifting_batch_at)
    # the stand-in compiles in a blink; the guard is about the step, not the model
    monkeypatch.setattr(wm_run, "WorldModel",
                        lambda cfg, *, rngs: MixerWorldModel(cfg.in_dim, cfg.action_dim, rngs=rngs))
    args = ARGS + ["--workdir", str(tmp_path / "run"), f"--trainer.steps={len(dtypes)}",
                   "--trainer.checkpoint_every=100", "--cache.log_inference_distance=false"]
    with pytest.raises(RuntimeError, match=f"step was traced {len(dtypes)} times .at most "
                                           f"{distributed.ENTRY_MAX_TRACES} allowed"):
        train_world_model.main(args)


def test_a_checkpoint_step_path_and_a_kept_ema_load_the_weights_they_name(tmp_path):
    """``--world-model <workdir>/checkpoints/<step>`` (GRPO, SFT on imagined frames) loads that step, not the newest;
    with trainer.ema_decay > 0 the saved EMA weights are what the learned simulator and every evaluation load
    (``experiment_world_model``), ``use_ema=False`` gives the trained weights. (One run serves both, to train as
    little as possible; a run without an EMA: the next test.)"""
    import configs
    from sword_jax.load import CheckpointError, experiment_world_model, load_world_model_params

    args = ARGS + ["--cache.log_inference_distance=false", "--trainer.eval_every=0"]  # loading depends on neither
    workdir = str(tmp_path / "ema")
    train_world_model.main(args + ["--workdir", workdir, "--trainer.steps=4", "--trainer.keep_checkpoints=2",
                                   "--trainer.ema_decay=0.5"])
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--model.num_layers=1", "--trainer.ema_decay=0.5"])
    checkpoints = os.path.join(workdir, "checkpoints")
    newest = _leaves(experiment_world_model(cfg, workdir)[1])
    at_2 = _leaves(experiment_world_model(cfg, os.path.join(checkpoints, "2"))[1])
    saved_2 = _leaves(load_world_model_params(cfg.model, checkpoints, step=2)[1])
    assert len(at_2) == len(newest) == len(saved_2) and any(not np.array_equal(a, b) for a, b in zip(at_2, newest))
    for a, b, c in zip(at_2, saved_2, _leaves(_params_at(workdir, 2)["ema_params"])):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(b, c)
    with pytest.raises(CheckpointError, match="does not exist"):
        experiment_world_model(cfg, os.path.join(checkpoints, "3"))

    state = _params_at(workdir, 4)
    loaded = experiment_world_model(cfg, workdir)[1][0]
    ema, params = (load_world_model_params(cfg.model, checkpoints, use_ema=use)[1][0] for use in (True, False))
    assert len(_leaves(loaded)) == len(_leaves(state["ema_params"])) > 0
    for a, b, c in zip(_leaves(loaded), _leaves(ema), _leaves(state["ema_params"])):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(b, c)
    for a, b in zip(_leaves(params), _leaves(state["params"])):
        np.testing.assert_array_equal(a, b)
    assert any(not np.array_equal(a, b) for a, b in zip(_leaves(ema), _leaves(params)))


def test_a_run_without_an_ema_loads_its_trained_weights_whatever_the_loading_configs_ema(tiny_run):
    """The tiny run trained no EMA: a loading config with trainer.ema_decay > 0 still gets the trained weights."""
    import configs
    from sword_jax.load import experiment_world_model

    workdir = os.path.join(tiny_run, "world_model")
    step = max(int(d) for d in os.listdir(os.path.join(workdir, "checkpoints")) if d.isdigit())
    state = _params_at(workdir, step)
    assert state.get("ema_params") is None
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--model.num_layers=1", "--trainer.ema_decay=0.5"])
    loaded = _leaves(experiment_world_model(cfg, workdir)[1][0])
    assert len(loaded) == len(_leaves(state["params"])) > 0
    for a, b in zip(loaded, _leaves(state["params"])):
        np.testing.assert_array_equal(a, b)
