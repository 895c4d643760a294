"""The comparison table's arithmetic and layout (the runs themselves are pipeline runs)."""

import numpy as np

from train import compare


def _result(lpips, success):
    metrics = {m: lpips * (i + 1) for i, m in enumerate(compare.METRICS)}
    return {"stages": {"evaluate": {"metrics": {"original": {"m": metrics}, "mixed": {"m": metrics}}},
                       "policy": {"success": {"grpo step 0": success[0], "grpo step 10": success[1]}}}}


def test_aggregate_means_and_spreads_and_markdown():
    results = {run: [_result(0.1 + 0.1 * s, (0.2, 0.4 + 0.1 * s)) for s in range(3)]
               for run in ("sword", "teacher_forcing", "no_augmentation", "wovr")}
    table = compare.aggregate(results)
    lpips = table["sword"]["metrics"]["original/lpips"]
    assert np.isclose(lpips["mean"], 0.2) and np.isclose(lpips["std"], 0.1) and lpips["n"] == 3
    assert np.isclose(table["wovr"]["success"]["grpo step 10"]["mean"], 0.5)
    text = compare.to_markdown(table, [0, 1, 2])
    assert "DLB vs teacher forcing" in text and "0.2 ± 0.1" in text
    assert text.index("grpo step 0") < text.index("grpo step 10")


def test_runs_cover_the_three_comparisons():
    runs = compare.runs_for("small")
    assert runs["teacher_forcing"][0] == "cache_ablation:small-tf"
    assert runs["wovr"][0] == "cache_ablation:small-wovr"
    assert "--augment.enabled=false" in runs["no_augmentation"][1]
    for _, ours, baseline, _ in compare.COMPARISONS:
        assert ours in runs and baseline in runs
