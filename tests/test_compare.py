"""The comparison's slices, merge and table (the runs themselves are pipeline runs, faked here)."""

import json
import os

import numpy as np
import pytest

from sword_jax.pipeline import compare as compare_lib
from sword_jax.pipeline import inputs as shared_inputs
from tests.conftest import example_env
from train import compare

FAKE_HASHES = {"data": "d" * 64, "vae": "v" * 64}


def _record(run, seed, lpips, success, hashes=FAKE_HASHES, file=None):
    metrics = {m: lpips * (i + 1) for i, m in enumerate(compare_lib.METRICS)}
    return {"format": compare.SLICE_FORMAT, "size": "small", "run": run, "seed": seed,
            "metrics": {"original": metrics, "mixed": metrics},
            "success": {"grpo step 0": success[0], "grpo step 10": success[1]},
            "shared": {"hashes": dict(hashes)}, "device": {"kind": "NVIDIA H100"},
            "wall_seconds": {"shared": 100.0, "slice": 300.0}, "code": {"commit": "abc123", "dirty": False}}


def _write(directory, record):
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, f"{record['run']}_seed{record['seed']}.json"), "w") as f:
        json.dump(record, f)


def test_aggregate_means_and_spreads_and_markdown():
    results = {run: [_record(run, s, 0.1 + 0.1 * s, (0.2, 0.4 + 0.1 * s)) for s in range(3)]
               for run in ("sword", "teacher_forcing", "no_augmentation", "wovr")}
    table = compare_lib.aggregate(results)
    lpips = table["sword"]["metrics"]["original/lpips"]
    assert np.isclose(lpips["mean"], 0.2) and np.isclose(lpips["std"], 0.1) and lpips["n"] == 3
    assert np.isclose(table["wovr"]["success"]["grpo step 10"]["mean"], 0.5)
    text = compare_lib.to_markdown(table, [0, 1, 2])
    assert "DLB vs teacher forcing" in text and "0.2 ± 0.1 (n=3)" in text
    assert text.index("grpo step 0") < text.index("grpo step 10")


def test_runs_cover_the_three_comparisons():
    runs = compare.runs_for("small")
    assert runs["teacher_forcing"][0] == "cache_ablation:small-tf"
    assert runs["wovr"][0] == "cache_ablation:small-wovr"
    assert "--augment.enabled=false" in runs["no_augmentation"][1]
    for _, ours, baseline, _ in compare_lib.COMPARISONS:
        assert ours in runs and baseline in runs


def _write_markers(workdir, stages):
    os.makedirs(os.path.join(workdir, "stages"), exist_ok=True)
    for stage in stages:
        with open(os.path.join(workdir, "stages", f"{stage}.json"), "w") as f:
            json.dump({"stage": stage, "results": {"path": f"{workdir}/{stage}"}}, f)


def test_every_eval_setting_is_read_by_one_kind_of_stage():
    """Each eval field is what the data stage reads, what the VAE's perceptual loss reads, or how the evaluation
    scores: a field added to the section must say which (adoption and a work dir's config check follow it)."""
    import dataclasses

    from sword_jax.metrics.config import EvalConfig

    kinds = (EvalConfig.data_fields, EvalConfig.perceptual_fields, EvalConfig.scoring_fields)
    named = [name for kind in kinds for name in kind]
    assert sorted(named) == sorted(f.name for f in dataclasses.fields(EvalConfig)), "each field in exactly one kind"


def test_runs_adopt_only_stages_whose_config_sections_agree(tmp_path):
    import dataclasses

    import configs

    donor = str(tmp_path / "sword" / "seed0")
    _write_markers(donor, compare.SHAREABLE)
    sword = configs.get("cache_ablation:small-linear-direct-all")
    tf = configs.get("cache_ablation:small-tf")
    wovr = configs.get("cache_ablation:small-wovr")
    assert compare.adopt_stages(str(tmp_path / "tf1"), donor, tf, sword) == list(compare.SHAREABLE)
    # WoVR trains without augmentation: its latents (no styled copies) are its own.
    assert "latents" not in compare.adopt_stages(str(tmp_path / "wovr"), donor, wovr, sword)
    assert os.path.exists(tmp_path / "wovr" / "stages" / "data.json")
    # A different simulator section shares nothing; a finished stage is never overwritten.
    other_sim = dataclasses.replace(sword, sim=dataclasses.replace(sword.sim, episodes_per_task=3))
    assert compare.adopt_stages(str(tmp_path / "other"), donor, other_sim, sword) == []
    # how the evaluation scores changes no stage's result here; how many held-out episodes it scores does
    scoring = dataclasses.replace(sword, eval=dataclasses.replace(sword.eval, metrics=("psnr",), report_videos=1))
    assert compare.adopt_stages(str(tmp_path / "scoring"), donor, scoring, sword) == list(compare.SHAREABLE)
    fewer = dataclasses.replace(sword, eval=dataclasses.replace(sword.eval, num_episodes=sword.eval.num_episodes + 1))
    assert "data" not in compare.adopt_stages(str(tmp_path / "fewer"), donor, fewer, sword)
    # another LPIPS network trains another VAE: it and what is made from it are the run's own, the data are shared
    vgg = dataclasses.replace(sword, eval=dataclasses.replace(sword.eval, lpips_net="vgg"))
    taken = compare.adopt_stages(str(tmp_path / "vgg"), donor, vgg, sword)
    assert "data" in taken and not {"vae", "latents", "light_decoder"} & set(taken)
    # how many processes record the policy's rollouts changes no result
    spread = dataclasses.replace(sword, data=dataclasses.replace(sword.data, policy_rollout_workers=4))
    assert compare.adopt_stages(str(tmp_path / "spread"), donor, spread, sword) == list(compare.SHAREABLE)
    _write_markers(str(tmp_path / "mine"), ["vae"])
    assert "vae" not in compare.adopt_stages(str(tmp_path / "mine"), donor, sword, sword)
    with open(tmp_path / "mine" / "stages" / "vae.json") as f:
        assert json.load(f)["results"]["path"].startswith(str(tmp_path / "mine"))
    with open(tmp_path / "tf1" / "stages" / "data.json") as f:
        assert json.load(f)["results"]["path"] == f"{donor}/data"


def _write_episodes(path, frames, compression=None):
    import h5py

    with h5py.File(path, "w") as f:
        for i, video in enumerate(frames):
            demo = f.create_group(f"data/demo_{i}")
            demo.create_dataset("actions", data=np.full((len(video), 7), 0.1 * i))
            demo.create_dataset("rewards", data=np.zeros(len(video), np.uint8))
            demo.create_dataset("states", data=np.random.default_rng(i + len(path)).normal(size=(len(video), 3)))
            demo.create_dataset("obs/agentview_rgb", data=video, compression=compression)


def test_data_hash_sees_frames_and_actions_not_the_file_layout(tmp_path):
    frames = [np.random.default_rng(i).integers(0, 255, (3, 8, 8, 3), dtype=np.uint8) for i in range(11)]
    _write_episodes(str(tmp_path / "a.hdf5"), frames)
    _write_episodes(str(tmp_path / "bb.hdf5"), frames, compression="gzip")  # other layout, other `states`
    reference = shared_inputs.hash_episodes(str(tmp_path / "a.hdf5"))
    assert shared_inputs.hash_episodes(str(tmp_path / "bb.hdf5")) == reference
    frames[10][2, 0, 0, 0] ^= 1  # demo_10 sorts after demo_2: numeric order, one bit
    _write_episodes(str(tmp_path / "c.hdf5"), frames)
    assert shared_inputs.hash_episodes(str(tmp_path / "c.hdf5")) != reference


def _fake_stages(calls):
    """Pipeline stages that record their calls and write what compare reads (eval results, success curve)."""
    from sword_jax.pipeline.stages import Stage

    def make(name, needs):
        def run(ctx):
            calls.append((name, ctx.workdir, ctx.cfg.seed))
            out = {"path": ctx.path(name, "x")}
            if name == "data":
                for split in ("train", "heldout"):
                    _write_episodes(ctx.path("data", f"{split}.hdf5"), [np.full((2, 4, 4, 3), ctx.cfg.seed, np.uint8)])
                out = {split: {"path": ctx.path("data", f"{split}.hdf5")} for split in ("train", "heldout")}
            elif name == "latents":
                np.savez(out["path"] + ".npz", latents=np.zeros(3), actions=np.ones(2), source=ctx.workdir)
                out["path"] += ".npz"
            elif name == "world_model":
                out = {"workdir": ctx.workdir, "final_step": 20, "first_loss": 2.0, "final_metrics": {"loss": 1.0}}
            elif name == "evaluate":
                curves = {"lpips": {"frames": [5, 6], "mean": [0.1, 0.2000000001], "stderr": [0.01, 0.02]}}
                per_split = {split: {ctx.cfg.name: {"overall": {"lpips": 0.15, "psnr": 20.0}, "curves": curves}}
                             for split in ("original", "mixed")}
                os.makedirs(ctx.path("eval"), exist_ok=True)
                with open(ctx.path("eval", "results.json"), "w") as f:
                    json.dump({"models": per_split, "vae_floor": {"original": {"overall": {"lpips": 0.12}}}}, f)
                out = {"metrics": {s: {m: r["overall"] for m, r in p.items()} for s, p in per_split.items()}}
            elif name in ("probe", "reward_model", "sft_policy"):
                out = {"loss": 0.5}
            elif name == "policy_data":
                out = {"path": "", "episodes": 0}
            elif name == "policy":
                grpo_dir = ctx.path("rl", "grpo")
                os.makedirs(grpo_dir, exist_ok=True)
                with open(os.path.join(grpo_dir, "success_curve.json"), "w") as f:
                    json.dump({"points": [{"step": 0, "mean": 0.25}, {"step": 10, "mean": 0.5}]}, f)
                out = {"success": {"grpo step 0": 0.25, "grpo step 10": 0.5}, "grpo": {"workdir": grpo_dir}}
            return out

        return Stage(name, run, name, needs=needs)

    from sim import pipeline_stages

    return [make(stage.name, stage.needs) for stage in pipeline_stages.STAGES]


def test_slices_build_shared_stages_once_and_write_their_files(tmp_path, monkeypatch):
    from sim import pipeline_stages

    calls = []
    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages(calls))
    monkeypatch.setattr(shared_inputs, "hash_vae", lambda cfg, path: "v" * 64)
    results = tmp_path / "results"
    argv = ["--size", "tiny", "--runs", "sword,teacher_forcing", "--seeds", "1", f"--out={tmp_path / 'w'}",
            f"--results={results}", "--trainer.steps=3"]
    table = compare.main(argv)
    names = [stage.name for stage in pipeline_stages.STAGES]
    shareable = [name for name in names if name in compare.SHAREABLE]
    shared = [(name, seed) for name, workdir, seed in calls if "/shared/" in workdir]
    # The shared stages run once, at the shared seed (0), not the slice's seed; teacher forcing adopts them
    # and stops after the evaluation.
    assert shared == [(name, 0) for name in shareable] and {"data", "vae", "sft_policy"} <= set(shareable)
    assert [name for name, workdir, _ in calls if "teacher_forcing/seed1" in workdir] == [
        name for name in names[:names.index("evaluate") + 1] if name not in compare.SHAREABLE]
    with open(results / "sword_seed1.json") as f:
        sword = json.load(f)
    with open(results / "teacher_forcing_seed1.json") as f:
        tf = json.load(f)
    assert sword["command"] == ("python -m train.compare --size tiny --runs sword --seeds 1 --trainer.steps=3")
    assert sword["overrides"] == ["--trainer.steps=3"] and sword["config"] == "cache_ablation:linear-direct-all"
    assert sword["shared"]["built_here"] == shareable
    assert tf["shared"]["built_here"] == [] and tf["shared"]["seed"] == 0
    assert set(sword["stage_seconds"]) == set(names) - set(shareable)
    assert set(sword["shared"]["stage_seconds"]) == set(shareable)
    assert sword["metrics"]["original"] == {"lpips": 0.15, "psnr": 20.0}
    assert sword["curves"]["mixed"]["lpips"]["mean"] == [0.1, 0.2]  # rounded to 6 digits
    assert sword["vae_floor"] == {"original": {"lpips": 0.12}}
    assert "| VAE floor (mean over slices) | 0.12 |" in (results / "comparison.md").read_text()
    assert [p["step"] for p in sword["success_curve"]] == [0, 10] and "success_curve" not in tf
    assert sword["device"]["platform"] == "cpu" and len(sword["code"]["source_hash"]) == 64
    hashes = sword["shared"]["hashes"]
    assert hashes["vae"] == "v" * 64 and hashes["data"] == tf["shared"]["hashes"]["data"]
    assert "latents[augment=on]" in hashes and "reward_model" not in hashes  # fake RL stages save no params
    assert table["teacher_forcing"]["metrics"]["original/lpips"]["n"] == 1
    assert "| sword | 1 | cpu" in (results / "comparison.md").read_text().lower()


def test_merge_counts_seeds_per_cell(tmp_path):
    for seed in range(3):
        _write(tmp_path, _record("sword", seed, 0.1 * (seed + 1), (0.1, 0.3)))
    for seed in range(2):
        _write(tmp_path, _record("teacher_forcing", seed, 0.2, (0.1, 0.2)))
    (tmp_path / "notes.json").write_text("[1, 2]")  # not a slice: ignored
    table = compare.merge(str(tmp_path))
    assert table["sword"]["metrics"]["mixed/lpips"]["n"] == 3
    written = json.loads((tmp_path / "comparison.json").read_text())
    assert written["finished_seeds_per_run"] == {"sword": 3, "teacher_forcing": 2}
    assert written["seeds"] == [0, 1, 2] and written["shared_input_mismatches"] == {}
    text = (tmp_path / "comparison.md").read_text()
    assert "0.2 ± 0.1 (n=3)" in text and "0.2 ± 0 (n=2)" in text and "WARNING" not in text
    assert "| teacher_forcing | 1 | NVIDIA H100 | 100 + 300 | 1 | abc123 | dddddddddddd | vvvvvvvvvvvv |" in text
    # Paired by seed where both runs finished (seeds 0 and 1): lower is better, higher for psnr.
    lpips = written["paired"]["sword vs teacher_forcing"]["original/lpips"]
    assert lpips["seeds"] == [0, 1] and np.allclose(lpips["diffs"], [-0.1, 0.0]) and lpips["ours_better"] == 1
    psnr = written["paired"]["sword vs teacher_forcing"]["mixed/psnr"]
    assert np.allclose(psnr["diffs"], [-0.5, 0.0]) and psnr["ours_better"] == 0 and psnr["n"] == 2
    assert "| original/lpips | -0.1 (s0), +0 (s1) | -0.05 | 1/2 seeds |" in text
    assert written["paired"]["sword vs no_augmentation"] == {}  # no no_augmentation slices


def test_merge_refuses_slices_from_different_shared_inputs(tmp_path):
    _write(tmp_path, _record("sword", 0, 0.1, (0.1, 0.3)))
    _write(tmp_path, _record("wovr", 0, 0.1, (0.1, 0.3), hashes={**FAKE_HASHES, "vae": "e" * 64}))
    with pytest.raises(SystemExit, match=r"different shared inputs \(vae: vvvvvvvvvvvv \(sword_seed0.json\) vs "
                                         r"eeeeeeeeeeee \(wovr_seed0.json\)\)"):
        compare.merge(str(tmp_path))
    assert not (tmp_path / "comparison.md").exists()
    compare.merge(str(tmp_path), allow_mismatch=True)
    text = (tmp_path / "comparison.md").read_text()
    assert text.startswith("> **WARNING") and "`vae`: vvvvvvvvvvvv in sword_seed0.json" in text
    assert set(json.loads((tmp_path / "comparison.json").read_text())["shared_input_mismatches"]) == {"vae"}


@pytest.mark.parametrize("argv, message", [
    (["--runs", "sword,bogus"], "--runs: unknown run(s) 'bogus'"),
    (["--runs", "sword,sword"], "listed twice"),
    (["--runs", "sword,"], "unknown run(s) ''"),
    (["--seeds", "0,x"], "--seeds takes comma-separated integers"),
    (["--seed=3"], "not a dotted config override"),  # not an abbreviation of --seeds
    (["--size", "huge"], "invalid choice: 'huge'"),
    (["merge"], "the following arguments are required: dir"),
    (["--runs", "sword,teacher_forcing", "--no-evaluate"], "--no-evaluate is for comparison-3 slices"),
    (["--runs", "wovr", "--no-evaluate", "--no-policy"], "with --no-policy"),
    (["--runs", "ground_truth", "--no-policy"], "cannot run with --no-policy"),
    (["--shared-seed", "each"], "--shared-seed takes a non-negative integer or 'slice', got 'each'"),
    (["--shared-seed", "-1"], "--shared-seed takes a non-negative integer or 'slice'"),
])
def test_bad_command_lines_are_one_line_errors(argv, message, capsys):
    from sword_jax import cli

    with pytest.raises(SystemExit) as exit_info:
        cli.run(compare.main, argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_merge_of_an_empty_folder_is_a_one_line_runtime_error(tmp_path, capsys):
    from sword_jax import cli

    with pytest.raises(SystemExit) as exit_info:
        cli.run(compare.main, ["merge", str(tmp_path)])
    assert exit_info.value.code == 1 and "no slice files" in capsys.readouterr().err


_BUILD_AND_HASH = """
import json, os, sys
import configs
from sword_jax.pipeline import inputs as shared_inputs
from train import compare
out = sys.argv[1]
shared_dir, _, _ = compare.build_shared("teacher_forcing", "tiny", out=out, shared_seed=0, overrides=[])
stages = {}
for name in os.listdir(os.path.join(shared_dir, "stages")):
    with open(os.path.join(shared_dir, "stages", name)) as f:
        stages[name[:-5]] = json.load(f)["results"]
cfg, _ = configs.from_argv(["--config", compare.runs_for("tiny")["teacher_forcing"][0], "--seed=0"])
print("HASHES " + json.dumps(shared_inputs.shared_hashes(cfg, stages)))
"""


@pytest.mark.slow
def test_shared_stages_rebuild_bit_identically_in_a_fresh_process(tmp_path):
    """What lets slices run in different jobs: the same config and shared seed give the same inputs.

    Teacher forcing's shared stages (data, VAE, latents, probe, reward model: about 5 minutes on 2
    CPU cores); the supervised policy is the only shared stage it leaves out.
    """
    import subprocess
    import sys

    hashes = []
    for attempt in ("a", "b"):
        # one CPU device, as a user's run has (the suite's 8 fake devices cannot split a tiny batch of 2)
        done = subprocess.run([sys.executable, "-c", _BUILD_AND_HASH, str(tmp_path / attempt)], cwd=compare.REPO,
                              capture_output=True, text=True, check=True, env=example_env())
        hashes.append(json.loads(done.stdout.rsplit("HASHES ", 1)[1]))
    assert {"data", "vae", "latents[augment=on]", "reward_model"} <= set(hashes[0])
    assert hashes[0] == hashes[1]


def _one_fake_slice(tmp_path, monkeypatch, run: str, seed: int, flag: str):
    """One tiny slice with ``flag`` on the fake stages: (every stage name, the stages that ran, its record)."""
    from sim import pipeline_stages

    calls = []
    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages(calls))
    monkeypatch.setattr(shared_inputs, "hash_vae", lambda cfg, path: "v" * 64)
    results = tmp_path / "results"
    compare.main(["--size", "tiny", "--runs", run, "--seeds", str(seed), flag, f"--out={tmp_path / 'w'}",
                  f"--results={results}"])
    names = [stage.name for stage in pipeline_stages.STAGES]
    return names, {name for name, _, _ in calls}, json.loads((results / f"{run}_seed{seed}.json").read_text())


def test_no_policy_slices_stop_after_the_evaluation(tmp_path, monkeypatch):
    """--no-policy: a comparison-3 run builds no supervised policy and runs no GRPO, and says so."""
    names, ran, record = _one_fake_slice(tmp_path, monkeypatch, "sword", 2, "--no-policy")
    assert ran == set(names[:names.index("evaluate") + 1]) and "policy" not in ran
    assert record["policy_stages"] is False and "success_curve" not in record
    assert record["command"] == "python -m train.compare --size tiny --runs sword --seeds 2 --no-policy"


def test_no_evaluate_slices_train_grpo_without_the_world_model_evaluation(tmp_path, monkeypatch):
    """--no-evaluate (comparison 3): no probe, no evaluation, no report, in the slice or its shared dir;
    the GRPO success curve is recorded and the slice says it was not evaluated."""
    names, ran, record = _one_fake_slice(tmp_path, monkeypatch, "wovr", 1, "--no-evaluate")
    assert ran == set(names) - {"probe", "evaluate", "report"} and "policy" in ran
    assert record["evaluated"] is False and record["metrics"] == {} and record["curves"] == {}
    assert [p["step"] for p in record["success_curve"]] == [0, 10]
    assert record["command"] == "python -m train.compare --size tiny --runs wovr --seeds 1 --no-evaluate"


class _Exited:
    """What a launched stage process looks like once it has exited."""

    def __init__(self, code: int):
        self.code = code

    def poll(self) -> int:
        return self.code


@pytest.mark.slow  # the slices-at-once test launches the stages in the default run
def test_parallel_slices_launch_each_stage_with_the_slices_command_and_record_the_same(tmp_path, monkeypatch):
    """--parallel: every stage is launched as ``train.pipeline <the slice's or shared dir's command> --only
    STAGE`` (here run in this process instead of a new one, so the fake stages apply), and the
    slice records equal a sequential run's."""
    from sim import pipeline_stages
    from train import pipeline

    calls, launched = [], []
    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages(calls))
    monkeypatch.setattr(shared_inputs, "hash_vae", lambda cfg, path: "v" * 64)

    def launcher(argv, workdir):
        def launch(stage):
            launched.append((stage.name, workdir, list(argv)))
            pipeline.main([*argv, "--only", stage.name])
            return _Exited(0)

        return launch

    monkeypatch.setattr(pipeline_stages, "stage_launcher", launcher)
    records = {}
    for mode, extra in (("sequential", []), ("parallel", ["--parallel", "2"])):
        results = tmp_path / mode / "results"
        compare.main(["--size", "tiny", "--runs", "teacher_forcing", "--seeds", "1", f"--out={tmp_path / mode / 'w'}",
                      f"--results={results}", *extra])
        records[mode] = json.loads((results / "teacher_forcing_seed1.json").read_text())
    shared = [(name, argv) for name, workdir, argv in launched if "shared" in workdir]
    own = [(name, argv) for name, workdir, argv in launched if "shared" not in workdir]
    assert shared and own
    assert all("--skip" in argv and "--stop-after" not in argv for _, argv in shared)  # the shared dir's stages only
    assert all(argv[argv.index("--stop-after") + 1] == "evaluate" for _, argv in own)
    assert {name for name, _ in own} == {"world_model", "evaluate"}  # the rest adopted from the shared dir

    def science(record):
        return {k: record[k] for k in ("metrics", "curves", "world_model", "policy_stages")} | {
            "hashes": record["shared"]["hashes"], "adopted": record["shared"]["adopted"]}

    assert science(records["parallel"]) == science(records["sequential"])


def test_slices_at_once_build_shared_stages_first_then_run_each_slice_as_a_child(tmp_path, monkeypatch):
    """--slices-at-once N: the parent builds every run's shared stages, then starts one ``train.compare``
    child per (run, seed) with the parent's arguments less its run/seed/concurrency flags (here run in
    this process, so the fake stages apply); the records equal a sequential run's and say how many
    slices shared the device. A failed child stops new ones and is named with its log."""
    from sim import pipeline_stages

    calls, children = [], []
    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages(calls))
    monkeypatch.setattr(shared_inputs, "hash_vae", lambda cfg, path: "v" * 64)

    def launch(argv, log_path, env, fail=()):
        children.append(list(argv))
        with monkeypatch.context() as m:
            m.setenv(compare.SLICES_AT_ONCE_ENV, env[compare.SLICES_AT_ONCE_ENV])
            if any(f"sword --seeds {seed}" in " ".join(argv) for seed in fail):
                return _Exited(3)
            compare.main(argv)
        return _Exited(0)

    monkeypatch.setattr(compare, "launch_slice", launch)
    records = {}
    for mode, extra in (("sequential", []), ("side_by_side", ["--slices-at-once", "2"])):
        results = tmp_path / mode / "results"
        compare.main(["--size", "tiny", "--runs", "sword,teacher_forcing", "--seeds", "1,2", "--no-policy",
                      f"--out={tmp_path / mode / 'w'}", f"--results={results}", *extra, "--trainer.steps=3"])
        records[mode] = {f.name: json.loads(f.read_text()) for f in sorted(results.glob("*_seed*.json"))}
    assert [c[c.index("--runs") + 1:c.index("--runs") + 4] for c in children] == [
        ["sword", "--seeds", "1"], ["teacher_forcing", "--seeds", "1"], ["sword", "--seeds", "2"],
        ["teacher_forcing", "--seeds", "2"]]
    assert all("--slices-at-once" not in c and c.count("--runs") == 1 and "--no-policy" in c
               and "--trainer.steps=3" in c for c in children)
    # No child built a shared stage: the parent did, before the first child started.
    assert all(built == [] for built in (r["shared"]["built_here"] for r in records["side_by_side"].values()))
    assert [r["slices_at_once"] for r in records["side_by_side"].values()] == [2] * 4
    assert [r["slices_at_once"] for r in records["sequential"].values()] == [1] * 4

    def science(record):
        return {k: record[k] for k in ("metrics", "curves", "world_model", "command")} | {
            "hashes": record["shared"]["hashes"], "adopted": record["shared"]["adopted"]}

    assert records["side_by_side"].keys() == records["sequential"].keys()
    assert all(science(records["side_by_side"][k]) == science(records["sequential"][k]) for k in records["sequential"])
    assert "| 2 |" in (tmp_path / "side_by_side" / "results" / "comparison.md").read_text()

    children.clear()
    monkeypatch.setattr(compare, "launch_slice", lambda argv, log, env: launch(argv, log, env, fail=(3,)))
    with pytest.raises(RuntimeError, match=r"slices failed: sword seed 3 \(.*\); not started: sword seed 4, teacher_forcing seed 4$"):
        compare.main(["--size", "tiny", "--runs", "sword,teacher_forcing", "--seeds", "3,4", "--no-policy",
                      f"--out={tmp_path / 'side_by_side' / 'w'}", f"--results={tmp_path / 'fail'}",
                      "--slices-at-once", "2", "--trainer.steps=3"])
    assert len(children) == 2  # sword 3 failed, teacher_forcing 3 was already running and finished; nothing new
    assert (tmp_path / "fail" / "teacher_forcing_seed3.json").exists()
    assert "| teacher_forcing | 3 |" in (tmp_path / "fail" / "comparison.md").read_text()  # merged what finished


def _fake_ground_truth_grpo(calls):
    """Stands in for GRPO against MuJoCo: records the call, writes a success curve like run_grpo's."""
    from sim import policy_stages

    def grpo_in_ground_truth(ctx):
        calls.append(("ground_truth_grpo", ctx.workdir, ctx.cfg.seed, sorted(ctx.results)))
        grpo_dir = ctx.path("rl", "grpo")
        os.makedirs(grpo_dir, exist_ok=True)
        points = [{"step": 0, "mean": 0.25, "ci95": [0.2, 0.3], "successes": 25, "episodes": 100},
                  {"step": 10, "mean": 0.5 + 0.01 * ctx.cfg.seed, "ci95": [0.45, 0.55],
                   "successes": 50 + ctx.cfg.seed, "episodes": 100}]
        with open(os.path.join(grpo_dir, "success_curve.json"), "w") as f:
            json.dump({"points": points}, f)
        return policy_stages._policy_result(ctx, {"curve": points, "workdir": grpo_dir})

    return grpo_in_ground_truth


def test_shared_seed_slice_replicates_each_seed_and_ground_truth_is_the_reference(tmp_path, monkeypatch):
    """--shared-seed slice: every seed builds its own shared stages at that seed, in its own folder, and
    that seed's runs (sword, wovr and the ground-truth reference) adopt them; merge checks hashes within
    a shared seed only, and comparison 3 shows each run's success per step, the reference and the
    per-seed gains, with a figure. The ground-truth run makes no world model and no detector."""
    from sim import pipeline_stages, policy_stages

    calls = []
    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages(calls))
    monkeypatch.setattr(policy_stages, "grpo_in_ground_truth", _fake_ground_truth_grpo(calls))
    monkeypatch.setattr(shared_inputs, "hash_vae", lambda cfg, path: "v" * 64)
    results, out = tmp_path / "results", tmp_path / "w"
    compare.main(["--size", "tiny", "--runs", "sword,wovr,ground_truth", "--seeds", "1,2", "--no-evaluate",
                  "--shared-seed", "slice", f"--out={out}", f"--results={results}"])
    roots = [(os.path.relpath(workdir, out).split(os.sep)[0], seed) for _, workdir, seed, *rest in calls]
    shared = sorted({(root, seed) for root, seed in roots if root.startswith("shared")})
    assert shared == [("shared-seed1", 1), ("shared-seed2", 2)]
    gt_calls = [c for c in calls if "ground_truth/seed" in c[1]]
    assert [c[0] for c in gt_calls] == ["ground_truth_grpo", "ground_truth_grpo"]
    assert all(c[3] == ["data", "sft_policy"] for c in gt_calls)  # no world model, detector or VAE
    records = {f.name: json.loads(f.read_text()) for f in results.glob("*_seed*.json")}
    assert len(records) == 6
    for name, record in records.items():
        assert record["shared"]["seed"] == record["seed"]
        assert record["command"].endswith(f"--shared-seed={record['seed']}")
    gt = records["ground_truth_seed2.json"]
    assert gt["shared"]["adopted"] == ["data", "sft_policy"] and set(gt["stage_seconds"]) == {"policy"}
    assert gt["shared"]["workdir"] == str(out / "shared-seed2" / "ground_truth")
    assert gt["shared"]["hashes"]["data"] == records["sword_seed2.json"]["shared"]["hashes"]["data"]
    assert "vae" not in gt["shared"]["hashes"]
    assert [p["mean"] for p in gt["success_curve"]] == [0.25, 0.52]
    # Data differs between seeds (the fake frames hold the seed), yet nothing is flagged: different replicates.
    assert records["sword_seed1.json"]["shared"]["hashes"]["data"] != records["sword_seed2.json"]["shared"]["hashes"]["data"]
    written = json.loads((results / "comparison.json").read_text())
    assert written["shared_input_mismatches"] == {}
    assert set(written["shared_input_hashes"]) == {"shared seed 1", "shared seed 2"}
    gains = written["paired"]["sword vs wovr"]
    assert gains["seeds"] == [1, 2] and gains["n"] == 2 and np.allclose(gains["sword"], [0.25, 0.25])
    text = (results / "comparison.md").read_text()
    assert "| ground_truth (GRPO in MuJoCo: reference) | 0.250 ± 0 (n=2) | 0.515 ± 0.0071 (n=2) |" in text
    assert "gained more than `wovr` at 0/2 seeds" in text and "WARNING" not in text
    from sword_jax.rl.env_rollout import difference_interval

    low, high = difference_interval(25, 100, 52, 100)
    assert f"| 2 | +0.250 | +0.250 | +0.270 [{low:+.3f}, {high:+.3f}] | +0.000 |" in text
    assert (results / "grpo_sword_vs_wovr.png").stat().st_size > 0


def test_hash_checks_stay_within_a_shared_seed():
    a = {**_record("sword", 0, 0.1, (0.1, 0.2)), "file": "a"}
    b = {**_record("wovr", 0, 0.1, (0.1, 0.2), hashes={"data": "x" * 64, "vae": "v" * 64}), "file": "b"}
    c = {**_record("sword", 1, 0.1, (0.1, 0.2), hashes={"data": "y" * 64, "vae": "w" * 64}), "file": "c"}
    c["shared"]["seed"] = 1
    assert compare_lib.hash_mismatches([a, c]) == {}
    assert compare_lib.hash_mismatches([a, b]) == {"data": {"d" * 64: ["a"], "x" * 64: ["b"]}}
    assert compare_lib.hash_mismatches([a, b, c]) == {"data (shared seed 0)": {"d" * 64: ["a"], "x" * 64: ["b"]}}
    assert compare_lib.agreed_hashes([a, b, c]) == {
        "shared seed 0": {"vae": "v" * 64}, "shared seed 1": {"data": "y" * 64, "vae": "w" * 64}}


def test_ground_truth_stage_runs_grpo_in_the_environments_from_the_supervised_policy(tmp_path, monkeypatch):
    import configs
    from sword_jax.pipeline.stages import Context
    from sim import grpo_training, policy_stages

    seen = {}

    def fake_run(cfg, inputs, *, simulator, env_workers):
        seen.update(simulator=simulator, inputs=inputs, workdir=cfg.workdir)
        return {"curve": [{"step": 0, "mean": 0.3}, {"step": 5, "mean": 0.4}], "workdir": "g"}

    monkeypatch.setattr(grpo_training, "run_grpo", fake_run)
    cfg, _ = configs.from_argv(["--config", "sword:tiny", f"--workdir={tmp_path}"])
    ctx = Context(cfg=cfg, workdir=str(tmp_path), cfg_name="sword:tiny", overrides=[])
    ctx.results.update(data={"demos": {"path": "demos.hdf5"}, "train": {"path": "train.hdf5"}},
                       sft_policy={"path": "policy_sft", "loss": 1.5, "seconds": 3.0})
    out = policy_stages.grpo_in_ground_truth(ctx)
    assert seen["simulator"] == "env" and seen["inputs"].policy == "policy_sft"
    assert seen["inputs"].demos == ("demos.hdf5",) and not seen["inputs"].world_model
    assert out["success"] == {"grpo step 0": 0.3, "grpo step 5": 0.4} and out["sft"] == {"loss": 1.5}


def test_table_names_missing_comparisons_and_slices_run_with_other_overrides(tmp_path):
    a = {**_record("wovr", 0, 0.1, (0.3, 0.2)), "overrides": ["--x=1", "--y=2"]}
    b = {**_record("sword", 0, 0.1, (0.3, 0.4)), "overrides": ["--x=1"]}
    _write(tmp_path, a)
    _write(tmp_path, b)
    compare.merge(str(tmp_path))
    text = (tmp_path / "comparison.md").read_text()
    assert "> - `--y=2` in wovr_seed0.json only" in text and "`--x=1`" not in text
    assert "No evaluated slices" not in text  # the fake records have metrics
    assert compare_lib.override_differences([a, {**a, "file": "c"}]) == {}
    assert "gained more than `wovr` at 1/1 seeds" in text  # sword +0.1 vs wovr -0.1
    only = tmp_path / "only_wovr"
    _write(only, a)
    compare.merge(str(only))
    assert "No evaluated slices of `sword` or `teacher_forcing` here." in (only / "comparison.md").read_text()


def test_exploitation_lines_compare_first_and_last_replays():
    from sword_jax.pipeline import grpo as pipeline_grpo

    def at(step, mean, fail, ok):
        by_h = {"48": {"real_failure": {"rate": fail, "of": 50}, "real_success": {"rate": ok, "of": 50}}}
        return {"step": step, "mean": mean, "replay": {"imagined_success_by_horizon": by_h}}

    lines = compare_lib.exploitation_lines([
        {"run": "sword", "seed": 1, "success_curve": [at(0, 0.30, 0.07, 0.34), at(25, 0.33, 0.15, 0.32), at(50, 0.23, 0.16, 0.28)],
         "policy": {"grpo": {"training_success": pipeline_grpo.training_success(
             [{"step": k + 1, "success_rate": 0.1 if k < 10 else 0.5} for k in range(50)])}}},
        {"run": "wovr", "seed": 1, "success_curve": [at(0, 0.30, 0.03, 0.24), at(50, 0.35, 0.02, 0.30)]},
        {"run": "wovr", "seed": 2, "success_curve": [at(0, 0.30, 0.03, 0.24)]}])  # one evaluation: no row
    assert "| sword | 1 | 0 -> 50 | 0.10 -> 0.50 | 0.07 -> 0.16 | 0.34 -> 0.28 | 0.300 -> 0.230 |" in lines
    assert "| wovr | 1 | 0 -> 50 | | 0.03 -> 0.02 | 0.24 -> 0.30 | 0.300 -> 0.350 |" in lines  # no history: empty cell
    assert pipeline_grpo.training_success([{"step": 1, "loss": 0.0}]) == {}
    assert lines[-1] == "False success rose at 1/2 slices; real success fell at 1/2."
    assert compare_lib.exploitation_lines([{"run": "sword", "seed": 0}]) == []


def test_replay_lines_show_whether_each_simulator_separates_real_outcomes():
    rate = lambda r, of: {"rate": r, "of": of, "ci95": [0.0, 1.0]}  # noqa: E731
    replay = {"imagined_success_by_horizon": {"48": {"real_success": rate(0.4, 43), "real_failure": rate(0.19, 57)},
                                              "all": {"real_success": rate(0.5, 43), "real_failure": rate(0.6, 57)}},
              "resample_disagreement": rate(0.2, 100)}
    lines = compare_lib.replay_lines([{"run": "wovr", "seed": 0, "success_curve": [{"step": 0, "replay": replay}]},
                                  {"run": "sword", "seed": 0, "success_curve": [{"step": 0}]}])
    assert lines[-1] == "| wovr | 0 | 0.40 / 0.19 (of 43 / 57) | 0.50 / 0.60 (of 43 / 57) |  | 0.20 |"
    assert compare_lib.replay_lines([{"run": "sword", "seed": 0}]) == []
    # Two runs replayed the same episodes: each run's separation and their paired difference.
    real = [1, 1, 0, 0]
    blind = {**replay, "real_success_flags": real, "imagined_first_success": [30, -1, 30, -1]}
    seeing = {**replay, "real_success_flags": real, "imagined_first_success": [30, 40, -1, -1]}
    lines = compare_lib.replay_lines([{"run": "sword", "seed": 3, "success_curve": [{"replay": blind}]},
                                  {"run": "wovr", "seed": 3, "success_curve": [{"replay": seeing}]}])
    assert "| +0.00 [" in lines[-4] and "| +1.00 [+1.00, +1.00] |" in lines[-3]
    assert lines[-1].startswith("- seed 3: `wovr` minus `sword` separation by action 48: +1.00 [")


def test_slices_start_as_soon_as_their_runs_shared_stages_are_built(tmp_path, monkeypatch):
    """Each run's slices start once the parent has built that run's shared stages, before the next
    run's are built; a failed build starts nothing new, lets the running slices finish, and is named."""
    events = []
    real_build = compare.build_shared

    def build(run, size, **kwargs):
        events.append(("build", run))
        if run == "wovr" and kwargs["out"].endswith("fail"):
            raise RuntimeError("disk full")
        return real_build(run, size, **kwargs)

    def launch(argv, log_path, env):
        events.append(("launch", argv[argv.index("--runs") + 1]))
        return _Exited(0)

    from sim import pipeline_stages

    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages([]))
    monkeypatch.setattr(compare, "build_shared", build)
    monkeypatch.setattr(compare, "launch_slice", launch)
    argv = ["--size", "tiny", "--runs", "sword,wovr,ground_truth", "--seeds", "1", "--no-evaluate", "--shared-seed",
            "slice", "--slices-at-once", "3", f"--results={tmp_path / 'r'}"]
    with pytest.raises(SystemExit, match="no slice files"):  # the fake children write none
        compare.main([*argv, f"--out={tmp_path / 'ok'}"])
    assert events == [("build", "sword"), ("launch", "sword"), ("build", "wovr"), ("launch", "wovr"),
                      ("build", "ground_truth"), ("launch", "ground_truth")]
    events.clear()
    with pytest.raises(RuntimeError, match=r"shared stages of wovr at seed 1 \(RuntimeError: disk full\); not started: "
                                           r"wovr seed 1, ground_truth seed 1$"):
        compare.main([*argv, f"--out={tmp_path / 'fail'}"])
    assert events == [("build", "sword"), ("launch", "sword"), ("build", "wovr")]


def test_shared_hashes_are_cached_per_file_until_the_file_changes(tmp_path, monkeypatch):
    path = tmp_path / "x.npz"
    np.savez(path, a=np.arange(3))
    calls = []

    def compute():
        calls.append(1)
        return shared_inputs.hash_npz(str(path))

    cache = str(tmp_path / "cache")
    first = shared_inputs.cached_hash(cache, "npz", str(path), compute)
    assert shared_inputs.cached_hash(cache, "npz", str(path), compute) == first and len(calls) == 1
    assert shared_inputs.cached_hash(cache, "other kind", str(path), compute) == first and len(calls) == 2
    np.savez(path, a=np.arange(4))
    os.utime(path, ns=(1, 1))  # a rewrite changes the stamp even within the clock's resolution
    assert shared_inputs.cached_hash(cache, "npz", str(path), compute) != first and len(calls) == 3
    assert shared_inputs.cached_hash(None, "npz", str(path), compute) and len(calls) == 4  # no cache: always computed


def test_grpo_stage_records_training_success_from_the_runs_history(tmp_path, monkeypatch):
    """The slice's training success is computed from the per-step history GRPO returns (data), and every
    committed comparison-3 slice carries it, so merging reads no log."""
    import configs
    from sword_jax.pipeline.grpo import training_success
    from sword_jax.pipeline.stages import Context
    from sim import grpo_training, policy_stages

    history = [{"step": k + 1, "rollout_success": 0.1 if k < 10 else 0.7} for k in range(12)]
    monkeypatch.setattr(grpo_training, "run_grpo", lambda cfg, inputs, *, simulator, env_workers: {
        "curve": [{"step": 0, "mean": 0.3}], "workdir": "g", "history": history})
    cfg, _ = configs.from_argv(["--config", "sword:tiny", f"--workdir={tmp_path}"])
    ctx = Context(cfg=cfg, workdir=str(tmp_path), cfg_name="sword:tiny", overrides=[])
    ctx.results.update(data={"demos": {"path": "demos.hdf5"}, "train": {"path": "train.hdf5"}},
                       sft_policy={"path": "policy_sft", "seconds": 3.0})
    training = policy_stages.grpo_in_ground_truth(ctx)["grpo"]["training_success"]
    assert training == training_success(history) and training["metric"] == "rollout_success"
    assert abs(training["first"] - 0.1) < 1e-9 and abs(training["last"] - (8 * 0.1 + 2 * 0.7) / 10) < 1e-9
    committed = compare_lib.load_slices(os.path.join(compare.REPO, "benchmarks", "results", "compare", "small_grpo"))
    assert len(committed) == 9
    assert all(s["policy"]["grpo"]["training_success"]["steps"] == 50 for s in committed)


class _RunsFor:
    """A launched slice that exits 0 after ``polls`` polls."""

    def __init__(self, polls: int, gpu: str):
        self.left, self.gpu, self.done = polls, gpu, False

    def poll(self):
        self.left -= 1
        self.done = self.left < 0
        return 0 if self.done else None


def test_gpus_put_each_slice_on_its_own_gpu(tmp_path):
    """--gpus: each slice runs with one GPU visible, the one fewest running slices hold, so with as many slices
    at once as GPUs no two share one; NVLink multicast stays off in every slice."""
    import argparse

    from sword_jax.pipeline import slices
    from sword_jax.pipeline.launch import NO_MULTICAST

    started, procs = [], []

    def launch(argv, log_path, env):
        gpu = env["CUDA_VISIBLE_DEVICES"]
        assert not [p for p in procs if p.gpu == gpu and not p.done], f"GPU {gpu} already holds a running slice"
        started.append((argv[argv.index("--seeds") + 1], gpu, env))
        procs.append(_RunsFor(polls=3 - len(started) % 3, gpu=gpu))  # uneven lengths: GPUs free up out of order
        return procs[-1]

    args = argparse.Namespace(out=str(tmp_path), slices_at_once=2, no_share=True, shared_seed=0, gpus=["2", "5"])
    slices.run_slices_side_by_side(["--size", "tiny", "--gpus", "2,5", "--slices-at-once", "2"], ["sword"],
                                   [0, 1, 2, 3], args, [], build=None, launch=launch, poll_s=0.0)
    assert [s[1] for s in started[:2]] == ["2", "5"] and sorted(s[1] for s in started) == ["2", "2", "5", "5"]
    assert all(env[k] == v for _, _, env in started for k, v in NO_MULTICAST.items())
    assert [s[0] for s in started] == ["0", "1", "2", "3"]


@pytest.mark.parametrize("gpus", ["", "0,,1", "0,1,0"])
def test_a_bad_gpu_list_is_refused(gpus, tmp_path):
    from sword_jax.cli import UsageError

    with pytest.raises(UsageError, match="--gpus takes comma-separated GPUs"):
        compare.main(["--size", "tiny", "--gpus", gpus, f"--out={tmp_path}"])


class _Stoppable:
    """A launched slice that runs until it is sent a signal, then exits ``code`` (75: stopped on request)."""

    def __init__(self, code: int = 75):
        self.code, self.signals = code, []

    def poll(self):
        return self.code if self.signals else None

    def send_signal(self, sig):
        self.signals.append(sig)


def _slice_args(tmp_path, at_once=2, no_share=True):
    import argparse

    return argparse.Namespace(out=str(tmp_path), slices_at_once=at_once, no_share=no_share, shared_seed=0, gpus=[],
                              size="tiny", no_policy=False, parallel=0, no_evaluate=True)


def test_a_stop_request_is_passed_to_the_running_slices_and_starts_no_more(tmp_path):
    """SIGUSR1 at the parent (its stop request): each running slice is sent the signal once, no pending slice
    starts, and once the slices have exited 75 StopRequested names them and the ones not started."""
    from sword_jax import cli
    from sword_jax.pipeline import slices

    procs = []

    def launch(argv, log_path, env):
        procs.append(_Stoppable())
        if len(procs) == 2:  # the request arrives while both slices run
            cli.request_stop()
        return procs[-1]

    try:
        with pytest.raises(cli.StopRequested, match=r"stopped on request: sword seed 0, sword seed 1; not started: "
                                                    r"sword seed 2; the same command resumes"):
            slices.run_slices_side_by_side(["--size", "tiny"], ["sword"], [0, 1, 2], _slice_args(tmp_path), [],
                                           build=None, launch=launch, poll_s=0.0)
    finally:
        cli.clear_stop_request()
    assert len(procs) == 2 and all(p.signals == [cli.STOP_SIGNAL] for p in procs)


def test_a_shared_build_that_stops_counts_as_stopped_and_a_failure_still_fails(tmp_path):
    from sword_jax import cli
    from sword_jax.pipeline import slices

    launched, built = [], []

    def build(run, size, **kwargs):
        built.append(run)
        if run == "wovr":
            raise cli.StopRequested("GRPO: stopped on request after step 3")

    def launch(argv, log_path, env):
        launched.append(argv[argv.index("--runs") + 1])
        return _Stoppable()

    try:
        with pytest.raises(cli.StopRequested, match=r"stopped on request: shared stages of wovr at seed 0, sword "
                                                    r"seed 0; not started: wovr seed 0"):
            slices.run_slices_side_by_side(["--size", "tiny"], ["sword", "wovr"], [0],
                                           _slice_args(tmp_path, no_share=False), [], build=build, launch=launch,
                                           poll_s=0.0)
    finally:
        cli.clear_stop_request()
    assert built == ["sword", "wovr"] and launched == ["sword"]

    procs = []  # the request arrives while two slices run; one then fails, the other stops: the failure is raised

    def launch_both(argv, log_path, env):
        procs.append(_Stoppable(1 if not procs else 75))
        if len(procs) == 2:
            cli.request_stop()
        return procs[-1]

    try:
        with pytest.raises(RuntimeError, match=r"slices failed: sword seed 0 \(.*\); stopped on request: sword seed 1; "
                                               r"not started: sword seed 2"):
            slices.run_slices_side_by_side(["--size", "tiny"], ["sword"], [0, 1, 2], _slice_args(tmp_path), [],
                                           build=None, launch=launch_both, poll_s=0.0)
    finally:
        cli.clear_stop_request()


def test_compare_reports_a_stop_in_a_shared_build_as_a_stop(tmp_path, monkeypatch):
    """train.compare --slices-at-once: a shared build stopped on request ends the command with StopRequested
    (cli.run: exit 75, the same command resumes), not as a failed build."""
    from sim import pipeline_stages
    from sword_jax import cli

    launched = []

    def build(run, size, **kwargs):
        if run == "wovr":
            raise cli.StopRequested("GRPO: stopped on request after step 3")

    def launch(argv, log_path, env):
        launched.append(argv[argv.index("--runs") + 1])
        return _Exited(cli.STOPPED_EXIT)  # the signal reached the running slice too

    monkeypatch.setattr(pipeline_stages, "STAGES", _fake_stages([]))
    monkeypatch.setattr(compare, "build_shared", build)
    monkeypatch.setattr(compare, "launch_slice", launch)
    try:
        with pytest.raises(cli.StopRequested, match="shared stages of wovr at seed 1.*not started: wovr seed 1"):
            compare.main(["--size", "tiny", "--runs", "sword,wovr", "--seeds", "1", "--no-evaluate", "--shared-seed",
                          "slice", "--slices-at-once", "2", f"--results={tmp_path / 'r'}", f"--out={tmp_path / 'o'}"])
    finally:
        cli.clear_stop_request()
    assert launched == ["sword"]
