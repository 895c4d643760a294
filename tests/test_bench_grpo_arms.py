"""benchmarks.bench_grpo_arms: the arms' commands and the greedy/sampled summary it writes from their files."""

import dataclasses
import json
import sys
from types import SimpleNamespace

import pytest

import configs
from benchmarks import bench_grpo_arms as arms
from benchmarks import bench_policy
from sword_jax.rl.env_rollout import difference_interval


def _point(step, successes, episodes=500, sampled=None):
    rate = successes / episodes
    point = {"step": step, "mean": rate, "successes": successes, "episodes": episodes, "ci95": [rate - 0.04, rate + 0.04]}
    if sampled is not None:
        point["sampled"] = {"temperature": 0.7, "mean": sampled / episodes, "successes": sampled, "episodes": episodes,
                            "ci95": [0.0, 1.0], "per_task": {}}
    return point


def _arm(root, name, points, history=None):
    grpo_dir = root / name / "rl" / "grpo"
    grpo_dir.mkdir(parents=True)
    (grpo_dir / "success_curve.json").write_text(json.dumps({"label": "x", "points": points}))
    if history is not None:
        (grpo_dir / "train_history.jsonl").write_text("".join(json.dumps(h) + "\n" for h in history))
    return str(root / name)


def test_summary_has_greedy_and_sampled_gains_and_rollout_blocks(tmp_path):
    history = [{"step": i + 1, "rollout_success": 0.1 if i < 10 else 0.3, "behaviour_nll": 2.0 - 0.01 * i}
               for i in range(12)]
    a = _arm(tmp_path, "a", [_point(0, 200, sampled=100), _point(50, 250, sampled=150), _point(100, 300, sampled=200)],
             history)
    b = _arm(tmp_path, "b", [_point(0, 200), _point(100, 190)])  # no sampled evaluations, no history
    summary = arms.summarize({"a": a, "b": b, "c": str(tmp_path / "never_ran")})
    assert summary["missing"] == ["c"]
    sa, sb = summary["arms"]["a"], summary["arms"]["b"]
    assert [p["success"] for p in sa["greedy"]] == [0.4, 0.5, 0.6]
    assert sa["greedy_gain"] == pytest.approx(0.2) and sa["sampled_gain"] == pytest.approx(0.2)
    assert sa["temperature"] == 0.7
    # first vs last point, the project's Newcombe interval of a difference of two proportions
    assert sa["greedy_gain_ci95"] == [round(x, 4) for x in difference_interval(200, 500, 300, 500)]
    assert sa["sampled_gain_ci95"] == [round(x, 4) for x in difference_interval(100, 500, 200, 500)]
    assert sa["rollout_success_per_10_steps"] == [0.1, 0.3]
    assert sa["behaviour_nll_per_10_steps"] == [round(sum(2.0 - 0.01 * i for i in range(10)) / 10, 4),
                                                round((2.0 - 0.1 + 2.0 - 0.11) / 2, 4)]
    assert "sampled" not in sb and sb["greedy_gain"] == pytest.approx(-0.02) and "rollout_success_per_10_steps" not in sb
    arms.write(summary, str(tmp_path / "out" / "arms"))
    assert json.loads((tmp_path / "out" / "arms.json").read_text())["arms"]["a"]["greedy_gain"] == sa["greedy_gain"]
    assert (tmp_path / "out" / "arms.png").stat().st_size > 0


def test_summarize_mode_of_the_command_line(tmp_path, capsys):
    a = _arm(tmp_path, "a", [_point(0, 200, sampled=100), _point(50, 260, sampled=150)])
    summary = arms.main(["--out", str(tmp_path / "s"), "--summarize", f"t07={a}"])
    assert summary["arms"]["t07"]["greedy_gain"] == pytest.approx(0.12)
    assert "t07: greedy 0.400 -> 0.520" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="NAME=WORKDIR"):
        arms.main(["--out", str(tmp_path / "s"), "--summarize", a])


def test_every_arm_evaluates_both_policies_from_the_same_start_in_its_own_workdir():
    args = SimpleNamespace(out="runs/x/arms", config="cache_ablation:small-linear-direct-all", seed=0,
                           policy="runs/p/rl/policy_sft", arm_workers=7, steps=100, eval_every=50, eval_episodes=50)
    specs = [arms.parse_arm("t10:"), arms.parse_arm("t07: --rl.grpo.temperature=0.7 --seed 1")]
    cmds = arms.commands(args, specs, ["--rl.grpo.learning_rate=2e-4"])
    assert list(cmds) == ["t10", "t07"]
    for name, cmd in cmds.items():
        assert cmd[:3] == [sys.executable, "-m", "train.grpo"]
        assert cmd[cmd.index("--policy") + 1] == "runs/p/rl/policy_sft"
        assert cmd[cmd.index("--simulator") + 1] == "env"
        assert "--rl.grpo.eval_sampled=true" in cmd and "--rl.grpo.learning_rate=2e-4" in cmd
        assert cmd[-2:] == ["--workdir", f"runs/x/{name}"]
    t07 = cmds["t07"]
    assert "--rl.grpo.temperature=0.7" in t07
    assert t07.index("--seed", t07.index("--rl.grpo.eval_sampled=true")) > 0  # the arm's own seed comes last, argparse keeps it
    with pytest.raises(ValueError, match="names must differ"):
        arms.commands(args, [arms.parse_arm("a:"), arms.parse_arm("a: --seed 1")], [])


@pytest.mark.parametrize("spec", ["no colon", ": --seed 1", "bad name: --seed 1"])
def test_bad_arm_specs_are_refused_with_the_expected_form(spec):
    with pytest.raises(ValueError, match="'name: overrides'"):
        arms.parse_arm(spec)


def test_command_line_refuses_missing_policy_and_plain_arguments(tmp_path):
    with pytest.raises(SystemExit, match="--policy"):
        arms.main(["--out", str(tmp_path / "s"), "--arm", "a:"])
    with pytest.raises(SystemExit, match="dotted config override"):
        arms.main(["--out", str(tmp_path / "s"), "--policy", "p", "--arm", "a:", "stray"])
    with pytest.raises(SystemExit, match="'name: overrides'"):
        arms.main(["--out", str(tmp_path / "s"), "--policy", "p", "--arm", "nocolon"])


def test_seeds_stage_reports_every_seed_the_repeat_and_records_the_smallest_gain(tmp_path, monkeypatch):
    """bench_policy seeds: per-seed gains with Newcombe intervals, the repeat's difference at its step, the
    step costs from the histories, one figure, and the latest.json record of the smallest gain."""
    recorded = {}
    monkeypatch.setattr(bench_policy.common, "merge_results", recorded.update)
    history = [{"trajectories_sampled": 512.0 * (1 + i % 2), "env_steps": 9e4, "step_seconds": 20.0,
                "clip_fraction": 0.05} for i in range(4)]
    dirs = {name: _arm(tmp_path, name, points, history) for name, points in {
        "s0": [_point(0, 350), _point(50, 420), _point(100, 450)],
        "s1": [_point(0, 340), _point(50, 400), _point(100, 430, sampled=300)],
        "s0b": [_point(0, 350), _point(50, 410), _point(100, 440)]}.items()}
    grpo_dir = {k: v + "/rl/grpo" for k, v in dirs.items()}
    args = SimpleNamespace(runs=",".join([grpo_dir["s0"], grpo_dir["s1"]]), repeat=f"{grpo_dir['s0']},{grpo_dir['s0b']}",
                           repeat_step=50, out=str(tmp_path), record=True)
    summary = bench_policy.run_seeds(args)
    gains = {d: r["gain"] for d, r in summary["per_seed"].items()}
    assert gains[grpo_dir["s0"]] == pytest.approx(0.2) and gains[grpo_dir["s1"]] == pytest.approx(0.18)
    assert summary["min_gain"] == pytest.approx(0.18) and summary["repeat"]["difference"] == pytest.approx(0.02)
    s1 = summary["per_seed"][grpo_dir["s1"]]
    assert s1["ci95"] == list(difference_interval(340, 500, 430, 500)) and s1["sampled_curve"] == [[100, 0.6]]
    assert s1["rollouts_per_step"] == 768.0 and s1["seconds_per_grpo_step"] == 20.0
    record = recorded["policy_grpo_ground_truth_gain_small"]
    assert record["value"] == pytest.approx(0.18) and set(record["per_seed"]) == {grpo_dir["s0"], grpo_dir["s1"]}
    assert record["repeat"]["step"] == 50 and record["rollouts_per_step"] == 768.0
    assert (tmp_path / "grpo_ground_truth_seeds.png").stat().st_size > 0
    with pytest.raises(SystemExit, match="does not exist"):
        bench_policy.run_seeds(SimpleNamespace(runs=str(tmp_path / "nope"), repeat="", repeat_step=50,
                                               out=str(tmp_path), record=False))


def test_seeds_stage_with_the_sampled_policy_deployed(tmp_path, monkeypatch):
    """--deployed sampled: the headline gains, the repeat and the record are the sampled policy's; both
    policies' gains and the better-of-the-two gain (greedy at the start, sampled at the end here) stay beside."""
    recorded = {}
    monkeypatch.setattr(bench_policy.common, "merge_results", recorded.update)
    dirs = {name: _arm(tmp_path, name, points) + "/rl/grpo" for name, points in {
        "s0": [_point(0, 350, sampled=250), _point(50, 340, sampled=380), _point(70, 345, sampled=390)],
        "s1": [_point(0, 355, sampled=270), _point(50, 400, sampled=390), _point(70, 398, sampled=392)],
        "s0b": [_point(0, 340, sampled=248), _point(50, 310, sampled=375)]}.items()}
    args = SimpleNamespace(runs=f"{dirs['s0']},{dirs['s1']}", repeat=f"{dirs['s0']},{dirs['s0b']}", repeat_step=50,
                           out=str(tmp_path), record=True, deployed="sampled")
    summary = bench_policy.run_seeds(args)
    s0, s1 = summary["per_seed"][dirs["s0"]], summary["per_seed"][dirs["s1"]]
    assert s0["gain"] == pytest.approx(0.28) and s0["greedy"]["gain"] == pytest.approx(-0.01)
    assert s0["ci95"] == list(difference_interval(250, 500, 390, 500))
    assert s0["best"]["gain"] == pytest.approx(0.08) and (s0["best"]["start_policy"], s0["best"]["end_policy"]) == (
        "greedy", "sampled")
    assert s1["best"]["end_policy"] == "greedy" and s1["best"]["gain"] == pytest.approx(0.086)
    assert summary["min_gain"] == pytest.approx(0.244) and summary["greedy_min_gain"] == pytest.approx(-0.01)
    assert summary["best_min_gain"] == pytest.approx(0.08) and summary["temperature"] == 0.7
    assert summary["repeat"]["difference"] == pytest.approx(0.01) and summary["repeat"]["policy"] == "sampled"
    assert set(summary["curves"]) == set(dirs.values()) and len(summary["curves"][dirs["s0b"]]["sampled"]) == 2
    record = recorded["policy_grpo_ground_truth_gain_small"]
    assert record["value"] == pytest.approx(0.244) and record["deployed"] == "sampled"
    assert "sampled at T=0.7" in record["value_is"] and record["best_min_gain"] == pytest.approx(0.08)
    assert (tmp_path / "grpo_ground_truth_seeds.png").stat().st_size > 0
    # rl.env.proprio=missing: the masked sampled policy (the trained mode) gets its gain and its own panel
    masked = [_point(0, 350, sampled=250), _point(20, 360, sampled=290)]
    masked[0]["sampled_proprio_masked"] = dict(masked[0]["sampled"], mean=0.45, successes=225)
    masked[1]["sampled_proprio_masked"] = dict(masked[1]["sampled"], mean=0.55, successes=275)
    m_dir = _arm(tmp_path / "m", "s0", masked) + "/rl/grpo"
    m_summary = bench_policy.run_seeds(SimpleNamespace(runs=m_dir, repeat="", repeat_step=50, out=str(tmp_path / "m"),
                                                       record=True, deployed="sampled", record_as="policy_grpo_x",
                                                       note="an arm", device="NVIDIA H200 x2"))
    other = recorded["policy_grpo_x"]  # another setting's record: its own key, no target, where the runs ran
    assert other["target"] is None and other["device"] == "NVIDIA H200 x2" and other["note"] == "an arm"
    assert other["value"] == pytest.approx(0.08) and recorded["policy_grpo_ground_truth_gain_small"] is record
    m_entry = m_summary["per_seed"][m_dir]
    assert m_entry["sampled_proprio_masked"]["gain"] == pytest.approx(0.1) and m_entry["gain"] == pytest.approx(0.08)
    assert [p[1] for p in m_summary["curves"][m_dir]["sampled_proprio_masked"]] == [0.45, 0.55]
    assert s0["sampled_proprio_masked"] is None  # not evaluated: no gain, no panel
    (tmp_path / "s2" / "rl" / "grpo").mkdir(parents=True)
    (tmp_path / "s2" / "rl" / "grpo" / "success_curve.json").write_text(json.dumps({"points": [_point(0, 1), _point(5, 2)]}))
    with pytest.raises(SystemExit, match="no sampled figure"):
        bench_policy.run_seeds(SimpleNamespace(**{**vars(args), "runs": str(tmp_path / "s2" / "rl" / "grpo"),
                                                  "repeat": "", "record": False}))


@pytest.mark.slow  # ~60 s of CPU (the C engine's renderer and the update compile); the loop's part is below
def test_grpo_stage_runs_from_a_saved_npz_policy(tmp_path):
    """The documented ground-truth command from a saved policy: parameters arrive from the .npz as numpy
    arrays, which the GRPO loop places on the device before its first step (it once read their sharding)."""
    import configs
    from sword_jax.rl.policy import build_policy

    cfg = configs.get("sword:tiny")
    _, params = build_policy(cfg.rl, seed=0)
    path = str(tmp_path / "policy.npz")
    bench_policy.save_npz(path, params)
    out = tmp_path / "out"
    bench_policy.main(["grpo", "--config", "sword:tiny", "--out", str(out), "--policy", path, "--eval-episodes", "1",
                       "--rl.grpo.steps=1", "--rl.grpo.eval_every=1", "--sim.max_steps=4", "--rl.grpo.rollout_batch=1",
                       "--rl.grpo.group_size=2", "--rl.grpo.minibatches=2"])
    result = json.loads((out / "grpo_env_results.json").read_text())
    assert [p["step"] for p in result["curve"]] == [0, 1] and len(result["history"]) == 1
    assert result["history"][0]["updates"] == 2.0


def test_the_grpo_loop_places_host_parameters_before_its_first_step(tmp_path):
    """A state whose parameters are numpy arrays (a policy read from an .npz) starts the GRPO loop: the
    loop puts them on the device (the cause of the documented command's crash, in seconds)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import configs
    from sword_jax.rl import grpo, grpo_loop

    rl = configs.get("sword:tiny").rl
    state = grpo.GRPOState(params={"w": np.ones((3,), np.float32)}, opt_state={"m": np.zeros((3,), np.float32)},
                           ref_params=None, step=np.zeros((), np.int32))

    def step(state, batch, key):
        del batch, key
        return state.replace(params={"w": state.params["w"] * 2.0}, step=state.step + 1), {"loss": jnp.float32(0.0)}

    seen = []
    result, _ = grpo_loop.train_grpo(
        step, state, lambda i: i, key=jax.random.key(0), rl=rl, workdir=str(tmp_path),
        evaluate=lambda done, params: (seen.append(type(params["w"])) or {"mean": 0.0, "per_task": {}}, {}),
        run_id={"x": 1}, progress=lambda point, eta: "", log=lambda *_: None)
    assert seen and all(issubclass(t, jax.Array) for t in seen)
    assert float(result.state.params["w"][0]) == 2.0 ** rl.grpo.steps


def test_grpo_seeds_places_one_run_per_gpu_with_multicast_off_and_passes_the_overrides(tmp_path):
    rl = configs.get("sword:small").rl
    mjx = dataclasses.replace(rl, env=dataclasses.replace(rl.env, backend="mjx"))
    args = SimpleNamespace(seeds="0,1,2", repeat_seed=0, gpus="0,1,2,3", out=str(tmp_path), policy="p.npz",
                           eval_episodes=50, config_name="sword:small", rl=mjx, demos=[])
    commands = bench_policy.seed_commands(args, ["--rl.env.backend=mjx", "--rl.grpo.steps=60"])
    assert [c[0] for c in commands] == [str(tmp_path / n / "grpo_env_mjx") for n in ("s0", "s1", "s2", "s0_repeat")]
    assert [c[2]["CUDA_VISIBLE_DEVICES"] for c in commands] == ["0", "1", "2", "3"]
    assert all(c[2]["NCCL_NVLS_ENABLE"] == "0" and "XLA_PYTHON_CLIENT_MEM_FRACTION" not in c[2] for c in commands)
    cmd = commands[3][1]
    assert cmd[cmd.index("--seed") + 1] == "0" and cmd[-2:] == ["--rl.env.backend=mjx", "--rl.grpo.steps=60"]
    shared = bench_policy.seed_commands(SimpleNamespace(**{**vars(args), "gpus": "0,1"}), [])
    assert [c[2]["CUDA_VISIBLE_DEVICES"] for c in shared] == ["0", "1", "0", "1"]
    assert all(c[2]["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.45" for c in shared)
    with pytest.raises(SystemExit, match="--seeds"):
        bench_policy.seed_commands(SimpleNamespace(**{**vars(args), "seeds": ""}), [])
    # the learned simulator's setting: the work dir names it, and every run reads the demonstrations
    setting = dataclasses.replace(mjx, env=dataclasses.replace(mjx.env, starts="keyframes", proprio="missing"))
    arm = bench_policy.seed_commands(SimpleNamespace(**{**vars(args), "rl": setting, "demos": ["a.hdf5", "b.hdf5"],
                                                        "repeat_seed": None}), [])
    assert [c[0] for c in arm] == [str(tmp_path / n / "grpo_env_proprio_missing_starts_keyframes_mjx")
                                   for n in ("s0", "s1", "s2")]
    assert all("--demos=a.hdf5" in c[1] and "--demos=b.hdf5" in c[1] for c in arm)


def test_execution_modes_of_the_policy_evaluations():
    """--execute: 'ens' ensembles greedy chunks every step, a number executes that many greedy actions per
    chunk, 'sample' runs the trained (sampled) policy every step without ensembling, 'sampleN' N sampled actions
    per chunk; anything else, or N outside 1..chunk_len, is refused."""
    rl = configs.get("sword:tiny").rl
    (ens, ens_greedy), (four, four_greedy), (sample, sample_greedy), (chunked, chunked_greedy) = (
        bench_policy._execution(rl, m) for m in ("ens", "4", "sample", "sample4"))
    assert (ens_greedy, four_greedy, sample_greedy, chunked_greedy) == (True, True, False, False)
    assert (ens.env.execute_steps, ens.env.action_ensemble) == (1, True)
    assert (four.env.execute_steps, four.env.action_ensemble) == (4, False)
    assert (sample.env.execute_steps, sample.env.action_ensemble) == (1, False)
    assert (chunked.env.execute_steps, chunked.env.action_ensemble) == (4, False)
    for bad in ("greedy", "sample0", "samplex", "0", str(rl.chunk_len + 1), f"sample{rl.chunk_len + 1}"):
        with pytest.raises(SystemExit, match=f"'{bad}' is not"):
            bench_policy._execution(rl, bad)


def test_eval_runs_the_policy_as_chunked_grpo_trains_it(tmp_path, monkeypatch):
    """bench_policy eval --execute sample4 --eval-proprio missing: the saved policy sampled, 4 actions of each
    chunk, reading its "missing proprio" input, on the C engine; the file names the proprio mode and every mode."""
    from sword_jax.rl import policy_success
    from sword_jax.rl.policy import build_policy

    cfg = configs.get("sword:tiny")
    _, params = build_policy(cfg.rl, seed=0)
    path = str(tmp_path / "policy.npz")
    bench_policy.save_npz(path, params)
    calls, evaluate = [], policy_success.evaluate_in_sim

    def recording(graphdef, params, rl, **kwargs):
        calls.append((rl.env.execute_steps, rl.env.action_ensemble, kwargs["greedy"], kwargs["proprio"]))
        return evaluate(graphdef, params, rl, **kwargs)

    monkeypatch.setattr(policy_success, "evaluate_in_sim", recording)
    out = tmp_path / "out"
    bench_policy.main(["eval", "--config", "sword:tiny", "--out", str(out), "--policy", path, "--eval-episodes", "1",
                       "--execute", "sample4,ens", "--eval-proprio", "missing", "--sim.max_steps=8"])
    assert calls == [(4, False, False, "missing"), (1, True, True, "missing")]
    result = json.loads((out / "eval_results.json").read_text())
    assert result["eval_proprio"] == "missing" and set(result["eval"]) == {"sample4", "ens"}
    assert all(r["episodes"] == len(cfg.sim.tasks) for r in result["eval"].values())
