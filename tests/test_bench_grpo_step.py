"""benchmarks.bench_grpo_step on sword:tiny: GRPO's own step timed in its three cases, the record it merges, and
its imagined frames per step counted as a GRPO run's ``step_times.jsonl`` counts them."""

import json
import math
import re

import pytest

from benchmarks import bench_grpo_step as bench
from sword_jax.cli import UsageError
from sword_jax.rl.grpo_loop import StepTimes


@pytest.mark.slow  # every case compiled end to end; the merge and argument tests stay in the default run
def test_tiny_run_records_every_case_and_counts_frames_as_grpo_does(tmp_path):
    results = tmp_path / "latest.json"
    results.write_text(json.dumps({"other_key": {"value": 1.0}}))
    out = bench.main(["--tiny", "--steps", "1", "--results", str(results)])
    written = json.loads(results.read_text())
    assert written["other_key"] == {"value": 1.0}  # merged beside the other figures
    entry = written[bench.KEY]
    for name in ("value", "target", "device", "date", "command", "rollout_batch", "group_size", "max_chunks",
                 "seed", "ratios", "cases"):
        assert name in entry, name
    cases = entry["cases"]
    assert set(cases) == {"before", "fast", "light"}
    assert [(cases[c]["precision"], cases[c]["decoder"]) for c in ("before", "fast", "light")] == [
        ("float32", "full"), ("fast", "full"), ("fast", "light")]
    assert entry["value"] == cases["light"]["imagined_frames_per_s"]
    for case in ("fast", "light"):
        assert entry["ratios"][f"{case}_over_before"] == pytest.approx(
            cases[case]["imagined_frames_per_s"] / cases["before"]["imagined_frames_per_s"])

    rl = out["config"].rl
    trajectories = rl.grpo.rollout_batch * rl.grpo.group_size
    # the bench's defaults execute 4 of each chunk's 8 actions: a chunk draws 4 frames, not rl.chunk_len
    assert (rl.imagined.execute_steps, rl.chunk_len) == (4, 8)
    assert cases["light"]["frame_size"] == rl.image_size  # the light decoder draws at the policy's size
    for case, row in cases.items():
        assert (row["trajectories"], row["frames_per_chunk"]) == (trajectories, 4), case
        (step,) = row["steps"]
        assert 1 <= step["mean_chunks"] <= rl.imagined.max_chunks and math.isfinite(step["loss"])
        # what GRPO's StepTimes writes for a step of these rollouts and this mean length
        grpo_row = StepTimes(None, trajectories * rl.imagined.execute_steps).add(1, step["mean_chunks"])
        assert step["imagined_frames"] == grpo_row["imagined_frames"] == trajectories * 4 * step["mean_chunks"]
        assert row["imagined_frames_per_step"] == step["imagined_frames"]
        assert row["imagined_frames_per_s"] == pytest.approx(step["imagined_frames"] / step["step_s"])
        assert row["frames_computed_per_step"] == trajectories * 4 * rl.imagined.max_chunks
        assert len(row["warmup_s"]) == 1


def test_tiny_run_merges_nothing_unless_asked(tmp_path, monkeypatch):
    monkeypatch.setattr(bench.common, "RESULTS", str(tmp_path / "latest.json"))
    monkeypatch.setattr(bench, "run_case", lambda cfg, case, *a, **kw: _fake_row(case))
    monkeypatch.setattr(bench, "random_weights", lambda cfg: {})
    out = bench.main(["--tiny", "--cases", "fast,before"])
    assert not (tmp_path / "latest.json").exists()
    # without the light case the value is the fastest case's; its ratio is absent, not made up
    assert out["entry"]["value"] == 200.0 and out["entry"]["ratios"] == {"fast_over_before": 2.0,
                                                                          "light_over_before": None}


def _fake_row(case):
    fps = {"before": 100.0, "fast": 200.0}[case]
    return {"case": case, "imagined_frames_per_s": fps, "trajectories": 8}


@pytest.mark.parametrize("argv,message", [(["--tiny", "--cases", "fast,slow"], "unknown case(s) ['slow']"),
                                          (["--tiny", "--warmup", "0"], "--warmup and --steps must be at least 1")])
def test_bad_arguments_are_refused_before_any_work(argv, message, monkeypatch):
    monkeypatch.setattr(bench, "random_weights", lambda cfg: pytest.fail("work began"))
    with pytest.raises(UsageError, match=re.escape(message)):
        bench.main(argv)
