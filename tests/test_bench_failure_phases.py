"""benchmarks.bench_failure_phases: the stages of designed trajectories, the branch points, the summary, the refused
command lines, and a tiny run on the C engine end to end."""

import json

import numpy as np
import pytest

from benchmarks import bench_failure_phases as fp
from sword_jax.cli import UsageError


def _path(held, xs):
    """Held at the decisions ``held``, the bowl at x positions ``xs`` (on the table's line y = 0), the plate at the
    origin."""
    bowl = np.stack([np.asarray(xs, float), np.zeros(len(xs)), np.full(len(xs), 0.9)], -1)
    return np.asarray(held, bool), bowl, np.zeros_like(bowl)


def test_each_episode_gets_its_furthest_stage():
    paths = [_path([0, 1, 0], [0.0, 0.0, 0.0]),  # succeeded (success decides, whatever the poses)
             _path([0, 0, 0], [0.3, 0.0, 0.0]),  # pushed over the plate, never held: never grasped
             _path([0, 1, 1], [0.3, 0.2, 0.1]),  # held, never within 3 cm of the plate in xy
             _path([0, 1, 0], [0.3, 0.02, 0.02]),  # held over the plate, let go: not placed
             _path([1, 0, 0], [0.3, 0.3, 0.02])]  # held away from the plate, over it only once let go
    held, bowl, plate = (np.stack([p[i] for p in paths]) for i in range(3))
    stages = fp.episode_stages(held, bowl, plate, np.array([1, 0, 0, 0, 0], bool))
    assert [fp.EPISODE_STAGES[s] for s in stages] == [
        "success", "never grasped", "grasped, never over the plate", "over the plate, not placed",
        "grasped, never over the plate"]
    assert fp.episode_stages(held, bowl, plate, np.zeros(5, bool), over_m=0.15)[2] == 3  # 10 cm is over at 15 cm
    with pytest.raises(ValueError, match=r"need held \[n, t\], bowl and plate \[n, t, 3\]"):
        fp.episode_stages(held[0], bowl[0], plate[0], np.zeros(1, bool))


def test_a_start_stage_reads_the_grasp_now_and_whether_there_was_one_before():
    bowl = np.array([[0.3, 0, 0.9], [0.3, 0, 1.0], [0.01, 0, 1.0], [0.01, 0, 0.9]])
    stages = fp.start_stages(np.array([0, 1, 1, 0], bool), bowl, np.zeros_like(bowl), np.array([0, 1, 1, 1], bool))
    assert [fp.START_STAGES[s] for s in stages] == ["before the grasp", "grasped", "over the plate", "after a release"]


def test_branch_points_are_decisions_at_which_the_episode_was_running():
    done = np.array([[0, 0, 1, 1], [0, 1, 1, 1], [1, 1, 1, 1]], bool)  # running at 2, 1 and 0 decisions
    ep, at = fp.branch_points(done, 10, np.random.default_rng(0))
    assert sorted(zip(ep.tolist(), at.tolist())) == [(0, 0), (0, 1), (1, 0)]  # all three, none twice
    ep, at = fp.branch_points(done, 2, np.random.default_rng(1))
    assert len(ep) == 2 and not done[ep, at].any()
    with pytest.raises(ValueError, match="no episode was running"):
        fp.branch_points(np.ones((2, 3), bool), 1, np.random.default_rng(0))
    ep, at = fp.branch_points(done[:2], 10, np.random.default_rng(0), at_rest=True)  # the start states alone
    assert sorted(zip(ep.tolist(), at.tolist())) == [(0, 0), (1, 0)]


def test_the_summary_counts_failures_and_where_the_mixed_groups_start():
    stages = np.array([0, 1, 1, 1, 2, 0])
    start_stage = np.array([0, 1, 2, 0])
    groups = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], bool)  # mixed: starts 1 (grasped) and 3 (before the grasp)
    s = fp.summarise(stages, start_stage, groups, np.array([5, -1, -1, -1, -1, 9]), np.array([2, -1, -1, -1, 4, 3]))
    assert s["episodes"] == 6 and s["success"] == pytest.approx(1 / 3)
    assert s["failure_shares"]["never grasped"] == pytest.approx(0.75)
    assert s["failure_shares"]["grasped, never over the plate"] == pytest.approx(0.25)
    assert s["starts"]["before the grasp"] == {"starts": 2, "mixed_groups": 1, "paid_success": 0.25}
    assert s["starts"]["after a release"] == {"starts": 0, "mixed_groups": 0, "paid_success": None}
    assert s["mixed_groups"] == 2 and s["mixed_after_the_grasp"] == pytest.approx(0.5)
    assert s["decisions_from_grasp_to_success"] == pytest.approx([3.75, 4.5, 5.25])  # 3 and 6 decisions
    assert "per_task" not in s
    by_task = fp.summarise(stages, start_stage, groups, np.array([5, -1, -1, -1, -1, 9]),
                           np.array([2, -1, -1, -1, 4, 3]), tasks=np.array([0, 0, 0, 1, 1, 1]),
                           start_tasks=np.array([1, 1, 0, 2]))["per_task"]
    assert list(by_task) == ["0", "1", "2"]  # task 2 has a start but no episode
    assert by_task["0"] == {"episodes": 3, "success": pytest.approx(1 / 3),
                            "episode_stages": {"success": 1, "never grasped": 2, "grasped, never over the plate": 0,
                                               "over the plate, not placed": 0},
                            "decisions_to_success": 5.0, "starts": 1, "mixed_groups": 0, "paid_success": 1.0}
    assert by_task["1"]["decisions_to_success"] == 9.0 and by_task["1"]["mixed_groups"] == 1
    assert by_task["1"]["paid_success"] == pytest.approx(0.25)
    assert by_task["2"]["episodes"] == 0 and by_task["2"]["success"] is None and by_task["2"]["mixed_groups"] == 1
    with pytest.raises(ValueError, match="need a task per episode"):
        fp.per_task(stages, groups, np.zeros(6), np.zeros(5), np.zeros(4))


def test_bad_command_lines_are_refused(tmp_path):
    policy = tmp_path / "p.npz"
    np.savez(policy, w=np.zeros(1))
    with pytest.raises(UsageError, match="--group-size >= 2"):
        fp.parse(["--policy", str(policy), "--out", str(tmp_path), "--group-size", "1"])
    with pytest.raises(UsageError, match="must be > 0"):
        fp.parse(["--policy", str(policy), "--out", str(tmp_path), "--over-m", "0"])
    with pytest.raises(UsageError, match="no such file"):
        fp.parse(["--policy", str(tmp_path / "missing.npz"), "--out", str(tmp_path)])


def test_the_grasp_is_read_from_the_finger_pads_contacts_along_an_expert_episode():
    """The scripted expert on the C engine: the bowl is not held at the start, is held for a stretch of the episode
    (both pads on it) without letting go, and the episode succeeds (the bowl resting on the plate, still held: an
    episode ends at its success)."""
    from sim import expert
    from sim.config import SimConfig
    from sim.env import CpuEnv
    from sim.lockstep import LockstepEnvs

    env = CpuEnv(SimConfig(resolution=16), 4)  # the bowl in the top drawer: carried down to the plate
    out = expert.rollout_cpu(env, env.init_states[3], record=True)
    assert out["success"]
    with LockstepEnvs([(4, env.init_states[3])], resolution=16, max_steps=200) as envs:
        envs.reset()
        held = [bool(envs.poses()["held"][0])]
        for action in out["actions"]:
            envs.step(action[None, None])
            held.append(bool(envs.poses()["held"][0]))
        assert envs.success[0]
    first, last = held.index(True), len(held) - 1 - held[::-1].index(True)
    assert not held[0] and held[-1] and last - first >= 10 and all(held[first: last + 1])


class _EndsAfter:
    """Lockstep-like episodes: episode ``i`` succeeds in its ``ends[i]``-th decision; ``poses`` reports as ``state``
    how many decisions it has taken."""

    def __init__(self, ends):
        self.ends, self.n, self.language = np.asarray(ends), len(ends), ["push it"] * len(ends)

    def _obs(self):
        return {"frames": np.zeros((self.n, 32, 32, 3), np.uint8), "proprio": np.zeros((self.n, 8), np.float32)}

    def reset(self, episodes=None):
        self.taken, self.done = np.zeros(self.n, int), np.zeros(self.n, bool)
        return self._obs()

    def step(self, actions):
        self.taken += ~self.done
        success = ~self.done & (self.taken == self.ends)
        self.done |= success
        return dict(self._obs(), success=success, executed=np.where(success, 1, 0), done=self.done.copy())

    def poses(self):
        return {"state": self.taken[:, None].astype(float)}


def test_a_recorded_read_lines_up_with_the_decision_it_comes_before():
    """The state read before decision c is the one run_policy marks valid at c: never the state an episode ended in
    (the branch points' source, whose misalignment would branch from finished episodes)."""
    import dataclasses

    import jax

    import configs
    from sword_jax.rl.env_rollout import make_act_fns, run_policy
    from sword_jax.rl.policy import build_policy

    rl = configs.get("sword:tiny").rl
    rl = dataclasses.replace(rl, env=dataclasses.replace(rl.env, execute_steps=1, action_ensemble=False))
    graphdef, params = build_policy(rl, seed=0)
    rec = fp.Recording(_EndsAfter([1, 3, 2]))
    out = run_policy(make_act_fns(graphdef, rl), params, rec, rl, key=jax.random.key(0), greedy=False, max_steps=5,
                     proprio="missing")
    valid = np.asarray(out.valid) > 0
    state = rec.stacked("state", valid.shape[1])[:, :-1, 0]  # the reads before each decision (the last: after all)
    assert valid.sum(1).tolist() == [1, 3, 2] and out.success.all()
    assert np.array_equal(state[valid], np.nonzero(valid)[1])  # before decision c, c decisions taken
    ep, at = fp.branch_points(~valid, 10, np.random.default_rng(0))
    assert len(ep) == 6 and np.all(state[ep, at] < np.array([1, 3, 2])[ep])  # none from an ended episode


@pytest.mark.slow  # an end-to-end run on the C engine; the file's other tests keep its tables in the default run
def test_a_tiny_run_on_the_c_engine(tmp_path, monkeypatch):
    """A random tiny policy, 3 episodes of 16 actions (4 decisions each, none succeeds) and as many short groups as
    there are branch points: every count adds up, only the 12 states before a decision are branched from (never
    the state an episode ended in), and the record carries the failure shares."""
    import configs
    from benchmarks import common
    from sword_jax.rl.params_io import save_params_npz
    from sword_jax.rl.policy import build_policy

    monkeypatch.setattr(common, "RESULTS", str(tmp_path / "latest.json"))
    _, params = build_policy(configs.get("sword:tiny").rl, seed=0)
    save_params_npz(str(tmp_path / "p.npz"), params)
    out = fp.main(["--policy", str(tmp_path / "p.npz"), "--out", str(tmp_path), "--config", "sword:tiny",
                   "--episodes", "3", "--starts", "100", "--group-size", "2", "--horizon", "1", "--max-steps", "16",
                   "--record"])
    assert out["episodes"] == 3 and sum(out["episode_stages"].values()) == 3 and out["success"] == 0
    assert sum(s["starts"] for s in out["starts"].values()) == 12 and out["episode_limit"] == 16
    assert sum(s["starts"] for s in out["per_task"].values()) == 12 and out["branch_from"] == "running"
    assert sum(s["episodes"] for s in out["per_task"].values()) == 3
    rested = fp.main(["--policy", str(tmp_path / "p.npz"), "--out", str(tmp_path / "rest"), "--config", "sword:tiny",
                      "--episodes", "3", "--starts", "100", "--group-size", "2", "--horizon", "1", "--max-steps", "16",
                      "--branch-from", "rest"])
    assert rested["branch_from"] == "rest" and rested["starts"]["before the grasp"]["starts"] == 3  # one per episode
    saved = json.loads((tmp_path / "failure_phases.json").read_text())
    assert saved["failure_shares"] == out["failure_shares"]
    entry = json.loads((tmp_path / "latest.json").read_text())["policy_failure_stages_small"]
    assert entry["value"] == out["failure_shares"].get("never grasped", entry["value"])
    # a whole chunk a decision: 16 actions are 2 decisions, so 6 states before a decision to branch from
    whole = fp.main(["--policy", str(tmp_path / "p.npz"), "--out", str(tmp_path / "whole"), "--config", "sword:tiny",
                     "--episodes", "3", "--starts", "100", "--group-size", "2", "--horizon", "1", "--max-steps", "16",
                     "--actions-per-decision", "8"])
    assert whole["actions_per_decision"] == 8 and out["actions_per_decision"] == 4
    assert sum(s["starts"] for s in whole["starts"].values()) == 6
    for bad in ("0", "9"):
        with pytest.raises(UsageError, match=f"actions a decision must be in \\[1, 8\\].*got {bad}"):
            fp.main(["--policy", str(tmp_path / "p.npz"), "--out", str(tmp_path / "bad"), "--config", "sword:tiny",
                     "--actions-per-decision", bad])
