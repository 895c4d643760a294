"""The world model measured while it trains: held-out and training segments' flow loss and sampler error
(``sword_jax.world_model.heldout``), inside the trainer and on designed models."""

import json
import os
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax import sharding as shd
from sword_jax.pipeline import world_model as wm_run
from sword_jax.world_model import data, heldout
from sword_jax.world_model.config import FlowConfig, TrainerConfig
from tests.support.world_model import MixerWorldModel
from train import train_world_model

FLOW = FlowConfig()
NUM_CONTEXT, NUM_FUTURE = 1, 2
NUM_COND = 1 + NUM_CONTEXT


class Oracle(nnx.Module):
    """Knows that every future latent is ``value``: the exact velocity of the straight path from noise to it."""

    def __init__(self, value: float):
        self.value = nnx.Param(jnp.float32(value))

    def __call__(self, latents, timesteps, actions):
        sigma = (timesteps / FLOW.num_train_timesteps)[:, :, None, None, None]
        return jnp.where(sigma > 0, (latents - self.value[...]) / jnp.maximum(sigma, 1e-6), 0.0)


class Curved(nnx.Module):
    """Velocity = the noisy latents: the sampler's path curves, so its error depends on the Euler steps."""

    def __init__(self):
        self.gain = nnx.Param(jnp.float32(1.0))

    def __call__(self, latents, timesteps, actions):
        return latents * self.gain[...]


def _batch(value: float, size: int = 4) -> dict:
    dataset = data.LatentDataset(np.full((3, 6, 2, 2, 4), value, np.float32),
                                 np.random.default_rng(0).normal(size=(3, 21, 7)).astype(np.float32))
    episodes, starts = heldout.fixed_segments(dataset, size, NUM_CONTEXT, NUM_FUTURE, seed=0)
    return {k: jnp.asarray(v) for k, v in dataset.segment(episodes, starts, NUM_CONTEXT, NUM_FUTURE).items()}


def _measure(model, steps, batch, key=0):
    graphdef, params, buffers = nnx.split(model, nnx.Param, ...)
    measure = jax.jit(heldout.make_measure(graphdef, FLOW, NUM_CONTEXT, steps))
    return {k: float(v) for k, v in measure(params, buffers, batch, jax.random.key(key)).items()}


def test_a_model_that_knows_the_future_has_no_loss_and_no_sample_error_at_any_step_count():
    out = _measure(Oracle(0.7), (1, 5), _batch(0.7))
    assert set(out) == {"loss", "sample_error_1", "sample_error_5", "sample_detail_1", "sample_detail_5",
                        "other_actions_error_1"}
    assert out["other_actions_error_1"] < 1e-8  # it ignores the actions: another segment's change nothing
    assert out["loss"] < 1e-8 and out["sample_error_1"] < 1e-8 and out["sample_error_5"] < 1e-8
    wrong = _measure(Oracle(0.2), (1, 5), _batch(0.7))  # a model that expects another future is charged
    assert wrong["loss"] > 0.1 and wrong["sample_error_1"] > 0.1 and wrong["sample_error_5"] > 0.1


class Lands(nnx.Module):
    """Lands every sample on ``target`` (a whole segment's latents; the straight path from the noise to it)."""

    def __init__(self, target):
        self.target = nnx.Variable(jnp.asarray(target, jnp.float32))

    def __call__(self, latents, timesteps, actions):
        sigma = (timesteps / FLOW.num_train_timesteps)[:, :, None, None, None]
        return jnp.where(sigma > 0, (latents - self.target[...]) / jnp.maximum(sigma, 1e-6), 0.0)


def test_the_sample_detail_is_one_for_the_truth_and_falls_for_a_blur():
    """A sample that lands on the true future has the data's detail (and no error); one that lands on each latent
    channel's spatial mean (the blur of a mean prediction) has none, and half the contrast about that mean keeps a
    quarter of it, while the squared error of the half-contrast sample stays small."""
    batch = _batch(0.0)
    rng = np.random.default_rng(1)
    latents = batch["latents"] + jnp.asarray(rng.normal(size=batch["latents"].shape), jnp.float32)
    batch = dict(batch, latents=latents)
    mean = jnp.mean(latents, axis=(2, 3), keepdims=True)
    for target, detail in ((latents, 1.0), (jnp.broadcast_to(mean, latents.shape), 0.0),
                           (mean + 0.5 * (latents - mean), 0.25)):
        out = _measure(Lands(target), (2,), batch)
        assert out["sample_detail_2"] == pytest.approx(detail, abs=1e-4)
    assert out["sample_error_2"] < 0.25 * 1.01, "the half-contrast sample is near the truth by squared error"
    assert heldout.latent_detail(jnp.zeros((1, 1, 3, 3, 2)), jnp.zeros((1, 1, 3, 3, 2))) == pytest.approx(1.0)


class ActionDriven(nnx.Module):
    """Knows that a segment's future latents are the mean of its actions from its last context frame on."""

    def __init__(self):
        self.gain = nnx.Param(jnp.float32(1.0))

    def __call__(self, latents, timesteps, actions):
        value = self.gain[...] * jnp.mean(actions[:, 4 * NUM_CONTEXT:], axis=(1, 2))[:, None, None, None, None]
        sigma = (timesteps / FLOW.num_train_timesteps)[:, :, None, None, None]
        return jnp.where(sigma > 0, (latents - value) / jnp.maximum(sigma, 1e-6), 0.0)


def test_a_model_the_actions_drive_is_charged_under_other_segments_actions():
    """Other segments' actions from the last context frame on: the model whose future the actions decide misses
    it, the one that ignores them does not; the first frame's and the earlier context actions stay the segment's."""
    batch = _batch(0.0)
    target = jnp.mean(batch["actions"][:, 4 * NUM_CONTEXT:], axis=(1, 2))
    latents = batch["latents"].at[:, NUM_COND:].set(jnp.broadcast_to(target[:, None, None, None, None],
                                                                      batch["latents"][:, NUM_COND:].shape))
    batch = dict(batch, latents=latents)
    out = _measure(ActionDriven(), (2,), batch)
    assert out["sample_error_2"] < 1e-8 and out["other_actions_error_2"] > 0.1
    swapped = heldout.other_actions(batch["actions"], NUM_CONTEXT)
    np.testing.assert_array_equal(swapped[:, :4 * NUM_CONTEXT], batch["actions"][:, :4 * NUM_CONTEXT])
    np.testing.assert_array_equal(swapped[1:, 4 * NUM_CONTEXT:], batch["actions"][:-1, 4 * NUM_CONTEXT:])
    np.testing.assert_array_equal(swapped[0, 4 * NUM_CONTEXT:], batch["actions"][-1, 4 * NUM_CONTEXT:])


def test_the_sample_error_tells_the_samplers_steps_apart_on_a_curved_path():
    out = _measure(Curved(), (1, 2, 20), _batch(0.7))
    # one Euler step from sigma 1 to 0 with velocity x lands on 0: the whole future is missed
    np.testing.assert_allclose(out["sample_error_1"], 1.0, rtol=1e-6)
    errors = [out[f"sample_error_{n}"] for n in (1, 2, 20)]
    assert len({round(e, 6) for e in errors}) == 3
    # the same key draws the same noise: a measurement is a function of the weights alone
    assert _measure(Curved(), (1, 2, 20), _batch(0.7)) == out
    assert _measure(Curved(), (1, 2, 20), _batch(0.7), key=1) != out


def test_the_segments_and_noise_levels_are_fixed_and_cover_the_training_range():
    dataset = data.LatentDataset(np.zeros((5, 9, 2, 2, 4), np.float32), np.zeros((5, 33, 7), np.float32))
    a = heldout.fixed_segments(dataset, 64, NUM_CONTEXT, NUM_FUTURE, seed=3)
    b = heldout.fixed_segments(dataset, 64, NUM_CONTEXT, NUM_FUTURE, seed=3)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert a[1].min() >= 1 and a[1].max() <= 9 - NUM_CONTEXT - NUM_FUTURE and len(set(a[0])) == 5
    sigmas = np.asarray(heldout.quantile_sigmas(8, FLOW))
    assert np.all(np.diff(sigmas) > 0) and 0 < sigmas[0] and sigmas[-1] < 1
    with pytest.raises(ValueError, match="hold no segment"):
        heldout.fixed_segments(data.LatentDataset(np.zeros((2, 3, 2, 2, 4), np.float32),
                                                  np.zeros((2, 9, 7), np.float32)), 4, 1, 2, seed=0)


def test_bad_settings_are_refused_by_name():
    with pytest.raises(ValueError, match="multiple of trainer.log_every"):
        TrainerConfig(log_every=10, eval_every=15).validate()
    with pytest.raises(ValueError, match="eval_sample_steps"):
        TrainerConfig(eval_sample_steps=(5, 5)).validate()
    with pytest.raises(ValueError, match="eval_batches"):
        TrainerConfig(eval_batches=0).validate()
    assert heldout.sample_steps(TrainerConfig(), FlowConfig(sample_steps=7)) == (7,)
    assert heldout.sample_steps(TrainerConfig(eval_sample_steps=(5, 20)), FLOW) == (5, 20)


ARGS = ["--config", "sword:tiny", "--trainer.log_every=1", "--trainer.checkpoint_every=3", "--mesh.data=2",
        "--mesh.tensor=4", "--cache.log_inference_distance=false", "--trainer.ema_decay=0.5"]


def _rows(workdir):
    return [json.loads(line) for line in open(os.path.join(workdir, "metrics.jsonl"))]


def test_the_trainer_measures_on_its_steps_without_changing_the_run_and_resumes_to_the_same_values(
        tmp_path, monkeypatch, capsys):
    """Training on real latents from files, over 8 CPU devices: the measurement lands on eval_every's steps and the
    last, changes no training number, and a resumed run measures what the uninterrupted one did."""
    monkeypatch.setattr(wm_run, "WorldModel", lambda cfg, *, rngs: MixerWorldModel(cfg.in_dim, cfg.action_dim, rngs=rngs))
    train, held, policy = (data.synthetic_latent_dataset(n, 9, 2, 2, 48, seed=s) for n, s in ((8, 0), (4, 1), (3, 2)))
    paths = {name: str(tmp_path / f"{name}.npz") for name in ("train", "held")}
    # the last 4 training episodes marked as the policy's rollouts: measured apart as well ("trainpolicy")
    np.savez(paths["train"], latents=train.latents, actions=train.actions, sources=np.repeat(np.uint8([0, 1]), 4))
    np.savez(paths["held"], latents=held.latents, actions=held.actions, policy_latents=policy.latents,
             policy_actions=policy.actions)
    real = ARGS + [f"--data.path={paths['train']}", f"--data.heldout_path={paths['held']}",
                   "--trainer.eval_sample_steps=1,3"]
    off, on, split = (str(tmp_path / n) for n in ("off", "on", "split"))
    train_world_model.main(real + ["--workdir", off, "--trainer.steps=5", "--trainer.eval_every=0"])
    train_world_model.main(real + ["--workdir", on, "--trainer.steps=5", "--trainer.eval_every=2",
                                   "--trainer.eval_segments=true"])
    assert ("2 x 2 fixed training segments and as many of 4 held-out episodes and of 3 held-out rollouts of the "
            "supervised policy; and training segments of the 4 training episodes that are the policy's rollouts"
            ) in capsys.readouterr().out
    plain, measured = _rows(off), _rows(on)
    names = set(heldout.metric_names((1, 3)))
    assert [sorted(names & set(r)) for r in measured] == [[], sorted(names), [], sorted(names), sorted(names)]
    for a, b in zip(plain, measured):
        assert a["loss"] == b["loss"] and a["grad_norm"] == b["grad_norm"]
        assert not names & set(a)
    at_2, at_4 = measured[1], measured[3]
    assert all(np.isfinite(at_4[n]) for n in names) and any(at_2[n] != at_4[n] for n in names)
    assert len({at_4[f"eval_{split}_loss"] for split in heldout.SPLITS}) == 4
    # trainer.eval_segments: each fixed segment measured alone at the end; a batch's figure is its segments'
    # energy-weighted mean, and the evaluation's the mean of its batches'
    segments = json.load(open(os.path.join(on, wm_run.SEGMENTS_FILE)))
    assert segments["step"] == 5 and sorted(segments["splits"]) == sorted(heldout.SPLITS)
    assert not os.path.exists(os.path.join(off, wm_run.SEGMENTS_FILE))
    for name, each in segments["splits"].items():
        assert len(each["episodes"]) == len(each["starts"]) == len(each["energy"]) == 2 * 2  # batches x size
        for n in (1, 3):
            error, energy = (np.asarray(each[k]).reshape(2, 2) for k in (f"sample_error_{n}", "energy"))
            per_batch = (error * energy).sum(1) / energy.sum(1)
            expected = measured[4][f"eval_{name}_sample_error_{n}"]  # step 5, the last
            assert per_batch.mean() == pytest.approx(expected, rel=1e-4), (name, n)
    assert set(segments["splits"]["trainpolicy"]["episodes"]) <= {4, 5, 6, 7}
    # a resumed run (3 steps, then to 5) measures step 4 and 5 as the uninterrupted one did
    train_world_model.main(real + ["--workdir", split, "--trainer.steps=3", "--trainer.eval_every=2"])
    train_world_model.main(real + ["--workdir", split, "--trainer.steps=5", "--trainer.eval_every=2"])
    resumed = {r["step"]: r for r in _rows(split)}
    for step in (4, 5):
        assert {n: resumed[step][n] for n in names} == {n: measured[step - 1][n] for n in names}


def test_held_out_data_that_does_not_fit_is_refused_and_none_measures_training_segments_alone(tmp_path, capsys):
    train = data.synthetic_latent_dataset(8, 9, 2, 2, 48, seed=0)
    odd = data.synthetic_latent_dataset(2, 7, 2, 2, 48, seed=1)
    path = str(tmp_path / "odd.npz")
    np.savez(path, latents=odd.latents, actions=odd.actions)
    cfg, _ = configs.from_argv(["--config", "sword:tiny", f"--data.heldout_path={path}"])
    with pytest.raises(SystemExit, match=r"data.heldout_path .*odd.npz holds heldout latents \(2, 7, 2, 2, 48\)"):
        wm_run.build_heldout(cfg, False, train)
    # the supervised policy's held-out rollouts beside the expert's: read as the "policy" split, checked alike
    np.savez(path, latents=train.latents[:2], actions=train.actions[:2], policy_latents=odd.latents,
             policy_actions=odd.actions)
    with pytest.raises(SystemExit, match=r"odd.npz holds policy latents \(2, 7, 2, 2, 48\)"):
        wm_run.build_heldout(cfg, False, train)
    np.savez(path, latents=train.latents[:2], actions=train.actions[:2], policy_latents=train.latents[2:5])
    with pytest.raises(ValueError, match="holds policy_latents without its pair"):
        wm_run.build_heldout(cfg, False, train)
    np.savez(path, latents=train.latents[:2], actions=train.actions[:2], policy_latents=train.latents[2:5],
             policy_actions=train.actions[2:5])
    splits = wm_run.build_heldout(cfg, False, train)
    assert sorted(splits) == ["heldout", "policy"] and splits["policy"].shape == (3, 9, 2, 2, 48)
    np.testing.assert_array_equal(splits["policy"].actions, train.actions[2:5])
    np.savez(path, latents=train.latents, actions=train.actions, sources=np.zeros(7, np.uint8))
    with pytest.raises(ValueError, match="sources must be 8 values of 0 .* got shape \\(7,\\)"):
        data.load_sources(path, 8)
    np.savez(path, latents=train.latents, actions=train.actions, sources=np.full(8, 3, np.uint8))
    with pytest.raises(ValueError, match="sources must be 8 values of 0"):
        data.load_sources(path, 8)
    np.savez(path, latents=train.latents, actions=train.actions, sources=np.arange(8, dtype=np.uint8) % 3)
    np.testing.assert_array_equal(data.load_sources(path, 8), np.arange(8) % 3)  # 2: the exploring expert's
    np.savez(path, latents=train.latents, actions=train.actions)
    assert data.load_sources(path, 8) is None
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--mesh.data=2", "--mesh.tensor=4"])
    assert wm_run.build_heldout(cfg, False, train) == {}
    synthetic = wm_run.build_heldout(cfg, True, train)  # synthetic: another seed's
    assert list(synthetic) == ["heldout"] and synthetic["heldout"].shape[1:] == train.shape[1:]
    mesh = shd.make_mesh(cfg.mesh)
    sampler = data.SegmentSampler(8, 9, NUM_CONTEXT, NUM_FUTURE, 2, seed=0)
    loader = data.SegmentLoader(train, sampler, NUM_CONTEXT, NUM_FUTURE, mesh)
    graphdef = nnx.graphdef(MixerWorldModel(48, 7, rngs=nnx.Rngs(0)))
    common = dict(loader=loader, num_context=NUM_CONTEXT, num_future=NUM_FUTURE, mesh=mesh, seed=0)
    with pytest.raises(ValueError, match="the heldout split's latents .* do not match the training data"):
        heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=odd, **common)
    with pytest.raises(ValueError, match="the policy split's latents .* do not match the training data"):
        heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=None, policy=odd, **common)
    alone = heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=None, **common)
    assert alone.names == ("eval_train_loss", f"eval_train_sample_error_{FLOW.sample_steps}",
                           f"eval_train_sample_detail_{FLOW.sample_steps}",
                           f"eval_train_other_actions_error_{FLOW.sample_steps}")
    # the policy split is measured beside the others and leaves their values as they were without it
    held, policy = (data.synthetic_latent_dataset(3, 9, 2, 2, 48, seed=s) for s in (1, 2))
    model = MixerWorldModel(48, 7, rngs=nnx.Rngs(0))
    _, params, buffers = nnx.split(model, nnx.Param, ...)
    state = types.SimpleNamespace(step=jnp.int32(cfg.trainer.eval_every), params=params, ema_params=None,
                                  buffers=buffers)
    two = heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=held, **common)
    three = heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=held, policy=policy, **common)
    assert three.names == heldout.metric_names((FLOW.sample_steps,), ("train", "heldout", "policy"))
    without, beside = ({k: float(v) for k, v in e(state).items()} for e in (two, three))
    assert {k: beside[k] for k in without} == without
    assert all(np.isfinite(beside[k]) for k in beside) and beside["eval_policy_loss"] != beside["eval_heldout_loss"]
    # and the policy's training rollouts (the training episodes the latents file's sources mark): segments of those
    # episodes alone, measured after the others, whose values stay as they were
    four = heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=held, policy=policy,
                                    train_policy=np.array([5, 6, 7]), **common)
    assert four.names == heldout.metric_names((FLOW.sample_steps,), heldout.SPLITS)
    assert {int(e) for b in four.batches["trainpolicy"] for e in np.asarray(b["episode"])} <= {5, 6, 7}
    everything = {k: float(v) for k, v in four(state).items()}
    assert {k: everything[k] for k in beside} == beside and np.isfinite(everything["eval_trainpolicy_loss"])
    assert everything["eval_trainpolicy_loss"] != everything["eval_train_loss"]
    with pytest.raises(ValueError, match=r"train_policy indices must lie in \[0, 8\)"):
        heldout.HeldOutEvaluator(graphdef, FLOW, cfg.trainer, train=train, heldout=None, train_policy=np.array([8]),
                                 **common)


def test_a_segment_s_error_is_its_share_of_the_batch_s():
    from sword_jax.world_model.cache_fidelity import latent_distance

    future = jnp.asarray(np.random.default_rng(0).normal(size=(3, 2, 2, 2, 4)), jnp.float32)
    future = future * jnp.asarray([1.0, 2.0, 0.5])[:, None, None, None, None]  # segments of unequal energy
    made = future.at[1].add(0.3).at[2].multiply(0.0)  # segment 0 right, 1 off by 0.3, 2 all zeros
    error, energy = heldout.segment_errors(made, future)
    assert error.shape == energy.shape == (3,)
    assert float(error[0]) == 0.0 and float(error[2]) == pytest.approx(1.0)
    assert float(error[1]) == pytest.approx(float(0.09 * 32 / energy[1]), rel=1e-5)
    np.testing.assert_allclose(energy, jnp.sum(jnp.square(future), axis=(1, 2, 3, 4)), rtol=1e-6)
    assert float(jnp.sum(error * energy) / jnp.sum(energy)) == pytest.approx(
        float(latent_distance(made, future)["rel_mse"]), rel=1e-5)
    # a per-segment measure draws the batch measure's noise: the same figure, segment by segment
    batch = _batch(0.7)
    graphdef, params, buffers = nnx.split(Oracle(0.2), nnx.Param, ...)
    each = jax.jit(heldout.make_measure(graphdef, FLOW, NUM_CONTEXT, (1, 5), per_segment=True))(
        params, buffers, batch, jax.random.key(0))
    assert set(each) == {"energy", "sample_error_1", "sample_error_5"} and each["energy"].shape == (4,)
    whole = _measure(Oracle(0.2), (1, 5), batch)
    for n in (1, 5):
        weighted = float(jnp.sum(each[f"sample_error_{n}"] * each["energy"]) / jnp.sum(each["energy"]))
        assert weighted == pytest.approx(whole[f"sample_error_{n}"], rel=1e-5)


def test_the_pipeline_report_says_the_last_measurement_of_every_split():
    from sword_jax.pipeline.report import _measured_segments

    final = {"loss": 0.06, "eval_train_loss": 0.05, "eval_heldout_loss": 0.09, "eval_train_sample_error_5": 0.2,
             "eval_heldout_sample_error_5": 0.3, "eval_train_sample_error_20": 0.1, "eval_heldout_sample_error_20": 0.25}
    assert _measured_segments(final) == (
        " On fixed segments at the end, flow loss 0.09 held-out against 0.05 training; the sampler's error at 5 Euler"
        " steps 0.3 held-out against 0.2 training; the sampler's error at 20 Euler steps 0.25 held-out against 0.1"
        " training.")
    final.update(eval_policy_loss=0.12, eval_policy_sample_error_5=0.4, eval_policy_sample_error_20=0.35)
    assert _measured_segments(final) == (
        " On fixed segments at the end, flow loss 0.09 held-out against 0.12 held-out policy rollouts against 0.05"
        " training; the sampler's error at 5 Euler steps 0.3 held-out against 0.4 held-out policy rollouts against"
        " 0.2 training; the sampler's error at 20 Euler steps 0.25 held-out against 0.35 held-out policy rollouts"
        " against 0.1 training.")
    final.update(eval_trainpolicy_loss=0.07, eval_trainpolicy_sample_error_5=0.22,
                 eval_trainpolicy_sample_error_20=0.12)
    assert _measured_segments(final).startswith(
        " On fixed segments at the end, flow loss 0.09 held-out against 0.12 held-out policy rollouts against 0.07"
        " training policy rollouts against 0.05 training; the sampler's error at 5 Euler steps 0.3 held-out against"
        " 0.4 held-out policy rollouts against 0.22 training policy rollouts against 0.2 training;")
    final.update(eval_trainpolicy_other_actions_error_5=0.3, eval_train_other_actions_error_5=0.5,
                 eval_heldout_other_actions_error_5=0.6, eval_policy_other_actions_error_5=0.7)
    assert _measured_segments(final).endswith(
        "; under other segments' actions at 5 Euler steps 0.6 held-out against 0.7 held-out policy rollouts against"
        " 0.3 training policy rollouts against 0.5 training.")
    final.update(eval_train_sample_detail_5=0.8, eval_heldout_sample_detail_5=0.6)
    assert ("; the samples' detail over the data's at 5 Euler steps 0.6 held-out against 0.8 training; under other"
            in _measured_segments(final))
    assert _measured_segments({"loss": 0.06}) == ""  # a run that measured nothing says nothing


def test_what_the_evaluation_reads_does_not_block_a_resume():
    """A world-model run resumes with other held-out data or evaluation settings or another number of processes
    recording the policy's rollouts, and from a config.json written
    before those keys existed; a change to what it trains on is still refused."""
    now = {"data": {"path": "a.npz", "batch_size": 2, "heldout_path": "h.npz", "heldout_policy_rollouts_per_task": 2,
                    "policy_rollout_workers": 4},
           "trainer": {"steps": 9, "learning_rate": 1e-3, "eval_every": 5, "eval_sample_steps": [5, 20]},
           "workdir": "new"}
    older = {"data": {"path": "a.npz", "batch_size": 2}, "trainer": {"steps": 5, "learning_rate": 1e-3},
             "workdir": "old"}
    assert wm_run._comparable(now) == wm_run._comparable(older)
    # how the pipeline's evaluation stage scores is not read by the world model; the held-out episodes' count is
    scored = {**now, "eval": {"num_episodes": 4, "metrics": ["psnr"], "report_videos": 1}}
    assert wm_run._comparable(scored) == wm_run._comparable({**now, "eval": {"num_episodes": 4,
                                                                            "metrics": ["lpips", "psnr"]}})
    assert wm_run._comparable(scored) != wm_run._comparable({**now, "eval": {"num_episodes": 8, "metrics": ["psnr"]}})
    older["data"]["batch_size"] = 4
    assert wm_run._comparable(now) != wm_run._comparable(older)
