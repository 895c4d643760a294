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
