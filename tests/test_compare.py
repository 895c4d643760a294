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


def _write_markers(workdir, stages):
    import json
    import os

    os.makedirs(os.path.join(workdir, "stages"), exist_ok=True)
    for stage in stages:
        with open(os.path.join(workdir, "stages", f"{stage}.json"), "w") as f:
            json.dump({"stage": stage, "results": {"path": f"{workdir}/{stage}"}}, f)


def test_runs_adopt_only_stages_whose_config_sections_agree(tmp_path):
    import json
    import os

    import configs

    donor = str(tmp_path / "sword" / "seed0")
    _write_markers(donor, compare.SHAREABLE)
    sword = configs.get("cache_ablation:small-linear-direct-all")
    tf = configs.get("cache_ablation:small-tf")
    wovr = configs.get("cache_ablation:small-wovr")
    other_seed = compare.adopt_stages(str(tmp_path / "tf1"), donor, tf, sword)
    assert other_seed == list(compare.SHAREABLE)
    # WoVR trains without augmentation: its latents (no styled copies) are its own.
    assert "latents" not in compare.adopt_stages(str(tmp_path / "wovr"), donor, wovr, sword)
    assert os.path.exists(tmp_path / "wovr" / "stages" / "data.json")
    # A different simulator section shares nothing; a finished stage is never overwritten.
    import dataclasses

    other_sim = dataclasses.replace(sword, sim=dataclasses.replace(sword.sim, episodes_per_task=3))
    assert compare.adopt_stages(str(tmp_path / "other"), donor, other_sim, sword) == []
    _write_markers(str(tmp_path / "mine"), ["vae"])
    adopted = compare.adopt_stages(str(tmp_path / "mine"), donor, sword, sword)
    assert "vae" not in adopted
    with open(tmp_path / "mine" / "stages" / "vae.json") as f:
        assert json.load(f)["results"]["path"].startswith(str(tmp_path / "mine"))
    with open(tmp_path / "tf1" / "stages" / "data.json") as f:
        assert json.load(f)["results"]["path"] == f"{donor}/data"


def test_partial_tables_are_written_while_runs_finish(tmp_path):
    import json

    results = {"sword": [_result(0.1, (0.2, 0.4))]}
    compare.write_tables(str(tmp_path), results, [0, 1, 2], size="small")
    with open(tmp_path / "comparison.json") as f:
        written = json.load(f)
    assert written["finished_seeds_per_run"] == {"sword": 1}
    assert "teacher_forcing" in (tmp_path / "comparison.md").read_text()
