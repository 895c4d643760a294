"""benchmarks.bench_grpo_value: the two arms' commands and GPUs, the summary of the runs it left, and what it
refuses."""

import json
import os

import pytest

import configs
from benchmarks import bench_grpo_value as gv
from benchmarks.bench_grpo_reward_source import RECIPE
from tests.test_bench_grpo_reward_source import _curve, _point


def _rl_of(cmd):
    """The RL config a run's command line parses into (it validates)."""
    return configs.from_argv(["--config", "sword:small", *[c for c in cmd if c.startswith("--rl.")]])[0].rl


def test_the_arms_differ_in_what_pays_a_rollout_cut_at_its_horizon(tmp_path):
    args = gv.parse(["run", "--workdir", str(tmp_path), "--policy", "/p/policy_d50.npz", "--seeds", "0,1",
                     "--gpus", "0,1", "--horizon", "2", "--value-episodes", "256"])
    commands = gv.run_commands(args)
    assert sorted(commands) == ["success_s0", "success_s1", "value_s0", "value_s1"]
    value, success = commands["value_s1"], commands["success_s1"]
    assert value[2:4] == ["benchmarks.bench_policy", "grpo"] and value[value.index("--seed") + 1] == "1"
    for flag in gv.SETTING + ("--rl.imagined.max_chunks=2", "--rl.value.episodes=256", "--rl.grpo.rollout_batch=64"):
        assert flag in value and flag in success, flag
    assert not any(f.startswith("--rl.imagined.max_chunks=") and f != "--rl.imagined.max_chunks=2" for f in value)
    assert [f for f in RECIPE if not f.startswith("--rl.imagined.max_chunks=")] == [
        f for f in value if f in RECIPE and not f.startswith("--rl.imagined.max_chunks=")]
    assert "--rl.value.bootstrap=true" in value and "--rl.value.bootstrap=false" in success
    swap = {"--rl.value.bootstrap=true": "--rl.value.bootstrap=false"}
    assert [swap.get(c, c).replace(os.path.join("value", "s1"), os.path.join("success", "s1")) for c in value] == success
    # the command line parses into a config that validates, for either arm
    for cmd in (value, success):
        assert _rl_of(cmd).env.starts == "branch" and _rl_of(cmd).value.episodes == 256
    assert not any("scale_by_std" in c for c in value)
    centred = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--arms", "value",
                                        "--scale-by-std", "false"]))
    assert "--rl.grpo.scale_by_std=false" in centred["value_s0"] and sorted(centred) == ["value_s0"]
    opened = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--branch-starts", "open"]))
    assert all("--rl.value.branch_starts=open" in cmd for cmd in opened.values())
    assert not any("branch_starts" in c for c in value) and not any("min_mixed_groups" in c for c in value)
    control = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--arms", "success,shuffled"]))
    shuffled = control["shuffled_s0"]
    assert "--rl.grpo.shuffle_returns=true" in shuffled and "--rl.value.bootstrap=false" in shuffled
    assert [c for c in shuffled if c != "--rl.grpo.shuffle_returns=true"] == [
        c.replace(os.path.join("success", "s0"), os.path.join("shuffled", "s0")) for c in control["success_s0"]]
    assert _rl_of(shuffled).grpo.shuffle_returns
    skipping = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--min-mixed-groups", "8"]))
    assert all("--rl.grpo.min_mixed_groups=8" in cmd for cmd in skipping.values())
    assert not any("kl_coef" in c for c in value)
    assert "--rl.grpo.learning_rate=1e-4" in value  # the recipe's
    slow = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--learning-rate", "2e-5"]))
    for cmd in slow.values():
        assert "--rl.grpo.learning_rate=2e-05" in cmd and not any(c == "--rl.grpo.learning_rate=1e-4" for c in cmd)
        assert _rl_of(cmd).grpo.learning_rate == 2e-5
    anchored = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--kl-coef", "0.05"]))
    for cmd in anchored.values():
        assert "--rl.grpo.kl_coef=0.05" in cmd
        assert _rl_of(cmd).grpo.kl_coef == 0.05
    assert gv.placement(list(commands), ["0", "1"]) == {"value_s0": "0", "success_s0": "1", "value_s1": "0",
                                                         "success_s1": "1"}


def test_runs_from_rest_keep_the_cut_and_may_fit_no_value(tmp_path):
    """--branch-starts rest: whole-episode GRPO's starts with the short rollout's horizon and execution."""
    rest = gv.run_commands(gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--arms", "success",
                                     "--branch-starts", "rest", "--horizon", "12", "--value-episodes", "0"]))
    cmd = rest["success_s0"]
    assert "--rl.env.starts=rest" in cmd and "--rl.env.starts=branch" not in cmd and "--rl.value.episodes=0" in cmd
    assert not any("branch_starts" in c for c in cmd)
    rl = _rl_of(cmd)
    assert rl.env.starts == "rest" and rl.value.episodes == 0 and rl.imagined.max_chunks == 12
    from benchmarks.bench_policy import grpo_dir

    assert grpo_dir(rl) == gv.GRPO_DIRS["rest"]
    with pytest.raises(SystemExit, match="or 0 with --branch-starts rest and no value arm"):
        gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--branch-starts", "rest",
                  "--value-episodes", "0"])  # the value arm needs a value
    with pytest.raises(SystemExit, match="--value-episodes >= 2"):
        gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", "--arms", "success", "--value-episodes", "0"])


def _value_record(path, brier):
    os.makedirs(os.path.join(path, "value"), exist_ok=True)
    with open(os.path.join(path, "value", "value.json"), "w") as f:
        json.dump({"real_episodes": 512, "episode_success": 0.45, "decisions": 20000,
                   "held_out": {"brier": brier, "brier_constant": 0.247, "auc": 0.81, "bins": []}}, f)


def test_summary_reads_each_run_its_payments_and_its_value(tmp_path, capsys):
    base = str(tmp_path)
    for arm, end in (("value", 0.60), ("success", 0.50)):
        grpo = os.path.join(base, arm, "s0", gv.GRPO_DIRS["branch"])
        history = [{"step": s, "rollout_success": 0.3 + 0.01 * s, "mixed_fraction": 0.9 if arm == "value" else 0.2}
                   for s in range(1, 11)]
        if arm == "value":
            for h in history:
                h.update(terminal_value=0.4 + 0.01 * h["step"], truncated_fraction=0.7, success_advantage_share=0.25)
        _curve(grpo, [_point(0, 0.7, 0.5, 0.45), _point(10, 0.7, 0.55, end)], history)
        _value_record(grpo, 0.15)
    os.makedirs(os.path.join(base, "value", "s1", gv.GRPO_DIRS["branch"]))  # a run that left no curve is not a run
    summary = gv.summarize(base)
    assert sorted(summary["runs"]) == ["success_s0", "value_s0"]
    assert summary["arms"]["success"]["label"] == "branched, paid success alone"
    assert {r["starts"] for r in summary["runs"].values()} == {"branch"}
    run = summary["runs"]["value_s0"]
    assert run["sampled_proprio_masked"]["gain"] == pytest.approx(0.15)
    assert run["terminal_value"] == {"first": pytest.approx(0.43), "last": pytest.approx(0.48)}
    assert run["truncated_fraction"] == pytest.approx(0.7) and run["value"]["held_out_brier"] == 0.15
    assert "terminal_value" not in summary["runs"]["success_s0"] and run["success_advantage_share"] == 0.25
    assert "success_advantage_share" not in summary["runs"]["success_s0"]  # a run from before it was logged
    assert summary["arms"]["value"]["smallest"] == pytest.approx(0.15)
    assert summary["arms"]["success"]["masked_gain_per_seed"] == {0: pytest.approx(0.05)}
    entries = gv.results_entries(summary, base, data="x.json")
    assert entries["policy_grpo_branched_value_small"]["value"] == pytest.approx(0.15)
    open_entry = gv.results_entries(summary, base, data="x.json", record_as="open")  # open starts: the success arm
    assert list(open_entry) == ["policy_grpo_branched_open_small"]
    assert open_entry["policy_grpo_branched_open_small"]["value"] == pytest.approx(0.05)
    wide = gv.results_entries(summary, base, data="x.json", record_as="open_b256")  # 256 starts a step, same arm
    assert list(wide) == ["policy_grpo_branched_open_b256_small"]
    assert wide["policy_grpo_branched_open_b256_small"]["value"] == pytest.approx(0.05)
    widest = gv.results_entries(summary, base, data="x.json", record_as="open_b1024")  # 1,024 starts a step
    assert list(widest) == ["policy_grpo_branched_open_b1024_small"]
    longer = gv.results_entries(summary, base, data="x.json", record_as="open_h12")  # 12-decision rollouts
    assert list(longer) == ["policy_grpo_branched_open_h12_small"]
    assert list(gv.results_entries(summary, base, data="x.json", record_as="rest_h12")) == ["policy_grpo_rest_h12_small"]
    assert list(gv.results_entries(summary, base, data="x.json", record_as="rest_whole")) == [
        "policy_grpo_rest_whole_small"]
    # runs from rest (their own work dir) are found and labelled as such; they left no value
    rested = os.path.join(base, "rested")
    _curve(os.path.join(rested, "success", "s0", gv.GRPO_DIRS["rest"]),
           [_point(0, 0.7, 0.5, 0.45), _point(10, 0.7, 0.55, 0.52)], [{"step": 1, "rollout_success": 0.2}])
    from_rest = gv.summarize(rested)
    assert from_rest["runs"]["success_s0"]["starts"] == "rest" and from_rest["runs"]["success_s0"]["value"] is None
    assert from_rest["arms"]["success"]["label"] == "from rest, cut at the horizon, paid success alone"
    anchored = gv.results_entries(summary, base, data="x.json", record_as="open_kl")  # anchored by a KL term
    assert list(anchored) == ["policy_grpo_branched_open_kl_small"]
    assert "contrasts" not in summary and "contrasts" not in entries["policy_grpo_branched_value_small"]  # no control
    gv.print_runs(summary)
    assert "value paid 0.430 -> 0.480" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no run of the value arm"):
        gv.results_entries({"arms": {}, "runs": {}}, base, data="x")


@pytest.mark.parametrize("argv,message", [
    (["run", "--arms", "value,full"], "--arms must name"),
    (["run", "--policy", "p.npz", "--rollout-batch", "30"], "multiple of 4"),
    (["run", "--policy", "p.npz", "--value-episodes", "1"], "--value-episodes >= 2"),
    (["run", "--policy", "p.npz", "--horizon", "0"], "--horizon"),
    (["run"], "needs --policy"),
    (["run", "--policy", "p.npz", "--min-mixed-groups", "65"], "--min-mixed-groups"),
    (["run", "--policy", "p.npz", "--kl-coef", "-0.1"], "--kl-coef"),
    (["run", "--policy", "p.npz", "--kl-coef", "nan"], "--kl-coef"),
    (["run", "--policy", "p.npz", "--learning-rate=-1e-4"], "--learning-rate"),
])
def test_bad_command_lines_are_refused_by_name(tmp_path, argv, message):
    with pytest.raises(SystemExit, match=message):
        gv.parse([*argv[:1], "--workdir", str(tmp_path), *argv[1:]])


@pytest.mark.parametrize("flag", ["--deadline-s", "--grace-s"])
@pytest.mark.parametrize("value", ["-1", "nan", "soon"])
def test_deadline_and_grace_are_seconds_at_least_zero(tmp_path, flag, value):
    from sword_jax.cli import UsageError

    with pytest.raises(UsageError, match=rf"argument {flag}: must be a finite number of seconds >= 0, got '{value}'"):
        gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", f"{flag}={value}"])
    assert gv.parse(["run", "--workdir", str(tmp_path), "--policy", "p.npz", f"{flag}=30"]).__dict__[
        flag[2:].replace("-", "_")] == 30.0


def test_an_arm_is_set_against_the_noise_only_control_at_the_seeds_both_ran():
    def run(arm, seed, gain, half, greedy=True):
        g = {"start": 0.5, "end": 0.5 + gain, "gain": gain, "ci95": [gain - half, gain + half]}
        return {"arm": arm, "seed": seed, "steps": 30 if arm == "success" else 20, "sampled_proprio_masked": g,
                "sampled": g, "greedy": g if greedy else None}

    runs = {"success_s0": run("success", 0, 0.05, 0.05), "shuffled_s0": run("shuffled", 0, -0.05, 0.05),
            "success_s1": run("success", 1, 0.02, 0.05), "shuffled_s1": run("shuffled", 1, -0.08, 0.05, greedy=False),
            "success_s2": run("success", 2, 0.30, 0.05)}  # no control at seed 2: left out
    c = gv.contrast(runs, "success")
    assert c["seeds"] == [0, 1] and c["control"] == "shuffled" and c["steps"] == 20
    masked = c["sampled_proprio_masked"]
    assert masked["per_seed"] == {0: pytest.approx(0.10), 1: pytest.approx(0.10)}
    # four independent gains of standard error 0.05 / 1.96 each: the mean of two differences has half-width 0.05
    assert masked["mean"] == pytest.approx(0.10) and masked["ci95"] == [pytest.approx(0.05), pytest.approx(0.15)]
    assert "greedy" not in c  # one run has no greedy evaluation
    assert gv.contrast(runs, "value") is None
    assert gv.contrast({"success_s0": runs["success_s0"]}, "success") is None
