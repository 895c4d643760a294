"""Action-following probe: recovers simulator state from frames; its metrics reach evaluation output."""

import json

import numpy as np
import pytest

from sword_jax.evaluation import probe as probe_lib
from sword_jax.evaluation.harness import evaluate_videos
from sword_jax.evaluation.probe import FidelityScorer
from sword_jax.evaluation.report import write_report
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.suite import MetricSuite
from tests.support.videos import panning_videos


# A learning property (17 s on 2 cores); the default run trains, resumes and refuses probes in
# test_probe_training_resumes_exactly_and_refuses_another_probe_s_checkpoint.
@pytest.mark.slow
def test_probe_recovers_state_better_than_a_constant(tmp_path):
    from sim.dataset import read_dataset
    from sim.probe_targets import episode_targets
    from train import gen_data, train_probe

    demos = str(tmp_path / "demos.hdf5")
    gen_data.main(["--task", "0,1", "--episodes", "3", "--out", demos, "--resolution", "32", "--max-steps", "48",
                   "--renderer", "jax", "--no-wrist"])
    summary = train_probe.main(["--config", "sword:tiny", "--demos", demos, "--out", str(tmp_path / "probe"),
                                "--steps", "150", "--holdout", "0.34"])
    # Held-out episodes: the probe beats predicting the training mean by a wide margin.
    assert summary["holdout_ee_cm"] < 0.5 * summary["holdout_constant_ee_cm"], summary
    assert summary["holdout_bowl_cm"] < 0.6 * summary["holdout_constant_bowl_cm"], summary
    assert summary["holdout_gripper_acc"] > summary["holdout_constant_gripper_acc"], summary

    # The saved probe scores a video against itself as perfect and reads a real floor against the truth.
    scorer = FidelityScorer.from_probe_file(summary["path"])
    episode = read_dataset(demos)[1][0]
    video = episode.agentview_rgb[None].astype(np.float32) / 255.0
    per_frame, _ = scorer.score(video, video, targets=episode_targets(episode)[None])
    assert np.all(per_frame["probe_ee_cm"] == 0) and np.all(per_frame["probe_gripper_agree"] == 1)
    assert 0 < per_frame["probe_floor_ee_cm"].mean() < summary["holdout_constant_ee_cm"]
    # The bowl target (its free joint's qpos) is the body's world position by forward kinematics.
    import mujoco

    from sim import scene

    model = scene.build_model()
    data = mujoco.MjData(model)
    data.qpos[:] = episode.states[-1, 1:1 + model.nq]
    mujoco.mj_kinematics(model, data)
    np.testing.assert_allclose(episode_targets(episode)[-1, 4:7], data.xpos[model.body(scene.TARGET_BOWL).id],
                               atol=1e-6)


def _brightness_probe(frames):
    """A stand-in probe: state = per-channel mean brightness (metres), gripper = red channel."""
    mean = frames.reshape(len(frames), -1, 3).mean(axis=1)
    return np.concatenate([mean, mean[:, :1] * 0.08, mean], axis=1)


def test_fidelity_metrics_against_horizon_in_evaluation_output(tmp_path):
    suite = MetricSuite(EvalConfig(allow_random_weights=True), metrics=("psnr",))
    gt = panning_videos(0, b=2, t=9)
    drift = np.linspace(0, 0.5, 9, dtype=np.float32)[None, :, None, None, None]
    pred = np.clip(gt + drift, 0, 1)  # brighter and brighter: the state read off it drifts
    targets = _brightness_probe(gt.reshape(-1, *gt.shape[2:])).reshape(2, 9, 7) + 0.01  # 1 cm per axis off
    rewards = np.zeros((2, 9), np.float32)
    rewards[0, 6:] = 1  # episode 0 succeeds at frame 6
    success = lambda frames: frames.reshape(len(frames), -1).mean(axis=1)  # brighter = "success"
    threshold = float(np.sort(success(gt[0]))[-2])  # ground truth: frames scoring in the top 2 of episode 0
    scorer = FidelityScorer(probe=_brightness_probe, success_score=success, success_threshold=threshold)
    results = evaluate_videos(suite, {"original": gt}, {"m": {"original": pred}}, given_frames=1,
                              progress=lambda _: None, fidelity=scorer,
                              truth_by_split={"original": {"targets": targets, "rewards": rewards}})
    result = results.models["original"]["m"]
    curve = result.curves["probe_ee_cm"]
    assert curve["frames"] == list(range(1, 9))
    assert curve["mean"][-1] > curve["mean"][0] > 0  # the error grows with the drift
    np.testing.assert_allclose(result.curves["probe_floor_ee_cm"]["mean"], 100 * np.sqrt(3) * 0.01, rtol=1e-4)
    assert result.curves["probe_floor_gripper_agree"]["mean"] == [1.0] * 8
    # Brightened frames all pass the detector: agreement falls, recall is perfect, precision is not.
    assert result.overall["reward_recall"] == 1.0 and result.overall["reward_precision"] < 1.0
    assert result.overall["reward_agree"] < 1.0 and "reward_floor_precision" in result.overall
    assert result.overall["psnr"] > 0  # pixel metrics still sit beside them

    write_report(str(tmp_path), results, {"original": {"ground truth": gt, "m": pred}}, max_episodes=1)
    saved = json.load(open(tmp_path / "results.json"))["models"]["original"]["m"]
    assert saved["curves"]["probe_bowl_cm"]["mean"][-1] > 0 and "reward_recall" in saved["overall"]


def test_load_split_carries_the_true_state(tmp_path):
    from sim import world_model_eval

    path = str(tmp_path / "split.npz")
    np.savez(path, frames=np.zeros((3, 5, 8, 8, 3), np.float32), actions=np.zeros((3, 5, 7), np.float32),
             targets=np.ones((3, 5, 7), np.float32), rewards=np.ones((3, 5), np.float32))
    split = world_model_eval.load_split(path, 2)
    assert split["targets"].shape == (2, 5, 7) and split["rewards"].shape == (2, 5)


def test_probe_config_rejects_bad_sizes():
    with pytest.raises(ValueError, match="power of two"):
        probe_lib.ProbeConfig(image_size=48).validate()


def test_probe_training_resumes_exactly_and_refuses_another_probe_s_checkpoint(tmp_path):
    """The probe trains on the shared loop: a run stopped after its step-3 checkpoint and rerun ends where an
    uninterrupted run ends; a checkpoint of another probe (another learning rate) is refused, naming the key."""
    import dataclasses

    import jax

    from sword_jax.evaluation import probe as probe_lib

    class Killed(Exception):
        pass

    def dies_at_step_5(line):
        if "step 5/6" in line:
            raise Killed

    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (40, 16, 16, 3), dtype=np.uint8)
    targets = rng.normal(size=(40, 7)).astype(np.float32)
    cfg = probe_lib.ProbeConfig(image_size=8, width=4, steps=6, batch_size=8)
    _, whole, _, _ = probe_lib.train_probe(frames, targets, cfg, checkpoint_dir=str(tmp_path / "a"),
                                           progress=lambda line: None, checkpoint_every=3)
    with pytest.raises(Killed):
        probe_lib.train_probe(frames, targets, cfg, checkpoint_dir=str(tmp_path / "b"), progress=dies_at_step_5,
                              checkpoint_every=3)
    lines = []
    _, resumed, _, metrics = probe_lib.train_probe(frames, targets, cfg, checkpoint_dir=str(tmp_path / "b"),
                                                   progress=lines.append, checkpoint_every=3)
    assert any("resumed from step 3" in line for line in lines)
    for x, y in zip(jax.tree.leaves(whole), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert np.isfinite(metrics["loss"])
    with pytest.raises(ValueError, match="learning_rate"):
        probe_lib.train_probe(frames, targets, dataclasses.replace(cfg, learning_rate=1e-3),
                              checkpoint_dir=str(tmp_path / "b"), progress=lambda line: None, checkpoint_every=3)
