"""Gains between two evaluations of one run, paired episode by episode: the interval, the outcomes an evaluation
point keeps, and the evaluations' common sampling noise."""

import jax
import numpy as np
import pytest

from sword_jax.pipeline import grpo as pipeline_grpo
from sword_jax.rl.env_rollout import (difference_interval, gain_interval, mean_interval, outcomes_text,
                                      paired_difference_interval, point_outcomes)
from sword_jax.rl.policy_success import success_summary


def test_uncorrelated_pairs_give_newcombes_unpaired_interval():
    before = np.array([1, 1, 0, 0] * 30, bool)  # the four kinds of pair equally often: correlation 0
    after = np.array([1, 0, 1, 0] * 30, bool)
    assert paired_difference_interval(before, after) == pytest.approx(difference_interval(60, 120, 60, 120))
    before = np.array([1, 1, 1, 0, 0, 0] * 20, bool)  # after succeeds in 2 of 3 whatever before did: phi = 0 again
    after = np.array([1, 1, 0, 1, 1, 0] * 20, bool)
    assert paired_difference_interval(before, after) == pytest.approx(difference_interval(60, 120, 80, 120))


def test_correlated_pairs_narrow_the_interval_around_the_difference():
    rng = np.random.default_rng(0)
    before = rng.random(500) < 0.5
    after = before.copy()
    flip = rng.choice(500, 60, replace=False)  # 60 episodes change outcome: 45 gained, 15 lost
    after[flip[:45]] = True
    after[flip[45:]] = False
    gained, lost = int(np.sum(~before & after)), int(np.sum(before & ~after))
    low, high = paired_difference_interval(before, after)
    d = (gained - lost) / 500
    assert low < d < high
    u_low, u_high = difference_interval(int(before.sum()), 500, int(after.sum()), 500)
    assert high - low < 0.6 * (u_high - u_low)  # most episodes keep their outcome: far narrower
    same_low, same_high = paired_difference_interval(before, before)  # nothing moved: an interval about 0
    assert same_low <= 0.0 <= same_high and same_high - same_low < 0.01


def test_paired_interval_covers_the_true_difference():
    """Coverage by simulation: pairs with a known joint distribution (a correlated gain of 5 points), 400 draws of
    500 episodes; the 95% interval holds the true difference in 93-98% of them and is narrower than the unpaired."""
    rng = np.random.default_rng(1)
    p_both, p_gain, p_loss = 0.40, 0.10, 0.05  # P(before=1, after=1), P(0 -> 1), P(1 -> 0); the rest fail twice
    hits, widths, unpaired = 0, [], []
    for _ in range(400):
        kind = rng.choice(4, 500, p=[p_both, p_gain, p_loss, 1 - p_both - p_gain - p_loss])
        before, after = np.isin(kind, (0, 2)), np.isin(kind, (0, 1))
        low, high = paired_difference_interval(before, after)
        hits += low <= p_gain - p_loss <= high
        widths.append(high - low)
        u = difference_interval(int(before.sum()), 500, int(after.sum()), 500)
        unpaired.append(u[1] - u[0])
    assert 0.93 <= hits / 400 <= 0.98
    assert np.mean(widths) < 0.75 * np.mean(unpaired)


def test_extreme_pairs_stay_inside_the_possible_range():
    everything = np.ones(50, bool)
    nothing = np.zeros(50, bool)
    low, high = paired_difference_interval(nothing, everything)  # every episode gained
    assert 0.85 < low <= high <= 1.0 + 1e-9
    low, high = paired_difference_interval(everything, everything)  # margins of zero: phi taken as 0
    assert low == pytest.approx(-high) and 0.0 < high < 0.08  # the Wilson intervals of 50 of 50, unnarrowed


def test_unpaired_outcomes_are_refused_by_name():
    with pytest.raises(ValueError, match="the same episodes, got 3 and 4"):
        paired_difference_interval([1, 0, 1], [1, 0, 1, 1])
    with pytest.raises(ValueError, match="the same episodes"):
        paired_difference_interval([], [])


def test_an_evaluation_point_keeps_its_outcomes_and_gains_pair_them():
    success = np.array([1, 0, 0, 1, 1, 0], bool)
    point = success_summary(success, [0, 0, 1, 1, 2, 2], 1.0)
    assert point["outcomes"] == "100110" == outcomes_text(success)
    np.testing.assert_array_equal(point_outcomes(point), success)
    later = success_summary(np.array([1, 1, 0, 1, 1, 1], bool), [0, 0, 1, 1, 2, 2], 1.0)
    assert gain_interval(point, later) == pytest.approx(paired_difference_interval(success, point_outcomes(later)))
    bare = {k: v for k, v in later.items() if k != "outcomes"}  # an older record: no outcomes
    assert gain_interval(point, bare) == pytest.approx(difference_interval(3, 6, 5, 6))
    other = success_summary(np.ones(5, bool), [0] * 5, 1.0)  # another evaluation set: not paired
    assert gain_interval(point, other) == pytest.approx(difference_interval(3, 6, 5, 5))
    with pytest.raises(ValueError, match="outcomes must be 6 characters 0 or 1"):
        gain_interval(dict(point, outcomes="10x110"), later)
    with pytest.raises(ValueError, match="outcomes must be 6 characters"):
        gain_interval(dict(point, outcomes="1001"), later)


def test_every_sampled_evaluation_of_a_run_draws_the_same_noise(monkeypatch):
    """pipeline.grpo.sampled_point: the key handed to the evaluation is step 0's at every step (common random
    numbers), and different runs' roots give different keys."""
    keys = []

    def fake_evaluate(graphdef, params, rl, *, greedy, key, **kwargs):
        keys.append(np.asarray(jax.random.key_data(key)))
        return success_summary(np.array([1, 0], bool), [0, 1], 0.0)

    class Grpo:
        temperature = 0.5

    class Rl:
        grpo = Grpo()

    monkeypatch.setattr(pipeline_grpo, "evaluate_in_sim", fake_evaluate)
    for step, root in ((0, 3), (25, 3), (50, 3), (25, 4)):
        point = pipeline_grpo.sampled_point(None, None, Rl(), step, jax.random.key(root), log=lambda *_: None)
        assert point["outcomes"] == "10" and point["temperature"] == 0.5
    np.testing.assert_array_equal(keys[0], keys[1])
    np.testing.assert_array_equal(keys[0], keys[2])
    assert not np.array_equal(keys[1], keys[3])


def test_a_summarised_gain_says_how_the_episodes_moved(capsys):
    """bench_grpo_refresh.gain_between (every GRPO launcher's summary): with outcomes, the paired interval and the
    episodes that gained and lost success; without, the unpaired interval and no ``paired``; and the line
    bench_grpo_value prints names them."""
    from benchmarks import bench_grpo_value
    from benchmarks.bench_grpo_refresh import gain_between
    from sword_jax.rl.env_rollout import outcome_changes

    tasks = [0] * 8
    start = success_summary(np.array([1, 1, 0, 0, 0, 0, 1, 0], bool), tasks, 0.0)
    end = success_summary(np.array([1, 0, 1, 1, 0, 0, 1, 1], bool), tasks, 0.0)
    assert outcome_changes(start, end) == {"gained": 3, "lost": 1, "episodes": 8}
    points = [dict(start, step=0, sampled=start), dict(end, step=30, sampled=end)]
    gain = gain_between(points, "sampled")
    assert gain["paired"] == {"gained": 3, "lost": 1, "episodes": 8} and gain["gain"] == pytest.approx(0.25)
    assert gain["ci95"] == pytest.approx(list(paired_difference_interval(point_outcomes(start), point_outcomes(end))))
    bare = [{k: v for k, v in p.items() if k != "outcomes"} for p in points]
    assert "paired" not in gain_between(bare, None) and outcome_changes(bare[0], bare[1]) is None
    run = {"steps": 30, "sampled": gain}
    bench_grpo_value.print_runs({"runs": {"success_s0": run}})
    line = capsys.readouterr().out
    assert "sampled 0.375 -> 0.625 (+0.250 [" in line and ", paired: 3 episodes gained, 1 lost)" in line


def test_mean_interval_sums_the_variances_its_intervals_give():
    """Each 95% interval of half-width 1.96 * sigma gives variance sigma^2; the mean of n estimates has half-width
    1.96 * sqrt(sum of variances) / n."""
    z = 1.959964
    mean, (low, high) = mean_interval([0.1, 0.3], [(-z * 0.03, z * 0.03), (0.3 - z * 0.04, 0.3 + z * 0.04)])
    assert mean == pytest.approx(0.2) and high - mean == pytest.approx(mean - low)
    assert high - mean == pytest.approx(z * 0.05 / 2)  # sqrt(0.03^2 + 0.04^2) = 0.05, over 2 values
    # two intervals per estimate (a difference of two independent gains) add both variances
    _, (low4, high4) = mean_interval([0.0], [(-z * 0.03, z * 0.03), (-z * 0.04, z * 0.04)])
    assert high4 == pytest.approx(z * 0.05) and low4 == pytest.approx(-z * 0.05)
    with pytest.raises(ValueError, match="at least one value"):
        mean_interval([], [])
