"""Smoke runs of the RL entry points on tiny data (SFT, reward model, GRPO on the toy simulator + resume)."""

import json
import os

import numpy as np
import pytest

from tests.support.rl import TINY_RL, write_demos


@pytest.mark.slow
def test_sft_and_reward_entry_points(tmp_path):
    from train import train_policy, train_reward

    data = write_demos(str(tmp_path / "demos.hdf5"))
    common = ["--config", "sword:tiny", f"--workdir={tmp_path}", "--demos", data] + TINY_RL
    result = train_policy.main(common + ["--rl.sft.steps=3", "--rl.sft.batch_size=4"])
    assert result["demos"] == 1 and np.isfinite(result["final_loss"])  # 2 successful demonstrations, 1 held out
    assert os.path.isdir(tmp_path / "rl" / "policy_sft")
    result = train_reward.main(common + ["--rl.reward_model.steps=3", "--rl.reward_model.batch_size=4"])
    assert "holdout" in result and os.path.isdir(tmp_path / "rl" / "reward_model")
    assert result["labels"] == "state" and "fires_on_failed" in result["holdout"]["true_success"]
    tail = train_reward.main(common + ["--rl.reward_model.steps=3", "--rl.reward_model.batch_size=4",
                                       "--rl.reward_model.labels=tail"])
    assert tail["labels"] == "tail" and tail["holdout"]["positives"] >= 1
    # Episodes that end where they are first solved show no solved frame: a clear error, not a detector of nothing.
    cut = str(tmp_path / "cut.hdf5")
    write_demos(cut, solved_steps=1)
    with pytest.raises(ValueError, match="no positive frame under rl.reward_model.labels=state"):
        train_reward.main(["--config", "sword:tiny", f"--workdir={tmp_path}", "--demos", cut] + TINY_RL)


@pytest.mark.slow
def test_grpo_entry_point_toy_and_resume(tmp_path):
    from sword_jax.pipeline.grpo import training_success
    from train import grpo as grpo_main

    args = ["--config", "sword:tiny", f"--workdir={tmp_path}", "--simulator", "toy", "--rl.imagined.max_chunks=2",
            "--rl.grpo.rollout_batch=2", "--rl.grpo.eval_every=2"] + TINY_RL
    grpo_main.main(args + ["--rl.grpo.steps=2"])
    out = grpo_main.main(args + ["--rl.grpo.steps=4"])  # resumes from step 2
    steps = [p["step"] for p in out["curve"]]
    assert steps == [0, 2, 4]
    with open(os.path.join(out["workdir"], "success_curve.json")) as f:
        assert len(json.load(f)["points"]) == 3
    assert os.path.exists(os.path.join(out["workdir"], "success_curve.png"))
    # The whole run's history (restored steps included), and its training-rollout summary.
    with open(os.path.join(out["workdir"], "train_history.jsonl")) as f:
        history = [json.loads(line) for line in f]
    assert [p["step"] for p in history] == [1, 2, 3, 4] and history == out["history"]
    summary = training_success(history, window=2)
    assert summary["metric"] == "success_rate" and summary["steps"] == 4
    assert summary["first"] == (history[0]["success_rate"] + history[1]["success_rate"]) / 2


@pytest.mark.slow
def test_grpo_resume_is_bit_identical_to_an_uninterrupted_run(tmp_path):
    """Start states, sampling keys and the update are functions of (seed, step): 2 + 2 steps == 4 steps."""
    import jax

    from sword_jax import checkpoint
    from train import grpo as grpo_main

    def run(workdir, *steps):
        args = ["--config", "sword:tiny", f"--workdir={workdir}", "--simulator", "toy", "--rl.imagined.max_chunks=2",
                "--rl.grpo.rollout_batch=2", "--rl.grpo.eval_every=2"] + TINY_RL
        for n in steps:
            out = grpo_main.main(args + [f"--rl.grpo.steps={n}"])
        ckpt = checkpoint.Checkpointer(os.path.join(out["workdir"], "checkpoints"))
        state, meta = ckpt.restore(None)
        ckpt.close()
        return state, meta

    resumed, meta = run(tmp_path / "a", 2, 4)
    straight, _ = run(tmp_path / "b", 4)
    assert meta["step"] == 4
    flat_a, flat_b = jax.tree.leaves(resumed), jax.tree.leaves(straight)
    assert len(flat_a) == len(flat_b) > 0
    for a, b in zip(flat_a, flat_b):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_grpo_refuses_in_several_processes_what_does_not_split_yet():
    """In a job of several processes train.grpo refuses, in one line naming the setting, the C-engine / MJX
    simulator, refreshes, and the learned simulator's replays, light decoder and reckoned proprio (not yet run over
    processes); the toy and the world model without them run there."""
    import dataclasses

    from sim.grpo_training import refuse_several_processes
    from sword_jax.rl.config import RLConfig

    rl = RLConfig()
    with pytest.raises(SystemExit, match=r"^train.grpo --simulator env does not run in several processes"):
        refuse_several_processes(rl, "env")
    refreshed = dataclasses.replace(rl, refresh=dataclasses.replace(rl.refresh, every=5))
    with pytest.raises(SystemExit, match=r"--rl.refresh.every=5 does not run in several processes.*--rl.refresh.every=0"):
        refuse_several_processes(refreshed, "world_model")
    with pytest.raises(SystemExit, match=r"^train.grpo --rl.imagined.eval_replay_episodes=\d+ does not run in several"):
        refuse_several_processes(rl, "world_model")
    unreplayed = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, eval_replay_episodes=0))
    refuse_several_processes(unreplayed, "world_model")
    refuse_several_processes(rl, "toy")
    for key, value in (("decoder", "light"), ("proprio", "reckoned")):
        other = dataclasses.replace(unreplayed, imagined=dataclasses.replace(unreplayed.imagined, **{key: value}))
        with pytest.raises(SystemExit, match=rf"^train.grpo --rl.imagined.{key}={value} does not run in several"):
            refuse_several_processes(other, "world_model")
