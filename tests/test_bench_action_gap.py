"""benchmarks.bench_action_gap: the greedy action gap and frame error of each view against hand computations on a
designed policy, the frames the policy read kept from its rollout (a tiny analytic environment), the summaries,
the refusals, and one small run on the C engine."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import configs
from benchmarks import bench_action_gap as ag
from benchmarks import bench_policy_view as pv
from sword_jax.rl.env_rollout import make_act_fns
from sword_jax.rl.imagined_check import greedy_actions
from sword_jax.rl.params_io import save_params_npz
from sword_jax.rl.policy import build_policy
from tests.test_scan_rollout import SIZE, LockstepSlide

BINS = 8
CENTRES = -0.875 + 0.25 * np.arange(BINS)  # the bin centres of 8 uniform bins over [-1, 1]


def brightness_policy(frames, tokens, proprio, proprio_valid):
    """Logits ``[n, 3, 2, BINS]`` whose argmax at chunk entry ``t``, dimension ``a`` is ``(level + t + a) % BINS``,
    ``level`` the bin of the frame's mean brightness: a policy whose actions move with brightness alone."""
    level = jnp.clip(jnp.floor(jnp.mean(frames, axis=(1, 2, 3)) * BINS), 0, BINS - 1).astype(jnp.int32)
    token = (level[:, None, None] + jnp.arange(3)[None, :, None] + jnp.arange(2)[None, None, :]) % BINS
    return 5.0 * jax.nn.one_hot(token, BINS) + 0.0 * proprio_valid[:, None, None, None]


def _flat(levels, size=16):
    return jnp.broadcast_to(jnp.asarray(levels, jnp.uint8)[:, None, None, None], (len(levels), size, size, 3))


def _no_inputs(n):
    return jnp.zeros((n, 4), jnp.int32), jnp.zeros((n, 8), jnp.float32), jnp.zeros((n,), jnp.float32)


def test_greedy_actions_are_the_bin_centres_of_the_first_executed_entries():
    frames = _flat([200, 20]).astype(jnp.float32) / 255.0  # brightness bins 6 and 0
    actions = np.asarray(greedy_actions(brightness_policy, frames, *_no_inputs(2), executed=2, action_bins=BINS))
    # entries (t, a) = (0, 0), (0, 1), (1, 0), (1, 1): tokens level + t + a, the third chunk entry left out
    np.testing.assert_allclose(actions[0], CENTRES[[6, 7, 7, 0]])
    np.testing.assert_allclose(actions[1], CENTRES[[0, 1, 1, 2]])


def test_each_views_gap_and_frame_error_are_those_of_the_frames_it_makes():
    """Flat frames: 20% dimmer moves brightness 200 to 160 (bin 6 to 5: every token one bin lower, except the
    entry that wrapped from 0 to 7) and 20 to 16 (bin 0 both); blur leaves a flat frame as it is; noise moves
    the frame, too little to move a bin."""
    frames = _flat([200, 20])
    views = jnp.asarray([pv.VIEWS[v] for v in ("real", "dim_20pct", "blur_2px", "noise_8")], jnp.float32)
    run = jax.jit(lambda f, k: ag.view_gaps(brightness_policy, f, *_no_inputs(2), views, key=k, image_size=8,
                                            executed=2, action_bins=BINS))
    real_actions, frame_error, gap = (np.asarray(x) for x in run(frames, jax.random.key(0)))
    np.testing.assert_allclose(real_actions[0], CENTRES[[6, 7, 7, 0]])
    np.testing.assert_array_equal(frame_error[0], 0.0)  # the real view is the real frame
    np.testing.assert_array_equal(gap[0], 0.0)
    np.testing.assert_allclose(frame_error[1], [40 / 255, 4 / 255], atol=1e-6)
    dimmed = np.abs(CENTRES[[5, 6, 6, 7]] - CENTRES[[6, 7, 7, 0]]).mean()  # = (0.25 * 3 + 1.75) / 4
    np.testing.assert_allclose(gap[1], [dimmed, 0.0], atol=1e-6)
    np.testing.assert_allclose(frame_error[2], 0.0, atol=1e-6)
    np.testing.assert_allclose(gap[2], 0.0)
    assert np.all(frame_error[3] > 1e-3) and np.all(gap[3] == 0.0)
    # the noise is the key's: another key, other noise
    assert not np.allclose(np.asarray(run(frames, jax.random.key(1))[1][3]), frame_error[3])


def test_the_vae_view_shows_the_round_trip_of_the_real_frame_and_the_other_views_do_not():
    """A round trip that shows every frame at brightness 20 (bin 0): the view vae's frame error is the distance
    to that flat frame, its gap that of bin 6's actions to bin 0's; the real view stays the real frame."""
    frames = _flat([200, 20])
    views = jnp.asarray([pv.VIEWS[v] for v in ("real", "vae", "dim_20pct")], jnp.float32)
    calls = []

    def to_twenty(unit):
        calls.append(unit.dtype)
        return jnp.full_like(unit, 20 / 255)

    real_actions, frame_error, gap = (np.asarray(x) for x in jax.jit(
        lambda f, k: ag.view_gaps(brightness_policy, f, *_no_inputs(2), views, key=k, image_size=8, executed=2,
                                  action_bins=BINS, round_trip=to_twenty))(frames, jax.random.key(0)))
    assert calls == [jnp.float32], "the round trip reads frames in [0, 1]"
    np.testing.assert_array_equal(frame_error[0], 0.0)
    np.testing.assert_array_equal(gap[0], 0.0)
    np.testing.assert_allclose(frame_error[1], [180 / 255, 0.0], atol=1e-6)
    np.testing.assert_allclose(gap[1], [np.abs(CENTRES[[0, 1, 1, 2]] - CENTRES[[6, 7, 7, 0]]).mean(), 0.0], atol=1e-6)
    np.testing.assert_allclose(frame_error[2], [40 / 255, 4 / 255], atol=1e-6)  # dimmed, not round-tripped


def test_the_kept_frames_are_those_the_policy_read_and_end_with_the_episode():
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, env=dataclasses.replace(cfg.rl.env, execute_steps=2,
                                                                             action_ensemble=False))
    graphdef, params = build_policy(rl, seed=0)
    envs = LockstepSlide([[0.3], [-0.2], [0.0]], ["push it"] * 3, max_steps=4)
    frames, taken, rollout = ag.policy_frames(make_act_fns(graphdef, rl), params, envs, rl, decisions=3,
                                              key=jax.random.key(0))
    assert frames.shape == (3, 3, SIZE, SIZE, 3) and frames.dtype == np.uint8
    np.testing.assert_array_equal(taken, np.asarray(rollout.valid[:, :3]) > 0)
    assert not taken[:, 2].any(), "the step limit of 4 actions ends every episode after two decisions"
    np.testing.assert_array_equal(frames[:, 0], envs.env._obs(jnp.asarray([0.3, -0.2, 0.0]))["frames"])
    read = np.asarray(rollout.obs_frames)[:, :3]  # what the policy read, at its own size
    np.testing.assert_array_equal(np.where(taken[..., None, None, None], frames, 0),
                                  np.where(taken[..., None, None, None], read, 0))
    assert np.all(np.asarray(rollout.proprio_valid) == 0.0), "the policy reads its missing-proprio input"


def test_lagged_environments_show_the_frame_of_the_decision_before():
    """Through :class:`LaggedEnvs` the policy reads at each decision what it would have read at the one before
    (the start frame at the first); proprio and success are the environment's; the lag's success is measured
    against the real frames' with the same key."""
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, image_size=SIZE, env=dataclasses.replace(cfg.rl.env, execute_steps=2,
                                                                             action_ensemble=False))
    plain, lagged = (LockstepSlide([[0.3], [-0.2]], ["push it"] * 2, max_steps=8) for _ in range(2))
    seen = ag.LaggedEnvs(lagged)
    assert seen.n == 2 and seen.language == ["push it"] * 2
    read = [plain.reset()["frames"]]
    np.testing.assert_array_equal(seen.reset()["frames"], read[0])
    actions = np.full((2, 2, 7), 0.5, np.float32)
    for _ in range(3):
        real, late = plain.step(actions), seen.step(actions)
        np.testing.assert_array_equal(late["frames"], read[-1])
        assert not np.array_equal(late["frames"], real["frames"])
        np.testing.assert_array_equal(late["proprio"], real["proprio"])
        np.testing.assert_array_equal(late["success"], real["success"])
        read.append(real["frames"])
    graphdef, params = build_policy(rl, seed=0)
    out = ag.lag_success(make_act_fns(graphdef, rl), params, plain, rl, max_steps=8, tasks=[0, 0],
                         key=jax.random.key(0))
    assert out["real"]["episodes"] == out["lag_1"]["episodes"] == 2
    assert out["difference"]["mean"] == out["lag_1"]["mean"] - out["real"]["mean"]
    lo, hi = out["difference"]["ci95"]
    assert lo <= out["difference"]["mean"] <= hi
    with_proprio = ag.lag_success(make_act_fns(graphdef, rl), params, plain, rl, max_steps=8, tasks=[0, 0],
                                  key=jax.random.key(0), proprio="true")
    assert with_proprio["real"]["episodes"] == 2
    with pytest.raises(ValueError, match="proprio"):
        ag.lag_success(make_act_fns(graphdef, rl), params, plain, rl, max_steps=8, tasks=[0, 0],
                       key=jax.random.key(0), proprio="reckoned")  # reckoned needs the action convention


def test_late_environments_show_the_frame_some_actions_before_the_decisions_end():
    """Through :class:`LateEnvs` with a lag of j actions the policy reads the frame after a decision's first k - j
    actions; proprio, success, executed and done are those after all k; a lag outside 1..k-1 is refused."""
    plain, late = (LockstepSlide([[0.3], [-0.2]], ["push it"] * 2, max_steps=8) for _ in range(2))
    seen = ag.LateEnvs(late, 1)
    assert seen.n == 2 and seen.language == ["push it"] * 2
    np.testing.assert_array_equal(seen.reset()["frames"], plain.reset()["frames"])
    actions = np.full((2, 3, 7), 0.5, np.float32)
    for _ in range(2):
        first = plain.step(actions[:, :2])
        after = plain.step(actions[:, 2:])
        shown = seen.step(actions)
        np.testing.assert_array_equal(shown["frames"], first["frames"])
        assert not np.array_equal(shown["frames"], after["frames"])
        np.testing.assert_array_equal(shown["proprio"], after["proprio"])
        np.testing.assert_array_equal(shown["success"], first["success"] | after["success"])
        np.testing.assert_array_equal(shown["executed"], first["executed"] + after["executed"])
        np.testing.assert_array_equal(shown["done"], after["done"])
    with pytest.raises(ValueError, match="needs decisions of more actions, got 1"):
        seen.step(actions[:, :1])
    with pytest.raises(ValueError, match="lag must be >= 1 action, got 0"):
        ag.LateEnvs(late, 0)


def test_consecutive_decisions_and_the_summary_over_episodes():
    taken = np.asarray([[True, True, True], [True, True, False]])
    actions = np.asarray([[[0.0, 0.0], [0.5, -0.5], [0.5, 0.5]], [[1.0, 1.0], [0.0, 1.0], [np.nan, np.nan]]])
    small = np.zeros((2, 3, 2, 2, 3))
    small[0, 1] = 0.1
    frame_error, gap = ag.consecutive(actions, small, taken)
    np.testing.assert_allclose(gap, [[0.5, 0.5], [0.5, np.nan]])
    np.testing.assert_allclose(frame_error, [[0.1, 0.1], [0.0, np.nan]])

    values = np.asarray([[0.1, 0.3, np.nan], [0.5, np.nan, np.nan], [0.2, 0.2, 0.2]])
    out = ag.summarize(values)
    assert out["mean"] == pytest.approx(1.5 / 6) and out["frames"] == 6
    np.testing.assert_allclose(out["per_decision"], [0.8 / 3, 0.25, 0.2], atol=1e-5)
    assert out["ci95"][0] < out["mean"] < out["ci95"][1] and 0.1 <= out["ci95"][0] and out["ci95"][1] <= 0.5
    one = ag.summarize(np.asarray([[0.3, 0.1]]))  # one episode: nothing to resample
    assert one["ci95"] == [pytest.approx(0.2)] * 2 and one["per_decision"] == [0.3, 0.1]
    none = ag.summarize(np.full((2, 2), np.nan))
    assert none["mean"] is None and none["frames"] == 0 and none["per_decision"] == [None, None]


def test_bad_arguments_are_refused_before_anything_runs():
    base = ["--policy", "missing.npz", "--out", "o"]
    with pytest.raises(SystemExit, match="--episodes-per-task and --decisions must be >= 1 .* got 0, 12 and 0"):
        ag.main(base + ["--episodes-per-task", "0"])
    with pytest.raises(SystemExit, match="got 3, 0 and 0"):
        ag.main(base + ["--decisions", "0"])
    with pytest.raises(SystemExit, match=r"--views must name some of real, blur_1px.*got \['real', 'sepia'\]"):
        ag.main(base + ["--views", "real,sepia"])
    with pytest.raises(SystemExit, match="give it with --vae"):
        ag.main(base + ["--views", "vae"])
    with pytest.raises(SystemExit, match="--lag-episodes-per-task"):
        ag.main(base + ["--views", "lag_1"])
    with pytest.raises(SystemExit, match="--lag-episodes-per-task >= 0"):
        ag.main(base + ["--lag-episodes-per-task", "-1"])
    with pytest.raises(SystemExit, match="--lag-proprio must list some of true, reckoned, missing once each"):
        ag.main(base + ["--lag-proprio", "true,true"])
    with pytest.raises(SystemExit, match="--lag-proprio must list"):
        ag.main(base + ["--lag-proprio", "exact"])
    with pytest.raises(SystemExit, match="needs the policy's reckoning missing.reckoning.json"):
        ag.main(base + ["--lag-proprio", "missing,reckoned"])
    with pytest.raises(SystemExit, match="--lag-keyframe-steps .* and --demos go together, got 2 and 0"):
        ag.main(base + ["--lag-keyframe-steps", "2"])
    with pytest.raises(SystemExit, match="go together, got 0 and 1"):
        ag.main(base + ["--demos", "d.hdf5"])
    with pytest.raises(SystemExit, match="no such demonstration file: nowhere.hdf5"):
        ag.main(base + ["--lag-keyframe-steps", "1", "--demos", "nowhere.hdf5"])
    with pytest.raises(SystemExit, match="--lag-late-actions needs --lag-keyframe-steps and distinct lags from 1 to 3"):
        ag.main(base + ["--lag-late-actions", "1", "--rl.imagined.execute_steps=4"])
    with pytest.raises(SystemExit, match="distinct lags from 1 to 3 .* got '1,4'"):
        ag.main(base + ["--lag-late-actions", "1,4", "--rl.imagined.execute_steps=4", "--lag-keyframe-steps", "1"])
    with pytest.raises(SystemExit, match="--lag-late-actions must be a comma list of ints, got 'a'"):
        ag.main(base + ["--lag-late-actions", "a"])
    with pytest.raises(SystemExit, match="--lag-workers must be >= 0, got -1"):
        ag.main(base + ["--lag-workers", "-1"])
    assert ag.parse_views("dim_20pct,real") == ["dim_20pct", "real"]
    assert ag.parse_views("dim_20pct,real", vae=True) == ["dim_20pct", "real", "vae"]  # --vae adds its view
    assert ag.parse_views("vae,real", vae=True) == ["vae", "real"]
    assert not {"vae", "lag_1"} & set(ag.GAP_VIEWS) and set(ag.GAP_VIEWS) < set(pv.VIEWS)


def test_a_small_run_on_the_c_engine_writes_its_table(tmp_path):
    cfg = configs.get("sword:tiny")
    path = str(tmp_path / "policy.npz")
    save_params_npz(path, build_policy(cfg.rl, seed=cfg.seed)[1])
    argv = ["--config", "sword:tiny", "--sim.tasks=0", "--rl.imagined.execute_steps=4",
            "--policy", path, "--episodes-per-task", "2", "--decisions", "2", "--views", "real,dim_20pct",
            "--out", str(tmp_path / "out"), "--lag-episodes-per-task", "1", "--lag-proprio", "true,missing",
            "--sim.max_steps=8"]
    results = ag.main(argv)
    with open(tmp_path / "out" / "action_gap.json") as f:
        assert json.load(f) == json.loads(json.dumps(results))
    assert results["episodes"] == 2 and results["frames"] == 4 and results["argv"] == argv
    by_proprio = results["lag_by_proprio"]
    assert list(by_proprio) == ["true", "missing"] and results["lag"] == by_proprio["true"]  # the first listed
    assert "proprio true" in by_proprio["true"]["mode"] and "proprio missing" in by_proprio["missing"]["mode"]
    assert all(lag[k]["episodes"] == 1 for lag in by_proprio.values() for k in ("real", "lag_1"))
    assert list(results["views"]) == ["real", "dim_20pct"]
    real, dim = results["views"]["real"], results["views"]["dim_20pct"]
    assert real["action_gap"]["mean"] == 0.0 and real["frame_error"]["mean"] == 0.0
    assert dim["frame_error"]["mean"] > 0.01 and dim["action_gap"]["frames"] == 4
    assert len(dim["action_gap"]["per_decision"]) == 2
    assert results["consecutive_decisions"]["frame_error"]["frames"] == 2
    assert os.path.basename(results["policy"]) == "policy.npz"


def test_the_lag_by_start_rolls_out_ground_truth_grpos_keyframe_starts_on_real_and_late_frames(tmp_path):
    """--lag-keyframe-steps with --demos: the start states of ground-truth GRPO's first steps from the
    demonstrations' keyframes, each rolled out on real and on late frames, counted by the start's step; the real
    frames' counts are those of the same rollouts run directly with the step's key."""
    from sim import grpo_env
    from sim.dataset import read_dataset
    from sim.lockstep import LockstepEnvs
    from sword_jax.rl import data as rl_data
    from sword_jax.rl.imagined_check import START_STEP_EDGES
    from train import gen_data

    demos = str(tmp_path / "demos.hdf5")
    gen_data.main(["--task", "0", "--episodes", "2", "--out", demos, "--resolution", "32", "--max-steps", "60",
                   "--stop-at-success"])
    cfg = configs.get("sword:tiny")
    path = str(tmp_path / "policy.npz")
    graphdef, params = build_policy(cfg.rl, seed=cfg.seed)
    save_params_npz(path, params)
    overrides = ["--sim.tasks=0", "--rl.imagined.execute_steps=4", "--rl.imagined.max_chunks=3",
                 "--rl.imagined.keyframe_fraction=1.0", "--rl.grpo.rollout_batch=3", "--rl.grpo.group_size=2"]
    results = ag.main(["--config", "sword:tiny", *overrides, "--policy", path, "--episodes-per-task", "1",
                       "--decisions", "1", "--views", "real", "--out", str(tmp_path / "out"),
                       "--lag-keyframe-steps", "2", "--demos", demos, "--lag-late-actions", "2"])
    lag = results["lag_by_start"]
    assert lag["steps"] == 2 and lag["starts_per_step"] == 3 and lag["group_size"] == 2 and lag["demos"] == [demos]
    assert lag["late_actions"] == [2]
    assert "12 actions from keyframes" in lag["mode"] and "4 actions a decision" in lag["mode"]
    cfg, _ = configs.from_argv(["--config", "sword:tiny", *overrides])
    episodes = rl_data.load_episodes([demos], read=read_dataset)
    steps = np.concatenate([np.repeat(grpo_env.keyframe_steps(episodes, cfg.rl, seed=cfg.seed, step=k), 2)
                            for k in range(2)])
    for view in ("real", "lag_1", "late_2_actions"):
        assert [b["from_step"] for b in lag[view]] == list(START_STEP_EDGES)
        assert sum(b["rollouts"] for b in lag[view]) == 12
        for b, hi in zip(lag[view], [*START_STEP_EDGES[1:], 10**9]):
            assert b["rollouts"] == int(np.sum((steps >= b["from_step"]) & (steps < hi)))
            assert 0 <= b["real"] <= b["rollouts"]
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=4, action_ensemble=False))
    starts = grpo_env.keyframe_env_starts(episodes, cfg.rl, seed=cfg.seed, step=1)
    with LockstepEnvs(starts, resolution=32, max_steps=12) as envs:
        direct = ag.lag_by_start(make_act_fns(graphdef, rl), params, envs, rl, draws=[(starts, steps[6:])], horizon=12,
                                 key=jax.random.key(cfg.seed))
        once = ag.run_policy(make_act_fns(graphdef, rl), params, envs, rl, greedy=False, max_steps=12,
                             key=jax.random.fold_in(jax.random.key(cfg.seed), 1), episodes=starts, record=False,
                             proprio="missing")
    assert sum(b["real"] for b in direct["real"]) == int(np.sum(once.success))
    assert sum(b["rollouts"] for b in direct["lag_1"]) == 6
    spread = ag.keyframe_lag(cfg, rl, graphdef, params, demos=[demos], steps=2, late_actions=[2], workers=2)
    assert all(spread[view] == lag[view] for view in ("real", "lag_1", "late_2_actions"))  # the same outcomes


@pytest.mark.slow  # the C engine run beside it covers the table in the default run
def test_a_small_run_with_a_vae_adds_its_round_trip_view(tmp_path):
    """--vae DIR (a tiny random VAE saved as train_vae saves one) adds the view vae to the table: the real frames
    round-tripped through it, which a random VAE moves."""
    from flax import nnx

    from sword_jax.checkpoint import Checkpointer
    from sword_jax.vae import api as vae_api

    cfg = configs.get("sword:tiny")
    path = str(tmp_path / "policy.npz")
    save_params_npz(path, build_policy(cfg.rl, seed=cfg.seed)[1])
    vae_dir = str(tmp_path / "vae")
    with Checkpointer(vae_dir) as ckpt:
        ckpt.save(0, nnx.to_pure_dict(nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(1)))[1]), {})
    argv = ["--config", "sword:tiny", "--sim.tasks=0", "--rl.imagined.execute_steps=4", "--policy", path,
            "--episodes-per-task", "1", "--decisions", "2", "--views", "real", "--vae", vae_dir,
            "--out", str(tmp_path / "out")]
    results = ag.main(argv)
    with open(tmp_path / "out" / "action_gap.json") as f:
        assert json.load(f) == json.loads(json.dumps(results))
    assert list(results["views"]) == ["real", "vae"] and results["vae"] == vae_dir
    vae = results["views"]["vae"]
    assert vae["parameters"]["vae_round_trip"] == 1.0
    assert vae["frame_error"]["mean"] > 0.01 and vae["action_gap"]["frames"] == results["frames"] == 2
    assert results["views"]["real"]["frame_error"]["mean"] == 0.0
