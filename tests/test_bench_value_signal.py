"""benchmarks.bench_value_signal: the pairwise AUCs within and across groups and the within-group variance share,
on designed values; its command line's refusals."""

import numpy as np
import pytest

from benchmarks import bench_value_signal as vs


def test_a_value_that_ranks_groups_but_not_their_members_scores_half_within_groups():
    # two groups: group 0's members all near 0.9, group 1's near 0.1; inside each, the later outcome is unrelated
    values = np.array([0.91, 0.90, 0.89, 0.92, 0.11, 0.10, 0.09, 0.12])
    success = np.array([1, 0, 1, 0, 0, 1, 0, 1], bool)
    groups = np.repeat([0, 1], 4)
    within = vs.pair_auc(values, success, groups)
    assert within["pairs"] == 8 and within["auc"] == pytest.approx(0.5)
    across = vs.pair_auc(values, success, None)
    assert across["pairs"] == 16 and across["auc"] == pytest.approx(0.5)  # here the groups' successes are even
    assert vs.within_share(values, groups) < 0.01
    # a value that orders each group's members by their outcome
    ordered = np.array([0.9, 0.1, 0.8, 0.2, 0.3, 0.7, 0.2, 0.6])
    assert vs.pair_auc(ordered, success, groups)["auc"] == 1.0
    assert vs.pair_auc(np.full(8, 0.5), success, groups)["auc"] == 0.5  # ties count a half
    assert vs.pair_auc(values, np.ones(8, bool), groups) == {"auc": None, "pairs": 0}


@pytest.mark.parametrize("argv", [["--value-episodes", "0"], ["--group-size", "1"], ["--horizon", "0"],
                                  ["--value-steps", "0"], ["--value-steps", "a"], ["--fit-seeds", ""]])
def test_bad_command_lines_are_refused(tmp_path, argv):
    with pytest.raises(SystemExit, match="bench_value_signal"):
        vs.main(["--policy", "p.npz", "--demos", "d.hdf5", "--out", str(tmp_path), *argv])


def test_an_auc_without_pairs_prints_as_na():
    assert vs._auc(None) == "n/a" and vs._auc(0.5) == "0.500"
