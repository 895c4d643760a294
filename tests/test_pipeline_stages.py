"""The pipeline's stage runner: --stop-after, resuming after it, and the stage order."""

from train import pipeline
from train.stagerunner import Stage


def test_stop_after_then_resume(tmp_path, monkeypatch):
    calls = []

    def make(name):
        def run(ctx):
            calls.append(name)
            return {"upstream": sorted(ctx.results)}

        return Stage(name, run, name)

    monkeypatch.setattr(pipeline, "STAGES", [make("a"), make("b"), make("c")])
    workdir = f"--workdir={tmp_path / 'run'}"
    results = pipeline.main([workdir, "--stop-after", "b"])
    assert calls == ["a", "b"] and set(results) == {"a", "b"}
    results = pipeline.main([workdir])
    assert calls == ["a", "b", "c"]  # a and b were done: skipped, their results reused
    assert results["c"]["upstream"] == ["a", "b"]


def test_policy_work_is_resumable_stages_around_the_world_model():
    names = [stage.name for stage in pipeline.STAGES]
    assert names[-2:] == ["policy", "report"]
    assert names.index("world_model") < names.index("policy")
    # The supervised policy's own rollouts (successes and failures) join the world model's data.
    assert names.index("data") < names.index("sft_policy") < names.index("policy_data") < names.index("latents")
    # The probe and the success detector score action following inside the evaluation.
    assert names.index("probe") < names.index("evaluate") and names.index("reward_model") < names.index("evaluate")
