"""The pipeline's stage runner: --stop-after, resuming after it, and the stage order."""

import os

from sim import pipeline_stages
from train import pipeline
from sword_jax.pipeline.stages import Stage


def test_stop_after_then_resume(tmp_path, monkeypatch):
    calls = []

    def make(name):
        def run(ctx):
            calls.append(name)
            return {"upstream": sorted(ctx.results)}

        return Stage(name, run, name)

    monkeypatch.setattr(pipeline_stages, "STAGES", [make("a"), make("b"), make("c")])
    workdir = f"--workdir={tmp_path / 'run'}"
    results = pipeline.main([workdir, "--stop-after", "b"])
    assert calls == ["a", "b"] and set(results) == {"a", "b"}
    results = pipeline.main([workdir])
    assert calls == ["a", "b", "c"]  # a and b were done: skipped, their results reused
    assert results["c"]["upstream"] == ["a", "b"]


def test_policy_work_is_resumable_stages_around_the_world_model():
    names = [stage.name for stage in pipeline_stages.STAGES]
    assert names[-2:] == ["policy", "report"]
    assert names.index("world_model") < names.index("policy")
    # The supervised policy's own rollouts (successes and failures) join the world model's data.
    assert names.index("data") < names.index("sft_policy") < names.index("policy_data") < names.index("latents")
    # The probe and the success detector score action following inside the evaluation.
    assert names.index("probe") < names.index("evaluate") and names.index("reward_model") < names.index("evaluate")


def test_stages_call_the_orchestration_with_the_config_their_command_line_would_parse(tmp_path, monkeypatch):
    """Each stage hands the function its entry point calls (``run_<part>``) the pipeline's typed config (work
    dir and data path set for the stage): the config ``python -m train.X`` parses from the same flags.
    ``--seed 3`` (two tokens) once fell out of the argv the pipeline rebuilt for its entry points."""
    import configs
    from sim import (data_stages, grpo_training, policy_stages, policy_training, probe_training, reward_training,
                     vae_training, world_model_eval)
    from sword_jax.pipeline import world_model
    from sword_jax.pipeline.stages import Context

    base = ["--config", "sword:tiny", "--seed", "3", "--model.num_layers=1", f"--workdir={tmp_path}"]
    cfg, _ = configs.from_argv(base)
    ctx = Context(cfg=cfg, workdir=str(tmp_path), cfg_name="sword:tiny", results={
        "data": {"train": {"path": "train.hdf5"}, "demos": {"path": "demos.hdf5"}},
        "vae": {"path": "vae_dir"}, "latents": {"path": "latents.npz", "heldout_path": "held.npz"},
        "world_model": {"workdir": "wm_dir"},
        "probe": {"path": "probe.npz"}, "reward_model": {"path": "rm_dir"}, "sft_policy": {"path": "sft_dir"}})
    calls = {}

    def stub(name, result):
        def run(cfg, *args, **kwargs):
            calls[name] = (cfg, args, kwargs)
            return dict(result)
        return run

    monkeypatch.setattr(vae_training, "run_vae", stub("vae", {"steps": 0}))
    monkeypatch.setattr(world_model, "run_world_model", stub("world_model", {"step": 2, "metrics": {}}))
    monkeypatch.setattr(probe_training, "run_probe", stub("probe", {"path": "probe.npz"}))
    monkeypatch.setattr(world_model_eval, "run_evaluation", stub("evaluate", {"report": "report.md", "out": "eval_dir"}))
    monkeypatch.setattr(data_stages, "write_eval_splits", lambda ctx: {"original": "o.npz", "mixed": "m.npz"})
    monkeypatch.setattr(reward_training, "run_reward_model", stub("reward_model", {"path": "rm_dir"}))
    monkeypatch.setattr(policy_training, "run_sft_policy", stub("sft_policy", {"path": "sft_dir"}))
    monkeypatch.setattr(grpo_training, "run_grpo",
                        stub("policy", {"curve": [{"step": 0, "mean": 0.5}], "workdir": "grpo_dir"}))
    for stage in (pipeline_stages.stage_vae, pipeline_stages.stage_world_model, pipeline_stages.stage_probe,
                  pipeline_stages.stage_evaluate, policy_stages.reward_model, policy_stages.sft_policy,
                  policy_stages.grpo_in_world_model):
        stage(ctx)

    def parsed(*flags):
        return configs.from_argv(base + list(flags))[0]

    vae_dir, wm_dir = str(tmp_path / "vae_run"), str(tmp_path / "world_model")
    assert calls["vae"] == (parsed("--workdir", vae_dir), (["train.hdf5"],), {})
    assert calls["world_model"] == (parsed("--workdir", wm_dir, "--data.path=latents.npz",
                                           "--data.heldout_path=held.npz"), (), {})
    assert calls["vae"][0].seed == 3 and calls["vae"][0].model.num_layers == 1
    assert os.path.isdir(vae_dir) and os.path.isdir(wm_dir)  # made for the stage, as the entry points expect
    assert calls["probe"] == (cfg, (["train.hdf5"], str(tmp_path / "probe"), probe_training.probe_config(cfg)), {})
    eval_cfg, (inputs,), _ = calls["evaluate"]
    assert eval_cfg == cfg and inputs == world_model_eval.EvalInputs(
        models={cfg.name: "wm_dir"}, episodes={"original": "o.npz", "mixed": "m.npz"}, out=str(tmp_path / "eval"),
        vae_checkpoint="vae_dir", probe="probe.npz", reward_model="rm_dir")
    assert calls["reward_model"][:2] == (cfg, (["demos.hdf5", "train.hdf5"],))  # state labels: + fixed-length
    assert calls["sft_policy"][:2] == (cfg, (["demos.hdf5"],))
    grpo_cfg, (grpo_inputs,), grpo_kwargs = calls["policy"]
    assert grpo_cfg == cfg and grpo_kwargs["simulator"] == "world_model"
    assert grpo_inputs == grpo_training.GRPOInputs(demos=("demos.hdf5",), world_model="wm_dir", vae="vae_dir",
                                                   policy="sft_dir", reward="rm_dir")


def test_adopt_takes_over_a_donors_stages_where_their_config_sections_agree(tmp_path, monkeypatch):
    import json

    import pytest

    from sword_jax import cli

    calls = []

    def make(name):
        def run(ctx):
            calls.append((os.path.basename(ctx.workdir), name))
            return {"made_in": ctx.workdir, "upstream": {k: v.get("made_in") for k, v in sorted(ctx.results.items())}}

        return Stage(name, run, name)

    monkeypatch.setattr(pipeline_stages, "STAGES", [make("data"), make("vae"), make("world_model")])
    donor = str(tmp_path / "donor")
    pipeline.main([f"--workdir={donor}"])
    assert calls == [("donor", "data"), ("donor", "vae"), ("donor", "world_model")]
    # another world model (DLB off) on the donor's data and VAE: only its own stage runs, reading the donor's files
    calls.clear()
    results = pipeline.main([f"--workdir={tmp_path / 'tf'}", "--cache.enabled=false", "--adopt", donor])
    assert calls == [("tf", "world_model")]
    assert results["world_model"]["upstream"] == {"data": donor, "vae": donor}
    with open(tmp_path / "tf" / "config.json") as f:
        assert json.load(f)["cache"]["enabled"] is False  # the run keeps its own config
    # a VAE section that differs is not adopted: that stage runs again here, the data is still the donor's
    calls.clear()
    results = pipeline.main([f"--workdir={tmp_path / 'vae2'}", "--vae.train_steps=3", "--adopt", donor])
    assert calls == [("vae2", "vae"), ("vae2", "world_model")]
    assert results["world_model"]["upstream"] == {"data": donor, "vae": str(tmp_path / "vae2")}
    # refusals name the problem and touch nothing already made, even beside --restart
    before = sorted(os.listdir(tmp_path / "tf" / "stages"))
    (tmp_path / "empty").mkdir()
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "config.json").write_text("{not json")
    for adopt, what in ((str(tmp_path / "tf"), "own work dir"), (str(tmp_path / "empty"), "no config.json"),
                        (str(tmp_path / "bad"), "not JSON")):
        with pytest.raises(cli.UsageError, match=what):
            pipeline.main([f"--workdir={tmp_path / 'tf'}", "--cache.enabled=false", "--restart", "--adopt", adopt])
    assert sorted(os.listdir(tmp_path / "tf" / "stages")) == before


def test_a_work_dir_made_before_a_setting_existed_resumes_while_it_holds_its_default(tmp_path):
    import json

    import pytest

    import configs
    from sword_jax.pipeline.stages import check_workdir_config

    cfg = configs.get("sword:tiny")
    check_workdir_config(cfg, str(tmp_path))
    path = tmp_path / "config.json"
    stored = json.loads(path.read_text())
    del stored["rl"]["imagined"]["start_encoding"], stored["flow"]["noise_scale"]  # as an earlier version saved it
    path.write_text(json.dumps(stored))
    check_workdir_config(cfg, str(tmp_path))  # both at their defaults: the behaviour that run had
    changed = configs.from_argv(["--rl.imagined.start_encoding=prefix"])[0]
    with pytest.raises(ValueError, match="rl.imagined.start_encoding"):
        check_workdir_config(changed, str(tmp_path))
    stored["seed"] = 7  # a stored value that differs is refused as before
    path.write_text(json.dumps(stored))
    with pytest.raises(ValueError, match="seed"):
        check_workdir_config(cfg, str(tmp_path))


def test_how_the_evaluation_scores_may_change_until_it_has_run(tmp_path):
    """eval.metrics and the other scoring settings, read by the evaluate stage alone, are taken (and stored) while
    that stage has not run; once it has, they are refused naming the evaluator that scores with other settings;
    what the data stage reads of the eval section (the held-out episodes' count) is refused throughout."""
    import json

    import pytest

    import configs
    from sword_jax.pipeline.stages import check_workdir_config

    made = configs.get("sword:tiny")
    check_workdir_config(made, str(tmp_path))
    other, _ = configs.from_argv(["--config", "sword:tiny", "--eval.metrics=psnr,ssim", "--eval.report_videos=1"])
    check_workdir_config(other, str(tmp_path))
    stored = json.loads((tmp_path / "config.json").read_text())
    assert stored["eval"]["metrics"] == ["psnr", "ssim"] and stored["eval"]["report_videos"] == 1
    check_workdir_config(other, str(tmp_path))  # now the stored config
    with pytest.raises(ValueError, match="eval.num_episodes"):
        check_workdir_config(configs.from_argv(["--config", "sword:tiny", "--eval.metrics=psnr,ssim",
                                                "--eval.report_videos=1", "--eval.num_episodes=9"])[0], str(tmp_path))
    with pytest.raises(ValueError, match="seed") as refused:  # a scoring change beside another is refused with it
        check_workdir_config(configs.from_argv(["--config", "sword:tiny", "--seed", "3"])[0], str(tmp_path))
    assert "already ran" not in str(refused.value), "the evaluation has not run: no hint that it has"
    (tmp_path / "stages").mkdir()
    (tmp_path / "stages" / "evaluate.json").write_text("{}")
    with pytest.raises(ValueError, match="evaluation already ran with the stored eval.metrics.*evaluate_world_model"):
        check_workdir_config(made, str(tmp_path))
    assert json.loads((tmp_path / "config.json").read_text()) == stored, "a refused config changes nothing stored"
