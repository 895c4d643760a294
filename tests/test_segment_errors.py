"""benchmarks.segment_errors: a world model's per-segment errors joined with their episodes' outcomes."""

import json
import os

import numpy as np
import pytest

from benchmarks import segment_errors as se
from sim.dataset import DatasetInfo, Episode, write_dataset
from sword_jax.cli import UsageError


@pytest.fixture(scope="module")
def expert_states():
    """The scripted expert on the C engine carrying the bowl from the top drawer to the plate (task 4): its flat
    states ``[time, qpos, qvel]`` and actions, one per step, and the step it succeeds at."""
    from sim import expert
    from sim.config import SimConfig
    from sim.env import CpuEnv

    env = CpuEnv(SimConfig(resolution=16), 4)
    out = expert.rollout_cpu(env, env.init_states[3], record=True)
    assert out["success"]
    flat = np.stack([np.concatenate([[s.data.time], s.data.qpos, s.data.qvel]) for s in out["states"]])
    return flat[:-1], np.asarray(out["actions"], np.float64), len(out["actions"]) - 1


def _episode(states, actions, success_at, seed, task_id=4, init_state_id=None):
    rng = np.random.default_rng(seed)
    steps = len(actions)
    rewards = np.zeros(steps)
    if success_at is not None:
        rewards[success_at:success_at + 2] = 1  # success need not last (the policy may carry the bowl away)
    return Episode(actions=actions, states=states, rewards=rewards,
                   dones=np.zeros(steps), agentview_rgb=rng.integers(0, 256, (steps, 8, 8, 3), dtype=np.uint8),
                   ee_states=rng.normal(size=(steps, 6)), gripper_states=rng.normal(size=(steps, 2)),
                   joint_states=rng.normal(size=(steps, 7)), model_file="<mujoco/>", task_id=task_id,
                   init_state_id=init_state_id, language_instruction="pick up the black bowl")


def test_outcomes_read_the_episodes_in_order_with_their_first_success_and_stages(tmp_path, expert_states):
    states, actions, solved = expert_states
    path = str(tmp_path / "policy.hdf5")
    episodes = [_episode(states, actions, 7, 0, init_state_id=3), _episode(states[:-2], actions[:-2], None, 1),
                _episode(states, actions, 0, 2)]
    write_dataset(path, episodes, DatasetInfo(env_name="sword/LiberoSpatial-v0"))
    out = se.episode_outcomes(path)
    assert out["first_success"].tolist() == [7, -1, 0]
    assert out["task_id"].tolist() == [4, 4, 4] and out["init_state_id"].tolist() == [3, -1, -1]
    steps = len(actions) - 2  # cut to the shortest
    assert out["rewards"].shape == (3, steps) and out["actions"].shape == (3, steps, 7)
    np.testing.assert_array_equal(out["actions"][1], actions[:steps])
    np.testing.assert_array_equal(out["rewards"][0], episodes[0].rewards[:steps])
    # the expert's stages in order: not yet grasped at the start, then held, then held over the plate by the end
    stages = out["stages"][0]
    assert out["stages"].shape == (3, steps) and stages[0] == 0 and stages[-1] == 2
    assert (np.diff(stages.astype(int)) >= 0).all() and {0, 1, 2} <= set(stages.tolist())
    np.testing.assert_array_equal(out["stages"][1], stages)


def test_a_stage_is_read_from_the_restored_state_and_a_release_after_a_grasp(expert_states):
    """A held bowl that the fingers no longer touch reads as let go (stage 3), not as never grasped."""
    states, _, _ = expert_states
    stages = se.step_stages(states[None], np.array([4]))[0]
    grasped = int(np.argmax(stages == 1))
    opened = states[grasped].copy()
    opened[1:] = states[0][1:]  # back at the start pose: the bowl in its drawer, the fingers away from it
    replayed = se.step_stages(np.stack([states[grasped], opened])[None], np.array([4]))[0]
    assert replayed.tolist() == [1, 3]


@pytest.mark.parametrize("frames, first, phase", [((5, 12), 13, "before success"), ((5, 12), 12, "spans success"),
                                                   ((5, 12), 5, "after success"), ((5, 12), 3, "after success"),
                                                   ((5, 12), -1, "failed episode")])
def test_a_segment_phase_is_its_future_frames_against_the_first_success(frames, first, phase):
    assert se.segment_phase(*frames, first) == phase


def _record():
    # 4 segments: episode 0 succeeds at step 10, episode 1 fails; k = 1 context and p = 2 future latents
    return {"step": 100, "splits": {"policy": {
        "episodes": [0, 0, 1, 1], "starts": [1, 3, 1, 9], "energy": [1.0, 3.0, 2.0, 2.0],
        "sample_error_5": [0.01, 0.03, 0.02, 0.04], "sample_error_20": [0.0, 0.0, 0.0, 0.0]},
        "heldout": {"episodes": [0], "starts": [2], "energy": [1.0], "sample_error_5": [0.5],
                    "sample_error_20": [0.4]}}}


def _outcomes():
    actions = np.zeros((2, 48, 7))
    actions[1, :, :3] = 0.5
    stages = np.zeros((2, 48), np.int8)
    stages[0, 8:] = 1  # episode 0 holds the bowl from step 8
    return {"first_success": np.array([10, -1]), "actions": actions, "rewards": np.zeros((2, 48)),
            "task_id": np.zeros(2, int), "init_state_id": np.zeros(2, int), "stages": stages}


def test_the_join_places_each_segment_and_weighs_each_group_as_the_evaluation_does():
    out = se.join(_record(), {"policy": _outcomes()}, context_latents=1, future_latents=2, euler=5,
                  early_actions=16)
    policy = out["splits"]["policy"]
    segs = policy["segments"]
    # the future of start s: frames 4 s + 1 .. 4 (s + 2)
    assert [s["frames"] for s in segs] == [[5, 12], [13, 20], [5, 12], [37, 44]]
    assert [s["phase"] for s in segs] == ["spans success", "after success", "failed episode", "failed episode"]
    assert [s["early"] for s in segs] == [True, False, True, False]
    assert segs[2]["motion"] == pytest.approx(0.5) and segs[0]["motion"] == 0.0
    # the stage of the state each prediction starts from: the last context frame's (frame 4 s)
    assert [s["stage"] for s in segs] == ["before the grasp", "grasped", "before the grasp", "before the grasp"]
    groups = policy["groups"]
    # the split's figure: the energy-weighted mean, as the evaluation's batch figure
    assert groups["all"]["error"] == pytest.approx((0.01 + 0.09 + 0.04 + 0.08) / 8)
    assert groups["failed episode"]["error"] == pytest.approx(0.03)
    assert groups["failed episode, first 16 actions"]["segments"] == 1
    assert groups["stage: grasped"]["segments"] == 1 and groups["stage: grasped"]["error"] == pytest.approx(0.03)
    # the phases partition the split: their shares add up to 1
    assert sum(groups[p]["share"] for p in se.PHASES if p in groups) == pytest.approx(1.0)
    assert groups["first 16 actions"]["share"] + groups["after 16 actions"]["share"] == pytest.approx(1.0)
    # a split without outcomes is grouped by time alone
    held = out["splits"]["heldout"]
    assert set(held["groups"]) == {"all", "first 16 actions"} and "phase" not in held["segments"][0]


def test_a_vae_of_another_temporal_factor_places_the_frames_by_it():
    out = se.join(_record(), {}, context_latents=1, future_latents=1, euler=5, early_actions=16,
                  frames_per_latent=8)
    assert [s["frames"] for s in out["splits"]["policy"]["segments"]] == [[9, 16], [25, 32], [9, 16], [73, 80]]


def test_the_join_refuses_a_missing_error_or_an_episode_outside_the_outcomes():
    with pytest.raises(ValueError, match="sample_error_7"):
        se.join(_record(), {}, context_latents=1, future_latents=2, euler=7, early_actions=16)
    short = {k: v[:1] for k, v in _outcomes().items()}
    with pytest.raises(ValueError, match="names episode 1, its outcomes hold 1 episodes"):
        se.join(_record(), {"policy": short}, context_latents=1, future_latents=2, euler=5, early_actions=16)


def test_the_command_joins_a_pipeline_record_and_names_bad_input(tmp_path):
    pipeline = tmp_path / "pipeline"
    (pipeline / "world_model").mkdir(parents=True)
    (pipeline / "config.json").write_text(json.dumps({"data": {"context_frames": 4, "predict_frames": 8},
                                                      "vae": {"temporal_downsample": [True, True, False]}}))
    with pytest.raises(UsageError, match="eval_segments=true"):
        se.main(["join", "--pipeline", str(pipeline), "--out", str(tmp_path / "s.json")])
    (pipeline / "world_model" / "heldout_segments.json").write_text(json.dumps(_record()))
    outcomes = str(tmp_path / "o.npz")
    np.savez(outcomes, **_outcomes())
    with pytest.raises(UsageError, match="SPLIT=FILE"):
        se.main(["join", "--pipeline", str(pipeline), "--outcomes", "policy", "--out", str(tmp_path / "s.json")])
    with pytest.raises(UsageError, match="no split \\['train'\\]"):
        se.main(["join", "--pipeline", str(pipeline), "--outcomes", f"train={outcomes}",
                 "--out", str(tmp_path / "s.json")])
    np.savez(str(tmp_path / "bad.npz"), first_success=np.array([1]))
    with pytest.raises(UsageError, match="missing"):
        se.main(["join", "--pipeline", str(pipeline), "--outcomes", f"policy={tmp_path / 'bad.npz'}",
                 "--out", str(tmp_path / "s.json")])
    out = str(tmp_path / "s.json")
    se.main(["join", "--pipeline", str(pipeline), "--outcomes", f"policy={outcomes}", "--out", out,
             "--early-actions", "16"])
    with open(out) as f:
        written = json.load(f)
    assert written["splits"]["policy"]["groups"]["after success"]["segments"] == 1
    assert os.path.getsize(out) > 0
