"""benchmarks.bench_eval_repeat: the comparison of repeated evaluations and the refused command lines (the MJX
evaluation itself runs on a GPU)."""

import json

import numpy as np
import pytest

from benchmarks import bench_eval_repeat as repeat
from sword_jax.cli import UsageError


def test_repeats_are_compared_with_the_first_episode_by_episode():
    first = np.array([1, 1, 0, 0, 1], bool)
    same = first.copy()
    moved = np.array([1, 0, 1, 1, 1], bool)  # episode 1 lost, episodes 2 and 3 gained
    c = repeat.compare_repeats([first, same, moved])
    assert c["episodes"] == 5 and c["success"] == pytest.approx([0.6, 0.6, 0.8])
    assert c["differing"] == [0, 3] and c["gained"] == [0, 2] and c["lost"] == [0, 1]
    assert c["differing_share"] == pytest.approx([0.0, 0.6])


def test_unmatched_repeats_are_refused():
    with pytest.raises(ValueError, match="at least 2 repeats, got 1"):
        repeat.compare_repeats([np.ones(3, bool)])
    with pytest.raises(ValueError, match=r"the same episodes, got sizes \[3, 4\]"):
        repeat.compare_repeats([np.ones(3, bool), np.ones(4, bool)])


def test_the_command_line_is_checked_before_anything_is_built(tmp_path):
    policy = tmp_path / "p.npz"
    np.savez(policy, w=np.zeros(1))
    args, overrides = repeat.parse(["--policy", str(policy), "--out", str(tmp_path), "--rl.grpo.temperature=0.5"])
    assert args.repeats == 3 and args.config == "sword:small" and overrides == ["--rl.grpo.temperature=0.5"]
    with pytest.raises(UsageError, match="--repeats must be >= 2"):
        repeat.parse(["--policy", str(policy), "--out", str(tmp_path), "--repeats", "1"])
    with pytest.raises(UsageError, match="--episodes-per-task must be in 1..50"):
        repeat.parse(["--policy", str(policy), "--out", str(tmp_path), "--episodes-per-task", "51"])
    with pytest.raises(UsageError, match="no such file"):
        repeat.parse(["--policy", str(tmp_path / "missing.npz"), "--out", str(tmp_path)])
    with pytest.raises(UsageError, match="not a dotted config override"):
        repeat.parse(["--policy", str(policy), "--out", str(tmp_path), "--temperature", "0.5"])
    with pytest.raises(UsageError, match="--policy and --out are needed"):
        repeat.parse(["--out", str(tmp_path)])
    with pytest.raises(UsageError, match="add --record"):
        repeat.parse(["--from", str(tmp_path / "eval_repeat.json")])
    with pytest.raises(UsageError, match="drop --policy"):
        repeat.parse(["--from", str(tmp_path / "eval_repeat.json"), "--record", "--policy", str(policy)])


def test_a_saved_result_is_checked_and_recorded_with_its_own_device(tmp_path, monkeypatch):
    from benchmarks import common

    monkeypatch.setattr(common, "RESULTS", str(tmp_path / "latest.json"))
    kept = repeat.outcome_strings({"greedy": [np.array([1, 0, 1, 1]), np.array([1, 1, 1, 1])],
                                   "sampled": [np.array([0, 0, 1, 1]), np.array([0, 0, 1, 1])]})
    assert kept == {"greedy": ["1011", "1111"], "sampled": ["0011", "0011"]}
    saved = tmp_path / "eval_repeat.json"
    saved.write_text(json.dumps({"device": "NVIDIA H200 x1 (gpu)", "config": "sword-small", "deterministic": True,
                                 "seconds": [3.0, 1.0], "outcomes": kept, "policies": {}}))
    result = repeat.main(["--from", str(saved), "--record"])  # the policies are compared again from the outcomes
    assert result["policies"]["greedy"]["differing"] == [1] and result["policies"]["sampled"]["differing"] == [0]
    entry = json.loads((tmp_path / "latest.json").read_text())["mjx_eval_repeat_deterministic_small"]
    assert entry["value"] == pytest.approx(0.25) and entry["device"] == "NVIDIA H200 x1 (gpu)"
    assert entry["deterministic"] is True and entry["complete"] is True
    plain = json.loads(saved.read_text())
    plain["deterministic"] = False  # a plain evaluation keeps its own entry beside the deterministic one
    saved.write_text(json.dumps(plain))
    repeat.main(["--from", str(saved), "--record"])
    assert set(json.loads((tmp_path / "latest.json").read_text())) >= {"mjx_eval_repeat_small",
                                                                        "mjx_eval_repeat_deterministic_small"}
    one = tmp_path / "one.json"  # cut off after its first repeat: nothing to compare
    one.write_text(json.dumps({"complete": False, "outcomes": {"greedy": ["1011"]}, "policies": {}}))
    with pytest.raises(UsageError, match="at least 2 repeats, got 1"):
        repeat.load_result(str(one))
    one.write_text(json.dumps({"complete": False, "policies": {}}))
    with pytest.raises(UsageError, match="fewer than 2 repeats finished"):
        repeat.load_result(str(one))
    one.write_text("{")
    with pytest.raises(UsageError, match="not JSON"):
        repeat.load_result(str(one))
    with pytest.raises(UsageError, match="cannot read it"):
        repeat.load_result(str(tmp_path / "missing.json"))
    one.write_text("[]")
    with pytest.raises(UsageError, match="no 'policies'"):
        repeat.load_result(str(one))


def test_repeated_evaluations_of_a_toy_runner_compare_every_policy(tmp_path):
    """repeat_evaluations on EnvGRPO with the tests' slide environment (deterministic on the CPU): every policy's
    repeats agree episode by episode, and the masked policy is there only when asked for."""
    import dataclasses

    import jax

    import configs
    from sword_jax.rl.jax_env_grpo import EnvGRPO
    from sword_jax.rl.policy import build_policy, tokenize_instructions
    from tests.test_scan_rollout import SIZE, SlideEnv

    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, env=dataclasses.replace(cfg.rl.env, execute_steps=1,
                                                                             action_ensemble=False),
                             grpo=dataclasses.replace(cfg.rl.grpo, rollout_batch=1, group_size=4))
    graphdef, params = build_policy(rl, seed=0)
    starts = np.array([[0.6], [-0.6], [0.3], [0.1]], np.float32)
    runner = EnvGRPO(graphdef, rl, SlideEnv(), max_steps=3, starts_at=None, eval_starts=starts,
                     eval_tokens=tokenize_instructions(["push it"] * 4, rl.policy.max_instruction_bytes),
                     eval_tasks=[0, 0, 1, 1], key=jax.random.key(3))
    runner.start_probe(params, str(tmp_path / "probe"))
    lines, seen = [], []
    comparison, seconds = repeat.repeat_evaluations(runner, params, 3, masked=True, log=lines.append,
                                                    on_repeat=lambda o, s: seen.append((len(o["greedy"]), len(s))))
    assert set(comparison) == set(repeat.POLICIES) and len(seconds) == 3 and len(lines) == 3
    assert seen == [(1, 1), (2, 2), (3, 3)]  # called after every repeat with what is done so far
    for c in comparison.values():
        assert c["episodes"] == 4 and c["differing"] == [0, 0] and len(set(c["success"])) == 1
    assert comparison["greedy"]["success"][0] >= 0.25  # the start past the goal succeeds whatever the policy does
    unmasked, _ = repeat.repeat_evaluations(runner, params, 2, masked=False, log=lines.append)
    assert "sampled_proprio_masked" not in unmasked and "proprio masked" not in lines[-1]
