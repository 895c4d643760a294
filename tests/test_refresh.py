"""GRPO in the learned simulator refreshed on the policy's real episodes (sword_jax.rl.refresh,
sword_jax.pipeline.grpo_refresh): the policy's recorded episodes, the refresh's effect on the world model and
the detector, the real-episode budget, and an exact resume across refreshes, on the tiny run's VAE and world
model with a toy pure-JAX environment standing in for MJX (MJX compiles for minutes on a CPU)."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import configs
from sword_jax import sharding as shd
from sword_jax.load import experiment_vae, experiment_world_model
from sword_jax.pipeline.grpo import GRPOInputs, world_model_setup
from sword_jax.pipeline.grpo_refresh import run_refreshed, stratified_collect_starts
from sword_jax.rl import grpo, imagined_check
from sword_jax.rl.config import RefreshConfig
from sword_jax.rl.params_io import save_params
from sword_jax.rl.policy import build_policy
from sword_jax.rl.policy_success import success_summary
from sword_jax.rl.refresh import RealEpisodes, Refresher, choose_horizon, first_success, stratified_split
from sword_jax.rl.reward_model import build_detector, shifted_reward_model, threshold_shift
from sword_jax.rl.scan_rollout import record_episodes
from sword_jax.rl.sim_builder import stored_for_simulator
from sword_jax.world_model.data import LatentDataset

SIZE = 32
TEXTS = ("put the bowl on the plate", "put the bowl in the drawer")


class Slide:
    """A square that the first action dimension moves right; success once it is past the goal. Frames at
    ``SIZE`` px, proprio 8-D (position first)."""

    goal = 0.3

    def _obs(self, pos):
        n = pos.shape[0]
        cols = jnp.arange(SIZE, dtype=jnp.float32)[None] / SIZE
        x = (pos[:, None] + 1.0) / 2.0
        column = (jnp.abs(cols - x) < 0.12).astype(jnp.float32)  # [n, W]
        img = jnp.broadcast_to(column[:, None, :, None], (n, SIZE, SIZE, 3)) * jnp.asarray([200.0, 80.0, 40.0])
        proprio = jnp.concatenate([pos[:, None], jnp.zeros((n, 7), jnp.float32)], axis=1)
        return {"frames": (img + 20.0).astype(jnp.uint8), "proprio": proprio}

    def reset(self, starts):
        pos = jnp.asarray(starts, jnp.float32)[:, 0]
        return pos, self._obs(pos)

    def step(self, pos, actions):
        pos = jnp.clip(pos + 0.08 * jnp.clip(actions[:, 0], -1.0, 1.0), -1.0, 1.0)
        return pos, self._obs(pos), pos > self.goal


def _cfg(workdir, group_size=1):
    cfg = configs.get("sword:tiny")
    rl = cfg.rl
    rl = dataclasses.replace(
        rl, env=dataclasses.replace(rl.env, execute_steps=4, action_ensemble=False, backend="mjx"),
        grpo=dataclasses.replace(rl.grpo, steps=2, eval_every=1, rollout_batch=2, group_size=2),
        imagined=dataclasses.replace(rl.imagined, max_chunks=2, execute_steps=4, eval_replay_settle_steps=2),
        reward_model=dataclasses.replace(rl.reward_model, batch_size=8),
        refresh=RefreshConfig(every=1, episodes=4, budget=6, episode_steps=cfg.data.episode_frames, world_model_steps=2,
                              detector_steps=2, replay_share=0.5, calibrate_fraction=0.5,
                              horizons=(4, 8), group_size=group_size))
    # the world model's fine-tune batch splits over the suite's 8 devices
    return dataclasses.replace(cfg, workdir=str(workdir), model=dataclasses.replace(cfg.model, num_layers=1), rl=rl,
                               data=dataclasses.replace(cfg.data, batch_size=8))


def _pool_starts(n, rng):
    tasks = np.arange(n) % 2
    return rng.uniform(-0.4, 0.2, (n, 1)).astype(np.float32), [TEXTS[t] for t in tasks], tasks


def _run(cfg, tiny_run, workdir, steps, light_decoder="", states=False):
    rl = dataclasses.replace(cfg.rl, grpo=dataclasses.replace(cfg.rl.grpo, steps=steps))
    graphdef, params = build_policy(rl, seed=0)
    det_graphdef, det_params = build_detector(rl, seed=0)
    reward = os.path.join(workdir, "detector")
    if not os.path.exists(reward):
        save_params(reward, det_params, rl, kind="reward_model", step=0)
    vae = experiment_vae(cfg, os.path.join(tiny_run, "vae_run", "vae"))
    env = Slide()
    first = jax.jit(lambda p, s, t, k: record_episodes(graphdef, p, env, s, t, rl, key=k, steps=cfg.data.episode_frames))
    from sword_jax.rl.policy import tokenize_instructions

    starts, texts, tasks = _pool_starts(4, np.random.default_rng(5))
    rec = first(params, jnp.asarray(starts), jnp.asarray(tokenize_instructions(texts, rl.policy.max_instruction_bytes)),
                jax.random.key(3))
    demos = RealEpisodes.from_recorded(jax.device_get(rec), texts, tasks)
    inputs = GRPOInputs(world_model=os.path.join(tiny_run, "world_model"), vae=os.path.join(tiny_run, "vae_run", "vae"),
                        reward=reward, light_decoder=light_decoder)
    episodes = demos.episode_set()
    if states:  # the slide's state is its position, the first proprio entry: keyframes the real env can reset to
        episodes = dataclasses.replace(episodes, states=episodes.proprio[..., :1].copy())
    setup = world_model_setup(cfg, rl, inputs, episodes)
    from sword_jax.vae import api as vae_api

    encoder = vae_api.encoder(*vae)

    def encode_frames(frames):
        return np.asarray(encoder(frames * np.float32(2.0) - np.float32(1.0)))

    base = LatentDataset(encode_frames(demos.frames[:, : cfg.data.episode_frames].astype(np.float32) / 255.0),
                         demos.actions[:, : cfg.data.episode_frames])

    def evaluate_real(step, p):
        rec = first(p, jnp.asarray(starts), jnp.asarray(tokenize_instructions(texts, rl.policy.max_instruction_bytes)),
                    jax.random.key(7))
        return success_summary(np.asarray(rec.success).any(1), tasks, 0.0), {}

    wm_graphdef, wm_state = experiment_world_model(cfg, inputs.world_model)  # float32, as trained
    _, vae_params = setup.sim.params
    precision = rl.imagined.sim_precision
    return run_refreshed(cfg, rl, graphdef, params, os.path.join(workdir, "grpo"), setup=setup, wm_state=wm_state,
                         make_simulator=lambda s: setup.sim.replace(params=(stored_for_simulator(wm_graphdef, s, precision),
                                                                            vae_params)),
                         encode_frames=encode_frames,
                         detector=(det_graphdef, setup.reward_model.params), base=base, env=env,
                         collect_starts=stratified_collect_starts(_pool_starts, cfg.seed), evaluate_real=evaluate_real,
                         max_traces=1)


@pytest.mark.slow  # ~1.5 min on 2 cores: one refresh, one GRPO step
def test_an_untrusted_simulator_leaves_the_policy_unchanged(tiny_run, tmp_path):
    cfg = _cfg(tmp_path)
    # a separation of 1 cannot be reached: the first refresh's simulator is untrusted, its steps are paused
    refresh = dataclasses.replace(cfg.rl.refresh, min_separation=1.0, pause_untrusted=True, budget=4)
    cfg = dataclasses.replace(cfg, rl=dataclasses.replace(cfg.rl, refresh=refresh))
    start = jax.device_get(build_policy(cfg.rl, seed=0)[1])
    out = _run(cfg, tiny_run, str(tmp_path), steps=1)
    assert out["refreshes"][0]["trust"]["trusted"] is False and out["refreshes"][0]["horizon"]["trusted"] is False
    assert [h["paused"] for h in out["history"]] == [1.0]
    for a, b in zip(jax.tree.leaves(start), jax.tree.leaves(jax.device_get(out["params"]))):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow  # ~1.5 min on 2 cores: one refresh, one GRPO step paid by execution
def test_a_refreshed_run_can_pay_its_rollouts_by_executing_their_actions(tiny_run, tmp_path):
    """rl.imagined.reward=executed with rl.refresh (keyframe starts, no branch): a step's trajectories are paid by
    their actions executed from the keyframes' recorded states and counted by where the starts stood, beside the
    refreshes' real episodes. Keyframes without recorded states, a refresh that branches and the calibrated reward
    with a refresh are refused."""
    cfg = _cfg(tmp_path)
    imagined = dataclasses.replace(cfg.rl.imagined, reward="executed", eval_replay_episodes=0)
    cfg = dataclasses.replace(cfg, rl=dataclasses.replace(cfg.rl, imagined=imagined,
                                                          refresh=dataclasses.replace(cfg.rl.refresh, budget=4,
                                                                                      branch=False)))
    cfg.rl.validate()
    for refused in (dataclasses.replace(cfg.rl, refresh=dataclasses.replace(cfg.rl.refresh, branch=True)),
                    dataclasses.replace(cfg.rl, imagined=dataclasses.replace(imagined, reward="calibrated",
                                                                             calibrate_steps=1))):
        with pytest.raises(ValueError, match="pays imagined actions by executing them on MJX"):
            refused.validate()
    with pytest.raises(ValueError, match="recorded states"):
        _run(cfg, tiny_run, str(tmp_path / "no_states"), steps=1)
    out = _run(cfg, tiny_run, str(tmp_path / "run"), steps=1, states=True)
    (row,) = out["history"]
    trajectories = cfg.rl.grpo.rollout_batch * cfg.rl.grpo.group_size
    assert row["real_rollouts"] == trajectories and row["real_episodes_used"] == 4
    assert sum(v for k, v in row.items() if k.startswith("start_a") and k.endswith("_rollouts")) == trajectories
    assert 0.0 <= row["detector_success"] <= 1.0 and 0.0 <= row["success_rate"] <= 1.0
    assert row["success_rate"] * trajectories == sum(v for k, v in row.items()
                                                     if k.startswith("start_a") and k.endswith("_real"))


@pytest.mark.slow  # ~1.5 min on 2 cores: one refresh with the closed loop, one GRPO step paid by execution
def test_a_refresh_fine_tunes_the_world_model_on_its_own_closed_loop_within_the_budget(tiny_run, tmp_path):
    """rl.refresh.closed_loop_starts: before the fine-tune, keyframe starts (drawn as GRPO's are) are rolled out by
    the policy in the simulator, their actions executed for real; the executions count against the budget, the
    segments (the simulator's own context, the real future) enter the fine-tune, and the record says how far the
    closed loop drifted. A budget that cannot pay for them skips them; keyframes without states are refused."""
    cfg = _cfg(tmp_path)
    imagined = dataclasses.replace(cfg.rl.imagined, reward="executed", eval_replay_episodes=0)
    starts = cfg.rl.imagined_starts_per_step
    refresh = dataclasses.replace(cfg.rl.refresh, budget=4 + starts * cfg.rl.grpo.group_size, branch=False,
                                  closed_loop_starts=starts, closed_loop_share=0.5)
    cfg = dataclasses.replace(cfg, rl=dataclasses.replace(cfg.rl, imagined=imagined, refresh=refresh))
    cfg.rl.validate()
    odd = dataclasses.replace(cfg.rl, refresh=dataclasses.replace(refresh, closed_loop_starts=starts + 1))
    with pytest.raises(ValueError, match="closed_loop_starts=3 must be a multiple"):
        odd.validate()
    with pytest.raises(ValueError, match="closed_loop_share"):
        dataclasses.replace(refresh, closed_loop_share=1.0).validate()
    with pytest.raises(ValueError, match="recorded states"):
        _run(cfg, tiny_run, str(tmp_path / "no_states"), steps=1)
    out = _run(cfg, tiny_run, str(tmp_path / "run"), steps=1, states=True)
    record = out["refreshes"][0]  # step 1's refresh is skipped: the budget is spent
    loop = record["closed_loop"]
    executions = starts * cfg.rl.grpo.group_size
    decisions = cfg.rl.imagined.max_chunks
    assert loop["episodes"] == executions and loop["actions"] == decisions * cfg.rl.imagined_actions_per_decision
    # 2 decisions of one latent, segments of 2 future latents: only the first decision's is whole
    assert loop["segments"] == executions and len(loop["latent_drift_by_decision"]) == decisions
    assert all(np.isfinite(v) and v > 0 for v in loop["latent_drift_by_decision"])
    assert 0.0 <= loop["real_success"] <= 1.0
    assert record["real_episodes_used"] == out["real_episodes_used"] == 4 + executions
    assert record["real_episodes"] == 4 and np.isfinite(record["world_model"]["last"]["loss"])
    # one trajectory's segments held out of the fine-tune, measured before and after it beside training segments
    fit = loop["fit"]
    assert fit["held_out_trajectories"] == 1
    for when in ("before", "after"):
        assert fit[when]["first_decision"]["segments"] == 1 and fit[when]["closed_loop"] is None
        assert fit[when]["training"]["segments"] == 128
        assert all(np.isfinite(fit[when][part][m]) for part in ("first_decision", "training")
                   for m in ("loss", "sample_error"))
    assert fit["before"]["training"] != fit["after"]["training"]  # the fine-tune changed the world model
    # the budget left after the refresh's own episodes does not pay for the closed loop: skipped, nothing spent
    tight = dataclasses.replace(refresh, budget=4 + executions - 1)
    cfg2 = dataclasses.replace(cfg, rl=dataclasses.replace(cfg.rl, refresh=tight))
    out2 = _run(cfg2, tiny_run, str(tmp_path / "tight"), steps=1, states=True)
    first = out2["refreshes"][0]
    assert "skipped" in first["closed_loop"] and first["real_episodes_used"] == 4


def _leaves(path):
    with np.load(path) as f:
        return [f[k] for k in sorted(f.files, key=lambda k: int(k.split("_")[1]))]


@pytest.mark.slow  # ~3.5 min on 2 cores: three short runs, each compiling the GRPO step, the fine-tunes and the replays
def test_refreshes_update_the_models_within_the_budget_and_resume_exactly(tiny_run, tmp_path):
    """Real episodes collected in groups of 2 per start (rl.refresh.group_size): each refresh's replay says how
    the simulator separates real outcomes inside the groups, and the run resumes exactly."""
    cfg = _cfg(tmp_path / "a", group_size=2)
    whole = _run(cfg, tiny_run, str(tmp_path / "a"), steps=2)
    records = whole["refreshes"]
    # refreshes at steps 0, 1 and 2: 4 + 2 real episodes, then the budget of 6 is spent
    assert [r["step"] for r in records] == [0, 1, 2]
    assert [r["real_episodes"] for r in records] == [4, 2, 0] and "budget" in records[2]["skipped"]
    assert whole["real_episodes_used"] == 6 and [h["real_episodes_used"] for h in whole["history"]] == [4, 6]
    # the world model and the detector changed at each refresh
    ref = os.path.join(str(tmp_path / "a"), "grpo", "refresh")
    wm0, wm2 = _leaves(os.path.join(ref, "step_000000", "world_model.npz")), _leaves(
        os.path.join(ref, "step_000001", "world_model.npz"))
    det0, det2 = _leaves(os.path.join(ref, "step_000000", "detector.npz")), _leaves(
        os.path.join(ref, "step_000001", "detector.npz"))
    assert any(not np.array_equal(a, b) for a, b in zip(wm0, wm2))
    assert any(not np.array_equal(a, b) for a, b in zip(det0, det2))
    first = records[0]
    assert first["world_model"]["real_episodes"] == 4 and records[1]["world_model"]["real_episodes"] == 6
    assert {"false_success", "missed_success", "imagined_success_by_horizon"} <= set(first["replay"])
    within = first["replay"]["within_group"]
    assert (within["groups"], within["group_size"]) == (2, 2) and 0 <= within["mixed_real_groups"] <= 2
    assert 0.0 <= within["all"]["imagined_mixed"] <= 1.0 and records[1]["replay"]["within_group"]["groups"] == 1
    assert {"threshold", "shift", "imagined_frames", "real_frames", "real_frames_run_threshold"} <= set(first["detector"])
    # the detector before and after the fine-tune, judged on the same held-out real frames at the run's threshold
    before, after = first["detector"]["real_frames_run_threshold"]["before"], first["detector"]["real_frames_run_threshold"]["after"]
    assert before["frames"] == after["frames"] == first["detector"]["real_frames"]["frames"] > 0
    chosen = next(r["horizon"] for r in records if "horizon" in r)  # the first calibrated refresh's choice
    assert chosen["actions"] in (4, 8) and set(chosen["separation"]) == {"4", "8"}
    calibrated = next(r["detector"] for r in records if "candidates" in r.get("detector", {}))
    # its threshold was set over the horizon it chose, each candidate at its own threshold
    assert calibrated["calibration"]["over_actions"] == chosen["actions"]
    assert set(calibrated["candidates"]) == set(calibrated["calibration"]["thresholds"]) == {"4", "8"}
    # stopped after the refresh at step 1 and rerun: bit-identical to the uninterrupted run
    cfg_b = _cfg(tmp_path / "b", group_size=2)
    _run(cfg_b, tiny_run, str(tmp_path / "b"), steps=1)
    resumed = _run(cfg_b, tiny_run, str(tmp_path / "b"), steps=2)
    for key in ("loss", "success_rate", "real_episodes_used"):
        assert [h[key] for h in resumed["history"]] == [h[key] for h in whole["history"]], key
    ref_b = os.path.join(str(tmp_path / "b"), "grpo", "refresh")
    for name in ("world_model.npz", "detector.npz"):
        for a, b in zip(_leaves(os.path.join(ref, "step_000001", name)), _leaves(os.path.join(ref_b, "step_000001", name))):
            np.testing.assert_array_equal(a, b)
    with open(os.path.join(str(tmp_path / "a"), "grpo", "success_curve.json")) as f:
        curve_a = json.load(f)["points"]
    with open(os.path.join(str(tmp_path / "b"), "grpo", "success_curve.json")) as f:
        curve_b = json.load(f)["points"]
    assert [p["mean"] for p in curve_a] == [p["mean"] for p in curve_b]


def test_grouped_collection_rolls_each_start_out_group_size_times():
    """rl.refresh.group_size=3: 6 episodes are 2 starts x 3 consecutive rollouts that share the start, the
    instruction and the task, and not the sampled actions; n that is not whole groups is refused."""
    from sword_jax.pipeline.grpo_refresh import make_collect

    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=4, action_ensemble=False),
                             grpo=dataclasses.replace(cfg.rl.grpo, temperature=1.0),
                             refresh=RefreshConfig(every=1, episodes=6, budget=12, group_size=3))
    graphdef, params = build_policy(rl, seed=0)
    asked = []

    def collect_starts(step, n):
        asked.append(n)
        return _pool_starts(n, np.random.default_rng(step))

    real = make_collect(graphdef, rl, Slide(), collect_starts, seed=0, steps=8)(params, 0, 6)
    assert asked == [2] and real.num == 6
    assert list(real.tasks) == [0, 0, 0, 1, 1, 1] and list(real.instructions) == [TEXTS[0]] * 3 + [TEXTS[1]] * 3
    first = real.frames[:, 0]
    assert all(np.array_equal(first[0], first[i]) for i in (1, 2)) and not np.array_equal(first[0], first[3])
    assert not np.array_equal(real.actions[0], real.actions[1])  # one start, different sampled actions
    with pytest.raises(ValueError, match="whole groups"):
        make_collect(graphdef, rl, Slide(), collect_starts, seed=0, steps=8)(params, 0, 4)


@pytest.mark.slow  # ~1 min on 2 cores
def test_a_run_of_zero_steps_measures_the_simulators_signal_and_trains_nothing(tiny_run, tmp_path):
    """rl.grpo.steps=0 with grouped refresh episodes: the probe of a learned simulator's signal (does its verdict
    follow the actions from one start?) before any GRPO step: step 0's evaluation and refresh, its replay's
    within-group separation, and a policy that did not move."""
    cfg = _cfg(tmp_path, group_size=2)
    # and the policy's own imagined groups checked in the environment first: 1 start x rl.grpo.group_size=2
    cfg = dataclasses.replace(cfg, rl=dataclasses.replace(
        cfg.rl, refresh=dataclasses.replace(cfg.rl.refresh, verify_starts=1)))
    out = _run(cfg, tiny_run, str(tmp_path), steps=0)
    assert [r["step"] for r in out["refreshes"]] == [0] and out["history"] == []
    within = out["refreshes"][0]["replay"]["within_group"]
    assert within["groups"] == 2 and set(within) >= {"4", "8", "all"}
    assert all("auc" in within[h] for h in ("4", "8", "all"))  # the detector scores' ranking, threshold-free
    checked = out["refreshes"][0]["verify"]
    # 2 imagined rollouts of rl.imagined.max_chunks=2 decisions x 4 actions (no horizon chosen before the first
    # refresh), executed for real and counted against the budget before the refresh's 4 episodes
    assert (checked["episodes"], checked["starts"], checked["group_size"], checked["actions"]) == (2, 1, 2, 8)
    assert 0 < checked["mean_actions"] <= 8 and checked["within_group"]["groups"] == 1
    assert checked["precision"]["of"] == checked["counts"]["real_and_imagined"] + checked["counts"]["imagined_only"]
    assert out["refreshes"][0]["real_episodes"] == 4 and out["refreshes"][0]["real_episodes_used"] == 6
    assert [p["step"] for p in out["curve"]] == [0] and out["real_episodes_used"] == 6
    with open(os.path.join(str(tmp_path), "grpo", "evaluations", "step_000000.json")) as f:
        kept = json.load(f)  # the evaluation is kept apart before the refresh that follows it
    assert kept["step"] == 0 and kept["mean"] == out["curve"][0]["mean"]
    _, initial = build_policy(cfg.rl, seed=0)
    for a, b in zip(jax.tree.leaves(initial), jax.tree.leaves(out["params"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_recorded_episodes_keep_every_frame_and_go_on_after_success():
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=3, action_ensemble=False))
    graphdef, params = build_policy(rl, seed=0)
    env = Slide()
    from sword_jax.rl.policy import tokenize_instructions

    starts = jnp.asarray([[0.29], [-0.5]], jnp.float32)
    tokens = jnp.asarray(tokenize_instructions(list(TEXTS), rl.policy.max_instruction_bytes))
    rec = record_episodes(graphdef, params, env, starts, tokens, rl, key=jax.random.key(0), steps=7)
    assert rec.frames.shape == (2, 8, SIZE, SIZE, 3) and rec.actions.shape == (2, 7, 7) and rec.success.shape == (2, 7)
    # replaying the recorded actions in the env gives the recorded frames and success, step by step
    pos, obs = env.reset(starts)
    for t in range(7):
        np.testing.assert_array_equal(np.asarray(obs["frames"]), np.asarray(rec.frames[:, t]))
        pos, obs, reached = env.step(pos, rec.actions[:, t])
        np.testing.assert_array_equal(np.asarray(reached), np.asarray(rec.success[:, t]))
    np.testing.assert_array_equal(np.asarray(obs["frames"]), np.asarray(rec.frames[:, 7]))
    real = RealEpisodes.from_recorded(jax.device_get(rec), TEXTS, np.asarray([0, 1]))
    lengths = real.lengths
    assert np.all((lengths == 7) | real.solved) and np.all(lengths[real.solved] == np.argmax(real.success, 1)[real.solved] + 1)
    branch = real.branch_set()
    assert np.array_equal(branch.lengths, lengths) and branch.frame_success[:, 0].sum() == 0


def test_a_threshold_shift_moves_the_detector_threshold_exactly():
    rl = configs.get("sword:tiny").rl
    graphdef, params = build_detector(rl, seed=0)
    frames = jax.random.uniform(jax.random.key(1), (16, SIZE, SIZE, 3))
    plain = np.asarray(shifted_reward_model(graphdef, params, 0.0).score(frames))
    c = float(np.median(plain))
    shifted = np.asarray(shifted_reward_model(graphdef, params, threshold_shift(c, rl.success_threshold)).score(frames))
    np.testing.assert_array_equal(shifted >= rl.success_threshold - 1e-6, plain >= c - 1e-6)
    assert threshold_shift(1.5, 0.9) > 0 and np.isfinite(threshold_shift(1.5, 0.9))


def test_stratified_split_takes_a_share_of_each_outcome():
    outcome = np.asarray([True] * 6 + [False] * 10)
    mask = stratified_split(outcome, 0.5, np.random.default_rng(0))
    assert mask[outcome].sum() == 3 and mask[~outcome].sum() == 5
    two = stratified_split(np.asarray([True, False, False]), 0.1, np.random.default_rng(0))
    assert two[1:].sum() == 1 and not two[0]  # one failure at least, never all of a kind


@pytest.mark.parametrize("bad, message", [(dict(every=2, episodes=4, budget=2), "budget"),
                                          (dict(every=-1), "every"),
                                          (dict(every=2, episodes=4, budget=8, calibrate_fraction=1.0), "calibrate"),
                                          (dict(every=2, episodes=4, budget=8, horizons=(48, 24)), "horizons"),
                                          (dict(every=2, episodes=6, budget=12, group_size=4), "whole groups"),
                                          (dict(every=2, episodes=4, budget=6, group_size=4), "whole groups"),
                                          (dict(group_size=0), "group_size"),
                                          (dict(verify_starts=-1), "verify_starts")])
def test_refresh_config_refuses_bad_settings(bad, message):
    with pytest.raises(ValueError, match=message):
        RefreshConfig(**bad).validate()


def test_a_check_of_imagined_rollouts_needs_an_environment_to_execute_them():
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, refresh=RefreshConfig(every=1, episodes=4, budget=8, verify_starts=2))
    with pytest.raises(ValueError, match="verify_starts needs verify="):
        Refresher(cfg, rl, wm_state=None, make_simulator=None, encode=None, encode_frames=None, detector=None,
                  base=None, collect=None, directory="unused")


def test_policy_npz_files_round_trip_and_refuse_another_architecture(tmp_path):
    from sword_jax.rl.params_io import load_params, save_params_npz

    rl = configs.get("sword:tiny").rl
    _, params = build_policy(rl, seed=0)
    path = str(tmp_path / "policy.npz")
    save_params_npz(path, params)
    _, fresh = build_policy(rl, seed=1)
    loaded, meta = load_params(path, fresh, kind="policy")
    for a, b in zip(jax.tree.leaves(loaded), jax.tree.leaves(params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert meta["format"] == "npz"
    wider = dataclasses.replace(rl, policy=dataclasses.replace(rl.policy, width=rl.policy.width * 2))
    _, other = build_policy(wider, seed=0)
    with pytest.raises(ValueError, match="shape"):
        load_params(path, other, kind="policy")


def test_first_success_needs_the_run_of_frames_within_the_length():
    scores = np.asarray([[0.1, 0.95, 0.2, 0.95, 0.96, 0.97], [0.95, 0.95, 0.1, 0.1, 0.1, 0.1], [0.9] * 6])
    lengths = np.asarray([6, 6, 3])
    assert first_success(scores, lengths, 0.9, 1).tolist() == [1, 0, 0]
    assert first_success(scores, lengths, 0.9, 2).tolist() == [4, 1, 1]
    assert first_success(scores, lengths, 0.9, 3).tolist() == [5, -1, 2]
    assert first_success(scores, lengths, 0.94, 3).tolist() == [5, -1, -1]


def test_choose_horizon_takes_the_longest_trusted_one():
    def entry(win, loss):
        return {"real_success": {"rate": win}, "real_failure": {"rate": loss}}

    by_h = {"24": entry(0.3, 0.05), "48": entry(0.6, 0.2), "96": entry(0.7, 0.6)}
    assert choose_horizon(by_h, (24, 48, 96), 0.2)[::2] == (48, True)
    h, separation, trusted = choose_horizon(by_h, (24, 48, 96), 0.5)
    # none trusted: the best-separating one, not the shortest
    assert (h, trusted) == (48, False) and separation["96"] == pytest.approx(0.1)
    # as measured on GPU: nothing is solved within 24 actions, so the shortest would pay no reward at all
    measured = {"24": entry(0.0, 0.0), "48": entry(0.06, 0.0)}
    assert choose_horizon(measured, (24, 48), 0.2)[::2] == (48, False)
    assert choose_horizon({"24": entry(0.1, 0.1), "48": entry(0.1, 0.1)}, (24, 48), 0.2)[0] == 48  # equals: longest
    assert choose_horizon({"24": entry(None, 0.1)}, (24,), 0.2) == (24, {"24": None}, False)


def test_pause_follows_the_trust_of_the_refresh_the_steps_follow():
    from types import SimpleNamespace

    from sword_jax.rl.refresh import Refresher

    records = [{"step": 0, "horizon": {"actions": 48}, "trust": {"actions": 48, "separation": 0.3, "trusted": True}},
               {"step": 5, "trust": {"actions": 48, "separation": 0.05, "trusted": False}},
               {"step": 10, "skipped": "budget spent"}]

    def paused(loaded, pause=True):
        return Refresher.paused(SimpleNamespace(conf=RefreshConfig(every=5, episodes=4, budget=8, horizons=(24, 48),
                                                                   pause_untrusted=pause),
                                                records=records, loaded=loaded))

    # after the skipped refresh at step 10 the steps still follow the models of step 5
    assert [paused(0), paused(5), paused(10), paused(-1)] == [False, True, True, False]
    assert not paused(5, pause=False)
    with pytest.raises(ValueError, match="pause_untrusted needs rl.refresh.horizons"):
        RefreshConfig(every=5, episodes=4, budget=8, pause_untrusted=True).validate()


def test_the_threshold_is_set_over_the_rollout_horizon_each_candidate_at_its_own():
    from types import SimpleNamespace

    from sword_jax.rl.refresh import Refresher, calibrate_held_out

    # one frame per action: real successes look solved from action 3 (scores 0.6-0.9); real failures drift
    # into a solved look (0.95) from action 6; one failure's replay scores 0.7 from action 3 on
    real = np.r_[np.ones(5, bool), np.zeros(5, bool)]
    scores = np.full((10, 12), 0.1)
    scores[:5, 3:] = np.linspace(0.6, 0.9, 5)[:, None]
    scores[5:, 6:] = 0.95
    scores[5, 3:6] = 0.7
    lengths = np.full(10, 12)
    conf = RefreshConfig(every=1, episodes=4, budget=8, horizons=(4, 8), max_false_success=0.0, min_separation=0.5)
    threshold, report, candidates = calibrate_held_out(scores, lengths, real, [4, 8], conf, 1)
    # by action 4 (frames 0-3) the 0.7 failure sets the bound: successes above it separate by 0.6; by action 8
    # every failure's drift is within reach and nothing below 0.95 may fire: none separates. Action 4 is taken.
    assert report["over_actions"] == 4 and threshold == report["thresholds"]["4"] == pytest.approx(np.nextafter(0.7, 1))
    assert report["thresholds"]["8"] > 0.95 and report["rule"] == "false_success"
    assert candidates["4"]["real_success"]["rate"] == pytest.approx(0.6) and candidates["8"]["real_success"]["rate"] == 0
    assert report["false_success"]["rate"] == 0.0 and report["separation"] == pytest.approx(0.6)
    # separation: letting the 0.7 failure fire by action 4 keeps every success (5/5 - 1/5 = 0.8 against 0.6)
    sep_threshold, sep_report, _ = calibrate_held_out(scores, lengths, real, [4],
                                                      dataclasses.replace(conf, calibration="separation"), 1)
    assert sep_report["rule"] == "separation" and sep_report["separation"] == pytest.approx(0.8)
    assert sep_threshold == pytest.approx(0.6) and sep_report["false_success"]["rate"] == pytest.approx(0.2)
    # without a held-out success only the false-success bound can be set
    assert calibrate_held_out(scores[5:], lengths[5:], real[5:], [4], dataclasses.replace(
        conf, calibration="separation"), 1)[1]["rule"] == "false_success"

    def over(**kw):
        records = kw.pop("records", [])
        return Refresher._calibration_horizons(SimpleNamespace(
            conf=RefreshConfig(every=1, episodes=4, budget=8, **kw), records=records,
            rl=SimpleNamespace(imagined=SimpleNamespace(max_chunks=12, execute_steps=4)),
            horizon=lambda: next((r["horizon"]["actions"] for r in records if "horizon" in r), None)))

    assert over(horizons=(24, 48)) == [24, 48] and over() == [48] and over(calibrate_over="episode") == [None]
    assert over(horizons=(24, 48), records=[{"step": 0, "horizon": {"actions": 24}}]) == [24]
    for bad in (dict(calibration="youden"), dict(calibrate_over="chunk")):
        with pytest.raises(ValueError, match="calibration must be false_success|separation"):
            RefreshConfig(every=1, episodes=4, budget=8, **bad).validate()


def test_horizons_must_be_whole_imagined_decisions():
    rl = configs.get("sword:tiny").rl
    bad = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, execute_steps=4),
                              refresh=RefreshConfig(every=2, episodes=4, budget=8, horizons=(6, 8)))
    with pytest.raises(ValueError, match="multiples of the imagined execution"):
        bad.validate()


def test_a_dlb_fine_tune_with_steps_between_log_steps_stays_finite():
    """The refresh's DLB fine-tune judges a step by its loss and gradient alone: between log steps its
    ``cache_vs_inference_*`` metrics are NaN by design and must not stop it (they once did, at step 0)."""
    from flax import nnx

    from sword_jax.rl.refresh import finetune_world_model

    cfg = configs.get("sword:tiny")
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, num_layers=1))
    assert cfg.cache.enabled and cfg.cache.log_inference_distance
    _, (params, rest) = experiment_world_model(cfg, None)
    rng = np.random.default_rng(0)
    latents = rng.standard_normal((2, cfg.data.episode_frames // cfg.vae.temporal_factor + 1, 4, 4,
                                   cfg.model.in_dim)).astype(np.float32)
    actions = rng.uniform(-1, 1, (2, cfg.data.episode_frames, cfg.model.action_dim)).astype(np.float32)
    before = jax.device_get(nnx.to_pure_dict(params))  # the fine-tune donates the arrays it is given
    logged = []
    mesh = shd.make_mesh(shd.MeshConfig(data=2, tensor=4))  # the tiny batch of 2 splits over data
    (new_params, _), last = finetune_world_model(cfg, (nnx.to_pure_dict(params), nnx.to_pure_dict(rest)),
                                                 LatentDataset(latents, actions), steps=8, learning_rate=1e-3, seed=1,
                                                 mesh=mesh, log=logged.append)
    assert last["step"] == 8 and last["nonfinite"] == 0 and np.isfinite(last["loss"])
    assert len([line for line in logged if "world model refresh step" in line]) == 4  # log steps 2, 4, 6, 8 only
    moved = jax.tree.leaves(jax.tree.map(lambda a, b: float(np.abs(np.asarray(a) - np.asarray(b)).max()),
                                         before, new_params))
    assert max(moved) > 0


@pytest.mark.slow  # ~1.5 min on 2 cores: one refresh and one GRPO step through the light decoder
def test_a_refresh_replays_and_recalibrates_through_the_light_decoder(tiny_run, tmp_path):
    """With ``rl.imagined.decoder=light`` a refresh runs through the light decoder (the fine-tuned world model's
    simulator keeps it for the replays that train and calibrate the detector), and GRPO's steps are timed with
    their imagined frames. The light decoder draws at the policy's size, half the real frames': the detector's
    fine-tune mixes both at its input size."""
    from tests.support.light_decoder import save_random_light_decoder

    cfg = _cfg(tmp_path)
    assert cfg.data.image_size == 32
    cfg = dataclasses.replace(cfg, rl=dataclasses.replace(cfg.rl, image_size=16, imagined=dataclasses.replace(
        cfg.rl.imagined, decoder="light")))
    save_random_light_decoder(str(tmp_path / "light" / "checkpoints"), cfg)
    out = _run(cfg, tiny_run, str(tmp_path), steps=1, light_decoder=str(tmp_path / "light"))
    first = out["refreshes"][0]
    assert {"imagined_frames", "real_frames", "real_frames_run_threshold"} <= set(first["detector"])
    with open(os.path.join(str(tmp_path), "grpo", "step_times.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    assert [r["step"] for r in rows] == [1] and rows[0]["imagined_frames"] > 0


def test_a_world_model_batch_that_does_not_split_over_the_mesh_is_refused_before_grpo_runs(tmp_path):
    """The refresh fine-tunes the world model on GRPO's mesh: a data.batch_size that does not split over it is
    refused when the refresher is made, not at the first refresh."""
    cfg = _cfg(tmp_path)
    cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, batch_size=2))
    with pytest.raises(ValueError, match=r"data.batch_size=2 does not split over the 8 devices"):
        Refresher(cfg, cfg.rl, wm_state=None, make_simulator=None, encode=None, encode_frames=None,
                  detector=(None, None), base=None, collect=None, directory=str(tmp_path))


def test_the_check_of_imagined_rollouts_runs_at_the_run_horizon_and_only_while_the_budget_pays_for_it():
    """Refresher._verify: rl.refresh.verify_starts x rl.grpo.group_size executions, counted against the budget, at
    rl.imagined.max_chunks decisions before a horizon is chosen and at the chosen one's after; skipped, with its
    reason and nothing counted, once the budget cannot pay for them."""
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, grpo=dataclasses.replace(cfg.rl.grpo, group_size=4),
                             imagined=dataclasses.replace(cfg.rl.imagined, max_chunks=3, execute_steps=4),
                             refresh=RefreshConfig(every=1, episodes=4, budget=20, verify_starts=2))
    calls = []

    def verify(params, sim, rm, step, decisions):
        calls.append((params, sim, rm, step, decisions))
        return {"episodes": 8, "imagined_success": 0.5, "real_success": 0.25, "precision": {"rate": 0.5, "of": 4},
                "false_success": {"rate": 1 / 3, "of": 6}}

    refresher = Refresher.__new__(Refresher)  # only what _verify reads
    refresher.conf, refresher.rl, refresher.used, refresher.records, refresher.verify = rl.refresh, rl, 0, [], verify
    refresher.simulator, refresher.reward_model, refresher.log = (lambda: "sim"), (lambda: "rm"), (lambda line: None)
    first = refresher._verify(0, "policy")
    assert calls == [("policy", "sim", "rm", 0, 3)] and refresher.used == 8 and first["episodes"] == 8
    refresher.records = [{"step": 0, "horizon": {"actions": 8}}]  # the first refresh chose 8 actions: 2 decisions
    refresher._verify(1, "policy")
    assert calls[-1][3:] == (1, 2) and refresher.used == 16
    skipped = refresher._verify(2, "policy")  # 4 of the 20 left, 8 asked
    assert "exceed what is left of the budget of 20" in skipped["skipped"] and refresher.used == 16 and len(calls) == 2
    refresher.conf = dataclasses.replace(rl.refresh, verify_starts=0)
    assert refresher._verify(3, "policy") is None


@pytest.mark.slow  # ~1.5 min on 2 cores each: two GRPO steps paid by the environment, then a resume
@pytest.mark.parametrize("paid_by", ["executed", "calibrated"])
def test_grpo_paid_by_executing_the_imagined_actions_runs_and_resumes_exactly(tiny_run, tmp_path, paid_by):
    """rl.imagined.reward=executed: GRPO in the tiny world model from keyframes whose recorded states reset the
    environment (the Slide's state is its position, what the demonstrations' proprio records), each imagined
    trajectory paid by the environment's outcome of its actions; the steps log the detector's verdict beside
    it, and a run stopped after its first step resumes to the uninterrupted run's parameters. With
    reward=calibrated and one calibration step, the second step is the detector's at the threshold the first
    set, and the run resumed after the first reads it from its records."""
    from sword_jax.pipeline.grpo import run_in_learned_simulator
    from sword_jax.rl.policy import tokenize_instructions

    cfg = _cfg(tmp_path)
    rl = dataclasses.replace(cfg.rl, refresh=RefreshConfig(), grpo=dataclasses.replace(cfg.rl.grpo, steps=2),
                             imagined=dataclasses.replace(cfg.rl.imagined, reward=paid_by, eval_replay_episodes=0,
                                                          calibrate_steps=int(paid_by == "calibrated")))
    cfg = dataclasses.replace(cfg, rl=rl)
    graphdef, params = build_policy(rl, seed=0)
    det_graphdef, det_params = build_detector(rl, seed=0)
    reward = os.path.join(str(tmp_path), "detector")
    save_params(reward, det_params, rl, kind="reward_model", step=0)
    env = Slide()
    starts, texts, tasks = _pool_starts(4, np.random.default_rng(5))
    tokens = jnp.asarray(tokenize_instructions(texts, rl.policy.max_instruction_bytes))
    rec = jax.jit(lambda p, s, t, k: record_episodes(graphdef, p, env, s, t, rl, key=k, steps=cfg.data.episode_frames))(
        params, jnp.asarray(starts), tokens, jax.random.key(3))
    demos = RealEpisodes.from_recorded(jax.device_get(rec), texts, tasks).episode_set()
    inputs = GRPOInputs(world_model=os.path.join(tiny_run, "world_model"), vae=os.path.join(tiny_run, "vae_run", "vae"),
                        reward=reward)
    setup = world_model_setup(cfg, rl, inputs, demos)
    assert setup.env_starts is None  # these episodes hold no simulator states
    with pytest.raises(ValueError, match="recorded simulator states"):
        run_in_learned_simulator(cfg, rl, graphdef, params, str(tmp_path / "refused"), setup, simulator="world_model",
                                 env_eval=None, max_traces=1, env=env, evaluate_real=lambda s, p: ({}, {}))
    setup = world_model_setup(cfg, rl, inputs, dataclasses.replace(demos, states=demos.proprio[..., :1].copy()))
    picked = setup.env_starts(0)
    assert picked.shape == (rl.grpo.rollout_batch, 1)
    at = setup.start_steps(0)  # the same keyframes' steps: t = 4 s, s >= 1, within the episode
    assert at.shape == (rl.grpo.rollout_batch,) and at.dtype == np.int32
    assert np.all(at >= 4) and np.all(at < demos.lengths.max())

    def evaluate_real(step, p):
        out = jax.jit(lambda p, k: record_episodes(graphdef, p, env, jnp.asarray(starts), tokens, rl, key=k,
                                                   steps=cfg.data.episode_frames))(p, jax.random.key(7))
        return success_summary(np.asarray(out.success).any(1), tasks, 0.0), {}

    def run(workdir, steps):
        r = dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, steps=steps))
        _, fresh = build_policy(rl, seed=0)  # a run donates its policy's arrays
        return run_in_learned_simulator(dataclasses.replace(cfg, rl=r), r, graphdef, fresh, workdir, setup,
                                        simulator="world_model", env_eval=None, max_traces=1, env=env,
                                        evaluate_real=evaluate_real)

    whole = run(str(tmp_path / "whole"), 2)
    assert [p["step"] for p in whole["history"]] == [1, 2]
    if paid_by == "calibrated":  # the detector paid the second step at the threshold the first one's cut set
        paid, judged = whole["history"]
        assert judged["detector_threshold"] == pytest.approx(
            grpo.calibrated_threshold([paid["detector_threshold_bounded"]])) and "detector_success" not in judged
    for point in whole["history"][:1 if paid_by == "calibrated" else None]:
        assert {"detector_success", "detector_agreement", "detector_false_success"} <= set(point)
        # and where the closed loop left the real one, decision by decision (decision 0 reads the real start),
        # with the share of it the world model's VAE alone causes (its round trip of the real frames)
        assert {f"closed_loop_{what}_{k}" for k in range(1, rl.imagined.max_chunks)
                for what in ("frame_error", "action_gap", "frame_error_vae", "action_gap_vae")} <= set(point)
        assert point["closed_loop_frame_error_vae_1"] > 0.0  # the tiny VAE changes the frames it round-trips
        # the whole horizon runs for every trajectory that did not succeed for real
        assert point["mean_chunks"] <= rl.imagined.max_chunks
        # its trajectories counted by where their starts stand, the real successes adding up to the step's
        edges = imagined_check.START_STEP_EDGES
        assert sum(point[f"start_a{a}_rollouts"] for a in edges) == point["real_rollouts"]
        assert sum(point[f"start_a{a}_said"] for a in edges) == pytest.approx(
            point["detector_success"] * point["real_rollouts"])
    run(str(tmp_path / "split"), 1)
    resumed = run(str(tmp_path / "split"), 2)
    assert [p["step"] for p in resumed["history"]] == [1, 2]
    for a, b in zip(whole["history"], resumed["history"]):
        assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)  # NaN figures equal too


def _prefix_refresher(tmp_path, start_encoding="prefix", encode_prefix=True):
    """A refresher of ``_cfg``'s run with ``rl.imagined.start_encoding``, the tiny random VAE's start encoders."""
    from tests.support.vae import encoders

    cfg = _cfg(tmp_path)
    rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, start_encoding=start_encoding))
    encode, prefix = encoders()
    return Refresher(cfg, rl, wm_state=None, make_simulator=None, encode=encode, encode_frames=None,
                     detector=build_detector(rl, seed=0), base=None, collect=None, directory=str(tmp_path),
                     encode_prefix=prefix if encode_prefix else None), rl


def test_a_refresh_encodes_its_branch_and_replay_starts_from_frame_0_with_the_prefix(tmp_path):
    """rl.imagined.start_encoding=prefix: the starts GRPO branches from a refresh's real episodes and the starts of
    the refresh's replays are the latents the latents stage makes of the whole episode at their keyframe; with the
    window they are encode_history's, as before. A refresh asked for the prefix without its encoder refuses."""
    from sword_jax.pipeline.grpo import start_state
    from sword_jax.rl.world_model_sim import encode_history
    from tests.support.vae import relative_error, tiny_vae, whole_latents

    _, vae_graphdef, vae_state = tiny_vae()
    n, t = 3, 20
    rng = np.random.default_rng(0)
    real = RealEpisodes(rng.integers(0, 256, (n, t + 1, SIZE, SIZE, 3), dtype=np.uint8),
                        np.zeros((n, t + 1, 8), np.float32), np.zeros((n, t, 7), np.float32),
                        np.zeros((n, t), bool), TEXTS[:1] * n, np.zeros(n, np.int64))
    whole = whole_latents(real.frames[:, :t + 1])  # (n, 1 + 5, ...)
    starts = {}
    for encoding in ("prefix", "window"):
        refresher, rl = _prefix_refresher(tmp_path / encoding, encoding)
        refresher.branch = real.branch_set()
        pick = refresher.branch_pick(3, 8)
        branch = start_state(pick, refresher.encode, rl, encode_prefix=refresher.encode_prefix)
        seen = []
        refresher._replay_fn = lambda sim, rm, start, *rest: seen.append(start) or ()  # the replay's starts only
        refresher._replay(real, None, None, jax.random.key(0), record=False)
        starts[encoding] = (pick, np.asarray(branch.latents[0]), np.asarray(seen[0].latents[0]))
    pick, branch, replay = starts["prefix"]
    assert "prefix" in pick and not set(pick["t"] % 4) - {0}
    later = pick["t"] >= 4
    assert later.sum() >= 4, pick["t"]
    truth = np.stack([whole[pick["episode"], 0], whole[pick["episode"], pick["t"] // 4]], axis=1)
    assert relative_error(branch[later], truth[later]) < 1e-4
    assert relative_error(replay, whole[:, :2]) < 1e-4  # the replays start at frame 4, latent 1
    window_pick, window_branch, window_replay = starts["window"]
    assert "prefix" not in window_pick
    np.testing.assert_array_equal(window_pick["t"], pick["t"])
    unit = lambda x: jnp.asarray(x, jnp.float32) / jnp.float32(255.0)  # noqa: E731
    np.testing.assert_array_equal(window_branch, np.asarray(encode_history(
        vae_graphdef, vae_state, unit(window_pick["first_frame"]), unit(window_pick["history"]))))
    np.testing.assert_array_equal(window_replay, np.asarray(encode_history(
        vae_graphdef, vae_state, unit(real.frames[:, 0]), unit(real.frames[:, [0, 0, 0, 0, 1, 2, 3, 4]]))))
    assert relative_error(window_branch[later][:, 1], truth[later][:, 1]) > 0.05
    with pytest.raises(ValueError, match="rl.imagined.start_encoding=prefix: the refresh"):
        _prefix_refresher(tmp_path / "none", encode_prefix=False)


def test_the_verify_starts_with_the_prefix_are_the_settled_frames_episode_from_frame_0():
    """rl.imagined.start_encoding=prefix: a verify start (the settled frame after a reset, its episode's first) is
    encoded from its prefix, the frame held to the end of the first context latent, i.e. the latents stage's latents
    of that episode at rest; the window's start is encode_history's, as before."""
    from sword_jax.pipeline.grpo import start_state
    from sword_jax.pipeline.grpo_refresh import verify_prefix
    from tests.support.vae import encoders, relative_error, whole_latents

    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, start_encoding="prefix"))
    frames = np.random.default_rng(2).integers(0, 256, (2, SIZE, SIZE, 3), dtype=np.uint8)
    window = imagined_check.still_window(frames, np.zeros((2, 8), np.float32), list(TEXTS), num_context=1,
                                         frames_per_latent=4, action_dim=7)
    encode, encode_prefix = encoders()
    prefixed = verify_prefix(window, num_context=1, frames_per_latent=4)
    start = start_state(prefixed, encode, rl, encode_prefix=encode_prefix)
    at_rest = whole_latents(np.repeat(frames[:, None], 5, axis=1))  # the episode at rest: frames 0..4
    assert relative_error(start.latents[0], at_rest) < 1e-4
    still = start_state(window, encode, rl, encode_prefix=encode_prefix)  # no prefix in the window: encode's
    np.testing.assert_array_equal(np.asarray(still.latents[0]), np.asarray(encode(
        jnp.asarray(frames, jnp.float32) / 255.0, jnp.asarray(window["history"], jnp.float32) / 255.0)))
    np.testing.assert_array_equal(np.asarray(start.latents[1]), np.asarray(still.latents[1]))


def test_the_replay_of_real_episodes_refuses_the_prefix_without_its_encoder():
    from sword_jax.pipeline.grpo import Replayer

    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, start_encoding="prefix"))
    with pytest.raises(ValueError, match=r"rl.imagined.start_encoding=prefix: the replay of real episodes"):
        Replayer(cfg, rl, None, None, lambda f, h: None, jax.random.key(0))
    assert Replayer(cfg, cfg.rl, None, None, lambda f, h: None, jax.random.key(0),
                    encode_prefix=lambda p, i: None).encode_prefix is None  # the window ignores it
