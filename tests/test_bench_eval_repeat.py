"""benchmarks.bench_eval_repeat: the comparison of repeated evaluations and the refused command lines (the MJX
evaluation itself runs on a GPU)."""

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
    lines = []
    comparison, seconds = repeat.repeat_evaluations(runner, params, 3, masked=True, log=lines.append)
    assert set(comparison) == set(repeat.POLICIES) and len(seconds) == 3 and len(lines) == 3
    for c in comparison.values():
        assert c["episodes"] == 4 and c["differing"] == [0, 0] and len(set(c["success"])) == 1
    assert comparison["greedy"]["success"][0] >= 0.25  # the start past the goal succeeds whatever the policy does
    unmasked, _ = repeat.repeat_evaluations(runner, params, 2, masked=False, log=lines.append)
    assert "sampled_proprio_masked" not in unmasked and "proprio masked" not in lines[-1]
