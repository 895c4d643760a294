"""benchmarks.bench_grpo_refresh: its command lines, its summary of refreshed runs and of ground-truth GRPO by
real episodes consumed (from the committed ground-truth runs), and its answers to bad arguments."""

import json
import os

import pytest

from benchmarks import bench_grpo_refresh as bench

GROUND_TRUTH = os.path.join(os.path.dirname(os.path.dirname(__file__)), "benchmarks", "results", "policy",
                            "grpo_mjx_seeds_small_4xh100")


class Args:
    workdir, config, policy, pipeline_seed, wovr_config, gpus = "w", "sword:small", "p.npz", 0, "", "0,1"
    seeds, arms, steps, refresh_every, budget, vae_steps, world_model_steps = [0, 1], {"refreshed", "once"}, 50, 5, 900, 10, 20
    deterministic = False


def test_commands_share_one_pipeline_and_differ_in_seed_and_budget():
    runs = bench.grpo_commands(Args, ["--rl.grpo.learning_rate=3e-5", "--sim.max_steps=200"])
    assert sorted(runs) == ["once_seed0", "refreshed_seed0", "refreshed_seed1"]
    flat = {name: " ".join(cmd) for name, cmd in runs.items()}
    assert all("--world-model w/pipeline/world_model" in c and "--policy p.npz" in c for c in flat.values())
    assert "--rl.refresh.budget=900" in flat["refreshed_seed1"] and "--seed 1" in flat["refreshed_seed1"]
    assert "--rl.refresh.budget=64" in flat["once_seed0"] and flat["once_seed0"].endswith("--workdir w/once_seed0")
    # an override comes after the recipe's flags, so it wins
    assert flat["refreshed_seed0"].index("learning_rate=1e-4") < flat["refreshed_seed0"].index("learning_rate=3e-5")
    class WithWovr(Args):
        wovr_config = "cache_ablation:small-wovr"

    both = bench.grpo_commands(WithWovr, [])
    assert sorted(both) == ["once_seed0", "refreshed_seed0", "refreshed_seed1", "wovr_refreshed_seed0",
                            "wovr_refreshed_seed1"]
    wovr = " ".join(both["wovr_refreshed_seed1"])
    assert "--config cache_ablation:small-wovr" in wovr and "--world-model w/pipeline_wovr/world_model" in wovr
    assert bench.pipelines(WithWovr) == {"pipeline": "sword:small", "pipeline_wovr": "cache_ablation:small-wovr"}
    pipe = " ".join(bench.pipeline_command(Args, ["--rl.grpo.steps=3", "--sim.max_steps=200"]))
    assert "--stop-after reward_model" in pipe and "--sim.max_steps=200" in pipe and "rl.grpo.steps" not in pipe


def _point(step, greedy, sampled, used, **extra):
    def entry(rate):
        return {"mean": rate, "ci95": [rate - 0.04, rate + 0.04], "episodes": 500, "successes": int(rate * 500)}

    return dict(step=step, **entry(greedy), sampled=entry(sampled), real_episodes_used=used, **extra)


def end_of(run):
    return run["sampled"]["end"]


def test_summary_reads_curves_gains_and_refreshes(tmp_path):
    for name, end in (("refreshed_seed0", 0.60), ("refreshed_seed1", 0.70), ("once_seed0", 0.40),
                      ("wovr_refreshed_seed0", 0.55)):
        grpo = tmp_path / name / "rl" / "grpo"
        grpo.mkdir(parents=True)
        real = {"trip": True, "rate": 0.3, "baseline": 0.61, "reason": "real success 0.300 < baseline 0.610 - ..."}
        guard = {"trip": False, "reason": "ok", "real_success": real, "rolled_back_to": 0}
        points = [_point(0, 0.70, 0.50, 64), _point(5, 0.71, end, 128, guard=guard)]
        for p in points:
            p["sampled_proprio_masked"] = dict(p["sampled"], mean=p["sampled"]["mean"] - 0.1)
        (grpo / "success_curve.json").write_text(json.dumps({"label": "x", "points": points}))
        records = [{"step": 0, "real_episodes": 64, "real_episodes_used": 64, "real_success": 0.5,
                    "replay": {"false_success": {"rate": 0.2, "of": 32}, "missed_success": {"rate": 0.5, "of": 32}},
                    "detector": {"threshold": 0.93, "calibration": {"false_success": {"rate": 0.0}}}}]
        (grpo / "refreshes.json").write_text(json.dumps(records))
        times = [{"step": 1, "step_s": 30.0, "imagined_frames": 600.0, "imagined_frames_per_s": 20.0}] + [
            {"step": k, "step_s": 2.0, "imagined_frames": 600.0 + k, "imagined_frames_per_s": 300.0 + k} for k in (2, 3, 4)]
        (grpo / "step_times.jsonl").write_text("".join(json.dumps(r) + "\n" for r in times))
    out = bench.summarize(str(tmp_path), GROUND_TRUTH)
    assert sorted(out["runs"]) == ["once_seed0", "refreshed_seed0", "refreshed_seed1", "wovr_refreshed_seed0"]
    assert out["sword_minus_wovr_sampled_gain"] == {"refreshed_seed0": pytest.approx(0.05)}
    assert out["sampled_min_gain"] == pytest.approx(0.10) and out["sampled_mean_gain"] == pytest.approx(0.15)
    run = out["runs"]["refreshed_seed0"]
    # medians of the steps: the first one's compilation does not move them
    assert run["step_s"] == 2.0 and run["imagined_frames_per_s"] == pytest.approx(302.5)
    assert run["real_episodes_used"] == 128 and run["refreshes"][0]["false_success_before"]["rate"] == 0.2
    assert run["sampled_proprio_masked"]["start"] == pytest.approx(0.40) and run["curve"][1]["sampled_proprio_masked"] == pytest.approx(end_of(run) - 0.1)
    assert run["guard"][0]["step"] == 5 and run["sampled"]["ci95"][0] < 0.10 < run["sampled"]["ci95"][1]
    assert run["guard"][0]["real_success"]["trip"] and run["guard"][0]["rolled_back_to"] == 0  # the real-success guard
    # ground-truth GRPO: 512 episodes per sampling round, about 570 per step on average (those runs predate the
    # per-step history, so the count is the summary's mean times the step)
    gt = out["ground_truth"]["s0"]
    assert gt[0]["step"] == 0 and gt[0]["sampled"] == 0.516 and gt[0]["real_episodes_used"] == 0
    assert gt[1]["step"] == 10 and 10 * 512 <= gt[1]["real_episodes_used"] <= 10 * 1024 and not gt[1]["episodes_exact"]
    assert bench.run_label("wovr_refreshed_seed1") == "GRPO in the refreshed WoVR-config world model, seed 1"
    assert bench.run_label("once_seed0") == "GRPO in the Sword world model adapted once, seed 0"
    (tmp_path / "gpu.txt").write_text("name, memory.total [MiB]\nNVIDIA H200, 143771 MiB\nNVIDIA H200, 143771 MiB\n")
    entries = bench.results_entries(out, str(tmp_path), data="d", note="n", command="python -m x")
    sword = entries["policy_grpo_world_model_gain_small"]
    assert sword["value"] == pytest.approx(0.10) and sword["device"] == "NVIDIA H200 x2" and sword["note"] == "n"
    assert sword["command"] == "python -m x" == entries["policy_grpo_sword_vs_wovr_small"]["command"]
    # latest.json keeps each refresh's headline figures, not the calibration's trade-off
    kept = sword["per_seed"]["refreshed_seed0"]["refreshes"][0]
    assert kept["real_success"] == 0.5 and kept["false_success_before"] == 0.2 and "calibration" not in kept
    assert sorted(sword["per_seed"]) == ["refreshed_seed0", "refreshed_seed1"] and sword["real_episodes_used"] == 128
    assert "within_group_separation_before_48" not in kept  # one episode per start: no groups to read
    within = {"group_size": 4, "groups": 16, "mixed_real_groups": 9,
              "48": {"separation": 0.05, "imagined_mixed": 0.2, "auc": 0.55}}
    grouped = bench.compact_refresh(dict(run["refreshes"][0], within_group_before=within))
    assert grouped["within_group_separation_before_48"] == 0.05 and grouped["imagined_mixed_groups_before_48"] == 0.2
    assert grouped["within_group_auc_before_48"] == 0.55
    assert grouped["real_mixed_groups"] == "9 of 16"
    assert not any(k.startswith("verify") for k in grouped)  # no imagined groups were checked
    check = {"imagined_success": 0.6, "real_success": 0.3, "precision": {"rate": 0.4}, "false_success": {"rate": 0.5},
             "within_group": {"all": {"separation": 0.1}}}
    checked = bench.compact_refresh(dict(run["refreshes"][0], verify=check))
    assert (checked["verify_precision"], checked["verify_false_success"], checked["verify_within_group_separation"],
            checked["verify_imagined_success"], checked["verify_real_success"]) == (0.4, 0.5, 0.1, 0.6, 0.3)
    assert bench.compact_refresh(dict(run["refreshes"][0], verify={"skipped": "b"}))["verify_skipped"] == "b"
    assert entries["policy_grpo_wovr_world_model_refreshed_gain_small"]["value"] == pytest.approx(0.05)
    assert entries["policy_grpo_sword_vs_wovr_small"]["value"] == 1
    bench.plot(out, str(tmp_path / "figure.png"))
    assert (tmp_path / "figure.png").stat().st_size > 10_000


def test_a_run_stopped_inside_a_refresh_keeps_the_evaluation_before_it(tmp_path):
    """The evaluation written before a refresh (evaluations/step_*.json) counts when the run was stopped inside
    that refresh, so its curve lacks the point; older ones and a complete curve are left as they are."""
    grpo = tmp_path / "refreshed_seed0" / "rl" / "grpo"
    grpo.mkdir(parents=True)
    points = [_point(0, 0.70, 0.50, 64), _point(10, 0.72, 0.55, 128)]
    (grpo / "success_curve.json").write_text(json.dumps({"label": "x", "points": points}))
    (grpo / "evaluations").mkdir()
    for p in (points[0], points[1], _point(20, 0.74, 0.40, 192)):
        (grpo / "evaluations" / f"step_{p['step']:06d}.json").write_text(json.dumps(p))
    run = bench.summarize_run(str(tmp_path / "refreshed_seed0"))
    assert run["steps"] == 20 and run["last_refresh_incomplete"]
    assert run["sampled"]["gain"] == pytest.approx(-0.10) and [c["step"] for c in run["curve"]] == [0, 10, 20]
    (grpo / "evaluations" / "step_000020.json").unlink()
    whole = bench.summarize_run(str(tmp_path / "refreshed_seed0"))
    assert whole["steps"] == 10 and "last_refresh_incomplete" not in whole


@pytest.mark.parametrize("argv, message", [(["run", "--workdir", "x"], "--policy"),
                                           (["summary", "--seeds", ""], "--seeds"),
                                           (["summary", "--budget", "10"], "--budget"),
                                           (["summary", "--steps", "-1"], "--steps"),
                                           (["run", "--policy", "p", "steps=3"], "dotted")])
def test_bad_arguments_are_one_line_errors(argv, message):
    with pytest.raises(SystemExit, match=message):
        bench.main(argv)


def test_variants_get_their_own_pipelines_runs_and_gpus():
    class Variants(Args):
        arms, variant, variant_gpus, data_backend = {"refreshed"}, ["lpips=--vae.perceptual_weight=1.0",
                                                                   "long='--trainer.steps=15000' --rl.refresh.every=10"], "2,3", "cpu"

    made = bench.pipes(Variants)
    assert [p.folder for p in made] == ["pipeline", "pipeline_lpips", "pipeline_long"]
    assert made[1].overrides == ("--vae.perceptual_weight=1.0",) and made[1].gpus == ("2", "3")
    assert made[2].gpus == ("3", "2") and made[2].seeds == (0,)  # each variant's pipeline on its own GPU
    runs = bench.grpo_commands(Variants, [])
    assert sorted(runs) == ["long_refreshed_seed0", "lpips_refreshed_seed0", "refreshed_seed0", "refreshed_seed1"]
    long = " ".join(runs["long_refreshed_seed0"])
    assert "--world-model w/pipeline_long/world_model" in long and long.index("--rl.refresh.every=5") < long.index(
        "--rl.refresh.every=10")  # a variant's own override wins over the recipe
    pipe = " ".join(bench.pipeline_command(Variants, [], name="pipeline_long", own=made[2].overrides))
    assert "--trainer.steps=15000" in pipe and "--sim.backend=cpu" in pipe and "refresh" not in pipe
    assert bench.run_label("lpips_refreshed_seed0") == "GRPO in the refreshed Sword (lpips) world model, seed 0"
    for bad in ("wovr=--vae.dim=8", "x", "x=", "x=--not-dotted"):
        with pytest.raises(SystemExit, match="variant"):
            bench.parse_variant(bad)


def test_wovr_pipeline_links_sword_episodes_and_refuses_other_data(tmp_path):
    class Wovr(Args):
        workdir, config, wovr_config = str(tmp_path), "sword:tiny", "cache_ablation:tiny-wovr"

    data = tmp_path / "pipeline" / "data"
    data.mkdir(parents=True)
    (tmp_path / "pipeline" / "stages").mkdir()
    results = {name: {"path": str(data / f"{name}.hdf5"), "episodes": 4} for name in ("train", "heldout", "demos")}
    for entry in results.values():
        open(entry["path"], "w").write("episodes")
    (tmp_path / "pipeline" / "stages" / "data.json").write_text(json.dumps({"stage": "data",
                                                                            "results": dict(results, seconds=1.0)}))
    bench.share_data(Wovr, [])
    marker = json.loads((tmp_path / "pipeline_wovr" / "stages" / "data.json").read_text())
    link = tmp_path / "pipeline_wovr" / "data" / "demos.hdf5"
    assert marker["results"]["demos"]["path"] == str(link) and link.read_text() == "episodes"
    assert marker["results"]["seconds"] == 1.0 and not (tmp_path / "pipeline_wovr" / "data" / "latents.npz").exists()

    class Other(Wovr):
        wovr_config = "sword:small"

    with pytest.raises(SystemExit, match="generate different episodes"):
        bench.share_data(Other, [])


def test_run_launches_each_pipelines_runs_when_built_and_stops_them_at_the_deadline(tmp_path, monkeypatch, capsys):
    import sys

    class Run(Args):
        workdir, wovr_config, gpus, wovr_gpus, ground_truth = str(tmp_path), "", "0,1", "", ""
        deadline_s, grace_s = 4.0, 0.0

    monkeypatch.setattr(bench, "pipeline_command", lambda *a, **k: [sys.executable, "-c", "pass"])
    curve = {"label": "x", "points": [_point(0, 0.7, 0.5, 64)]}
    write = (f"import json, os, time; d = os.path.join(os.getcwd(), 'rl', 'grpo'); os.makedirs(d, exist_ok=True); "
             f"json.dump({curve!r}, open(os.path.join(d, 'success_curve.json'), 'w')); time.sleep(600)")
    runs = {name: [sys.executable, "-c", write.replace("os.getcwd()", repr(str(tmp_path / name)))]
            for name in ("refreshed_seed0", "refreshed_seed1")}
    monkeypatch.setattr(bench, "pipe_runs", lambda *a: runs)
    out = bench.run(Run, [], poll_s=0.2)
    assert out["stopped_at_deadline"] == ["refreshed_seed0", "refreshed_seed1"]
    assert sorted(out["runs"]) == ["refreshed_seed0", "refreshed_seed1"] and out["seconds"] < 60
    printed = capsys.readouterr().out
    assert "refreshed_seed0 on GPU 0" in printed and "refreshed_seed1 on GPU 1" in printed


def test_policy_rollouts_put_the_given_policy_in_the_pipeline():
    """With --policy-rollouts the pipeline starts from the policy GRPO starts from and adds its own episodes
    to the world model's and detector's data; without, it skips both stages."""
    plain = bench.pipeline_command(Args, [])
    assert "--data.policy_rollouts_per_task=0" in plain and "probe,evaluate,sft_policy,policy_data" in plain
    assert not any(flag.startswith("--rl.sft.init") for flag in plain)

    class WithRollouts(Args):
        policy_rollouts = 20

    flags = bench.pipeline_command(WithRollouts, ["--rl.grpo.steps=3"])
    assert "--data.policy_rollouts_per_task=20" in flags and "--data.policy_rollouts_per_task=0" not in flags
    assert flags[flags.index("--skip") + 1] == "probe,evaluate"
    assert f"--rl.sft.init={os.path.abspath('p.npz')}" in flags and "--rl.grpo.steps=3" not in flags
    assert bench.PIPELINE_FLAGS[bench.PIPELINE_FLAGS.index("--skip") + 1] == "probe,evaluate,sft_policy,policy_data"


def test_run_variants_add_runs_in_swords_pipeline_built_once(tmp_path, monkeypatch, capsys):
    """--run-variant NAME=--rl...: more runs in Sword's world model with other GRPO settings, on their own
    GPUs, started when Sword's one pipeline is built; settings of another section are refused."""
    import sys

    class Run(Args):
        workdir, wovr_config, gpus, ground_truth, deadline_s, grace_s = str(tmp_path), "", "0,1", "", 0.0, 0.0
        arms, run_variant, run_variant_gpus = {"refreshed"}, ["nr=--rl.refresh.replay_share=0"], "2,3"

    made = bench.pipes(Run)
    assert [(p.folder, p.prefix, p.runs_only, p.gpus) for p in made] == [
        ("pipeline", "", False, ("0", "1")), ("pipeline", "nr_", True, ("2", "3"))]
    assert bench.pipelines(Run) == {"pipeline": "sword:small"}
    runs = bench.grpo_commands(Run, [])
    assert sorted(runs) == ["nr_refreshed_seed0", "nr_refreshed_seed1", "refreshed_seed0", "refreshed_seed1"]
    nr = " ".join(runs["nr_refreshed_seed1"])
    assert f"--world-model {tmp_path}/pipeline/world_model" in nr
    assert nr.endswith(f"--rl.refresh.replay_share=0 --workdir {tmp_path}/nr_refreshed_seed1")
    assert "replay_share" not in " ".join(runs["refreshed_seed1"])

    class Probe(Run):  # --steps 0: each run is step 0's evaluation and refresh, a probe of its simulator
        steps, run_variant = 0, ["g2=--flow.guidance_scale=2"]

    probe = " ".join(bench.grpo_commands(Probe, ["--rl.refresh.group_size=8"])["g2_refreshed_seed0"])
    assert "--rl.grpo.steps=0" in probe and "--flow.guidance_scale=2" in probe and "--rl.refresh.group_size=8" in probe

    builds = []
    monkeypatch.setattr(bench, "pipeline_command", lambda *a, **k: builds.append(k.get("name")) or [sys.executable, "-c", "pass"])
    monkeypatch.setattr(bench, "pipe_runs", lambda args, overrides, p: {
        f"{p.prefix}refreshed_seed{k}": [sys.executable, "-c", "pass"] for k in p.seeds})
    out = bench.run(Run, [], poll_s=0.05)
    assert builds == ["pipeline"] and sorted(out["exit_codes"]) == sorted(runs)
    printed = capsys.readouterr().out
    assert "nr_refreshed_seed0 on GPU 2" in printed and "nr_refreshed_seed1 on GPU 3" in printed
    with pytest.raises(SystemExit, match="GRPO's settings"):
        bench.parse_variant("nr=--trainer.steps=5", "--run-variant")
    with pytest.raises(SystemExit, match="GRPO's settings"):  # how the world model trained: its own pipeline
        bench.parse_variant("ad=--flow.action_dropout=0.1", "--run-variant")
    # how it samples is the runs' own: action guidance in the pipeline's world model
    assert bench.parse_variant("g2=--flow.guidance_scale=2 --rl.refresh.group_size=8", "--run-variant") == (
        "g2", ("--flow.guidance_scale=2", "--rl.refresh.group_size=8"))

    class Two(Run):  # two run variants of one seed each: one GPU each
        seeds, run_variant = [0], ["a=--rl.refresh.replay_share=0", "b=--rl.imagined.decoder=light"]

    assert [p.gpus[0] for p in bench.pipes(Two)] == ["0", "2", "3"]


def test_a_light_decoder_run_variant_has_its_pipeline_distil_the_decoder_and_its_runs_use_it(tmp_path, monkeypatch):
    import sys

    class Run(Args):
        workdir, wovr_config, gpus, ground_truth, deadline_s, grace_s = str(tmp_path), "", "0", "", 0.0, 0.0
        arms, seeds, run_variant = {"refreshed"}, [0], ["light=--rl.imagined.decoder=light"]

    runs = bench.grpo_commands(Run, [])
    light = runs["light_refreshed_seed0"]
    assert light[light.index("--light-decoder") + 1] == os.path.join(str(tmp_path), "pipeline", "light_decoder")
    assert "--light-decoder" not in runs["refreshed_seed0"]
    # the last decoder setting wins
    assert not bench.uses_light_decoder([], bench.Pipe("p", "c", ("--rl.imagined.decoder=light", "--rl.imagined.decoder=full")))
    assert bench.uses_light_decoder(["--rl.imagined.decoder=full"], bench.Pipe("p", "c", ("--rl.imagined.decoder=light",)))
    assert bench.LIGHT in bench.pipeline_command(Run, [], light=True) and bench.LIGHT not in bench.pipeline_command(Run, [])
    built = []
    monkeypatch.setattr(bench, "pipeline_command", lambda *a, **k: built.append(k) or [sys.executable, "-c", "pass"])
    monkeypatch.setattr(bench, "pipe_runs", lambda args, overrides, p: {
        f"{p.prefix}refreshed_seed{k}": [sys.executable, "-c", "pass"] for k in p.seeds})
    bench.run(Run, [], poll_s=0.05)
    assert [(k["name"], k["light"]) for k in built] == [("pipeline", True)]  # one pipeline, distilling the decoder


def test_each_run_is_one_line_of_its_gains(capsys):
    point = {"start": 0.5, "end": 0.6, "gain": 0.1, "ci95": [-0.02, 0.22]}
    summary = {"runs": {"refreshed_seed0": {"steps": 10, "real_episodes_used": 128, "greedy": point, "sampled": point,
                                            "imagined_frames_per_s": 900.0},
                        "refreshed_seed1": {"steps": 0, "real_episodes_used": 64, "greedy": point, "sampled": point}}}
    bench.print_runs(summary)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and lines[0].startswith("[refresh] refreshed_seed0: steps 10, real episodes 128")
    assert "sampled 0.500 -> 0.600 (+0.100 [-0.020, +0.220])" in lines[0] and "900 imagined frames/s" in lines[0]
    assert "imagined frames" not in lines[1]


def test_wait_until_deadline_stops_only_what_runs_past_it():
    import subprocess
    import sys
    import time

    from benchmarks.bench_grpo_refresh import wait_until_deadline

    def spawn(seconds):
        return subprocess.Popen([sys.executable, "-c", f"import time; time.sleep({seconds})"], start_new_session=True)

    start = time.perf_counter()
    procs = {"long": spawn(60), "short": spawn(0)}
    assert wait_until_deadline(procs, 1.0, start, tag="t", poll_s=0.1) == ["long"]
    assert procs["long"].poll() is not None and time.perf_counter() - start < 30
    quick = {"a": spawn(0), "b": spawn(0.2)}
    assert wait_until_deadline(quick, 0.0, time.perf_counter(), tag="t", poll_s=0.05) == []
    assert all(p.returncode == 0 for p in quick.values())


# a command under cli.run that stops when asked, as a training loop does (tests/test_train_loop.py): exit 75
_STOPPABLE = """
import sys, time
from sword_jax import cli
def main(argv):
    print("ready", flush=True)  # cli.run has set its handler
    while not cli.stop_requested():
        time.sleep(0.02)
    raise cli.StopRequested("toy: stopped on request after step 3 of 9")
cli.run(main)
"""


def test_wait_until_deadline_with_grace_asks_first_and_stops_what_does_not_listen():
    import signal
    import subprocess
    import sys
    import time

    from benchmarks.bench_grpo_refresh import wait_until_deadline
    from sword_jax import cli

    deaf = ("import signal, time; signal.signal(signal.SIGUSR1, signal.SIG_IGN); print('ready', flush=True); "
            "time.sleep(60)")
    procs = {"listens": subprocess.Popen([sys.executable, "-c", _STOPPABLE], stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, text=True, start_new_session=True),
             "deaf": subprocess.Popen([sys.executable, "-c", deaf], stdout=subprocess.PIPE, text=True,
                                      start_new_session=True),
             "done": subprocess.Popen([sys.executable, "-c", "pass"], start_new_session=True)}
    for name in ("deaf", "listens"):  # their handlers are set before the deadline
        assert procs[name].stdout.readline().strip() == "ready"
    start = time.perf_counter()
    assert wait_until_deadline(procs, 0.5, start, tag="t", poll_s=0.05, grace_s=3.0) == ["deaf", "listens"]
    took = time.perf_counter() - start
    assert procs["listens"].returncode == cli.STOPPED_EXIT == 75
    assert procs["listens"].stderr.read().strip().endswith("toy: stopped on request after step 3 of 9")
    assert procs["deaf"].returncode == -signal.SIGTERM  # asked, did not stop, stopped after the grace
    assert 3.0 < took < 30
