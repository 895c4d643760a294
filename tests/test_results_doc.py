"""The README and docs/RESULTS.md: their generated tables agree with the committed JSON, their links lead
somewhere, the README stays what a newcomer reads, and no file narrates how the work was scheduled."""

import glob
import json
import os
import re
import shutil
import subprocess
from unittest import mock

import pytest

from benchmarks import report
from tests.conftest import REPO

# Wording that narrates how a result was obtained rather than stating its run, device, limit and date.
NARRATION = re.compile(r"|".join([
    r"\bthis session\b", r"\bthe session'?s?\b", r"\bsession device", r"\bGPU session\b", r"\bcut-off session\b",
    r"\bdevice[- ]time\b", r"\bdevice lease\b", r"\bleases?\b", r"\bleased\b", r"\bmachine loans?\b", r"\bloaned\b",
    r"\bwork periods?\b", r"\btime budgets?\b", r"\bbudget_left", r"\bmachine runs?\b", r"\bmachine time\b",
    r"\bthe machine was held\b", r"\bwarm machine\b", r"\bheld \d+ (?:s|minutes)\b",
]), re.I)


def _tracked(*patterns: str) -> list[str]:
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", *patterns], cwd=REPO,
                         capture_output=True, text=True, check=True).stdout.split()
    return [path for path in out if os.path.exists(os.path.join(REPO, path))]


def _strings(tree):
    if isinstance(tree, dict):
        for value in tree.values():
            yield from _strings(value)
    elif isinstance(tree, list):
        for value in tree:
            yield from _strings(value)
    elif isinstance(tree, str):
        yield tree


def test_generated_tables_agree_with_the_json():
    assert report.stale() == [], "run python -m benchmarks.report"
    text = open(os.path.join(REPO, "docs", "RESULTS.md")).read()
    names = re.findall(r"<!-- table:([\w-]+) -->", text) + re.findall(
        r"<!-- table:([\w-]+) -->", open(os.path.join(REPO, "README.md")).read())
    assert sorted(names) == sorted(report.TABLES)  # every generator has its place, once


def test_a_table_that_disagrees_with_its_json_is_found(tmp_path):
    for name in report.DOCUMENTS:
        os.makedirs(tmp_path / os.path.dirname(name), exist_ok=True)
        shutil.copy(os.path.join(REPO, name), tmp_path / name)
    assert report.stale(str(tmp_path)) == []
    results = tmp_path / "docs" / "RESULTS.md"
    text = results.read_text()
    assert "| Original, DLB | 0.183 ± 0.005 |" in text  # claim 1's latent MSE, from compare/small/comparison.json
    results.write_text(text.replace("| Original, DLB | 0.183 ± 0.005 |", "| Original, DLB | 0.150 ± 0.005 |"))
    assert report.stale(str(tmp_path)) == [os.path.join("docs", "RESULTS.md")]
    readme = tmp_path / "README.md"
    readme.write_text(readme.read_text().replace("<!-- /table:readme-results -->", "| extra | row |\n"
                                                 "<!-- /table:readme-results -->"))
    assert report.stale(str(tmp_path)) == ["README.md", os.path.join("docs", "RESULTS.md")]


def _anchors(path: str) -> set[str]:
    """GitHub's anchors of a markdown file's headings."""
    return {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
            for heading in re.findall(r"^#+ (.*)$", open(path).read(), re.M)}


def test_readme_is_short_and_its_links_lead_somewhere():
    lines = open(os.path.join(REPO, "README.md")).read().splitlines()
    assert len(lines) <= 300 and max(len(line) for line in lines) <= 300
    for name in ("README.md", os.path.join("docs", "RESULTS.md")):
        for target in re.findall(r"\]\(([^)\s]+)\)", open(os.path.join(REPO, name)).read()):
            if target.startswith("http"):
                continue
            path, _, anchor = target.partition("#")
            resolved = os.path.normpath(os.path.join(REPO, os.path.dirname(name), path or os.path.basename(name)))
            assert os.path.exists(resolved), f"{name}: link to a missing {target}"
            assert not anchor or anchor in _anchors(resolved), f"{name}: no section #{anchor} in {path or name}"


def test_the_readme_commands_are_those_ci_runs():
    readme = open(os.path.join(REPO, "README.md")).read()
    ci = open(os.path.join(REPO, ".ci", "run")).read().splitlines()
    install = re.search(r"## Install\n\n```bash\n(.*?)\n```", readme, re.S).group(1)
    assert [step for step in install.split(" && ") if step not in ci] == []  # CI installs as the README says
    quick = re.search(r"## Quick start\n\n```bash\n(.*?)\n```", readme, re.S).group(1).splitlines()
    assert len(quick) == 2 and quick[0].startswith("python -m train.pipeline ")
    assert quick[1].split("#")[0].strip() in ci  # and runs the README's test command


def test_no_file_narrates_how_the_work_was_scheduled():
    found = []
    for path in _tracked("README.md", "docs/*", "*.py", "benchmarks/results/*.md"):
        if path == "tests/test_results_doc.py":
            continue
        for number, line in enumerate(open(os.path.join(REPO, path), errors="replace"), 1):
            if NARRATION.search(line):
                found.append(f"{path}:{number}: {line.strip()[:120]}")
    for path in _tracked("benchmarks/results/*.json"):
        for text in _strings(json.load(open(os.path.join(REPO, path)))):
            if NARRATION.search(text):
                found.append(f"{path}: {NARRATION.search(text).group(0)!r} in {text[:120]!r}")
    assert found == []


def test_the_narration_check_catches_what_it_is_for():
    for text in ("cut off by the session's device time", "one H200 lease each", "the machine was held 33 minutes",
                 "one 30-minute machine run holds", "within this session", "a time budget of 30 minutes"):
        assert NARRATION.search(text), text
    for text in ("built once per test session", "scope='session'", "start_new_session=True", "released weights",
                 "stopped by the run's 30-minute time limit", "a 25-minute run on 4 x H100"):
        assert not NARRATION.search(text), text
    assert len(glob.glob(os.path.join(REPO, "benchmarks", "results", "**", "*.json"), recursive=True)) > 10


def test_the_report_names_the_tasks_as_the_simulator_does():
    from benchmarks import report
    from sim.tasks import LANGUAGE

    assert len(report.TASK_NAMES) == len(LANGUAGE)
    for short, sentence in zip(report.TASK_NAMES, LANGUAGE):
        assert short.replace("table centre", "table center") in sentence, (short, sentence)


def test_the_per_task_table_gives_each_run_its_own_gain(tmp_path, monkeypatch):
    """grpo_per_task: a cell is the run's success at the step minus its own step 0, per seed, in points."""
    def curve(run, points):
        path = tmp_path / "policy" / "f" / f"s{run}" / "r"
        path.mkdir(parents=True)
        (path / "success_curve.json").write_text(json.dumps({"points": points}))

    for seed in range(3):
        masked = [{"0": 0.5, "1": 0.2}, {"0": 0.5 + 0.1 * seed, "1": 0.1}, {"0": 0.9, "1": 0.9}]
        curve(seed, [{"step": s, "per_task": {"0": 0.7, "1": 0.6 - 0.02 * s},
                      "sampled_proprio_masked": {"per_task": m}} for s, m in zip((0, 10, 15), masked)])
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_per_task((("masked, step 10", "f", "s{}", "sampled_proprio_masked", 10),
                                  ("greedy, last", "f", "s{}", "greedy", None)))
    rows = [line.split(" | ") for line in table.splitlines()[2:]]
    assert rows[0][1:] == ["0.50 / 0.70", "+0, +10, +20", "+0, +0, +0 |"]
    assert rows[1][1:] == ["0.20 / 0.60", "-10, -10, -10", "-30, -30, -30 |"]


def test_step_span_names_the_steps_the_runs_reached():
    assert report._step_span({"runs": {"a": {"steps": 17}, "b": {"steps": 14}, "c": {"steps": 15}}}) == "14-17"
    assert report._step_span({"runs": {"a": {"steps": 15}, "b": {"steps": 15}}}) == "15"


def _paired_runs(tmp_path, folder, ends, start="1100"):
    """Seeds 0-2 of a run in policy/<folder>/success/s<k>: step 0 ``start`` and step 10 ``ends[k]`` for every
    evaluated policy."""
    for seed, end in enumerate(ends):
        path = tmp_path / "policy" / folder / "success" / f"s{seed}" / "r"
        path.mkdir(parents=True)
        point = lambda step, text: {"step": step, "episodes": len(text), "outcomes": text, **{
            m: {"episodes": len(text), "outcomes": text} for m in ("sampled", "sampled_proprio_masked")}}
        (path / "success_curve.json").write_text(json.dumps({"points": [point(0, start), point(10, end)]}))


def test_the_cut_against_whole_episodes_is_paired_episode_by_episode(tmp_path, monkeypatch):
    import pytest

    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    _paired_runs(tmp_path, "a", ["1111", "1100", "1110"])
    _paired_runs(tmp_path, "b", ["1100", "1100", "1100"])
    table = report.grpo_rest_cut_vs_whole((("cut", "a"), ("whole", "b"), 10))
    rows = [line.split(" | ") for line in table.splitlines()[2:]]
    assert [r[0].strip("| ") for r in rows] == ["sampled, proprio masked", "sampled, true proprio", "greedy"]
    for row in rows:
        assert row[1].startswith("1.000 / 0.500, +50.0 [") and row[2].startswith("0.500 / 0.500, +0.0 [")
        assert row[3].startswith("0.750 / 0.500, +25.0 [") and row[4].startswith("+25.0 [")
    _paired_runs(tmp_path, "c", ["1100", "1100", "1100"], start="0011")
    with pytest.raises(ValueError, match="step-0 outcomes .* differ"):
        report.grpo_rest_cut_vs_whole((("cut", "a"), ("other", "c"), 10))


def test_the_rest_reward_source_table_pays_every_rollout_of_each_arm(tmp_path, monkeypatch):
    """grpo_reward_source_rest: the real-frame arm's payment is every step's rollout success times its
    trajectories, with a Wilson interval; the world-model arm's is the closed-loop record's; gains and the
    detector come from the summary; the per-decision table is the mean over the steps of the run's history."""
    from sword_jax.rl.env_rollout import wilson_interval

    record = tmp_path / "policy" / "rest"
    gt = record / "gt" / "s0" / "grpo_dir"
    gt.mkdir(parents=True)
    gt.joinpath("success_curve.json").write_text(json.dumps({"points": []}))  # what marks the run's folder
    gt.joinpath("train_history.jsonl").write_text("\n".join(json.dumps(
        {"step": s, "rollout_success": r, "trajectories_sampled": 100}) for s, r in ((1, 0.25), (2, 0.35))) + "\n")
    gain = {"start": 0.5, "end": 0.6, "gain": 0.1, "ci95": [-0.02, 0.22]}
    run = {"steps": 2, "paid_success": {"first": 0.25, "last": 0.35}, "mixed_median": 0.75, "seed": 0,
           "sampled_proprio_masked": gain, "greedy": gain}
    (record / "grpo_reward_source.json").write_text(json.dumps({"runs": {
        "exec_s0": {**run, "arm": "exec", "detector": {"success": 0.2, "precision": 0.05}},
        "gt_s0": {**run, "arm": "gt"}}}))
    (record / "closed_loop.json").write_text(json.dumps({"runs": {"wm": {
        "paid_success": {"rate": 0.015, "ci95": [0.01, 0.02], "of": 200}}}}))
    history = record / "exec_s0" / "rl" / "grpo"
    history.mkdir(parents=True)
    history.joinpath("train_history.jsonl").write_text("\n".join(json.dumps(
        {f"closed_loop_{what}_{k}": value + k for what in ("frame_error", "frame_error_vae", "motion", "action_gap",
                                                            "action_gap_vae", "action_gap_prev") for k in (1, 2)})
        for value in (0.0, 0.5)) + "\n")
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    monkeypatch.setattr(report, "REWARD_SOURCE_REST", ("policy", "rest"))
    rows = [line.split(" | ") for line in report.grpo_reward_source_rest().splitlines()[2:]]
    low, high = wilson_interval(60, 200)
    assert rows[0][0].startswith("| real frames") and rows[0][3] == f"0.300 [{low:.3f}, {high:.3f}] of 200"
    assert rows[0][6:8] == ["0.50 -> 0.60, +10.0 [-2.0, +22.0]"] * 2 and rows[0][8] == " |"
    assert rows[1][0].startswith("| the world model's") and rows[1][3] == "0.015 [0.010, 0.020] of 200"
    assert rows[1][4:6] == ["0.250 -> 0.350", "0.75"] and rows[1][8] == "0.20 / 0.05 |"
    decisions = [line.split(" | ") for line in report.sim_fidelity_decisions(("policy", "rest", "exec_s0"))
                 .splitlines()[2:]]
    assert [row[1] for row in decisions] == ["1.250", "2.250"]  # means of 1, 1.5 and of 2, 2.5


def test_the_chunk_table_reads_each_runs_own_actions_a_decision(tmp_path, monkeypatch):
    """failure_rest_chunk: decisions to a success become actions at each run's own actions a decision, the
    episodes' success carries a Wilson interval, and the mixed groups are counted over every start."""
    from sword_jax.rl.env_rollout import wilson_interval

    def run(name, k, horizon, success, mixed):
        (tmp_path / "policy" / name).mkdir(parents=True)
        (tmp_path / "policy" / name / "failure_phases.json").write_text(json.dumps({
            "actions_per_decision": k, "horizon_decisions": horizon, "episodes": 20, "success": success / 20,
            "episode_stages": {"success": success, "never grasped": 2, "grasped, never over the plate": 3,
                               "over the plate, not placed": 20 - success - 5},
            "decisions_to_success": [5.0, 6.5, 8.0], "mixed_groups": mixed,
            "starts": {"before the grasp": {"starts": 16, "mixed_groups": mixed, "paid_success": 0.25}},
            "per_task": {"1": {"starts": 6, "mixed_groups": 1}, "0": {"starts": 10, "mixed_groups": mixed - 1}}}))

    run("four", 4, 12, 8, 12)
    run("eight", 8, 6, 6, 9)
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    monkeypatch.setattr(report, "FAILURE_REST_CHUNK_RUNS", ("four", "missing", "eight"))
    rows = [line.split(" | ") for line in report.failure_rest_chunk().splitlines()[2:]]
    low, high = wilson_interval(6, 20)
    assert len(rows) == 2 and rows[0][0] == "| 4" and rows[1][0] == "| 8"
    assert rows[1][1] == f"0.300 [{low:.3f}, {high:.3f}] of 20" and rows[1][2] == "2 / 3 / 9"
    assert rows[0][3] == "20, 26, 32" and rows[1][3] == "40, 52, 64"
    assert rows[1][4:7] == ["6 (48 actions)", "9 of 16 (0.56)", "0.250"] and rows[1][7] == "8/10, 1/6 |"


def test_the_held_out_table_reads_every_split_the_trainer_measured(tmp_path, monkeypatch):
    """world-model-heldout: per step, the logged loss (mean of the last 10) and each split's fixed-noise loss and
    sample errors, the policy split's where the run measured it; the last row is the relative change."""
    folder = tmp_path / "policy" / "run" / "pipeline" / "world_model"
    folder.mkdir(parents=True)
    rows = [{"step": 50 * i, "loss": 1.0} for i in range(1, 5)]
    for i, scale in ((1, 2.0), (3, 1.0)):  # steps 100 and 200
        rows[i].update({f"eval_{split}_{name}": scale * base for split, base in (("train", 0.1), ("heldout", 0.2),
                                                                               ("policy", 0.4))
                        for name in ("loss", "sample_error_5")})
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.world_model_heldout(("policy", "run"), (100, 200)).splitlines()
    assert table[0].split(" | ")[2:5] == ["fixed-noise loss: training segments", "fixed-noise loss: held-out expert segments",
                                          "fixed-noise loss: held-out policy segments"]
    assert table[3] == "| 200 | 1.0000 | 0.1000 | 0.2000 | 0.4000 | 0.2000 | 0.4000 | 0.1000 |"
    assert table[4] == "| 100 -> 200 | +0% | -50% | -50% | -50% | -50% | -50% | -50% |"


def test_the_scaling_table_compares_runs_by_their_policy_rollouts_and_leaves_unmeasured_splits_named(
        tmp_path, monkeypatch):
    """world-model-policy-scaling: one row per run and step, the run named by its config's policy rollouts per
    task; the held-out policy error over the held-out expert one and over the training policy one; a run that did
    not measure the training policy split says so rather than a number."""
    for name, per_task, splits in (("a", 20, ("train", "heldout", "policy")),
                                   ("b", 100, ("train", "heldout", "policy", "trainpolicy"))):
        folder = tmp_path / "policy" / name / "pipeline"
        (folder / "world_model").mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps({"data": {"policy_rollouts_per_task": per_task}}))
        base = {"train": 0.1, "heldout": 0.2, "policy": 0.4, "trainpolicy": 0.25}
        rows = [{"step": 10, "loss": 1.0}]
        rows += [{"step": s, "eval_heldout_loss": 1.0, **{f"eval_{k}_sample_error_5": base[k] / (s // 100)
                                                          for k in splits}} for s in (100, 200)]
        (folder / "world_model" / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.world_model_policy_scaling((("policy", "a"), ("policy", "b")), (100, 200)).splitlines()
    assert table[0].split(" | ")[-2:] == ["held-out policy / held-out expert", "held-out policy / training policy |"]
    assert table[2] == "| 20 | 100 | 0.2000 | 0.4000 | not measured | 0.1000 | 2.00 | not measured |"
    assert table[5] == "| 100 | 200 | 0.1000 | 0.2000 | 0.1250 | 0.0500 | 2.00 | 1.60 |"
    assert len(table) == 6


def test_the_reward_source_table_orders_the_arms_and_counts_mixed_groups_of_the_step():
    """A reward-source summary's table: ground truth, exec, det in that order whatever the runs' names; each gain
    with its interval, a mode a run did not evaluate named "not run"; the mixed groups as a share, or counted of
    the step's groups; the detector's verdicts only where reality paid."""
    def run(arm, seed, masked=True, detector=None):
        gain = {"gain": -0.05, "ci95": [-0.1, 0.0]}
        return {"arm": arm, "seed": seed, "steps": 30, "sampled": gain, "greedy": {"gain": 0.1, "ci95": [0.02, 0.18]},
                **({"sampled_proprio_masked": gain} if masked else {}), "mixed_median": 0.1875,
                "paid_success": {"first": 0.25, "last": 0.3}, **({"detector": detector} if detector else {})}

    summary = {"arms": {a: {"label": a.upper()} for a in ("gt", "exec", "det")},
               "runs": {"a": run("det", 1), "b": run("exec", 0, detector={"success": 0.1, "agreement": 0.8,
                                                                          "precision": 0.75}),
                        "c": run("gt", 2, masked=False)}}
    table = report._reward_source_table(summary).splitlines()
    assert [row.split(" | ")[0] for row in table[2:]] == ["| GT", "| EXEC", "| DET"]
    assert table[2] == ("| GT | s2 | 30 | -5.0 [-10.0, +0.0] | not run | +10.0 [+2.0, +18.0] | 0.250 -> 0.300 | 0.19 "
                        "|  |")
    assert table[3].endswith("| 0.19 | 0.10 / 0.80 / 0.75 |")
    assert report._reward_source_table(summary, group_of=32).splitlines()[4].endswith("| 6 of 32 |  |")
    # a summary with a run evaluated as its GRPO executes the sampled policy: that column after the sampled one,
    # "not run" for the runs without it (a None from the summary, or no entry)
    summary["runs"]["b"]["sampled_as_trained"] = {"gain": 0.2, "ci95": [0.15, 0.25]}
    summary["runs"]["a"]["sampled_as_trained"] = None
    table = report._reward_source_table(summary).splitlines()
    assert table[0].split(" | ")[4] == "sampled as trained (its rollouts' execution)"
    assert table[0].count("|") == table[2].count("|")
    assert table[3].startswith("| EXEC | s0 | 30 | -5.0 [-10.0, +0.0] | +20.0 [+15.0, +25.0] | -5.0 [-10.0, +0.0] |")
    assert table[2].split(" | ")[4] == table[4].split(" | ")[4] == "not run"


def test_the_horizon_honesty_table_reads_its_record_row_by_row(tmp_path, monkeypatch):
    """grpo-horizon-honesty: per row of a horizons.json, in its order, each arm's paid success with its interval
    and trajectories, the share kept, the mixed groups counted of the step's groups and the detector's figures; an
    arm that did not run, a ratio without both arms and a precision without a verdict of success say so."""
    def arm(rate, ci, of, mixed, detector=None):
        return {"runs": ["x_s0"], "steps": 4, "mixed_groups_median": mixed, "mixed_share_median": mixed / 64,
                "paid_success": {"successes": round(rate * of), "rate": rate, "ci95": ci, "of": of},
                **({"detector": detector} if detector else {})}

    rows = [{"decisions": 1, "actions_per_decision": 8, "actions": 8, "group_size": 8, "groups_per_step": 64,
             "arms": {"gt": arm(0.5, [0.48, 0.53], 2048, 12.5), "exec": arm(0.25, [0.23, 0.28], 2048, 9, {
                 "success": 0.125, "agreement": 0.75, "false_success": 0.1, "precision": 0.5})},
             "exec_over_gt": 0.5},
            {"decisions": 6, "actions_per_decision": 8, "actions": 48, "group_size": 8, "groups_per_step": 64,
             "arms": {"exec": arm(0.0625, [0.051, 0.076], 1536, 3, {"success": 0.0, "agreement": 0.9,
                                                                      "false_success": 0.0, "precision": None})},
             "exec_over_gt": None}]
    (tmp_path / "policy" / "hz").mkdir(parents=True)
    (tmp_path / "policy" / "hz" / "horizons.json").write_text(json.dumps({"rows": rows}))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_horizon_honesty(("policy", "hz", "horizons.json")).splitlines()
    assert len(table) == 4 and "grpo-horizon-honesty" in report.TABLES
    assert table[2] == ("| 1 x 8 = 8 | 0.500 [0.480, 0.530] of 2,048 | 0.250 [0.230, 0.280] of 2,048 | 0.50 "
                        "| 12.5 of 64 | 9 of 64 | 0.12 / 0.75 / 0.50 |")
    assert table[3] == "| 6 x 8 = 48 | not run | 0.062 [0.051, 0.076] of 1,536 |  |  | 3 of 64 | 0.00 / 0.90 / n/a |"
    # an executed run that recorded how the detector's scores rank the real outcomes
    assert report._detector_cell({"success": 0.5, "agreement": 0.75, "precision": 0.5, "auc": 0.625,
                                  "recall_bounded": 0.25}) == "0.50 / 0.75 / 0.50; AUC 0.62"


def test_the_first_half_table_labels_each_row_by_its_setting_in_the_settings_order(tmp_path, monkeypatch):
    """grpo-first-half-decisions: one row per ground-truth run of each setting's summary, in FIRST_HALF_SETTINGS'
    order and labelled by the setting, its groups counted of the step's 64, and no detector column."""
    def run(seed, sampled, masked):
        return {"arm": "gt", "seed": seed, "steps": 20, "sampled": {"gain": sampled, "ci95": [sampled - 0.05, 0.0]},
                "sampled_proprio_masked": {"gain": masked, "ci95": [-0.1, 0.1]},
                "greedy": {"gain": 0.05, "ci95": [0.0, 0.1]}, "mixed_median": 0.84375,
                "paid_success": {"first": 0.25, "last": 0.375}}

    root = tmp_path / "policy" / report.FIRST_HALF_DECISIONS[1]
    for i, folder in enumerate(report.FIRST_HALF_SETTINGS):
        (root / folder).mkdir(parents=True)
        runs = {"gt_s1": run(1, -0.01 * i, 0.02), "gt_s0": run(0, 0.0, 0.0)}
        summary = {"arms": {"gt": {"label": "GT"}}, "runs": runs}
        (root / folder / "grpo_reward_source.json").write_text(json.dumps(summary))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_first_half_decisions().splitlines()
    labels = list(report.FIRST_HALF_SETTINGS.values())
    assert len(table) == 2 + 2 * len(labels) and "grpo-first-half-decisions" in report.TABLES
    assert [row.split(" | ")[:2] for row in table[2:]] == [[f"| {label}", s] for label in labels for s in ("s0", "s1")]
    assert table[5] == (f"| {labels[1]} | s1 | 20 | -1.0 [-6.0, +0.0] | +2.0 [-10.0, +10.0] | +5.0 [+0.0, +10.0] "
                        "| 0.250 -> 0.375 | 54 of 64 |")
    assert table[0].count("|") == table[2].count("|")  # the detector's column left out of header and rows alike


def test_the_as_trained_table_reads_each_runs_curve_at_step_20_and_its_last(tmp_path, monkeypatch):
    """grpo-first-half-as-trained: one row per run of each advantage rule in FIRST_HALF_AS_TRAINED_ARMS' order, the
    as-trained gain at step 20 and at the last step with the success between, the other policies' gains at the last
    step, and the paid success over the first and last 5 steps; a run without a step-20 point leaves that cell
    empty."""
    def figure(mean):
        return {"mean": mean, "successes": int(round(mean * 500)), "episodes": 500}

    def point(step, trained, sampled=0.5, greedy=0.75):
        return {"step": step, **figure(greedy), "sampled": figure(sampled), "sampled_proprio_masked": figure(sampled),
                "sampled_as_trained": figure(trained)}

    root = tmp_path / "policy" / report.FIRST_HALF_AS_TRAINED[1]
    for i, folder in enumerate(report.FIRST_HALF_AS_TRAINED_ARMS):
        for seed in (1, 0):
            run = root / folder / "gt" / f"s{seed}" / "grpo_env_proprio_missing_starts_keyframes_mjx"
            run.mkdir(parents=True)
            steps = (0, 20, 40) if seed == 0 else (0, 40)
            points = [point(s, 0.36 + 0.001 * s * (i + 1), sampled=0.5 - 0.001 * s) for s in steps]
            (run / "success_curve.json").write_text(json.dumps({"points": points}))
            (run / "train_history.jsonl").write_text("".join(
                json.dumps({"rollout_success": 0.4 if k < 5 else 0.6}) + "\n" for k in range(40)))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_first_half_as_trained().splitlines()
    labels = list(report.FIRST_HALF_AS_TRAINED_ARMS.values())
    assert len(table) == 6 and "grpo-first-half-as-trained" in report.TABLES
    assert [row.split(" | ")[:2] for row in table[2:]] == [[f"| {label}", s] for label in labels for s in ("s0", "s1")]
    cells = [c.strip() for c in table[4].strip("|").split("|")]  # scaled by their std, s0: 0.002 a step
    assert cells[2] == "40" and cells[3].startswith("+4.0 [") and cells[4].startswith("+8.0 [")
    assert cells[5] == "0.360 -> 0.440" and cells[6].startswith("-4.0 [") and cells[8].startswith("+0.0 [")
    assert cells[9] == "0.400 -> 0.600"
    assert [c.strip() for c in table[3].strip("|").split("|")][3] == ""  # s1 was not evaluated at step 20
    assert table[0].count("|") == table[2].count("|")


def test_the_world_model_table_puts_its_arms_beside_ground_truth_at_step_20(tmp_path, monkeypatch):
    """grpo-first-half-world-model: ground truth's centred runs then the world model's exec and cal runs, each at
    step 20 (the later ground-truth steps not counted): the real episodes consumed by then, the as-trained gain and
    success, what reality paid the training rollouts (cal: only its executed steps), the median mixed groups and
    the detector from the summary; the README's words give the exec gains and ground truth's smallest."""
    def figure(mean):
        return {"mean": mean, "successes": int(round(mean * 500)), "episodes": 500}

    def point(step, trained):
        return {"step": step, **figure(0.75), "sampled": figure(0.5), "sampled_as_trained": figure(trained)}

    def write(run, points, history):
        run.mkdir(parents=True)
        (run / "success_curve.json").write_text(json.dumps({"points": points}))
        (run / "train_history.jsonl").write_text("".join(json.dumps(h) + "\n" for h in history))

    gt = tmp_path / "policy" / report.FIRST_HALF_AS_TRAINED[1] / "centred" / "gt"
    for seed, gain in ((0, 0.1), (1, 0.12)):
        write(gt / f"s{seed}" / "grpo_env_proprio_missing_starts_keyframes_mjx",
              [point(0, 0.36), point(20, 0.36 + gain), point(40, 0.6)],
              [{"step": k, "rollout_success": 0.4 if k <= 20 else 0.9, "trajectories_sampled": 512.0,
                "mixed_groups": 50 if k <= 20 else 10} for k in range(1, 41)])
    wm = tmp_path / "policy" / report.FIRST_HALF_WORLD_MODEL[1]
    write(wm / "exec_s0" / "rl" / "grpo", [point(0, 0.36), point(20, 0.40)],
          [{"step": k, "success_rate": 0.08, "real_rollouts": 512.0, "mixed_groups": 20} for k in range(1, 21)])
    write(wm / "cal_s0" / "rl" / "grpo", [point(0, 0.36), point(20, 0.30)],
          [{"step": k, "success_rate": 0.06, "real_rollouts": 512.0, "mixed_groups": 18} for k in range(1, 5)]
          + [{"step": k, "success_rate": 0.5, "mixed_groups": 18} for k in range(5, 21)])
    detector = {"success": 0.45, "agreement": 0.6, "precision": 0.15, "auc": 0.77, "recall_bounded": 0.14,
                "precision_bounded": 0.19}
    (wm / "grpo_reward_source.json").write_text(json.dumps({
        "runs": {"exec_s0": {"arm": "exec", "seed": 0, "detector": detector},
                 "cal_s0": {"arm": "cal", "seed": 0, "detector": dict(detector, success=0.42)}},
        "arms": {"exec": {"steps": 20, "as_trained_gain_per_seed": {"0": 0.04}}}}))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_first_half_world_model().splitlines()
    assert len(table) == 6 and "grpo-first-half-world-model" in report.TABLES
    rows = [[c.strip() for c in row.strip("|").split("|")] for row in table[2:]]
    assert [r[:2] for r in rows] == [[report.FIRST_HALF_WORLD_MODEL_ARMS.get(a, a), s] for a, s in (
        ("real frames, paid by MJX (ground truth)", "s0"), ("real frames, paid by MJX (ground truth)", "s1"),
        ("exec", "s0"), ("cal", "s0"))]
    assert rows[1][2] == "10,240" and rows[1][3].startswith("+12.0 [") and rows[1][4] == "0.360 -> 0.480"
    assert rows[1][7] == "0.400" and rows[1][8] == "50 of 64" and rows[1][9] == ""  # steps 21-40 not read
    assert rows[2][2] == "10,240" and rows[2][3].startswith("+4.0 [") and rows[2][7] == "0.080"
    assert rows[2][9] == "0.45 / 0.60 / 0.15; AUC 0.77; at its 5% bound: recall 0.14, precision 0.19"
    assert rows[3][2] == "2,048" and rows[3][3].startswith("-6.0 [") and rows[3][7] == "0.060 (steps 1-4)"
    assert rows[3][8] == "18 of 64" and rows[3][9].startswith("0.42 / 0.60")
    assert table[0].count("|") == table[2].count("|")
    assert report._first_half_world_model_text() == (" (+10.0 or more in 20); Sword's world model, paid by reality, "
                                                      "+4.0 in 20")
    (wm / "grpo_reward_source.json").unlink()
    assert report._first_half_world_model_text() == ""


def test_the_by_start_table_pools_late_starts_and_divides_like_bins():
    """grpo-by-start: ground truth's and the world model's bins of one seed side by side; the bins from 48 actions
    on pooled into one; the kept share is exec's real success over gt's; a bin either arm lacks is left out; the
    detector's precision is blank where it said no success."""
    def gt(*counts):
        return [{"from_step": a, "rollouts": n, "real": r} for a, (n, r) in zip((0, 24, 48, 72, 96), counts)]

    def ex(*counts):
        return [{"from_step": a, "rollouts": n, "real": r, "said": s, "said_real": b}
                for a, (n, r, s, b) in zip((0, 24, 48, 72, 96), counts)]

    pooled = report._by_start_pooled(gt((10, 4), (20, 16), (6, 3), (2, 2), (0, 0)))
    assert pooled == [{"from_step": 0, "to_step": 24, "rollouts": 10, "real": 4},
                      {"from_step": 24, "to_step": 48, "rollouts": 20, "real": 16},
                      {"from_step": 48, "to_step": None, "rollouts": 8, "real": 5}]
    summary = {"runs": {"gt_s0": {"arm": "gt", "seed": 0, "by_start": gt((100, 40), (0, 0), (8, 8), (0, 0), (0, 0))},
                        "exec_s0": {"arm": "exec", "seed": 0, "by_start": ex((100, 5, 40, 4), (4, 2, 0, 0),
                                                                             (4, 4, 0, 0), (4, 2, 4, 2), (0, 0, 0, 0))}}}
    summary["runs"]["rexec_s0"] = dict(summary["runs"]["exec_s0"], arm="rexec")
    with mock.patch.object(report, "_load", return_value=summary):
        table = report.grpo_by_start().splitlines()
    rows = [[c.strip() for c in row.strip("|").split("|")] for row in table[2:]]
    assert "grpo-by-start" in report.TABLES and table[0].count("|") == table[2].count("|")
    exec_rows = [["0-23", "s0", "as trained", "100", "0.400", "100", "0.050", "12%", "0.40", "0.10"],  # 24-47: no gt
                 ["48+", "s0", "as trained", "8", "1.000", "8", "0.750", "75%", "0.50", "0.50"]]
    assert rows == [exec_rows[0], [*exec_rows[0][:2], "refreshed", *exec_rows[0][3:]],
                    exec_rows[1], [*exec_rows[1][:2], "refreshed", *exec_rows[1][3:]]]
    del summary["runs"]["gt_s0"], summary["runs"]["rexec_s0"]  # no ground truth: its cells and the share blank
    with mock.patch.object(report, "_load", return_value=summary):
        rows = [[c.strip() for c in row.strip("|").split("|")] for row in report.grpo_by_start().splitlines()[2:]]
    assert [r[0] for r in rows] == ["0-23", "24-47", "48+"] and rows[1][3:8] == ["", "", "4", "0.500", ""]
    assert "grpo-by-start-window" in report.TABLES


def test_the_by_start_table_sets_records_side_by_side_each_against_its_own_ground_truth():
    """grpo_by_start of several records: each world-model arm's kept share is over its own record's gt, and within a
    bin and seed the rows keep the records' order."""
    def rec(arm, gt_real, wm_real):
        return {"runs": {"gt_s0": {"arm": "gt", "seed": 0, "by_start": [{"from_step": 0, "rollouts": 100,
                                                                         "real": gt_real}]},
                         f"{arm}_s0": {"arm": arm, "seed": 0, "by_start": [
                             {"from_step": 0, "rollouts": 100, "real": wm_real, "said": 10, "said_real": 5}]}}}

    loaded = {"a": rec("exec", 40, 10), "b": rec("rexec", 50, 20)}
    with mock.patch.object(report, "_load", side_effect=lambda *path: loaded[path[1]]):
        rows = [[c.strip() for c in row.strip("|").split("|")]
                for row in report.grpo_by_start(("policy", "b"), ("policy", "a")).splitlines()[2:]]
    assert [r[2] for r in rows] == ["refreshed", "as trained"]
    assert [(r[4], r[6], r[7]) for r in rows] == [("0.500", "0.200", "40%"), ("0.400", "0.100", "25%")]
    assert "grpo-by-start-refresh" in report.TABLES


def test_the_refresh_fidelity_table_means_each_runs_steps_and_names_its_refresh(tmp_path, monkeypatch):
    """grpo_refresh_fidelity: per seed the run as trained before the refreshed one, the means over steps of the
    rollouts' real success and of the closed loop at its first and last decision, and the refresh's fine-tune."""
    def run(record, arm, seed, base, refresh=None):
        d = tmp_path / "policy" / record / f"{arm}_s{seed}" / "rl" / "grpo"
        d.mkdir(parents=True)
        d.joinpath("train_history.jsonl").write_text("\n".join(json.dumps(
            {"success_rate": base + v, **{f"closed_loop_{what}_{k}": base + v + k for k in (1, 3) for what in
                                          ("frame_error", "frame_error_vae", "action_gap", "action_gap_vae")}})
            for v in (0.0, 0.5)) + "\n")
        if refresh:
            d.joinpath("refreshes.json").write_text(json.dumps([{"world_model": refresh}]))

    run("a", "exec", 1, 0.0)
    run("b", "rexec", 1, 0.25, {"real_episodes": 128, "training_episodes": 600, "steps": 1000, "last": {"loss": 0.05}})
    run("b", "rexec", 0, 0.0)
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_refresh_fidelity(((("policy", "a"), "exec", "as trained"),
                                          (("policy", "b"), "rexec", "refreshed"))).splitlines()
    rows = [[c.strip() for c in row.strip("|").split("|")] for row in table[2:]]
    assert [r[:3] for r in rows] == [["s0", "refreshed", "2"], ["s1", "as trained", "2"], ["s1", "refreshed", "2"]]
    assert rows[1][3:8] == ["0.250", "1.250 / 3.250", "3.250", "1.250 / 3.250", "3.250"] and rows[1][8] == ""
    assert rows[2][3:5] == ["0.500", "1.500 / 3.500"]
    assert rows[2][8] == "128 real episodes + 600 training, 1,000 steps, loss 0.050"
    assert "grpo-refresh-fidelity" in report.TABLES and table[0].count("|") == table[2].count("|")


def test_the_closed_loop_tables_name_their_record_and_read_its_refresh(tmp_path, monkeypatch):
    """grpo-by-start names the closed-loop record's rexec by its own label; the fidelity table says what its refresh
    added; grpo_closed_loop_fit reads each seed's latent drift at decisions 1, 2, 6, 12 and the held-out sample errors
    before and after the fine-tune, blank where a part held no segment."""
    loop = {"episodes": 512, "starts": 64, "group_size": 8, "real_success": 0.3, "share": 0.5,
            "latent_drift_by_decision": [0.1 * (d + 1) for d in range(12)],
            "fit": {"held_out_trajectories": 64,
                    "before": {"first_decision": None, "closed_loop": {"sample_error": 0.04},
                               "training": {"sample_error": 0.002}},
                    "after": {"first_decision": None, "closed_loop": {"sample_error": 0.03},
                              "training": {"sample_error": 0.003}}}}
    d = tmp_path / "policy" / "cl" / "rexec_s1" / "rl" / "grpo"
    d.mkdir(parents=True)
    wm = {"real_episodes": 128, "training_episodes": 600, "steps": 2000, "last": {"loss": 0.06}}
    d.joinpath("refreshes.json").write_text(json.dumps([{"world_model": wm, "closed_loop": loop}]))
    d.joinpath("train_history.jsonl").write_text(json.dumps(
        {"success_rate": 0.3, **{f"closed_loop_{w}_{k}": 0.1 for k in (1, 2) for w in
                                 ("frame_error", "frame_error_vae", "action_gap", "action_gap_vae")}}) + "\n")
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    rows = [[c.strip() for c in row.strip("|").split("|")]
            for row in report.grpo_closed_loop_fit(("policy", "cl")).splitlines()[2:]]
    assert rows == [["s1", "512 (64 starts x 8)", "0.300", "0.100 / 0.200 / 0.600 / 1.200", "64", "",
                     "0.0400 -> 0.0300 (-25%)", "0.0020 -> 0.0030 (+50%)"]]
    fidelity = report.grpo_refresh_fidelity(((("policy", "cl"), "rexec", "on its loop"),)).splitlines()[2]
    assert "128 real episodes + 600 training + its closed loop (512 trajectories, 50% of each batch), 2,000 steps" \
        in fidelity
    summary = {"runs": {"rexec_s0": {"arm": "rexec", "seed": 0, "by_start": [
        {"from_step": 0, "rollouts": 10, "real": 1, "said": 0, "said_real": 0}]}}}
    with mock.patch.object(report, "_load", return_value=summary):
        rows = [[c.strip() for c in row.strip("|").split("|")]
                for row in report.grpo_by_start(report.BY_START_CLOSED_LOOP).splitlines()[2:]]
    assert [r[2] for r in rows] == ["refreshed on its closed loop"]
    assert {"grpo-by-start-closed-loop", "grpo-closed-loop-fidelity", "grpo-closed-loop-fit"} <= set(report.TABLES)


def test_the_closed_loop_decisions_table_means_each_decision_over_steps_per_seed(tmp_path, monkeypatch):
    """grpo-closed-loop-decisions: per decision, each record's frame error and greedy action gap as means over its
    steps, one cell per record and figure with its seeds' means as s0 / s1; a seed a record lacks is left out."""
    def run(record, arm, seed, base):
        d = tmp_path / "policy" / record / f"{arm}_s{seed}" / "rl" / "grpo"
        d.mkdir(parents=True)
        d.joinpath("train_history.jsonl").write_text("\n".join(json.dumps(
            {f"closed_loop_{w}_{k}": base + k + v for k in (1, 2) for w in ("frame_error", "action_gap")})
            for v in (0.0, 0.5)) + "\n")

    run("a", "exec", 0, 0.0)
    run("a", "exec", 1, 10.0)
    run("b", "rexec", 1, 20.0)
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.grpo_closed_loop_decisions(((("policy", "a"), "exec", "A"), (("policy", "b"), "rexec", "B")))
    rows = [[c.strip() for c in row.strip("|").split("|")] for row in table.splitlines()[2:]]
    assert rows == [["1", "1.250 / 11.250", "21.250", "1.250 / 11.250", "21.250"],
                    ["2", "2.250 / 12.250", "22.250", "2.250 / 12.250", "22.250"]]
    assert "frame error, B (s0 / s1)" in table.splitlines()[0] and "grpo-closed-loop-decisions" in report.TABLES


def test_the_lag_by_start_table_sets_the_late_frames_share_beside_the_world_models(tmp_path, monkeypatch):
    """lag-by-start: per bin and seed the real and late frames' success pooled from 48 actions on, the late
    frames' share of the real one, and the world model's own share from its by-start record (blank where its
    ground truth paid nothing)."""
    def bins(*counts):
        return [{"from_step": a, "rollouts": n, "real": r} for a, (n, r) in zip((0, 24, 48, 72, 96), counts)]

    lag = tmp_path / "policy" / "lag" / "s1"
    lag.mkdir(parents=True)
    (lag / "action_gap.json").write_text(json.dumps({"lag_by_start": {
        "real": bins((100, 50), (80, 40), (10, 8), (2, 2), (0, 0)),
        "lag_1": bins((100, 1), (80, 20), (10, 3), (2, 1), (0, 0))}}))
    wm = tmp_path / "policy" / "wm"
    wm.mkdir(parents=True)
    (wm / "grpo_reward_source.json").write_text(json.dumps({"runs": {
        "gt_s1": {"arm": "gt", "seed": 1, "by_start": bins((100, 40), (100, 0), (10, 5), (0, 0), (0, 0))},
        "exec_s1": {"arm": "exec", "seed": 1, "by_start": [  # an executed arm's bins carry the detector's counts too
            dict(b, said=0, said_real=0) for b in bins((100, 4), (100, 50), (10, 5), (0, 0), (0, 0))]}}}))
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.lag_by_start_table(("policy", "lag"), ("policy", "wm")).splitlines()
    rows = [[c.strip() for c in row.strip("|").split("|")] for row in table[2:]]
    assert rows == [["0-23", "s1", "100", "0.500", "0.010", "2%", "10%"],
                    ["24-47", "s1", "80", "0.500", "0.250", "50%", ""],
                    ["48+", "s1", "12", "0.833", "0.333", "40%", "100%"]]
    assert "lag-by-start" in report.TABLES and table[0].count("|") == table[2].count("|")


def test_the_lag_by_actions_table_reads_each_late_view_as_a_share_of_the_real_frames(tmp_path, monkeypatch):
    """lag-by-start-actions: per bin (those from 48 actions on pooled) and seed the real frames' success, then each
    lag in actions and the whole decision's, each with its share of the real success (blank where that is 0);
    runs of different lags are refused."""
    def bins(*counts):
        return [{"from_step": a, "rollouts": n, "real": r} for a, (n, r) in zip((0, 24, 48, 72, 96), counts)]

    def run(seed, lags=(1, 3)):
        d = tmp_path / "rec" / f"late_actions_s{seed}"
        d.mkdir(parents=True, exist_ok=True)
        (d / "action_gap.json").write_text(json.dumps({"lag_by_start": {
            "late_actions": list(lags), "real": bins((100, 40), (50, 0), (4, 2), (4, 2), (0, 0)),
            "late_1_actions": bins((100, 10), (50, 0), (4, 1), (4, 1), (0, 0)),
            "late_3_actions": bins((100, 2), (50, 0), (4, 0), (4, 1), (0, 0)),
            "lag_1": bins((100, 1), (50, 0), (4, 0), (4, 0), (0, 0))}}))

    run(0)
    run(1)
    monkeypatch.setattr(report, "RESULTS_DIR", str(tmp_path))
    table = report.lag_by_start_actions(("rec",)).splitlines()
    assert "1 action late (kept)" in table[0] and "3 actions late (kept)" in table[0] and "a decision late" in table[0]
    rows = [[c.strip() for c in row.strip("|").split("|")] for row in table[2:]]
    first = ["100", "0.400", "0.100 (25%)", "0.020 (5%)", "0.010 (2%)"]
    assert rows[:2] == [["0-23", "s0", *first], ["0-23", "s1", *first]]
    assert rows[2] == ["24-47", "s0", "50", "0.000", "", "", ""]
    assert rows[4] == ["48+", "s0", "8", "0.500", "0.250 (50%)", "0.125 (25%)", "0.000 (0%)"]
    assert "lag-by-start-actions" in report.TABLES and table[0].count("|") == table[2].count("|")
    run(1, lags=(1,))
    with pytest.raises(ValueError, match="read different lags"):
        report.lag_by_start_actions(("rec",))
