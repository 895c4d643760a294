"""The stage runner's dependency rules: --only checks what a stage needs, and --parallel runs stages
side by side in their own processes, each as soon as the stages it needs are done."""

import subprocess
import sys

import pytest

from sword_jax.pipeline import stages as stagerunner
from sword_jax.pipeline.stages import Context, Stage
from sim import pipeline_stages
from train import pipeline

# A stand-in for ``train.pipeline --only STAGE``: sleeps, then writes the stage's marker with its
# start and end times (or exits with an error code and writes nothing).
FAKE_STAGE = """
import json, os, sys, time
marker, sleep, code = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
start = time.time()
time.sleep(sleep)
if code:
    sys.exit(code)
os.makedirs(os.path.dirname(marker), exist_ok=True)
with open(marker + ".tmp", "w") as f:
    json.dump({"stage": os.path.basename(marker)[:-5], "results": {"start": start, "end": time.time()}}, f)
os.replace(marker + ".tmp", marker)
"""


def _stages(needs: dict[str, tuple[str, ...]]) -> list[Stage]:
    def never(ctx):  # the parallel runner never calls a stage in its own process
        raise AssertionError("run in-process")

    return [Stage(name, never, name, needs=deps) for name, deps in needs.items()]


def _launcher(ctx: Context, sleep: dict[str, float], fail: frozenset[str] = frozenset()):
    started = []

    def launch(stage):
        started.append(stage.name)
        marker = ctx.path("stages", f"{stage.name}.json")
        return subprocess.Popen([sys.executable, "-c", FAKE_STAGE, marker, str(sleep.get(stage.name, 0.2)),
                                 "3" if stage.name in fail else "0"])

    return launch, started


DIAMOND = {"a": (), "b": ("a",), "c": ("a",), "d": ("b", "c")}


def test_parallel_stages_start_when_their_needs_are_done_and_run_side_by_side(tmp_path):
    ctx = Context(cfg=None, workdir=str(tmp_path))
    launch, started = _launcher(ctx, {"a": 0.2, "b": 1.0, "c": 1.0, "d": 0.2})
    results = stagerunner.run_stages_parallel(_stages(DIAMOND), ctx, launch, max_running=2, poll_s=0.05,
                                              log=lambda *_: None)
    assert started == ["a", "b", "c", "d"] and set(results) == set(DIAMOND)
    a, b, c, d = (results[k] for k in "abcd")
    assert b["start"] >= a["end"] and c["start"] >= a["end"]  # after what they need
    assert d["start"] >= max(b["end"], c["end"])
    assert b["start"] < c["end"] and c["start"] < b["end"]  # b and c overlapped


def test_parallel_respects_max_running(tmp_path):
    ctx = Context(cfg=None, workdir=str(tmp_path))
    launch, _ = _launcher(ctx, {"b": 0.4, "c": 0.4})
    results = stagerunner.run_stages_parallel(_stages(DIAMOND), ctx, launch, max_running=1, poll_s=0.05,
                                              log=lambda *_: None)
    b, c = results["b"], results["c"]
    assert c["start"] >= b["end"]  # one at a time, in list order


def test_parallel_failure_starts_nothing_new_and_keeps_what_finished(tmp_path):
    ctx = Context(cfg=None, workdir=str(tmp_path))
    launch, started = _launcher(ctx, {"b": 0.1, "c": 0.8}, fail=frozenset({"b"}))
    with pytest.raises(RuntimeError, match=r"stage\(s\) b failed; not started: d"):
        stagerunner.run_stages_parallel(_stages(DIAMOND), ctx, launch, max_running=2, poll_s=0.05,
                                        log=lambda *_: None)
    assert started == ["a", "b", "c"]
    assert (tmp_path / "stages" / "c.json").exists()  # running alongside the failure: waited for and kept
    # A later run resumes: a and c are done, b runs again (now succeeding), then d.
    ctx = Context(cfg=None, workdir=str(tmp_path))
    launch, started = _launcher(ctx, {})
    stagerunner.run_stages_parallel(_stages(DIAMOND), ctx, launch, max_running=2, poll_s=0.05, log=lambda *_: None)
    assert started == ["b", "d"]


def test_parallel_skips_needs_outside_the_run(tmp_path):
    """A need that is not among the run's stages (left out with --skip) is not waited for."""
    ctx = Context(cfg=None, workdir=str(tmp_path))
    launch, started = _launcher(ctx, {})
    stages = [s for s in _stages(DIAMOND) if s.name != "c"]
    stagerunner.run_stages_parallel(stages, ctx, launch, max_running=2, poll_s=0.05, log=lambda *_: None)
    assert started == ["a", "b", "d"]


def test_only_runs_its_stages_and_refuses_one_whose_needs_have_not_run(tmp_path):
    calls = []

    def make(name, needs=()):
        return Stage(name, lambda ctx: calls.append(name) or {}, name, needs=needs)

    stages = [make("a"), make("b", ("a",)), make("c")]
    ctx = Context(cfg=None, workdir=str(tmp_path))
    with pytest.raises(RuntimeError, match="stage 'b' needs 'a', which has not run yet"):
        stagerunner.run_stages(stages, ctx, only={"b"}, log=lambda *_: None)
    assert calls == []
    stagerunner.run_stages(stages, ctx, only={"c"}, log=lambda *_: None)  # a and b are left for later
    assert calls == ["c"]
    stagerunner.run_stages(stages, ctx, only={"a", "b"}, log=lambda *_: None)
    assert calls == ["c", "a", "b"]


def test_every_pipeline_stage_needs_only_earlier_stages():
    stagerunner.check_order(pipeline_stages.STAGES)
    needs = {s.name: set(s.needs) for s in pipeline_stages.STAGES}
    assert {"vae"} <= needs["latents"] and "sft_policy" not in needs["vae"]  # the VAE does not wait for the policy
    assert needs["reward_model"] == {"data", "policy_data"}  # the detector does not wait for the world model
    with pytest.raises(ValueError, match="stage 'b' needs \\['c'\\], which do not come before it"):
        stagerunner.check_order(_stages({"a": (), "b": ("c",), "c": ()}))


def test_parallel_children_get_the_command_without_parallel_only_or_restart():
    argv = ["--config", "sword:small", "--parallel", "2", "--only=vae", "--restart", "--seed", "1", "--parallel=3"]
    assert stagerunner.without_flags(argv, {"--parallel": True, "--only": True, "--restart": False}) == [
        "--config", "sword:small", "--seed", "1"]


def test_parallel_refuses_bad_arguments(tmp_path):
    from sword_jax.cli import UsageError

    with pytest.raises(UsageError, match="--parallel must be >= 0"):
        pipeline.main([f"--workdir={tmp_path}", "--parallel", "-1"])
    with pytest.raises(UsageError, match="--only: unknown stage"):
        pipeline.main([f"--workdir={tmp_path}", "--only", "vea"])


# A stage that checkpoints and exits 75 when asked to stop (SIGUSR1), as one under cli.run does; it marks itself
# ready once its handler is installed.
STOPPABLE_STAGE = """
import signal, sys, time
signal.signal(signal.SIGUSR1, lambda *_: sys.exit(75))
open(sys.argv[1], "w").close()
time.sleep(60)
"""


def test_parallel_stages_are_asked_to_stop_and_the_run_ends_as_stopped(tmp_path):
    """A stop request (SIGUSR1 at train.pipeline --parallel) is passed on to the running stages, which exit 75;
    no more stages start, and StopRequested names the stopped stages and those not started."""
    import threading

    from sword_jax import cli

    ctx = Context(cfg=None, workdir=str(tmp_path))
    quick, _ = _launcher(ctx, {"a": 0.1})
    ready = {name: tmp_path / f"{name}.ready" for name in "bc"}

    def launch(stage):
        if stage.name in ready:
            return subprocess.Popen([sys.executable, "-c", STOPPABLE_STAGE, str(ready[stage.name])])
        return quick(stage)

    def ask_once_both_run():
        while not all(p.exists() for p in ready.values()):
            threading.Event().wait(0.02)
        cli.request_stop()

    asker = threading.Thread(target=ask_once_both_run, daemon=True)
    asker.start()
    lines = []
    try:
        with pytest.raises(cli.StopRequested, match=r"stopped on request: (b, c|c, b); not started: d; the same "
                                                    r"command resumes"):
            stagerunner.run_stages_parallel(_stages(DIAMOND), ctx, launch, max_running=2, poll_s=0.05,
                                            log=lines.append)
    finally:
        cli.clear_stop_request()
    assert any("asked 2 running stage(s) to stop" in line for line in lines)
    assert (tmp_path / "stages" / "a.json").exists() and not (tmp_path / "stages" / "d.json").exists()
