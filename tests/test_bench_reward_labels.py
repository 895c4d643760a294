"""benchmarks.bench_reward_labels: the detectors on the policy's own episodes under the k-frame rule."""

import json
import os

import numpy as np
import pytest

from benchmarks import bench_reward_labels as bench
from sword_jax.rl import data as rl_data


def _episodes(solved_from: list[int | None], t: int = 10) -> rl_data.EpisodeSet:
    e = len(solved_from)
    solved = np.zeros((e, t), bool)
    for i, first in enumerate(solved_from):
        if first is not None:
            solved[i, first:] = True
    return rl_data.EpisodeSet(np.zeros((e, t, 4, 4, 3), np.uint8), np.zeros((e, t, 7), np.float32),
                              np.zeros((e, t, 8), np.float32), np.full(e, t), solved.any(1),
                              ("pick up the bowl",) * e, solved)


def test_rule_reports_read_each_k_as_the_imagined_success_rule():
    # failed episodes 0 (a one-frame spike) and 1 (a two-frame run); episode 2 solved from frame 4 and scored so
    eps = _episodes([None, None, 4])
    scores = np.zeros((3, 10))
    scores[0, 2] = 0.95
    scores[1, 5:7] = 0.95
    scores[2, 4:] = 0.95
    reports = bench.rule_reports(scores, eps, 0.9)
    assert list(reports) == ["1", "2", "4", "8"]
    assert [reports[k]["fires_on_failed"] for k in reports] == [1.0, 0.5, 0.0, 0.0]
    assert [reports[k]["misses"] for k in reports] == [0.0, 0.0, 0.0, 1.0]  # a run of 6 frames never makes 8
    assert [reports[k]["separation"] for k in reports] == [0.0, 0.5, 1.0, 0.0]
    assert reports["4"]["frame_precision"] == 1.0 and reports["4"]["frame_recall"] == 3 / 6
    assert bench.rule_reports(scores[:2], _episodes([None, None]), 0.9)["1"]["separation"] is None


@pytest.mark.slow  # an end-to-end run; the rule-report test stays in the default run
def test_policy_path_end_to_end(tmp_path, monkeypatch):
    """With --policy the bench records the policy's train and held-out episodes, trains both detectors and
    reports each on both held-out sets for every k; a one-frame spike fires at k=1 and at no larger k."""
    import configs
    from sim import datagen
    from sword_jax.rl.params_io import save_params_npz
    from sword_jax.rl.policy import build_policy

    cfg = configs.get("sword:tiny")
    _, params = build_policy(cfg.rl, seed=1)
    policy = str(tmp_path / "policy.npz")
    save_params_npz(policy, params)

    def spike_scores(score, frames):  # every episode scores high on frame 1 alone
        scores = np.zeros(frames.shape[:2], np.float32)
        scores[:, 1] = 0.99
        return scores

    monkeypatch.setattr(bench, "score_episodes", spike_scores)
    data_dir, out = str(tmp_path / "data"), str(tmp_path / "out.json")
    results = bench.main(["--config", "sword:tiny", "--tasks", "0", "--per-task", "2", "--steps", "8",
                          "--detector-steps", "2", "--policy", policy, "--policy-per-task", "1",
                          "--policy-heldout-per-task", "1", "--temperature", "0.5", "--workers", "1",
                          "--data-dir", data_dir, "--out", out])
    with open(out) as f:
        assert json.load(f) == json.loads(json.dumps(results))
    assert results["resolution"] == cfg.data.image_size and set(results["labels"]) == {"tail", "state"}
    policy_results = results["policy_episodes"]
    assert policy_results["temperature"] == 0.5 and policy_results["steps"] == 8
    assert {name: s["episodes"] for name, s in policy_results["episodes"].items()} == {"policy_train": 1,
                                                                                     "policy_heldout": 1}
    detectors = policy_results["detectors"]
    assert set(detectors) == {"experts", "experts_and_policy"}
    # 2 fixed + 2 demos + 1 policy episode
    assert detectors["experts_and_policy"]["train_episodes"] == 5
    for entry in detectors.values():
        for split, episodes in (("policy_heldout", 1), ("expert_heldout", 2)):
            by_k = entry[split]
            assert list(by_k) == ["1", "2", "4", "8"]
            # 8 steps: nothing is solved, so every episode fails
            assert by_k["1"]["frames"] == 8 * episodes and by_k["1"]["episodes_failed"] == episodes
            assert by_k["1"]["fires_on_failed"] == 1.0
            assert [by_k[k]["fires_on_failed"] for k in ("2", "4", "8")] == [0.0, 0.0, 0.0]
            assert all("separation" in by_k[k] for k in by_k)
    # the expert files are reused as written; one of another size is not
    fixed = os.path.join(data_dir, "fixed.hdf5")
    written = os.path.getmtime(fixed)
    bench.generate(data_dir, (0,), 2, cfg.data.image_size, 8, 1)
    assert os.path.getmtime(fixed) == written
    gen = datagen.GenDataConfig(out=fixed, tasks=(0,), episodes=2, backend="cpu", resolution=2 * cfg.data.image_size,
                                max_steps=8, wrist_camera=False, overwrite=True, renderer="jax", noise=0.1,
                                noisy_share=0.5, seed=1)
    assert not bench.written_with(gen)
    np.savez(policy, w=np.zeros(2))
    with pytest.raises(ValueError, match="no parameter"):  # a policy of another architecture is refused
        bench.generate_policy(data_dir, cfg, cfg.rl, policy, (0,), 1, 1, 32, 4)
