"""benchmarks.bench_grpo_reward_source: the three arms' commands and GPUs, and the summary of runs it left."""

import argparse
import json
import os

import numpy as np
import pytest

from benchmarks import bench_grpo_reward_source as rs
from sword_jax import cli


def _args(tmp_path, gpus="0,1,2,3", seeds="0,1,2", arms=("gt", "exec", "det")):
    args = argparse.Namespace(
        workdir=str(tmp_path), policy="/p/policy_d50.npz", config="sword:small", gpus=gpus.split(","),
        seeds=[int(s) for s in seeds.split(",")], steps=40, eval_every=10, rollout_batch=64, policy_rollouts=20, vae_steps=1000,
        eval_episodes_per_task=50,
        world_model_steps=3000, deadline_s=0.0, grace_s=0.0, arms=list(arms), vae_variant="base", horizon=12, keyframe_fraction=None,
        keyframe_from=None, deterministic=False, scale_by_std=True, calibrate_steps=4, refresh_every=10,
        refresh_episodes=64, refresh_budget=256, refresh_set=[], latents="")
    return args


def _flag(cmd, name):
    return [c for c in cmd if c.startswith(name)]


def test_each_arm_differs_from_the_others_in_one_part(tmp_path):
    commands = rs.run_commands(_args(tmp_path))
    assert sorted(commands) == sorted(f"{a}_s{s}" for a in ("gt", "exec", "det") for s in (0, 1, 2))
    gt, ex, det = commands["gt_s1"], commands["exec_s1"], commands["det_s1"]
    # the setting and the recipe are the same everywhere
    for cmd in (gt, ex, det):
        for flag in rs.RECIPE + ("--rl.grpo.steps=40", "--rl.grpo.eval_every=10", "--rl.grpo.rollout_batch=64"):
            assert flag in cmd, (flag, cmd)
        assert cmd[cmd.index("--seed") + 1] == "1"
    assert gt[2:4] == ["benchmarks.bench_policy", "grpo"] and "--rl.env.starts=keyframes" in gt
    assert "--rl.env.proprio=missing" in gt and "--rl.grpo.max_sample_rounds=1" in gt
    # the world-model arms: the pipeline's models, no refresh, and only the reward apart
    assert ex[2:4] == ["train.grpo", "--config"] and "--rl.imagined.reward=executed" in ex
    assert [c for c in ex if c != "--rl.imagined.reward=executed"] == [c.replace("det_s1", "exec_s1") for c in det]
    assert not _flag(ex, "--rl.refresh") and not _flag(det, "--rl.imagined.reward")
    pipe = os.path.join(str(tmp_path), "pipeline")
    assert ex[ex.index("--world-model") + 1] == os.path.join(pipe, "world_model")
    assert f"--demos={os.path.join(pipe, 'data', 'demos.hdf5')}" in gt
    assert ex[ex.index("--workdir") + 1] == os.path.join(str(tmp_path), "exec_s1")
    # every arm is evaluated on as many real episodes
    few = rs.run_commands(argparse.Namespace(**{**vars(_args(tmp_path)), "eval_episodes_per_task": 5}))
    assert "--rl.grpo.eval_episodes_per_task=5" in few["exec_s0"] and "--rl.grpo.eval_episodes_per_task=5" in few["det_s2"]
    assert few["gt_s0"][few["gt_s0"].index("--eval-episodes") + 1] == "5"
    assert "--rl.grpo.eval_episodes_per_task=50" in ex and gt[gt.index("--eval-episodes") + 1] == "50"


def test_the_calibrated_arm_is_the_detectors_arm_paid_by_execution_for_its_first_steps(tmp_path, monkeypatch):
    """cal: the det arm's command with rl.imagined.reward=calibrated and --calibrate-steps; it reads the detector
    from a bundle; its summary reads the detector's figures from the executed steps alone and gives the threshold
    they set; a calibration as long as the run is refused."""
    commands = rs.run_commands(_args(tmp_path, arms=("det", "cal")))
    cal, det = commands["cal_s1"], commands["det_s1"]
    assert [c for c in cal if c not in ("--rl.imagined.reward=calibrated", "--rl.imagined.calibrate_steps=4")] == [
        c.replace("det_s1", "cal_s1") for c in det]
    assert "--rl.imagined.reward=calibrated" in cal and "--rl.imagined.calibrate_steps=4" in cal
    bundle = tmp_path / "bundle"
    for d in ("world_model/checkpoints", "vae_run/vae"):
        (bundle / d).mkdir(parents=True)
    args = rs.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--bundle", str(bundle), "--arms", "cal",
                     "--steps", "10", "--calibrate-steps", "3"])
    with pytest.raises(SystemExit, match="lacks rl/reward_model"):
        rs.check_bundle(args)
    with pytest.raises(SystemExit, match="cal arm needs 1 <= --calibrate-steps < --steps"):
        rs.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--arms", "cal", "--steps", "3",
                  "--calibrate-steps", "3"])
    executed = {"success_rate": 0.25, "kept_fraction": 0.5, "real_rollouts": 512.0, "detector_success": 0.5,
                "detector_agreement": 0.75,
                "detector_false_success": 0.25, "detector_auc": 0.75, "detector_threshold_bounded": 0.5,
                "detector_recall_bounded": 0.5, "detector_precision_bounded": 0.5}
    judged = {"success_rate": 0.375, "kept_fraction": 0.25, "detector_threshold": 0.5000001}
    _curve(tmp_path / "cal_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5), _point(5, 0.7, 0.52)],
           [executed, executed, judged, judged, judged])
    run = rs.summarize(str(tmp_path))["runs"]["cal_s0"]
    assert run["arm"] == "cal" and run["executed_steps"] == 2 and run["calibrated_threshold"] == 0.5000001
    assert run["real_rollouts"] == 1024  # the two executed steps' 512 each; the detector's steps take none
    assert run["detector"]["auc"] == 0.75 and run["detector"]["success"] == 0.5
    assert run["paid_success"] == {"first": pytest.approx(0.325), "last": pytest.approx(0.325)}


def test_the_runs_are_placed_beside_the_pipeline_then_over_every_gpu(tmp_path):
    gpu = rs.placement(_args(tmp_path))
    assert [gpu[f"gt_s{s}"] for s in (0, 1, 2)] == ["1", "2", "3"]  # the pipeline builds on GPU 0 meanwhile
    assert [gpu[n] for n in ("exec_s0", "det_s0", "exec_s1", "det_s1", "exec_s2", "det_s2")] == ["0", "1", "2", "3", "0", "1"]
    one = rs.placement(_args(tmp_path, gpus="5"))
    assert set(one.values()) == {"5"}
    # the world-model arms alone (another world model beside a ground-truth arm already run) take every GPU
    wm = rs.placement(_args(tmp_path, arms=("exec", "det")))
    assert sorted(wm) == sorted(rs.run_commands(_args(tmp_path, arms=("exec", "det"))))
    assert [wm[n] for n in ("exec_s0", "det_s0", "exec_s1", "det_s1")] == ["0", "1", "2", "3"] and "gt_s0" not in wm
    assert sorted(rs.run_commands(_args(tmp_path, arms=("exec",)))) == ["exec_s0", "exec_s1", "exec_s2"]


def test_the_pipeline_can_take_several_gpus_and_the_ground_truth_runs_the_rest(tmp_path, monkeypatch):
    """--pipeline-gpus: the pipeline's commands see those GPUs (CUDA_VISIBLE_DEVICES), the ground-truth runs take
    the GPUs it leaves, or every GPU where it takes them all; GPUs outside --gpus, a GPU named twice, or several
    with --pipeline (which builds nothing) are refused by name."""
    import sys

    base = ["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--seeds", "0,1", "--gpus", "0,1,2"]
    args = rs.parse([*base, "--pipeline-gpus", "0,1"])
    assert args.pipeline_gpus == ["0", "1"]
    gpu = rs.placement(args)
    assert (gpu["gt_s0"], gpu["gt_s1"]) == ("2", "2")
    assert [gpu[n] for n in ("exec_s0", "det_s0", "exec_s1", "det_s1")] == ["0", "1", "2", "0"]
    every = rs.placement(rs.parse([*base, "--pipeline-gpus", "2,0,1"]))
    assert (every["gt_s0"], every["gt_s1"]) == ("0", "1")
    assert rs.parse(base).pipeline_gpus == ["0"] and rs.placement(rs.parse(base))["gt_s1"] == "2"
    for bad, match in ((["--pipeline-gpus", "0,3"], "must name GPUs of --gpus"),
                       (["--pipeline-gpus", "1,1"], "each once"),
                       (["--pipeline-gpus", "0,1", "--pipeline", str(tmp_path)], "with --pipeline it builds none")):
        with pytest.raises(SystemExit, match=match):
            rs.parse([*base, *bad])
    # the pipeline's two commands start with the GPUs they were given
    seen = "import os, sys; open(sys.argv[1], 'a').write(os.environ['CUDA_VISIBLE_DEVICES'] + ';')"
    monkeypatch.setattr(rs, "pipeline_command", lambda base, overrides, stop_after: [
        sys.executable, "-c", seen, str(tmp_path / "pipeline_gpus")])
    monkeypatch.setattr(rs, "run_commands", lambda a: {"gt_s0": [sys.executable, "-c", seen, str(tmp_path / "gt")]})
    monkeypatch.setattr(rs, "summarize", lambda workdir: {"runs": {}, "arms": {}})
    run = rs.parse([*base, "--seeds", "0", "--arms", "gt", "--pipeline-gpus", "1,2"])
    assert rs.run(run, poll_s=0.05)["exit_codes"] == {"gt_s0": 0}
    # the ground-truth arm alone: the pipeline builds its data, not the world model's stages
    assert (tmp_path / "pipeline_gpus").read_text() == "1,2;" and (tmp_path / "gt").read_text() == "0;"


def _curve(path, points, history):
    os.makedirs(path, exist_ok=True)
    with open(os.path.join(path, "success_curve.json"), "w") as f:
        json.dump({"points": points}, f)
    with open(os.path.join(path, "train_history.jsonl"), "w") as f:
        f.write("".join(json.dumps(h) + "\n" for h in history))


def _point(step, greedy, sampled, masked=None, as_trained=None):
    out = {"step": step, "mean": greedy, "successes": int(greedy * 500), "episodes": 500,
           "sampled": {"mean": sampled, "successes": int(sampled * 500), "episodes": 500}}
    if masked is not None:
        out["sampled_proprio_masked"] = {"mean": masked, "successes": int(masked * 500), "episodes": 500}
    if as_trained is not None:
        out["sampled_as_trained"] = {"mean": as_trained, "successes": int(as_trained * 500), "episodes": 500}
    return out


def _loop(x, vae=False):
    """A step's closed-loop figures at decisions 1, 2 and 10: frame error k x, action gap k x / 10; with ``vae``
    the VAE round trip's too, half of each."""
    figures = ("frame_error", "action_gap") + (("frame_error_vae", "action_gap_vae") if vae else ())
    return {f"closed_loop_{what}_{k}": k * x * (1.0 if what.startswith("frame_error") else 0.1)
                                        * (0.5 if what.endswith("_vae") else 1.0)
            for k in (1, 2, 10) for what in figures}


def test_summary_gains_payments_and_the_detector_on_designed_runs(tmp_path, monkeypatch):
    _curve(tmp_path / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5, 0.5), _point(20, 0.72, 0.6, 0.56)],
           [{"rollout_success": 0.4, "mixed_fraction": 0.8}] * 5 + [{"rollout_success": 0.5, "mixed_fraction": 0.9}] * 5)
    nan = float("nan")
    _curve(tmp_path / "exec_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5, 0.5), _point(20, 0.7, 0.54, 0.5)],
           [{"success_rate": 0.2, "kept_fraction": 0.5, "detector_success": 0.4, "detector_agreement": 0.6,
             "detector_false_success": 0.3, **_loop(0.1, vae=True)}] * 9
           + [{"success_rate": 0.3, "kept_fraction": 0.7, "detector_success": 0.2, "detector_agreement": 0.8,
               "detector_false_success": nan, **_loop(0.2, vae=True)}])
    # a run of the same arm from before the VAE's share was logged
    _curve(tmp_path / "exec_s1" / "rl" / "grpo", [_point(0, 0.7, 0.5, 0.5), _point(20, 0.7, 0.56, 0.5)],
           [{"success_rate": 0.2, "kept_fraction": 0.5, "detector_success": 0.4, "detector_agreement": 0.6,
             "detector_false_success": 0.3, **_loop(0.1)}] * 10)
    _curve(tmp_path / "det_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5, 0.5), _point(10, 0.6, 0.4, 0.45)],
           [{"success_rate": 0.3, "kept_fraction": 0.4}] * 10)
    os.makedirs(tmp_path / "det_s1" / "rl" / "grpo")  # a run that left no evaluation is not counted
    summary = rs.summarize(str(tmp_path))
    assert sorted(summary["runs"]) == ["det_s0", "exec_s0", "exec_s1", "gt_s0"]
    gt, ex, det = (summary["runs"][n] for n in ("gt_s0", "exec_s0", "det_s0"))
    assert gt["sampled"]["gain"] == pytest.approx(0.1) and gt["sampled"]["ci95"][0] < 0.1 < gt["sampled"]["ci95"][1]
    assert gt["paid_success"] == {"first": pytest.approx(0.4), "last": pytest.approx(0.5)} and gt["mixed_median"] == pytest.approx(0.85)
    assert ex["detector"] == {"success": pytest.approx(0.38), "agreement": pytest.approx(0.62),
                              "false_success": pytest.approx(0.3),  # the step without failures left out
                              # 9 steps pay 0.4 of which 0.3 x 0.8 failed; the last step's 0.2 all succeeded
                              "precision": pytest.approx((9 * (0.4 - 0.3 * 0.8) + 0.2) / 3.8)}
    assert "detector" not in gt and "detector" not in det and "closed_loop" not in gt
    loop = ex["closed_loop"]  # decisions in numeric order (10 after 2), means over the 10 steps
    assert loop["decisions"] == [1, 2, 10]
    assert loop["frame_error"] == pytest.approx([0.11, 0.22, 1.1]) and loop["action_gap"] == pytest.approx([0.011, 0.022, 0.11])
    assert loop["frame_error_vae"] == pytest.approx([0.055, 0.11, 0.55])
    assert loop["action_gap_vae"] == pytest.approx([0.0055, 0.011, 0.055])
    older = summary["runs"]["exec_s1"]["closed_loop"]  # still summarised, without the VAE's share
    assert set(older) == {"decisions", "frame_error", "action_gap"}
    assert older["frame_error"] == pytest.approx([0.1, 0.2, 1.0])
    rs.print_runs(summary)
    assert det["steps"] == 10 and det["greedy"]["gain"] == pytest.approx(-0.1)
    assert summary["arms"]["det"]["smallest"] == pytest.approx(-0.1) and summary["arms"]["exec"]["steps"] == 20
    monkeypatch.setattr(rs.common, "device_name", lambda: "cpu")
    entry = rs.results_entries(summary, str(tmp_path), data="d")["policy_grpo_reward_source_small"]
    assert entry["value"] == pytest.approx(0.04) and set(entry["arms"]) == {"gt", "exec", "det"}
    with pytest.raises(SystemExit, match="exec arm"):
        rs.results_entries({"runs": {}, "arms": {}}, str(tmp_path), data="d")


def test_every_run_counts_the_real_episodes_its_grpo_steps_consumed(tmp_path):
    """real_episodes: a ground-truth run's steps' trajectories_sampled, a world-model run's executed real_rollouts
    (0 for the detector's arm), its evaluations not counted; per arm by seed, and each world-model arm's mean over
    the gt arm's, None without a gt run or where the gt run did not count its trajectories."""
    _curve(tmp_path / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5), _point(3, 0.72, 0.55)],
           [{"step": s, "rollout_success": 0.4, "trajectories_sampled": 512.0, "mixed_fraction": 0.5}
            for s in (1, 2, 3)])
    executed = {"success_rate": 0.25, "kept_fraction": 0.5, "real_rollouts": 512.0, "detector_success": 0.5,
                "detector_agreement": 0.75, "detector_false_success": 0.25}
    judged = {"success_rate": 0.375, "kept_fraction": 0.25, "detector_threshold": 0.5}
    _curve(tmp_path / "cal_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5), _point(5, 0.7, 0.52)],
           [executed, executed, judged, judged, judged])
    _curve(tmp_path / "det_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5), _point(5, 0.7, 0.45)],
           [{"success_rate": 0.3, "kept_fraction": 0.4}] * 5)
    summary = rs.summarize(str(tmp_path))
    runs, arms = summary["runs"], summary["arms"]
    assert runs["gt_s0"]["real_episodes"] == 1536  # 3 steps of 512
    assert runs["cal_s0"]["real_episodes"] == 1024  # its 2 executed steps; the detector's steps take none
    assert runs["cal_s0"]["real_rollouts"] == 1024 and runs["det_s0"]["real_episodes"] == 0
    assert "real_rollouts" not in runs["det_s0"] and "real_rollouts" not in runs["gt_s0"]
    assert arms["gt"]["real_episodes_per_seed"] == {0: 1536} and arms["cal"]["real_episodes_per_seed"] == {0: 1024}
    assert arms["det"]["real_episodes_per_seed"] == {0: 0}
    assert arms["cal"]["real_episodes_vs_gt"] == 1024 / 1536 and arms["det"]["real_episodes_vs_gt"] == 0.0
    assert "real_episodes_vs_gt" not in arms["gt"]
    # without the gt run, or with one that did not count its trajectories, there is nothing to divide by
    _curve(tmp_path / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5), _point(3, 0.72, 0.55)],
           [{"step": s, "rollout_success": 0.4, "mixed_fraction": 0.5} for s in (1, 2, 3)])
    summary = rs.summarize(str(tmp_path))
    assert summary["runs"]["gt_s0"]["real_episodes"] is None
    assert summary["arms"]["cal"]["real_episodes_vs_gt"] is None
    (tmp_path / "gt" / "s0" / rs.GT_DIR / "success_curve.json").unlink()
    arms = rs.summarize(str(tmp_path))["arms"]
    assert "gt" not in arms
    assert arms["cal"]["real_episodes_vs_gt"] is None and arms["det"]["real_episodes_vs_gt"] is None


def test_the_executed_steps_are_pooled_by_where_their_starts_stood(tmp_path, capsys):
    """by_start: an exec run's executed steps' counts by the start's step summed per bin, with the real success,
    the detector's success and its precision (None where nothing divides), and printed with the run; a run whose
    steps did not count them has none."""
    def counts(a0, a24):  # (rollouts, real, said, said_real) of the bins from 0 and from 24
        return {f"start_a{a}_{k}": float(v) for a, c in ((0, a0), (24, a24), (48, (0, 0, 0, 0)))
                for k, v in zip(("rollouts", "real", "said", "said_real"), c)}
    executed = {"success_rate": 0.25, "kept_fraction": 0.5, "real_rollouts": 8.0, "detector_success": 0.5,
                "detector_agreement": 0.75, "detector_false_success": 0.25}
    _curve(tmp_path / "exec_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5), _point(2, 0.7, 0.52)],
           [dict(executed, step=1, **counts((4, 1, 3, 1), (4, 2, 1, 1))),
            dict(executed, step=2, **counts((6, 0, 2, 0), (2, 1, 2, 1)))])
    _curve(tmp_path / "exec_s1" / "rl" / "grpo", [_point(0, 0.7, 0.5), _point(2, 0.7, 0.52)],
           [dict(executed, step=1), dict(executed, step=2)])
    summary = rs.summarize(str(tmp_path))
    assert summary["runs"]["exec_s0"]["by_start"] == [
        {"from_step": 0, "rollouts": 10, "real": 1, "said": 5, "said_real": 1, "real_success": 0.1,
         "detector_success": 0.5, "precision": 0.2},
        {"from_step": 24, "rollouts": 6, "real": 3, "said": 3, "said_real": 2, "real_success": 0.5,
         "detector_success": 0.5, "precision": 2 / 3},
        {"from_step": 48, "rollouts": 0, "real": 0, "said": 0, "said_real": 0, "real_success": None,
         "detector_success": None, "precision": None}]
    assert "by_start" not in summary["runs"]["exec_s1"]
    # ground truth's steps count their trajectories with no detector: no verdicts
    _curve(tmp_path / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5), _point(2, 0.72, 0.55)],
           [{"step": s, "rollout_success": 0.5, "trajectories_sampled": 8.0, "mixed_fraction": 0.5,
             "start_a0_rollouts": 8.0, "start_a0_real": 4.0} for s in (1, 2)])
    summary = rs.summarize(str(tmp_path))
    assert summary["runs"]["gt_s0"]["by_start"] == [{"from_step": 0, "rollouts": 16, "real": 8, "real_success": 0.5}]
    rs.print_runs(summary)
    printed = capsys.readouterr().out
    # exec's bins beside the same seed's ground truth: the share kept where ground truth has the bin
    assert ("by the start's step: 0+: 10 rollouts, real 0.10, kept 20%, said 0.50, 24+: 6 rollouts, real 0.50, "
            "said 0.50" in printed)
    assert "48+" not in printed and "gt_s0: 2 steps" in printed and "0+: 16 rollouts, real 0.50; " not in printed
    (gt_line,) = [line for line in printed.splitlines() if line.startswith("[reward-source] gt_s0")]
    assert "by the start's step: 0+: 16 rollouts, real 0.50" in gt_line and "kept" not in gt_line


def test_the_figure_plots_what_reality_paid_and_the_closed_loop_per_decision(tmp_path):
    """figure: each run's paid success per step (the gt run's rollouts, the exec run's imagined actions and what the
    detector said of them), its real success at each evaluation, and per decision of the exec run the action gaps,
    means over its steps; a work dir without runs is refused."""
    _curve(tmp_path / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5, 0.5), _point(2, 0.75, 0.55)],
           [{"step": s, "rollout_success": 0.3 + 0.01 * s} for s in (1, 2)])
    prev = {f"closed_loop_action_gap_prev_{k}": 0.2 for k in (1, 2, 10)}
    _curve(tmp_path / "exec_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5, 0.5, 0.3), _point(2, 0.7, 0.5, 0.5, 0.4)],
           [{"step": s, "success_rate": 0.01 * s, "detector_success": 0.25, **_loop(0.1 * s, vae=True), **prev}
            for s in (1, 2)])
    series = rs.figure(str(tmp_path), str(tmp_path / "f.png"))
    assert (tmp_path / "f.png").stat().st_size > 0
    assert series["gt_s0"] == {"steps": [1, 2], "paid": [0.31, 0.32],
                               "evaluated": {"steps": [0, 2], "greedy": [0.7, 0.75], "sampled": [0.5, 0.55]}}
    ex = series["exec_s0"]
    assert ex["paid"] == [0.01, 0.02] and ex["detector"] == [0.25, 0.25]
    assert ex["evaluated"]["sampled_as_trained"] == [0.3, 0.4]  # evaluated as trained: drawn beside the others
    assert ex["action_gap"]["decisions"] == [1, 2, 10]
    assert ex["action_gap"]["world_model"] == pytest.approx([0.015, 0.03, 0.15])  # k x 0.1 x mean(0.1, 0.2)
    assert ex["action_gap"]["_vae"] == pytest.approx([0.0075, 0.015, 0.075]) and ex["action_gap"]["_prev"] == [0.2] * 3
    with pytest.raises(SystemExit, match="no runs"):
        rs.figure(str(tmp_path / "empty"), str(tmp_path / "g.png"))


def test_the_by_start_figure_pools_each_runs_rollouts_per_bin_and_leaves_out_thin_bins(tmp_path):
    """figure --by-start: per run its steps' counts summed per bin of the start's step, the real success with a
    Wilson interval, the detector's verdict for the world model's run; a bin of fewer than --min-rollouts left out
    (the 24 bin here), runs named by their work dir where there are several; refused where no run counted."""
    def counts(a0, a24, said=None):
        row = {"start_a0_rollouts": 40.0, "start_a0_real": a0, "start_a24_rollouts": 4.0, "start_a24_real": a24}
        if said is not None:
            row.update(start_a0_said=said, start_a0_said_real=a0 / 2, start_a24_said=0.0, start_a24_said_real=0.0)
        return row

    gt_dir, wm_dir = tmp_path / "gt_work", tmp_path / "wm_work"
    _curve(gt_dir / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5)],
           [{"step": s, "rollout_success": 0.4, "trajectories_sampled": 44.0, **counts(16.0, 2.0)} for s in (1, 2)])
    _curve(wm_dir / "exec_s1" / "rl" / "grpo", [_point(0, 0.7, 0.5)],
           [{"step": s, "success_rate": 0.1, "real_rollouts": 44.0, **counts(4.0, 1.0, said=20.0)} for s in (1, 2)])
    out = tmp_path / "b.png"
    series = rs.main(["figure", "--by-start", "--workdirs", f"{gt_dir},{wm_dir}", "--out", str(out)])
    assert out.stat().st_size > 0 and sorted(series) == ["gt_work/gt_s0", "wm_work/exec_s1"]
    gt, ex = series["gt_work/gt_s0"], series["wm_work/exec_s1"]
    assert (gt["from_step"], gt["rollouts"], gt["real_success"]) == ([0], [80], [0.4]) and "detector_success" not in gt
    assert (ex["arm"], ex["seed"], ex["real_success"], ex["detector_success"]) == ("exec", 1, [0.1], [0.5])
    lo, hi = gt["ci95"][0]
    assert lo < 0.4 < hi
    every = rs.main(["figure", "--by-start", "--workdirs", str(wm_dir), "--min-rollouts", "1", "--out", str(out)])
    assert every["exec_s1"]["from_step"] == [0, 24] and every["exec_s1"]["real_success"] == [0.1, 0.25]
    with pytest.raises(SystemExit, match="counted 100 or more"):
        rs.by_start_figure([str(wm_dir)], str(out), min_rollouts=100)
    with pytest.raises(SystemExit, match="not more"):
        rs.main(["figure", "--by-start", "--episodes", "--workdirs", str(wm_dir), "--out", str(out)])


def test_the_episodes_figure_puts_each_evaluation_at_the_real_episodes_consumed_by_then(tmp_path):
    """figure --episodes: runs of two work dirs (ground truth in one, the world model's arms in another); each
    evaluation at the real episodes its steps had consumed (gt: trajectories sampled; cal: its executed steps only),
    the chosen policy's success with a Wilson interval; refused for a gt run that did not count its trajectories, a
    policy no point holds, an unknown policy, and more than one figure kind at once."""
    gt_dir, wm_dir = tmp_path / "gt_work", tmp_path / "wm_work"
    _curve(gt_dir / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5, as_trained=0.36), _point(4, 0.7, 0.5, as_trained=0.5)],
           [{"step": s, "rollout_success": 0.4, "trajectories_sampled": 512.0} for s in (1, 2, 3, 4)])
    executed = {"success_rate": 0.1, "real_rollouts": 512.0, "detector_success": 0.5}
    _curve(wm_dir / "cal_s1" / "rl" / "grpo", [_point(0, 0.7, 0.5, as_trained=0.36), _point(4, 0.7, 0.5, as_trained=0.3)],
           [dict(executed, step=1), dict(executed, step=2)] + [{"step": s, "success_rate": 0.1, "detector_threshold": 0.9}
                                                               for s in (3, 4)])
    out = tmp_path / "e.png"
    series = rs.main(["figure", "--episodes", "--workdirs", f"{gt_dir},{wm_dir}", "--evaluated", "sampled_as_trained",
                      "--out", str(out)])
    assert out.stat().st_size > 0
    assert series["gt_s0"]["real_episodes"] == [0, 2048] and series["gt_s0"]["success"] == [0.36, 0.5]
    assert series["cal_s1"]["real_episodes"] == [0, 1024] and series["cal_s1"]["success"] == [0.36, 0.3]
    assert series["cal_s1"]["arm"] == "cal" and series["cal_s1"]["seed"] == 1
    lo, hi = series["gt_s0"]["ci95"][1]
    assert lo < 0.5 < hi and hi - lo == pytest.approx(0.087, abs=0.003)  # Wilson at 250 of 500
    assert rs.episodes_figure([str(wm_dir)], str(tmp_path / "g.png"), "greedy")["cal_s1"]["success"] == [0.7, 0.7]
    with pytest.raises(SystemExit, match="no evaluation of sampled_proprio_masked"):
        rs.episodes_figure([str(wm_dir)], str(tmp_path / "g.png"), "sampled_proprio_masked")
    with pytest.raises(SystemExit, match="--evaluated must be greedy or one of"):
        rs.episodes_figure([str(wm_dir)], str(tmp_path / "g.png"), "best")
    with pytest.raises(SystemExit, match="not more"):
        rs.main(["figure", "--episodes", "--workdirs", str(wm_dir), "--closed-loop", "x.json", "--out", str(out)])
    with pytest.raises(SystemExit, match="needs --workdirs"):
        rs.main(["figure", "--episodes", "--out", str(out)])
    _curve(gt_dir / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5), _point(4, 0.7, 0.5)],
           [{"step": s, "rollout_success": 0.4} for s in (1, 2, 3, 4)])
    with pytest.raises(SystemExit, match="did not record trajectories_sampled"):
        rs.episodes_figure([str(gt_dir)], str(tmp_path / "g.png"))


def test_a_short_horizon_from_every_phase_in_the_8x_vaes_world_model(tmp_path, monkeypatch):
    """--horizon, --keyframe-fraction and --vae-variant: every arm rolls out as far from the same keyframes; the
    pipeline trains the 8x VAE and the world-model arms load it."""
    args = rs.parse(["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--horizon", "2",
                     "--keyframe-fraction", "1.0", "--vae-variant", "vae8x", "--seeds", "0"])
    commands = rs.run_commands(args)
    for name, cmd in commands.items():
        assert _flag(cmd, "--rl.imagined.max_chunks") == ["--rl.imagined.max_chunks=2"], name
        assert _flag(cmd, "--rl.imagined.keyframe_fraction") == ["--rl.imagined.keyframe_fraction=1.0"], name
        assert "--rl.imagined.execute_steps=4" in cmd
    for name in ("exec_s0", "det_s0"):
        cmd = commands[name]
        assert cmd[cmd.index("--config") + 2:cmd.index("--simulator")] == list(rs.VAE_VARIANTS["vae8x"])
    seen = []
    monkeypatch.setattr(rs, "pipeline_command", lambda base, overrides, stop_after: seen.append(overrides) or [
        __import__("sys").executable, "-c", "raise SystemExit(1)"])
    with pytest.raises(SystemExit, match="never started"):
        rs.run(args, poll_s=0.05)
    assert seen == [rs.VAE_VARIANTS["vae8x"]] * 2  # the data stage's command and the whole pipeline's
    default = rs.run_commands(_args(tmp_path))
    assert all(not _flag(c, "--rl.imagined.keyframe_fraction") and "--rl.imagined.max_chunks=12" in c
               for c in default.values())
    assert "--vae.dim_mult=1,4,4" not in default["exec_s0"]
    for bad, message in ((("--horizon", "0"), "--horizon must be >= 1"),
                         (("--keyframe-fraction", "1.5"), "--keyframe-fraction in \\[0, 1\\]")):
        with pytest.raises(SystemExit, match=message):
            rs.parse(["summary", "--workdir", str(tmp_path), *bad])



def test_keyframes_from_a_later_phase_reach_every_arm(tmp_path):
    """--keyframe-from: every arm draws its keyframes from that fraction of each demonstration on (the phases where
    the world model's closed loop keeps reality's payment), as a config key its command sets; without it no arm
    sets it; above the keyframe fraction (the flag's, else the config's 0.5) or below 0 it is refused by name."""
    import configs
    from configs.cli import apply_overrides

    args = rs.parse(["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--keyframe-from", "0.3",
                     "--keyframe-fraction", "1.0", "--arms", "gt,exec,det,cal", "--seeds", "0"])
    commands = rs.run_commands(args)
    assert sorted(commands) == ["cal_s0", "det_s0", "exec_s0", "gt_s0"]
    for name, cmd in commands.items():
        assert _flag(cmd, "--rl.imagined.keyframe_from") == ["--rl.imagined.keyframe_from=0.3"], name
        assert _flag(cmd, "--rl.imagined.keyframe_fraction") == ["--rl.imagined.keyframe_fraction=1.0"], name
        imagined = apply_overrides(configs.get("sword:small"), _flag(cmd, "--rl.")).validate().rl.imagined
        assert (imagined.keyframe_from, imagined.keyframe_fraction) == (0.3, 1.0), name
    under_default = rs.run_commands(rs.parse(["run", "--workdir", str(tmp_path), "--keyframe-from", "0.5"]))
    assert all(_flag(c, "--rl.imagined.keyframe_from") == ["--rl.imagined.keyframe_from=0.5"]
               and not _flag(c, "--rl.imagined.keyframe_fraction") for c in under_default.values())
    assert not any(_flag(c, "--rl.imagined.keyframe_from") for c in rs.run_commands(_args(tmp_path)).values())
    for bad, upper in ((("--keyframe-from", "0.6"), "0.5"), (("--keyframe-from", "0.6", "--keyframe-fraction", "0.5"),
                       "0.5"), (("--keyframe-from", "-0.1", "--keyframe-fraction", "1.0"), "1.0")):
        with pytest.raises(SystemExit, match=rf"--keyframe-from must be in \[0, the keyframe fraction {upper}\]"):
            rs.parse(["run", "--workdir", str(tmp_path), *bad])


def test_the_rest_recipe_from_the_first_keyframe_with_centred_advantages(tmp_path):
    """--keyframe-fraction 0 --scale-by-std false: every arm starts at the demonstrations' first keyframe (frame 4,
    a latent in) and leaves its advantages centred, as the recipe that lifts on MJX from rest does."""
    from sword_jax.rl import data as rl_data

    args = rs.parse(["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--keyframe-fraction", "0",
                     "--scale-by-std", "false", "--arms", "gt,exec", "--seeds", "0,1"])
    commands = rs.run_commands(args)
    assert sorted(commands) == ["exec_s0", "exec_s1", "gt_s0", "gt_s1"]
    for name, cmd in commands.items():
        assert _flag(cmd, "--rl.imagined.keyframe_fraction") == ["--rl.imagined.keyframe_fraction=0.0"], name
        assert _flag(cmd, "--rl.grpo.scale_by_std") == ["--rl.grpo.scale_by_std=false"], name
    assert not any(_flag(c, "--rl.grpo.scale_by_std") for c in rs.run_commands(_args(tmp_path)).values())
    episodes = argparse.Namespace(num_episodes=5, lengths=np.array([60, 90, 120, 200, 33]))
    ep, t = rl_data.keyframe_indices(episodes, 64, np.random.default_rng(0), max_fraction=0.0)
    assert set(t.tolist()) == {4} and set(ep.tolist()) <= set(range(5))
    _, later = rl_data.keyframe_indices(episodes, 64, np.random.default_rng(0), max_fraction=1.0)
    assert later.max() > 4
    with pytest.raises(cli.UsageError, match="--scale-by-std"):
        rs.parse(["run", "--workdir", str(tmp_path), "--scale-by-std", "maybe"])


def test_world_model_settings_reach_the_pipeline_and_the_world_model_arms_only(tmp_path, monkeypatch):
    """--world-model-set: each override goes to both pipeline stages and to the arms that load the world model,
    after the VAE variant's; the ground-truth arm, which has none, is unchanged. A key that is not the config's, a
    value it cannot take, or an rl.* key (the arms' recipe) is refused by name before anything starts."""
    sets = ("trainer.ema_decay=0.999", "model.scan_layers=false")
    args = rs.parse(["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--vae-variant", "vae8x",
                     "--seeds", "0", *(a for kv in sets for a in ("--world-model-set", kv))])
    wanted = [*rs.VAE_VARIANTS["vae8x"], "--trainer.ema_decay=0.999", "--model.scan_layers=false"]
    commands = rs.run_commands(args)
    for name in ("exec_s0", "det_s0"):
        cmd = commands[name]
        assert cmd[cmd.index("--config") + 2:cmd.index("--simulator")] == wanted, name
    assert commands["gt_s0"] == rs.run_commands(argparse.Namespace(**{**vars(args), "world_model_set": []}))["gt_s0"]
    seen = []
    monkeypatch.setattr(rs, "pipeline_command", lambda base, overrides, stop_after: seen.append(list(overrides)) or [
        __import__("sys").executable, "-c", "raise SystemExit(1)"])
    with pytest.raises(SystemExit, match="never started"):
        rs.run(args, poll_s=0.05)
    assert seen == [wanted] * 2  # the data stage's command and the whole pipeline's
    for kv, message in (("trainer.ema_decy=0.9", "'ema_decy' is not a field of TrainerConfig"),
                        ("trainer.ema_decay=1.5", "ema_decay must be in \\[0, 1\\)"),
                        ("model.scan_layers=maybe", "cannot parse 'maybe'"),
                        ("rl.grpo.steps=3", "outside rl"), ("ema_decay", "KEY=VALUE")):
        with pytest.raises(SystemExit, match=message):
            rs.parse(["run", "--workdir", str(tmp_path), "--world-model-set", kv])


def test_a_whole_chunk_a_decision_for_every_arm(tmp_path):
    """--actions-per-decision 8: every arm executes 8 actions a decision (rl.imagined.execute_steps), the rest of the
    recipe as it was; only 4 and 8 (one or two latents of the world model) are taken."""
    args = rs.parse(["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--horizon", "6",
                     "--actions-per-decision", "8", "--seeds", "0"])
    four = rs.run_commands(argparse.Namespace(**{**vars(args), "actions_per_decision": 4}))
    for name, cmd in rs.run_commands(args).items():
        assert _flag(cmd, "--rl.imagined.execute_steps") == ["--rl.imagined.execute_steps=8"], name
        assert _flag(cmd, "--rl.imagined.max_chunks") == ["--rl.imagined.max_chunks=6"], name
        assert [c.replace("execute_steps=8", "execute_steps=4") for c in cmd] == four[name]
    assert all("--rl.imagined.execute_steps=4" in c for c in rs.run_commands(_args(tmp_path)).values())
    with pytest.raises(cli.UsageError, match="--actions-per-decision"):
        rs.parse(["run", "--workdir", str(tmp_path), "--actions-per-decision", "2"])


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="--seeds"):
        rs.main(["summary", "--workdir", str(tmp_path), "--seeds", ""])
    with pytest.raises(SystemExit, match="--rollout-batch"):
        rs.main(["summary", "--workdir", str(tmp_path), "--rollout-batch", "30"])
    with pytest.raises(SystemExit, match="--eval-episodes-per-task >= 1"):
        rs.main(["summary", "--workdir", str(tmp_path), "--eval-episodes-per-task", "0"])
    with pytest.raises(SystemExit, match="--arms must name some of gt, exec, det"):
        rs.main(["summary", "--workdir", str(tmp_path), "--arms", "exec,oracle"])
    with pytest.raises(SystemExit, match="--policy"):
        rs.main(["run", "--workdir", str(tmp_path)])


def test_runs_start_once_their_inputs_are_built_and_a_deadline_stops_the_rest(tmp_path, monkeypatch):
    """The ground-truth runs start after the data stage, the world-model runs after the whole pipeline; each
    run sees what it needs already there. A deadline stops what is still going."""
    import sys

    def step(marker):  # a stage that leaves its marker
        return [sys.executable, "-c", f"open({str(tmp_path / marker)!r}, 'w').close()"]

    monkeypatch.setattr(rs, "pipeline_command", lambda base, overrides, stop_after: step(stop_after))

    def check(needs, name):  # a run that records whether its input was there when it started
        return [sys.executable, "-c", f"import os; open({str(tmp_path / name)!r}, 'w').write("
                                      f"str(os.path.exists({str(tmp_path / needs)!r})))"]

    monkeypatch.setattr(rs, "run_commands", lambda args: {
        "gt_s0": check("data", "gt_s0.seen"), "exec_s0": check("reward_model", "exec_s0.seen"),
        "det_s0": check("reward_model", "det_s0.seen")})
    monkeypatch.setattr(rs, "summarize", lambda workdir: {"runs": {}, "arms": {}})
    args = _args(tmp_path, gpus="0,1", seeds="0")
    summary = rs.run(args, poll_s=0.05)
    assert summary["exit_codes"] == {"gt_s0": 0, "exec_s0": 0, "det_s0": 0} and summary["stopped_at_deadline"] == []
    assert all((tmp_path / f"{n}.seen").read_text() == "True" for n in ("gt_s0", "exec_s0", "det_s0"))
    assert (tmp_path / "reward_source_summary.json").exists()
    monkeypatch.setattr(rs, "run_commands", lambda args: {"gt_s0": [sys.executable, "-c", "import time; time.sleep(60)"],
                                                          "exec_s0": step("x"), "det_s0": step("y")})
    args.deadline_s = 1.0
    summary = rs.run(args, poll_s=0.05)
    assert summary["stopped_at_deadline"] == ["gt_s0"] and summary["exit_codes"]["exec_s0"] == 0


def test_gpu_share_caps_the_world_model_runs_memory_and_leaves_the_ground_truth_alone(tmp_path, monkeypatch):
    """--gpu-share F: the world-model runs on a GPU split 0.9 x F of its memory between them (their
    XLA_PYTHON_CLIENT_MEM_FRACTION), alone or several; the ground-truth runs are not capped; a share outside (0, 1]
    is refused by name."""
    import sys

    monkeypatch.delenv("XLA_PYTHON_CLIENT_MEM_FRACTION", raising=False)
    monkeypatch.setattr(rs, "pipeline_command", lambda base, overrides, stop_after: [sys.executable, "-c", ""])

    def seen(name):  # a run that records the memory cap it was started with
        return [sys.executable, "-c", f"import os; open({str(tmp_path / name)!r}, 'w').write("
                                      f"str(os.environ.get('XLA_PYTHON_CLIENT_MEM_FRACTION')))"]

    monkeypatch.setattr(rs, "summarize", lambda workdir: {"runs": {}, "arms": {}})
    for share, runs, want in ((0.5, ("exec_s0", "exec_s1"), 0.225), (0.25, ("exec_s0",), 0.225), (1.0, ("exec_s0",),
                                                                                                   None)):
        monkeypatch.setattr(rs, "run_commands", lambda a, runs=runs: {"gt_s0": seen("gt_s0"),
                                                                      **{n: seen(n) for n in runs}})
        args = _args(tmp_path, gpus="0", seeds="0,1", arms=("gt", "exec"))
        args.gpu_share = share
        assert rs.run(args, poll_s=0.05)["exit_codes"]["gt_s0"] == 0
        assert (tmp_path / "gt_s0").read_text() == "None"
        for n in runs:
            cap = (tmp_path / n).read_text()
            assert (cap == "None") if want is None else float(cap) == pytest.approx(want, abs=0.006)
    for bad in ("0", "1.5"):
        with pytest.raises(SystemExit, match="--gpu-share must be in"):
            rs.parse(["run", "--workdir", str(tmp_path), "--gpu-share", bad])


def test_a_pipeline_built_elsewhere_is_shared_and_each_run_waits_for_its_stages(tmp_path, monkeypatch):
    """--pipeline DIR: nothing is built here; the commands read DIR's data and models, the ground-truth run starts
    once DIR's data stage has finished and the world-model run once its VAE, world model and detector have, as the
    other command builds them. A folder that is not there is refused by name."""
    import sys
    import threading
    import time

    shared = tmp_path / "first" / "pipeline"
    (shared / "stages").mkdir(parents=True)
    monkeypatch.setattr(rs, "pipeline_command", lambda *a, **k: pytest.fail("--pipeline builds nothing"))
    args = rs.parse(["run", "--workdir", str(tmp_path / "second"), "--policy", "/p/policy_d50.npz", "--seeds", "0",
                     "--arms", "gt,exec", "--pipeline", str(shared), "--actions-per-decision", "8", "--horizon", "6"])
    commands = rs.run_commands(args)
    assert commands["exec_s0"][commands["exec_s0"].index("--world-model") + 1] == str(shared / "world_model")
    assert f"--demos={shared / 'data' / 'demos.hdf5'}" in commands["gt_s0"]
    assert commands["exec_s0"][commands["exec_s0"].index("--workdir") + 1] == str(tmp_path / "second" / "exec_s0")

    def seen(name):  # a run that records which of the shared pipeline's stages had finished when it started
        return [sys.executable, "-c", f"import os; open({str(tmp_path / name)!r}, 'w').write(' '.join(sorted("
                                      f"os.listdir({str(shared / 'stages')!r}))))"]

    monkeypatch.setattr(rs, "run_commands", lambda a: {"gt_s0": seen("gt"), "exec_s0": seen("exec")})
    monkeypatch.setattr(rs, "summarize", lambda workdir: {"runs": {}, "arms": {}})

    def other_command():  # the stages finishing one after another in the other command's pipeline
        for stage in ("data", "vae", "world_model", "reward_model"):
            time.sleep(0.3)
            (shared / "stages" / f"{stage}.json").write_text("{}")

    builder = threading.Thread(target=other_command)
    builder.start()
    summary = rs.run(args, poll_s=0.05)
    builder.join()
    assert summary["exit_codes"] == {"gt_s0": 0, "exec_s0": 0}
    assert "data.json" in (tmp_path / "gt").read_text().split()
    assert (tmp_path / "exec").read_text().split() == ["data.json", "reward_model.json", "vae.json", "world_model.json"]
    with pytest.raises(SystemExit, match="--pipeline .*missing: no such folder"):
        rs.parse(["run", "--workdir", str(tmp_path), "--pipeline", str(tmp_path / "missing")])


def test_deterministic_runs_start_with_xlas_deterministic_ops_and_the_summary_says_so(tmp_path, monkeypatch):
    """--deterministic adds the flag to the runs' XLA_FLAGS (once, after the caller's), multicast stays off, and the
    work dir's xla_flags.txt carries it into the summary and the latest.json entry; without it, nothing is added."""
    import sys

    monkeypatch.setenv("XLA_FLAGS", "--xla_dump_to=/tmp/x")
    monkeypatch.setattr(rs, "pipeline_command", lambda base, overrides, stop_after: [sys.executable, "-c", "pass"])
    seen = "import os; open({!r}, 'w').write(os.environ.get('XLA_FLAGS', '') + '|' + os.environ['NCCL_NVLS_ENABLE'])"
    monkeypatch.setattr(rs, "run_commands", lambda args: {n: [sys.executable, "-c", seen.format(str(tmp_path / n))]
                                                          for n in ("gt_s0", "exec_s0")})
    args = _args(tmp_path, gpus="0", seeds="0", arms=("gt", "exec"))
    args.deterministic = True
    summary = rs.run(args, poll_s=0.05)
    flags = "--xla_dump_to=/tmp/x --xla_gpu_deterministic_ops=true"
    assert (tmp_path / "gt_s0").read_text() == (tmp_path / "exec_s0").read_text() == flags + "|0"
    assert summary["deterministic"] is True and summary["xla_flags"] == flags
    assert rs.common.with_flag(flags, "--xla_gpu_deterministic_ops=true") == flags  # added once
    entry = rs.smallest_gain_entry({**summary, "arms": {"gt": {"smallest": 0.1}}, "runs": {}}, "gt", str(tmp_path),
                                   bench="x", unit="u", data="d")
    assert entry["deterministic"] is True
    plain = tmp_path / "plain"
    args = _args(plain, gpus="0", seeds="0", arms=("gt", "exec"))
    assert rs.run(args, poll_s=0.05)["deterministic"] is False
    assert (plain / "xla_flags.txt").read_text() == "--xla_dump_to=/tmp/x\n"
    assert rs.common.workdir_xla_flags(str(tmp_path / "never_launched")) == {}  # an older work dir: nothing claimed


def test_the_machines_gpus_are_recorded_where_nvidia_smi_answers(tmp_path, monkeypatch):
    import subprocess

    listed = "name, memory.total [MiB]\nNVIDIA H100 80GB HBM3, 81559 MiB\nNVIDIA H100 80GB HBM3, 81559 MiB\n"
    monkeypatch.setattr(rs.common.subprocess, "run", lambda *a, **kw: subprocess.CompletedProcess(a, 0, listed, ""))
    rs.common.record_gpus(str(tmp_path / "gpu.txt"))
    assert (tmp_path / "gpu.txt").read_text() == listed

    def missing(*a, **kw):
        raise FileNotFoundError("nvidia-smi")

    monkeypatch.setattr(rs.common.subprocess, "run", missing)
    rs.common.record_gpus(str(tmp_path / "none.txt"))
    assert not (tmp_path / "none.txt").exists()
    assert rs.common.workdir_device(str(tmp_path)) == "NVIDIA H100 80GB HBM3 x2"


def test_closed_loop_summary_from_a_runs_history_or_its_progress_lines(tmp_path, capsys):
    """The closed-loop summary parses the lines :func:`sword_jax.pipeline.grpo.payment_note` writes, pools the
    paid successes over the steps, averages the first and last decisions' figures, reads every decision from a
    history where there is one, and refuses a log without the record."""
    from sword_jax.pipeline.grpo import payment_note

    def point(step, paid, error, gap):
        p = {"step": step, "success_rate": paid, "detector_success": 0.25, "detector_agreement": 0.75}
        for k in range(1, 4):
            p[f"closed_loop_frame_error_{k}"], p[f"closed_loop_action_gap_{k}"] = error * k, gap * k
        return p

    points = [point(1, 2 / 8, 0.01, 0.1), point(2, 0.0, 0.03, 0.3)]
    log = tmp_path / "run.log"
    log.write_text("eval step 0: MJX success 0.5\n" + "".join(
        f"grpo step {p['step']}/2 {payment_note(p, 3)} return 0.1 loss 0.0 eta 1s\n" for p in points))
    metrics = tmp_path / "metrics.jsonl"
    metrics.write_text("".join(json.dumps({"step": 100 * i, "loss": 1.0 / i}) + "\n" for i in range(1, 13)))
    grpo = tmp_path / "grpo"
    grpo.mkdir()
    (grpo / "train_history.jsonl").write_text("".join(json.dumps(p) + "\n" for p in points))
    run = rs.closed_loop_summary([("wm", str(grpo), str(log), str(metrics))], trajectories=8)["wm"]
    assert run["steps"] == 2 and run["paid_success"]["rate"] == pytest.approx(2 / 16) and run["paid_success"]["of"] == 16
    assert run["frame_error_first"] == pytest.approx(0.02) and run["frame_error_last"] == pytest.approx(0.06)
    assert run["action_gap_first"] == pytest.approx(0.2) and run["action_gap_last"] == pytest.approx(0.6)
    assert run["detector_success"] == pytest.approx(0.25)
    assert run["world_model_steps"] == 1200 and run["world_model_loss"] == pytest.approx(
        sum(1.0 / i for i in range(3, 13)) / 10)
    assert run["per_decision"] == {"decisions": [1, 2, 3], "frame_error": pytest.approx([0.02, 0.04, 0.06]),
                                   "action_gap": pytest.approx([0.2, 0.4, 0.6])}
    assert run["source"] == "history" and not any("vae" in k for k in run)  # a run without the VAE's share
    # without the history, the progress lines give the same figures but the decisions in between
    (grpo / "train_history.jsonl").unlink()
    from_log = rs.closed_loop_summary([("wm", str(grpo), str(log), str(metrics))], trajectories=8)["wm"]
    assert from_log["source"] == "progress lines" and "per_decision" not in from_log
    assert from_log["paid_success"] == run["paid_success"]
    for key in ("frame_error_first", "frame_error_last", "action_gap_first", "action_gap_last"):
        assert from_log[key] == pytest.approx(run[key], abs=1e-3)
    assert not any("vae" in k for k in from_log)

    # a run that logged the VAE round trip's share: its progress lines say it at decision 1, the summary keeps it
    for p in points:
        for k in range(1, 4):
            p[f"closed_loop_frame_error_vae_{k}"] = p[f"closed_loop_frame_error_{k}"] / 2
            p[f"closed_loop_action_gap_vae_{k}"] = p[f"closed_loop_action_gap_{k}"] / 4
    note = payment_note(points[1], 3)
    assert note.endswith("greedy action gap 0.300 -> 0.900 (the VAE alone at decision 1: frame error 0.015, gap 0.075)")
    log.write_text("".join(f"grpo step {p['step']}/2 {payment_note(p, 3)} return 0.1 loss 0.0 eta 1s\n"
                           for p in points))
    (grpo / "train_history.jsonl").write_text("".join(json.dumps(p) + "\n" for p in points))
    run = rs.closed_loop_summary([("wm", str(grpo), str(log), str(metrics))], trajectories=8)["wm"]
    assert run["frame_error_vae_first"] == pytest.approx(0.01) and run["action_gap_vae_first"] == pytest.approx(0.05)
    assert run["per_decision"]["frame_error_vae"] == pytest.approx([0.01, 0.02, 0.03])
    assert run["per_decision"]["action_gap_vae"] == pytest.approx([0.05, 0.1, 0.15])
    (grpo / "train_history.jsonl").unlink()
    from_log = rs.closed_loop_summary([("wm", str(grpo), str(log), str(metrics))], trajectories=8)["wm"]
    for key in ("frame_error_first", "action_gap_last", "frame_error_vae_first", "action_gap_vae_first"):
        assert from_log[key] == pytest.approx(run[key], abs=1e-3)
    out = rs.main(["closed-loop", "--run", "wm", str(grpo), str(log), str(metrics), "--trajectories", "8",
                   "--out", str(tmp_path / "closed_loop.json")])
    assert out["runs"]["wm"]["action_gap_vae_first"] == from_log["action_gap_vae_first"]
    assert "the VAE alone at the first: frame error 0.010, gap 0.050" in capsys.readouterr().out
    (tmp_path / "plain.log").write_text(f"grpo step 1/2 {payment_note({'success_rate': 0.5}, 3)} eta 1s\n")
    with pytest.raises(SystemExit, match="holds no step with the closed-loop record"):
        rs.closed_loop_summary([("wm", str(grpo), str(tmp_path / "plain.log"), str(metrics))], trajectories=8)
    with pytest.raises(SystemExit, match="closed-loop needs --run"):
        rs.main(["closed-loop", "--out", str(tmp_path / "o.json")])
    with pytest.raises(SystemExit, match="summary needs --workdir"):
        rs.main(["summary"])


def test_closed_loop_runs_compared_over_their_first_steps_and_drawn_side_by_side(tmp_path):
    """closed-loop --first-steps keeps each run's steps up to it (a longer run compares over the same steps as a
    shorter one), --decision-actions records each run's actions a decision (one per run, positive), and figure
    --closed-loop draws the runs against the actions executed; a JSON without per-decision records is refused."""
    from sword_jax.pipeline.grpo import payment_note

    def point(step, paid, error):
        p = {"step": step, "success_rate": paid, "detector_success": 0.25, "detector_agreement": 0.75}
        for k in range(1, 4):
            p[f"closed_loop_frame_error_{k}"], p[f"closed_loop_action_gap_{k}"] = error * k, 2 * error * k
        return p

    metrics = tmp_path / "metrics.jsonl"
    measured = {"eval_train_loss": 0.08, "eval_heldout_loss": 0.12, "eval_heldout_sample_error_5": 0.3}
    metrics.write_text("".join(json.dumps({"step": 100 * i, "loss": 0.1, **(measured if i == 2 else {})}) + "\n"
                               for i in range(1, 4)))
    runs = []
    for name, points in (("long", [point(s, 0.125 * s, 0.01 * s) for s in (1, 2, 3, 4)]),
                         ("short", [point(1, 0.5, 0.02), point(2, 0.25, 0.02)])):
        grpo = tmp_path / name
        grpo.mkdir()
        (grpo / "train_history.jsonl").write_text("".join(json.dumps(p) + "\n" for p in points))
        runs.append((name, str(grpo), str(tmp_path / "none.log"), str(metrics)))
    out = tmp_path / "closed_loop.json"
    argv = ["closed-loop", "--trajectories", "8", "--out", str(out)]
    for r in runs:
        argv += ["--run", *r]
    result = rs.main([*argv, "--first-steps", "2", "--decision-actions", "4,8"])
    long, short = result["runs"]["long"], result["runs"]["short"]
    assert result["first_steps"] == 2 and long["steps"] == short["steps"] == 2
    assert long["paid_success"]["rate"] == pytest.approx(3 / 16)  # steps 1-2 alone: 1 + 2 of 16
    assert long["per_decision"]["frame_error"] == pytest.approx([0.015, 0.03, 0.045])  # mean of steps 1-2
    assert (long["actions_per_decision"], short["actions_per_decision"]) == (4, 8)
    assert long["world_model_evaluation"] == {"step": 200, **measured}  # the trainer's last measurement
    assert rs.world_model_loss(str(metrics), 150) == {"steps": 100, "loss": 0.1}  # none yet at the step a run read
    assert rs.main(argv)["runs"]["long"]["steps"] == 4 and "first_steps" not in json.loads(out.read_text())
    for bad in ("4", "4,0", "4,x"):
        with pytest.raises(SystemExit, match="--decision-actions"):
            rs.main([*argv, "--decision-actions", bad])
    rs.main([*argv, "--first-steps", "2", "--decision-actions", "4,8"])
    series = rs.main(["figure", "--closed-loop", str(out), "--out", str(tmp_path / "f.png"), "--title", "t"])
    assert (tmp_path / "f.png").stat().st_size > 0
    assert series["long"]["actions"] == [4, 8, 12] and series["short"]["actions"] == [8, 16, 24]
    assert series["short"]["paid"] == [0.5, 0.25] and series["long"]["action_gap"] == pytest.approx([0.03, 0.06, 0.09])
    (grpo / "train_history.jsonl").unlink()  # the short run now read from its (missing) log's progress lines
    (tmp_path / "none.log").write_text(f"grpo step 1/2 {payment_note(point(1, 0.5, 0.02), 3)} eta 1s\n")
    rs.main(argv)
    with pytest.raises(SystemExit, match="short read from progress lines"):
        rs.main(["figure", "--closed-loop", str(out), "--out", str(tmp_path / "g.png")])
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(SystemExit, match="is not closed-loop's JSON"):
        rs.main(["figure", "--closed-loop", str(tmp_path / "bad.json"), "--out", str(tmp_path / "g.png")])


def test_a_progress_line_names_a_step_that_applied_no_update():
    from sword_jax.pipeline.grpo import skipped_note

    assert skipped_note({"skipped_update": 1.0}) == "(no update: too few mixed groups) "
    assert skipped_note({"skipped_update": 0.0}) == skipped_note({}) == ""


def test_the_world_models_figure_draws_its_trainers_measurements_and_refuses_a_run_without_them(tmp_path):
    """figure --world-model draws the logged loss and, per split, the fixed-noise loss and the sample error at each
    Euler step count, at the steps they were measured; a metrics.jsonl with no measurement, one that is not JSON
    lines, and --world-model beside --closed-loop are refused by name."""
    metrics = tmp_path / "metrics.jsonl"
    rows = [{"step": 50 * i, "loss": 1.0 / i} for i in range(1, 7)]
    for i, r in enumerate(rows[1::2], 1):
        r.update(eval_train_loss=0.5 / i, eval_heldout_loss=0.6 / i, eval_heldout_sample_error_5=0.2 / i,
                 eval_heldout_sample_error_20=0.3 / i, eval_train_sample_error_5=0.1 / i)
    metrics.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "wm.png"
    series = rs.main(["figure", "--world-model", str(metrics), "--out", str(out), "--title", "t"])
    assert out.stat().st_size > 0
    assert series["steps"] == [50, 100, 150, 200, 250, 300] and series["eval_steps"] == [100, 200, 300]
    assert series["eval_heldout_sample_error_20"] == pytest.approx([0.3, 0.15, 0.1])
    assert series["eval_train_loss"] == pytest.approx([0.5, 0.25, 0.5 / 3])
    assert "eval_train_sample_error_20" not in series  # only what the trainer measured
    metrics.write_text("".join(json.dumps({"step": 50 * i, "loss": 1.0}) + "\n" for i in range(1, 4)))
    with pytest.raises(SystemExit, match="no measurement of fixed segments"):
        rs.main(["figure", "--world-model", str(metrics), "--out", str(out)])
    metrics.write_text("not json\n")
    with pytest.raises(SystemExit, match="is not a metrics.jsonl"):
        rs.main(["figure", "--world-model", str(metrics), "--out", str(out)])
    with pytest.raises(SystemExit, match="not more"):
        rs.main(["figure", "--world-model", str(metrics), "--closed-loop", str(out), "--out", str(out)])


def test_a_bundle_gives_the_world_model_runs_their_weights_and_the_pipeline_builds_only_its_data(tmp_path, monkeypatch):
    """--bundle DIR (train.bundle unpack's folder): the world-model arms read its world model, VAE and detector and
    start once the pipeline's data stage has finished, the only stage built; the summary names the bundle's source.
    A bundle without what the arms read, or no such folder, is refused by name before anything starts."""
    import sys

    bundle = tmp_path / "bundle"
    for sub in ("world_model/checkpoints", "vae_run/vae", "rl/reward_model"):
        (bundle / sub).mkdir(parents=True)
    (bundle / "bundle.json").write_text(json.dumps({"source": "/elsewhere/run", "sha256": "ab", "world_model": {"step": 9}}))
    args = _args(tmp_path / "work", seeds="0", arms=("exec", "det"))
    args.bundle, args.pipeline = str(bundle), ""
    commands = rs.run_commands(args)
    for name in ("exec_s0", "det_s0"):
        cmd = commands[name]
        assert cmd[cmd.index("--world-model") + 1] == str(bundle / "world_model")
        assert cmd[cmd.index("--vae") + 1] == str(bundle / "vae_run" / "vae")
        assert cmd[cmd.index("--reward") + 1] == str(bundle / "rl" / "reward_model")
        assert cmd[cmd.index("--demos") + 1] == str(tmp_path / "work" / "pipeline" / "data" / "demos.hdf5")
        assert rs.needs(args, name) == ("data",)
    built = []

    def step(base, overrides, stop_after):
        built.append(stop_after)
        return [sys.executable, "-c", f"open({str(tmp_path / stop_after)!r}, 'w').close()"]

    monkeypatch.setattr(rs, "pipeline_command", step)
    def seen(name):  # a run that records whether the data stage had finished when it started
        return [sys.executable, "-c",
                f"import os; open({str(tmp_path / name)!r}, 'w').write(str(os.path.exists({str(tmp_path / 'data')!r})))"]

    monkeypatch.setattr(rs, "run_commands", lambda a: {n: seen(n) for n in ("exec_s0", "det_s0")})
    monkeypatch.setattr(rs, "summarize", lambda workdir: {"runs": {}, "arms": {}})
    summary = rs.run(args, poll_s=0.05)
    assert built == ["data"] and summary["exit_codes"] == {"exec_s0": 0, "det_s0": 0}
    assert all((tmp_path / n).read_text() == "True" for n in ("exec_s0", "det_s0"))
    assert summary["bundle"] == {"path": str(bundle), "source": "/elsewhere/run", "sha256": "ab",
                                 "world_model": {"step": 9}}
    (bundle / "rl" / "reward_model").rmdir()
    with pytest.raises(SystemExit, match="--bundle .* lacks rl/reward_model"):
        rs.run(args, poll_s=0.05)
    args.arms = ["exec"]
    rs.check_bundle(args)  # the executed reward reads no detector
    with pytest.raises(SystemExit, match="--bundle .*nowhere: no such folder"):
        rs.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--bundle", str(tmp_path / "nowhere")])


def test_the_refreshed_arm_reads_latents_that_a_bundled_run_encodes_before_it_starts(tmp_path, monkeypatch):
    """ref: train.grpo in the world model with its refresh (every --refresh-every steps, --refresh-episodes each,
    within --refresh-budget, --refresh-set's settings) and the latents it mixes in; no reward flag (the detector
    pays, the refresh calibrates it). From a bundle, which carries no latents, run encodes the pipeline's training
    episodes with the bundle's VAE once the data stage is done and starts ref only then; --latents skips that; with a
    pipeline its own latents are read. Bad refresh settings are refused by name."""
    import sys

    bundle = tmp_path / "bundle"
    for sub in ("world_model/checkpoints", "vae_run/vae", "rl/reward_model"):
        (bundle / sub).mkdir(parents=True)
    work = tmp_path / "work"
    args = _args(work, seeds="0", arms=("exec", "ref", "rexec"))
    args.bundle, args.pipeline = str(bundle), ""
    args.refresh_set = ["rl.refresh.world_model_steps=1000"]
    commands = rs.run_commands(args)
    ref, ex = commands["ref_s0"], commands["exec_s0"]
    assert ["--rl.refresh.every=10", "--rl.refresh.episodes=64", "--rl.refresh.budget=256",
            "--rl.refresh.world_model_steps=1000"] == _flag(ref, "--rl.refresh")
    assert ref[ref.index("--latents") + 1] == str(work / "latents.npz") and not _flag(ref, "--rl.imagined.reward")
    assert not _flag(ex, "--rl.refresh") and "--latents" not in ex
    rexec = commands["rexec_s0"]  # refreshed, and paid by execution as exec is
    assert _flag(rexec, "--rl.refresh") == ["--rl.refresh.branch=false", *_flag(ref, "--rl.refresh")]
    assert "--rl.imagined.reward=executed" in rexec  # from the keyframes, whose recorded states it executes from
    assert rexec[rexec.index("--latents") + 1] == str(work / "latents.npz")
    assert rs.latents_command(args)[2:] == ["train.encode_latents", "--config", "sword:small", "--vae",
                                            str(bundle / "vae_run" / "vae"), "--out", str(work / "latents.npz"),
                                            str(work / "pipeline" / "data" / "train.hdf5")]
    built = []

    def step(base, overrides, stop_after):
        built.append(stop_after)
        return [sys.executable, "-c", f"open({str(tmp_path / stop_after)!r}, 'w').close()"]

    def seen(name):  # a run that records whether the latents had been encoded when it started
        return [sys.executable, "-c", f"import os; open({str(tmp_path / name)!r}, 'w')"
                                      f".write(str(os.path.exists({str(tmp_path / 'encoded')!r})))"]

    monkeypatch.setattr(rs, "pipeline_command", step)
    monkeypatch.setattr(rs, "latents_command", lambda a: [sys.executable, "-c", "import time; time.sleep(0.3); "
                                                          f"open({str(tmp_path / 'encoded')!r}, 'w').close()"])
    monkeypatch.setattr(rs, "run_commands", lambda a: {n: seen(n) for n in ("exec_s0", "ref_s0", "rexec_s0")})
    monkeypatch.setattr(rs, "summarize", lambda workdir: {"runs": {}, "arms": {}})
    summary = rs.run(args, poll_s=0.05)
    assert built == ["data"] and summary["exit_codes"] == {"exec_s0": 0, "ref_s0": 0, "rexec_s0": 0}
    assert [(tmp_path / n).read_text() for n in ("exec_s0", "ref_s0", "rexec_s0")] == ["False", "True", "True"]
    (tmp_path / "encoded").unlink()
    args.latents = str(tmp_path / "given.npz")  # latents given: none encoded, ref starts after the data
    assert rs.latents_path(args) == args.latents
    summary = rs.run(args, poll_s=0.05)
    assert (tmp_path / "ref_s0").read_text() == "False"
    args.latents, args.bundle = "", ""
    assert rs.latents_path(args) == str(work / "pipeline" / "data" / "latents.npz")

    def parse(*extra):
        return rs.parse(["run", "--workdir", str(work), "--policy", "p.npz", "--arms", "ref", "--steps", "20",
                         "--eval-every", "5", *extra])

    assert parse("--refresh-every", "10").refresh_every == 10
    with pytest.raises(SystemExit, match="--refresh-every must be a positive multiple of --eval-every"):
        parse("--refresh-every", "7")
    with pytest.raises(SystemExit, match="--refresh-set takes rl.refresh.KEY=VALUE"):
        parse("--refresh-set", "rl.grpo.steps=3")
    with pytest.raises(SystemExit, match="the ref arm's refresh: .*budget"):
        parse("--refresh-episodes", "64", "--refresh-budget", "32")
    with pytest.raises(SystemExit, match="the rexec arm's refresh: .*branch"):  # executed from keyframes only
        parse("--arms", "rexec", "--refresh-set", "rl.refresh.branch=true")
    assert parse("--arms", "ref,rexec").arms == ["ref", "rexec"]
    with pytest.raises(SystemExit, match="with --bundle and --pipeline needs --latents"):
        parse("--bundle", str(bundle), "--pipeline", str(tmp_path))


def test_a_refreshed_runs_summary_counts_its_refreshes_episodes_and_reads_their_records(tmp_path, capsys):
    """A refreshed run's real episodes are its refreshes' (cumulative real_episodes_used, not summed over steps),
    step by step in the episodes figure too; its summary carries each refresh's record as bench_grpo_refresh
    reads it."""
    history = [{"step": k, "success_rate": 0.9, "kept_fraction": 0.5, "real_episodes_used": used}
               for k, used in ((1, 64.0), (2, 64.0), (3, 128.0))]
    assert rs.real_episodes(history) == 128
    assert rs.episodes_consumed(history) == {0: 0, 1: 64, 2: 64, 3: 128}
    executed = [dict(h, real_rollouts=16.0) for h in history]  # paid by execution too: both count
    assert rs.real_episodes(executed) == 128 + 48
    assert rs.episodes_consumed(executed) == {0: 0, 1: 80, 2: 96, 3: 176}
    grpo = tmp_path / "ref_s0" / "rl" / "grpo"
    grpo.mkdir(parents=True)
    point = {"step": 0, "mean": 0.5, "successes": 250, "episodes": 500,
             "sampled": {"mean": 0.4, "successes": 200, "episodes": 500}}
    (grpo / "success_curve.json").write_text(json.dumps({"points": [point, dict(point, step=3)]}))
    (grpo / "train_history.jsonl").write_text("".join(json.dumps(h) + "\n" for h in history))
    record = {"step": 0, "real_episodes": 64, "real_success": 0.5, "replay": {"false_success": {"rate": 0.6, "of": 30}},
              "detector": {"threshold": 0.99, "calibration": {"rule": "false_success"}}}
    (grpo / "refreshes.json").write_text(json.dumps([record]))
    summary = rs.summarize(str(tmp_path))
    run = summary["runs"]["ref_s0"]
    assert run["arm"] == "ref" and run["real_episodes"] == 128
    assert [(r["step"], r["false_success_before"], r["threshold"]) for r in run["refreshes"]] == [
        (0, {"rate": 0.6, "of": 30}, 0.99)]
    rs.print_runs(summary)
    assert ("; refresh at step 0: 64 real episodes (real success 0.50), its replay's false success before 0.60 of "
            "30 real failures, threshold 0.990" in capsys.readouterr().out)
    # a refresh on the world model's closed loop: its trajectories and the held-out fit before and after
    record["closed_loop"] = {"episodes": 512, "fit": {"before": {"closed_loop": {"sample_error": 0.04}},
                                                      "after": {"closed_loop": {"sample_error": 0.03}}}}
    (grpo / "refreshes.json").write_text(json.dumps([record]))
    rs.print_runs(rs.summarize(str(tmp_path)))
    assert ("threshold 0.990, its closed loop 512 trajectories (held-out sample error from its own context 0.0400 -> "
            "0.0300)" in capsys.readouterr().out)
    assert rs.closed_loop_note({"skipped": "budget"}) == "" and rs.closed_loop_note(None) == ""


def _launch_line(name, cmd):
    """The line ``run`` prints as it starts a run (its command without the interpreter)."""
    return f"[reward-source] {name} on GPU 0 (95 s): {' '.join(cmd[2:])}\n"


def test_horizons_pool_each_arms_paid_success_and_mixed_groups_by_the_runs_own_commands(tmp_path):
    """horizons: each work dir's decisions and actions come from its runs' commands (commands.json, or for an older
    work dir the launcher's lines beside it); what reality paid is pooled over every step (a ground-truth step's
    own trajectories where recorded), the ratio is exec's rate over gt's, the mixed groups are medians of counts,
    the detector's figures are exec's, and the rows come by actions whatever order the work dirs are given in."""
    from sword_jax.rl.env_rollout import wilson_interval

    def setting(horizon):
        args = _args(tmp_path, seeds="0")
        args.horizon, args.actions_per_decision, args.rollout_batch = horizon, 8, 4  # 4 groups x 8 a step
        return rs.run_commands(args)

    # 2 decisions of 8: the commands recorded by run (merged: the ground-truth arm's, then exec's)
    h2 = tmp_path / "hz" / "h2"
    commands = setting(2)
    h2.mkdir(parents=True)
    rs.record_commands(str(h2), {"gt_s0": commands["gt_s0"]})
    rs.record_commands(str(h2), {"exec_s0": commands["exec_s0"], "det_s0": commands["det_s0"]})
    _curve(h2 / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5)],
           [{"step": 1, "rollout_success": 0.25, "trajectories_sampled": 32, "mixed_fraction": 0.5},
            {"step": 2, "rollout_success": 0.375, "trajectories_sampled": 32, "mixed_fraction": 0.75},
            {"step": 3, "rollout_success": 0.5, "trajectories_sampled": 64, "mixed_fraction": 0.25}])  # 2 rounds
    _curve(h2 / "exec_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5)],
           [{"step": 1, "success_rate": 0.125, "sampled_mixed_fraction": 0.25, "kept_fraction": 0.25,
             "detector_success": 0.25, "detector_agreement": 0.75, "detector_false_success": 0.2},
            {"step": 2, "success_rate": 0.25, "sampled_mixed_fraction": 0.5, "kept_fraction": 0.25,
             "detector_success": 0.125, "detector_agreement": 0.875, "detector_false_success": 0.0}])
    _curve(h2 / "det_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5)], [{"step": 1, "success_rate": 0.9, "kept_fraction": 1}])
    # 1 decision of 8: a work dir from before commands.json, its launcher's output beside it
    h1 = tmp_path / "hz" / "h1"
    commands = setting(1)
    (tmp_path / "hz" / "h1.out").write_text("[reward-source] the runs start as ...\n" + "".join(
        _launch_line(n, commands[n]) for n in ("gt_s0", "exec_s0")) + "run rc 0\n")
    _curve(h1 / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5)],
           [{"step": 1, "rollout_success": 0.5, "mixed_fraction": 0.5},
            {"step": 2, "rollout_success": 0.625, "mixed_fraction": 1.0}])
    _curve(h1 / "exec_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5)],
           [{"step": s, "success_rate": paid, "kept_fraction": mixed}  # a run without the sampled share
            for s, paid, mixed in ((1, 0.5, 0.75), (2, 0.25, 0.5), (3, 0.375, 0.25))])

    out = tmp_path / "record"
    result = rs.main(["horizons", "--workdirs", f"{h2},{h1}/", "--out", str(out), "--title", "t"])
    assert json.loads((out / "horizons.json").read_text()) == {k: v for k, v in result.items() if k != "figure"}
    assert (out / "horizons.png").stat().st_size > 0 and result["title"] == "t"
    assert [r["workdir"] for r in result["rows"]] == [str(h1), str(h2)]
    first, second = result["rows"]
    assert [r["actions"] for r in result["rows"]] == [8, 16] and (first["decisions"], second["decisions"]) == (1, 2)
    assert first["source"] == str(tmp_path / "hz" / "h1.out") and second["source"] == str(h2 / "commands.json")
    for r in result["rows"]:
        assert (r["actions_per_decision"], r["group_size"], r["groups_per_step"]) == (8, 8, 4)
    gt, ex = second["arms"]["gt"], second["arms"]["exec"]
    assert set(second["arms"]) == {"gt", "exec"} and gt["runs"] == ["gt_s0"] and ex["runs"] == ["exec_s0"]
    assert gt["paid_success"] == {"successes": 52, "rate": 52 / 128, "of": 128,
                                  "ci95": pytest.approx(list(wilson_interval(52, 128)))}
    assert ex["paid_success"]["successes"] == 12 and ex["paid_success"]["of"] == 64  # 2 steps of 4 x 8
    assert second["exec_over_gt"] == pytest.approx((12 / 64) / (52 / 128))
    assert (gt["steps"], gt["mixed_groups_median"], gt["mixed_share_median"]) == (3, 2, 0.5)  # 2, 3, 2 of 4, 4, 8
    assert (ex["mixed_groups_median"], ex["mixed_share_median"]) == (1.5, 0.375)  # the sampled share, not the kept
    # 0.25 - 0.2 x (1 - 0.125) and 0.125 of the detector's 0.375 were real successes
    assert ex["detector"] == {"success": 0.1875, "agreement": 0.8125, "false_success": pytest.approx(0.1),
                              "precision": pytest.approx(0.2 / 0.375)} and "detector" not in gt
    gt, ex = first["arms"]["gt"], first["arms"]["exec"]
    assert gt["paid_success"]["successes"] == 36 and gt["paid_success"]["of"] == 64
    assert ex["paid_success"]["successes"] == 36 and ex["paid_success"]["of"] == 96
    assert first["exec_over_gt"] == pytest.approx(2 / 3)
    assert (gt["mixed_groups_median"], ex["mixed_groups_median"], ex["steps"]) == (3, 2, 3)
    series = result["figure"]
    assert series["gt"]["actions"] == [8, 16] and series["gt"]["paid"] == [36 / 64, 52 / 128]
    assert series["exec"]["mixed_share"] == [0.5, 0.375]
    assert series["exec_over_gt"]["ratio"] == pytest.approx([2 / 3, (12 / 64) / (52 / 128)])


def test_horizons_refuse_a_work_dir_that_does_not_record_its_runs_commands(tmp_path):
    """A work dir whose runs' commands are nowhere (no commands.json, no launcher line), whose ground-truth and
    exec runs were started at different horizons, or that is not there, is refused by its name."""
    bare = tmp_path / "h3"
    _curve(bare / "exec_s0" / "rl" / "grpo", [_point(0, 0.7, 0.5)], [{"step": 1, "success_rate": 0.5,
                                                                       "kept_fraction": 0.5}])
    (bare / "exec_s0.log").write_text("eval step 0: MJX success 0.7\n")  # the run's own log names no horizon
    with pytest.raises(SystemExit, match=f"{bare} records no exec run's command, so its horizon is unknown"):
        rs.main(["horizons", "--workdirs", str(bare), "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()
    args = _args(tmp_path, seeds="0", arms=("gt", "exec"))
    twelve = rs.run_commands(args)
    args.horizon = 2
    rs.record_commands(str(bare), {"gt_s0": twelve["gt_s0"], "exec_s0": rs.run_commands(args)["exec_s0"]})
    with pytest.raises(SystemExit, match=f"{bare}: its runs' commands in .*commands.json set different rollouts"):
        rs.horizon_row(str(bare))
    with pytest.raises(SystemExit, match="nowhere: no such folder"):
        rs.horizon_row(str(tmp_path / "nowhere"))
    with pytest.raises(SystemExit, match="horizons needs --workdirs"):
        rs.main(["horizons", "--out", str(tmp_path / "o")])


def test_the_detectors_separation_is_averaged_over_the_steps_where_both_outcomes_occurred():
    """detector_figures: the AUC and the bounded threshold's figures that an executed step records are means over
    the steps that hold a number (NaN: a step without one of the outcomes, or with nothing paid); rows from before
    they were recorded give the four verdict figures alone."""
    nan = float("nan")
    base = {"success_rate": 0.5, "detector_success": 0.5, "detector_agreement": 0.5, "detector_false_success": 0.25}
    rows = [dict(base, detector_auc=0.75, detector_threshold_bounded=0.5, detector_recall_bounded=0.5,
                 detector_precision_bounded=1.0),
            dict(base, detector_auc=0.5, detector_threshold_bounded=0.25, detector_recall_bounded=0.25,
                 detector_precision_bounded=nan),
            dict(base, detector_auc=nan, detector_threshold_bounded=nan, detector_recall_bounded=nan,
                 detector_precision_bounded=nan)]
    out = rs.detector_figures(rows)
    assert out["auc"] == pytest.approx(0.625) and out["threshold_bounded"] == pytest.approx(0.375)
    assert out["recall_bounded"] == pytest.approx(0.375) and out["precision_bounded"] == 1.0
    assert set(rs.detector_figures([base])) == {"success", "agreement", "false_success", "precision"}


def test_a_run_evaluated_as_trained_has_that_gain_and_curve_and_others_none(tmp_path, capsys, monkeypatch):
    """A run whose evaluations also ran the sampled policy as its training rollouts execute it has that policy's
    gain and curve beside the others (and its printed line says so); a run without them has None and no curve
    entry. The arm lists the gains of its runs that have one; --record writes the ground-truth arm's smallest as
    policy_grpo_ground_truth_as_trained_small, and no world-model entry without an exec arm."""
    _curve(tmp_path / "gt" / "s0" / rs.GT_DIR, [_point(0, 0.7, 0.5, 0.5, 0.3), _point(20, 0.72, 0.5, 0.5, 0.4)],
           [{"rollout_success": 0.4, "trajectories_sampled": 512.0, "mixed_fraction": 0.8}] * 20)
    _curve(tmp_path / "gt" / "s1" / rs.GT_DIR, [_point(0, 0.7, 0.5), _point(20, 0.72, 0.55)],
           [{"rollout_success": 0.4, "trajectories_sampled": 512.0, "mixed_fraction": 0.8}] * 20)
    summary = rs.summarize(str(tmp_path))
    runs = summary["runs"]
    trained, plain = runs["gt_s0"], runs["gt_s1"]
    gt = summary["arms"]["gt"]
    assert gt["as_trained_gain_per_seed"] == {0: pytest.approx(0.1)} and gt["as_trained_smallest"] == pytest.approx(0.1)
    monkeypatch.setattr(rs.common, "device_name", lambda: "cpu")
    entries = rs.results_entries(summary, str(tmp_path), data="d")
    assert set(entries) == {"policy_grpo_ground_truth_as_trained_small"}
    entry = entries["policy_grpo_ground_truth_as_trained_small"]
    assert entry["value"] == pytest.approx(0.1) and entry["arms"]["gt"]["smallest"] == pytest.approx(0.0)
    assert trained["sampled_as_trained"]["gain"] == pytest.approx(0.1)
    assert trained["sampled"]["gain"] == pytest.approx(0.0)  # a different policy's gain
    assert [c["sampled_as_trained"] for c in trained["curve"]] == [0.3, 0.4]
    assert plain["sampled_as_trained"] is None and all("sampled_as_trained" not in c for c in plain["curve"])
    rs.print_runs({"runs": runs})
    lines = capsys.readouterr().out.splitlines()
    assert "sampled as trained 0.300 -> 0.400 (+0.100)" in lines[0] and "as trained" not in lines[1]
