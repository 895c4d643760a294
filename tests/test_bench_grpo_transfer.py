"""benchmarks.bench_grpo_transfer: the three arms' commands and the summary it writes from their files."""

import argparse
import json

import pytest

from benchmarks import bench_grpo_transfer as transfer
from sword_jax.rl.env_rollout import difference_interval


def _curve(path, points):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"label": "x", "points": points}))


def _point(step, successes, episodes=200, **extra):
    rate = successes / episodes
    return {"step": step, "mean": rate, "successes": successes, "episodes": episodes, "ci95": [rate - 0.05, rate + 0.05],
            **extra}


def test_summary_reads_every_arm_and_names_the_missing(tmp_path):
    masked = lambda s: {"mean": s / 200, "successes": s, "episodes": 200, "ci95": [0, 1]}  # noqa: E731
    replay = {"imagined_success": 0.3, "real_success": 0.2, "false_success": {"rate": 0.1}, "missed_success": None,
              "resample_disagreement": {"rate": 0.2}, "counts": {}}
    _curve(tmp_path / "pipeline" / "rl" / "grpo" / "success_curve.json",
           [_point(0, 40, proprio_masked=masked(30), replay=replay), _point(50, 30, proprio_masked=masked(20), replay=replay)])
    _curve(tmp_path / "ground_truth" / "rl" / "grpo" / "success_curve.json",
           [_point(0, 40, train_mode=masked(40)), _point(50, 80, train_mode=masked(80))])
    (tmp_path / "pipeline" / "rl" / "grpo" / "train_history.jsonl").write_text(
        "".join(json.dumps({"step": i, "success_rate": 0.1 * (i > 10)}) + "\n" for i in range(1, 13)))
    (tmp_path / "ground_truth" / "rl" / "grpo" / "train_history.jsonl").write_text(
        json.dumps({"step": 1, "rollout_success": 0.25}) + "\n" + json.dumps({"step": 2, "rollout_success": 0.5}) + "\n")
    summary = transfer.summarize(str(tmp_path))
    assert summary["missing"] == ["ground_truth_keyframes"]
    wm, gt = summary["arms"]["world_model"], summary["arms"]["ground_truth"]
    assert wm["gain"] == pytest.approx(-0.05) and gt["gain"] == pytest.approx(0.2)
    # 0.2 -> 0.4 on 200 episodes each: the project's Newcombe interval of the difference
    assert gt["gain_ci95"] == list(difference_interval(40, 200, 80, 200))
    assert gt["gain_ci95"][0] < 0.2 < gt["gain_ci95"][1]
    assert wm["trained_mode_gain"] == pytest.approx(-0.05)
    assert wm["replay"][0]["false_success"] == {"rate": 0.1}
    assert wm["rollout_success_per_10_steps"] == [0.0, 0.1]
    assert gt["rollout_success_per_10_steps"] == [0.375]


def test_commands_share_the_policy_and_settings():
    args = argparse.Namespace(workdir="w", config="sword:tiny", seed=3, steps=4, eval_every=2, eval_episodes=5,
                                       arm_workers=2, parallel=2)
    cmds = transfer.commands(args, ["--rl.grpo.learning_rate=1e-4"])
    for arm in transfer.ARMS:
        assert "--rl.grpo.learning_rate=1e-4" in cmds[arm] and "--rl.grpo.steps=4" in cmds[arm]
    assert cmds["world_model"][2] == "train.pipeline" and "--parallel" in cmds["world_model"]
    for arm in ("ground_truth", "ground_truth_keyframes"):
        assert cmds[arm][cmds[arm].index("--policy") + 1] == "w/pipeline/rl/policy_sft"
    assert "--rl.env.starts=keyframes" in cmds["ground_truth_keyframes"]
    assert "--rl.env.starts=keyframes" not in cmds["ground_truth"]


def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit, match="dotted config override"):
        transfer.main(["--workdir", "x", "stray"])
    with pytest.raises(SystemExit, match="--steps"):
        transfer.main(["--workdir", "x", "--steps", "0"])
