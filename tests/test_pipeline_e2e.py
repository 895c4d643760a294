"""The real pipeline end to end on the tiny config (no stage monkeypatched): data, SFT, policy rollouts,
VAE, latents, world model, success detector on state labels, then GRPO inside the world model with its
real-environment evaluations in both proprio modes and the replay of the evaluated episodes in the world
model (issue 22, item 10; issue 17). About 3 minutes on 2 cores."""

import json
import os
import subprocess
import sys

import pytest

from tests.conftest import REPO, example_env


@pytest.mark.slow
def test_tiny_pipeline_runs_every_stage_through_grpo_in_the_world_model(tmp_path):
    workdir = str(tmp_path / "run")
    # A fresh process with one CPU device, as a user runs it (the suite's 8 fake devices do not divide tiny batches).
    run = subprocess.run([sys.executable, "-m", "train.pipeline", "--config", "sword:tiny", f"--workdir={workdir}",
                          "--skip", "probe,evaluate", "--stop-after", "policy", "--rl.env.execute_steps=4",
                          "--rl.env.action_ensemble=false", "--rl.grpo.steps=2", "--rl.grpo.eval_every=2"],
                         cwd=REPO, env=example_env(), capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    with open(os.path.join(workdir, "stages", "policy.json")) as f:
        policy = json.load(f)["results"]
    # The detector learned the success predicate from the fixed-length expert episodes, which show solved frames.
    with open(os.path.join(workdir, "rl", "reward_result.json")) as f:
        reward = json.load(f)
    assert reward["labels"] == "state" and reward["holdout"]["true_success"]["solved_frames"] > 0
    with open(os.path.join(workdir, "rl", "grpo", "success_curve.json")) as f:
        points = json.load(f)["points"]
    assert [p["step"] for p in points] == [0, 2]
    for point in points:  # real-environment success, with the mode GRPO trained (proprio masked) beside it
        assert 0.0 <= point["mean"] <= 1.0 and point["episodes"] == 2
        assert point["proprio_masked"]["proprio"] == "missing" and point["proprio_masked"]["episodes"] == 2
        # the evaluated episodes replayed in the world model from frame 4, judged by the detector
        replay = point["replay"]
        assert replay["episodes"] + replay["left_out"] == 2 and sum(replay["counts"].values()) == replay["episodes"]
        assert replay["real_success"] == (None if not replay["episodes"] else sum(replay["real_success_flags"]) / replay["episodes"])
        assert replay["settle_steps"] == 8 and sorted(replay["sustained_success_sweep"], key=int) == ["1", "2", "4", "8"]
        assert list(replay["imagined_success_by_horizon"]) == ["24", "48", "96", "all"]
        assert len(replay["imagined_longest_success_run"]) == replay["episodes"]
    assert set(policy["success"]) == {"grpo step 0", "grpo step 2"}
    # the world model measured on held-out expert episodes and on held-out rollouts of the supervised policy
    with open(os.path.join(workdir, "stages", "latents.json")) as f:
        latents = json.load(f)["results"]
    with open(os.path.join(workdir, "stages", "policy_data.json")) as f:
        rolled = json.load(f)["results"]
    assert latents["heldout_policy_episodes"] == rolled["heldout"]["episodes"] > 0
    with open(os.path.join(workdir, "world_model", "metrics.jsonl")) as f:
        measured = [r for r in map(json.loads, f) if "eval_policy_loss" in r]
    assert measured and all(r["eval_policy_loss"] > 0 and r["eval_heldout_loss"] > 0 for r in measured)
    # and on the training episodes that are the policy's rollouts (the latents file's sources)
    assert all(r["eval_trainpolicy_loss"] > 0 for r in measured) and latents["policy_episodes"] > 0
