"""benchmarks.bench_grpo_arms: the arms' commands and the greedy/sampled summary it writes from their files."""

import json
import sys
from types import SimpleNamespace

import pytest

from benchmarks import bench_grpo_arms as arms
from benchmarks import bench_policy


def _point(step, successes, episodes=500, sampled=None):
    rate = successes / episodes
    point = {"step": step, "mean": rate, "successes": successes, "episodes": episodes, "ci95": [rate - 0.04, rate + 0.04]}
    if sampled is not None:
        point["sampled"] = {"temperature": 0.7, "mean": sampled / episodes, "successes": sampled, "episodes": episodes,
                            "ci95": [0.0, 1.0], "per_task": {}}
    return point


def _arm(root, name, points, history=None):
    grpo_dir = root / name / "rl" / "grpo"
    grpo_dir.mkdir(parents=True)
    (grpo_dir / "success_curve.json").write_text(json.dumps({"label": "x", "points": points}))
    if history is not None:
        (grpo_dir / "train_history.jsonl").write_text("".join(json.dumps(h) + "\n" for h in history))
    return str(root / name)


def test_summary_has_greedy_and_sampled_gains_and_rollout_blocks(tmp_path):
    history = [{"step": i + 1, "rollout_success": 0.1 if i < 10 else 0.3, "behaviour_nll": 2.0 - 0.01 * i}
               for i in range(12)]
    a = _arm(tmp_path, "a", [_point(0, 200, sampled=100), _point(50, 250, sampled=150), _point(100, 300, sampled=200)],
             history)
    b = _arm(tmp_path, "b", [_point(0, 200), _point(100, 190)])  # no sampled evaluations, no history
    summary = arms.summarize({"a": a, "b": b, "c": str(tmp_path / "never_ran")})
    assert summary["missing"] == ["c"]
    sa, sb = summary["arms"]["a"], summary["arms"]["b"]
    assert [p["success"] for p in sa["greedy"]] == [0.4, 0.5, 0.6]
    assert sa["greedy_gain"] == pytest.approx(0.2) and sa["sampled_gain"] == pytest.approx(0.2)
    assert sa["temperature"] == 0.7
    # first vs last point, the project's Newcombe interval of a difference of two proportions
    assert sa["greedy_gain_ci95"] == [round(x, 4) for x in bench_policy.diff_interval(200, 500, 300, 500)]
    assert sa["sampled_gain_ci95"] == [round(x, 4) for x in bench_policy.diff_interval(100, 500, 200, 500)]
    assert sa["rollout_success_per_10_steps"] == [0.1, 0.3]
    assert sa["behaviour_nll_per_10_steps"] == [round(sum(2.0 - 0.01 * i for i in range(10)) / 10, 4),
                                                round((2.0 - 0.1 + 2.0 - 0.11) / 2, 4)]
    assert "sampled" not in sb and sb["greedy_gain"] == pytest.approx(-0.02) and "rollout_success_per_10_steps" not in sb
    arms.write(summary, str(tmp_path / "out" / "arms"))
    assert json.loads((tmp_path / "out" / "arms.json").read_text())["arms"]["a"]["greedy_gain"] == sa["greedy_gain"]
    assert (tmp_path / "out" / "arms.png").stat().st_size > 0


def test_summarize_mode_of_the_command_line(tmp_path, capsys):
    a = _arm(tmp_path, "a", [_point(0, 200, sampled=100), _point(50, 260, sampled=150)])
    summary = arms.main(["--out", str(tmp_path / "s"), "--summarize", f"t07={a}"])
    assert summary["arms"]["t07"]["greedy_gain"] == pytest.approx(0.12)
    assert "t07: greedy 0.400 -> 0.520" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="NAME=WORKDIR"):
        arms.main(["--out", str(tmp_path / "s"), "--summarize", a])


def test_every_arm_evaluates_both_policies_from_the_same_start_in_its_own_workdir():
    args = SimpleNamespace(out="runs/x/arms", config="cache_ablation:small-linear-direct-all", seed=0,
                           policy="runs/p/rl/policy_sft", arm_workers=7, steps=100, eval_every=50, eval_episodes=50)
    specs = [arms.parse_arm("t10:"), arms.parse_arm("t07: --rl.grpo.temperature=0.7 --seed 1")]
    cmds = arms.commands(args, specs, ["--rl.grpo.learning_rate=2e-4"])
    assert list(cmds) == ["t10", "t07"]
    for name, cmd in cmds.items():
        assert cmd[:3] == [sys.executable, "-m", "train.grpo"]
        assert cmd[cmd.index("--policy") + 1] == "runs/p/rl/policy_sft"
        assert cmd[cmd.index("--simulator") + 1] == "env"
        assert "--rl.grpo.eval_sampled=true" in cmd and "--rl.grpo.learning_rate=2e-4" in cmd
        assert cmd[-2:] == ["--workdir", f"runs/x/{name}"]
    t07 = cmds["t07"]
    assert "--rl.grpo.temperature=0.7" in t07
    assert t07.index("--seed", t07.index("--rl.grpo.eval_sampled=true")) > 0  # the arm's own seed comes last, argparse keeps it
    with pytest.raises(ValueError, match="names must differ"):
        arms.commands(args, [arms.parse_arm("a:"), arms.parse_arm("a: --seed 1")], [])


@pytest.mark.parametrize("spec", ["no colon", ": --seed 1", "bad name: --seed 1"])
def test_bad_arm_specs_are_refused_with_the_expected_form(spec):
    with pytest.raises(ValueError, match="'name: overrides'"):
        arms.parse_arm(spec)


def test_command_line_refuses_missing_policy_and_plain_arguments(tmp_path):
    with pytest.raises(SystemExit, match="--policy"):
        arms.main(["--out", str(tmp_path / "s"), "--arm", "a:"])
    with pytest.raises(SystemExit, match="dotted config override"):
        arms.main(["--out", str(tmp_path / "s"), "--policy", "p", "--arm", "a:", "stray"])
    with pytest.raises(SystemExit, match="'name: overrides'"):
        arms.main(["--out", str(tmp_path / "s"), "--policy", "p", "--arm", "nocolon"])
