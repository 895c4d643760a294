"""The policy's imagined rollouts checked in the real environment (sword_jax.rl.imagined_check): fixed actions
executed open loop, the report against designed outcomes, and the whole check on the toy world, where a
simulator equal to the environment agrees everywhere and a detector that always fires pays every real failure."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import grpo, imagined_check
from sword_jax.rl.config import EnvConfig, GRPOConfig, ImaginedConfig, PolicyConfig, RefreshConfig, RLConfig
from sword_jax.rl.grpo_loop import grpo_run_id
from sword_jax.rl.learned_simulator import (RewardModel, ToyState, instruction_target, toy_render, toy_reward_model,
                                            toy_simulator, toy_start_states)
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.rollout import Rollout, imagined_rollout

CFG = RLConfig(image_size=8, action_bins=8, proprio_dim=4,
               policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
               grpo=GRPOConfig(group_size=4), imagined=ImaginedConfig(max_chunks=4))
TEXTS = ["pick up the black bowl on the plate", "put the bowl on the stove", "open the drawer"]
STEP = 0.05


class Line:
    """A point the first action dimension moves by 0.1 a step; success once past 0.25."""

    def reset(self, starts):
        pos = jnp.asarray(starts, jnp.float32)[:, 0]
        return pos, {}

    def step(self, pos, actions):
        pos = pos + 0.1 * actions[:, 0]
        return pos, {}, pos > 0.25


class ToyEnv:
    """The toy world as a real environment: starts ``[position xy, target xy]``, success when the toy detector's
    score of the rendered state passes the threshold (what the imagined verdict reads)."""

    def __init__(self, threshold):
        self.rm, self.threshold = toy_reward_model(), threshold

    def _frames(self, pos, target):
        return jax.vmap(lambda p, t: toy_render(ToyState(p, t), 8))(pos, target)

    def reset(self, starts):
        starts = jnp.asarray(starts, jnp.float32)
        state = (starts[:, :2], starts[:, 2:])
        return state, {"frames": self._frames(*state)}

    def step(self, state, actions):
        pos, target = state
        pos = jnp.clip(pos + STEP * jnp.clip(actions[:, :2], -1.0, 1.0), -1.0, 1.0)
        frames = self._frames(pos, target)
        return (pos, target), {"frames": frames}, self.rm.score(frames) >= self.threshold


def test_execute_open_loop_finds_the_first_success_within_each_trajectory():
    actions = jnp.asarray(np.stack([np.full(6, 1.0), np.full(6, 1.0), np.full(6, -1.0), [0, 0, 0, 1, 1, 1]]),
                          jnp.float32)[..., None]
    # from 0: +0.1 a step passes 0.25 after the third action (index 2); the second stops before it
    first = imagined_check.execute_open_loop(Line(), jnp.zeros((4, 1)), actions, jnp.asarray([6, 2, 6, 6]))
    np.testing.assert_array_equal(np.asarray(first), [2, -1, -1, 5])


def test_report_against_designed_outcomes():
    # 2 groups of 4: group 0 real [T, T, F, F] imagined [T, F, T, F]; group 1 real [T, F, F, F] imagined [T, F, F, F]
    real = np.asarray([3, 5, -1, -1, 7, -1, -1, -1])
    imagined = np.asarray([7, -1, 15, -1, 7, -1, -1, -1])
    scores = np.zeros((8, 16))
    scores[[0, 2, 4], 5] = 0.95
    scores[1, 5] = 0.6
    checked = imagined_check.CheckedRollouts(imagined, real, scores, np.full(8, 16))
    out = imagined_check.report(checked, 4, horizons=(8,))
    assert out["counts"] == {"real_and_imagined": 2, "imagined_only": 1, "real_only": 1, "neither": 4}
    assert out["precision"]["rate"] == pytest.approx(2 / 3) and out["precision"]["of"] == 3
    assert out["false_success"]["rate"] == pytest.approx(1 / 5)
    within = out["within_group"]
    assert within["mixed_real_groups"] == 2
    # group 0: 1/2 - 1/2 = 0; group 1: 1 - 0 = 1 (whole trajectories); by 8 actions group 0's imagined success at 15
    # does not count: 1/2 - 0
    assert within["all"]["separation"] == pytest.approx(0.5)
    assert within["8"]["separation"] == pytest.approx(0.75)
    # scores rank group 0's successes (0.95, 0.6) against its failures (0.95, 0): 2.5 of 4 pairs; group 1: 1
    assert within["all"]["auc"] == pytest.approx((0.625 + 1.0) / 2)


def test_still_window_lays_out_a_start_at_rest_and_refuses_bad_frames():
    frames = np.random.default_rng(0).integers(0, 255, (2, 8, 8, 3), dtype=np.uint8)
    w = imagined_check.still_window(frames, np.zeros((2, 8)), ["a", "b"], num_context=1, frames_per_latent=4,
                                    action_dim=7)
    assert w["history"].shape == (2, 8, 8, 8, 3) and (w["history"] == frames[:, None]).all()
    assert w["actions"].shape == (2, 5, 7) and not w["actions"].any()
    with pytest.raises(ValueError, match="uint8"):
        imagined_check.still_window(frames.astype(np.float32), np.zeros((2, 8)), ["a", "b"], num_context=1,
                                    frames_per_latent=4, action_dim=7)
    with pytest.raises(ValueError, match="instructions"):
        imagined_check.still_window(frames, np.zeros((2, 8)), ["a"], num_context=1, frames_per_latent=4, action_dim=7)


def _designed(cfg):
    """The policy, the toy simulator, and the designed starts with their environment states ``[position xy,
    target xy]``: start 1 near its target (some of its group reach it), start 0 far (none do)."""
    graphdef, params = build_policy(cfg, seed=0)
    sim = toy_simulator(frame_size=8, step_size=STEP, chunk_len=cfg.chunk_len)
    tokens = jnp.asarray(tokenize_instructions(TEXTS, 32))
    start = toy_start_states(tokens, key=jax.random.key(5), frame_size=8)
    targets = jax.vmap(instruction_target)(tokens)
    near = targets[1] + jnp.asarray([0.12, 0.0])
    start = start._replace(proprio=start.proprio.at[1, :2].set(near),
                           frame=start.frame.at[1].set(toy_render(ToyState(near, targets[1]), 8)))
    return graphdef, params, sim, start, jnp.concatenate([start.proprio[:, :2], targets], axis=1)


def _toy_check(reward_model):
    graphdef, params, sim, start, env_starts = _designed(CFG)
    env_starts = jnp.repeat(env_starts, CFG.grpo.group_size, axis=0)

    def go(key):
        rollout = imagined_rollout(graphdef, params, sim, reward_model, start, CFG, key=key,
                                   group_size=CFG.grpo.group_size)
        return rollout, imagined_check.check(rollout, ToyEnv(CFG.success_threshold), env_starts, CFG.action_bins)

    return jax.device_get(jax.jit(go)(jax.random.key(2)))


def test_a_simulator_equal_to_the_environment_agrees_on_every_trajectory():
    rollout, checked = _toy_check(toy_reward_model())
    imagined, real = checked.imagined_first >= 0, checked.real_first >= 0
    assert imagined.any() and not imagined.all(), "the designed starts give both outcomes"
    np.testing.assert_array_equal(imagined, real)
    # the real success falls inside the decision the imagined one was placed at the end of
    e = rollout.tokens.shape[2]
    assert np.all(checked.imagined_first[imagined] - checked.real_first[imagined] < e)
    np.testing.assert_array_equal(checked.lengths, np.asarray(rollout.valid).sum(1) * e)
    out = imagined_check.report(checked, CFG.grpo.group_size)
    assert out["agreement"]["rate"] == 1.0 and out["precision"]["rate"] == 1.0 and out["false_success"]["rate"] == 0.0


def test_a_detector_that_always_fires_pays_every_real_failure():
    always = RewardModel(params={}, score_fn=lambda params, frames: jnp.ones(frames.shape[0], jnp.float32))
    rollout, checked = _toy_check(always)
    assert (checked.imagined_first >= 0).all()
    # every trajectory stops after its first decision, so the real world gets only those actions
    np.testing.assert_array_equal(checked.lengths, rollout.tokens.shape[2])
    out = imagined_check.report(checked, CFG.grpo.group_size)
    real = checked.real_first >= 0
    assert out["false_success"]["rate"] == 1.0 and out["false_success"]["of"] == int((~real).sum()) > 0
    assert out["precision"]["rate"] == pytest.approx(real.mean())


# ---- rl.imagined.reward=executed: the real environment pays the imagined actions ----

EXEC = RLConfig(image_size=8, action_bins=8, proprio_dim=4,
                policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
                grpo=GRPOConfig(group_size=4, rollout_batch=3, minibatches=1),
                imagined=ImaginedConfig(max_chunks=4, reward="executed"), env=EnvConfig(backend="mjx"))


def _constant_score(params, frames):
    return jnp.full(frames.shape[0], params["score"], jnp.float32)


# detectors that never or always fire: one score function (their score is a parameter), so a step compiled for
# one serves the other
NEVER = RewardModel(params={"score": np.float32(0.0)}, score_fn=_constant_score)
ALWAYS = RewardModel(params={"score": np.float32(1.0)}, score_fn=_constant_score)


def test_paid_by_execution_masks_after_the_real_success_and_pays_it():
    n, c, e = 3, 4, 2
    rollout = Rollout(obs_frames=jnp.zeros((n, c, 8, 8, 3)), proprio=jnp.zeros((n, c, 4)), proprio_valid=jnp.zeros((n, c)),
                      instruction_tokens=jnp.zeros((n, 32), jnp.int32), tokens=jnp.zeros((n, c, e, 7), jnp.int32),
                      log_probs=jnp.zeros((n, c, e, 7)), valid=jnp.ones((n, c)), rewards=jnp.full((n, c), 0.3),
                      scores=jnp.zeros((n, c)), success=jnp.zeros(n, bool), returns=jnp.zeros(n),
                      frames=jnp.zeros((0,)))
    # real success after action 3 (decision 1), never, after action 0 (decision 0)
    paid = jax.device_get(imagined_check.paid_by_execution(rollout, jnp.asarray([3, -1, 0]), EXEC))
    np.testing.assert_array_equal(paid.success, [True, False, True])
    np.testing.assert_array_equal(paid.valid, [[1, 1, 0, 0], [1, 1, 1, 1], [1, 0, 0, 0]])
    np.testing.assert_array_equal(paid.rewards, [[0, 1, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]])
    bonus = EXEC.grpo.success_bonus
    np.testing.assert_allclose(paid.returns, [1 + bonus, 0, 1 + bonus])
    score_rule = dataclasses.replace(EXEC, imagined=dataclasses.replace(EXEC.imagined, return_rule="score"))
    np.testing.assert_allclose(imagined_check.paid_by_execution(rollout, jnp.asarray([3, -1, 0]), score_rule).returns,
                               paid.returns)


def test_detector_metrics_against_designed_verdicts():
    said, real = jnp.asarray([True, False, True, False]), jnp.asarray([True, False, False, False])
    out = jax.device_get(imagined_check.detector_metrics(said, real))
    # agreement 3/4; the one paid failure of three
    assert out["detector_success"] == pytest.approx(0.5)
    assert out["detector_agreement"] == pytest.approx(0.75)
    assert out["detector_false_success"] == pytest.approx(1 / 3)
    assert np.isnan(imagined_check.detector_metrics(said, jnp.ones(4, bool))["detector_false_success"])


def test_detector_separation_against_designed_scores():
    """The detector's ranking of real outcomes by each trajectory's highest frame score, and the lowest threshold
    that pays at most the bound's share of real failures, on designed scores."""
    # highest scores 0.9, 0.6, 0.6 (successes) and 0.7, 0.6, 0.3, 0.2, 0.1, 0.1, 0.0 (failures); chunk by chunk
    peaks = jnp.asarray([[0.1, 0.9], [0.6, 0.2], [0.6, 0.6], [0.7, 0.0], [0.3, 0.6], [0.3, 0.0], [0.0, 0.2],
                         [0.1, 0.0], [0.1, 0.1], [0.0, 0.0]])
    real = jnp.asarray([True, True, True] + [False] * 7)
    out = jax.device_get(imagined_check.detector_separation(peaks, real, max_false_success=0.15))
    # success 0.9 beats all 7; each 0.6 beats 5, ties one (half) and loses to 0.7: (7 + 5.5 + 5.5) / 21
    assert out["detector_auc"] == pytest.approx(18 / 21)
    # 15% of 7 failures: one may be paid, so a trajectory is paid above the second highest failure (0.6)
    assert out["detector_threshold_bounded"] == pytest.approx(0.6)
    assert out["detector_recall_bounded"] == pytest.approx(1 / 3)  # 0.9 alone; the 0.6 successes miss it
    assert out["detector_precision_bounded"] == pytest.approx(1 / 2)  # 0.9 and the failure's 0.7
    strict = jax.device_get(imagined_check.detector_separation(peaks, real, max_false_success=0.0))
    assert strict["detector_threshold_bounded"] == pytest.approx(0.7) and strict["detector_precision_bounded"] == 1.0
    # failures alone: the cut is still theirs (the highest, none of 10 may be paid), nothing else is defined
    one_sided = jax.device_get(imagined_check.detector_separation(peaks, jnp.zeros(10, bool)))
    assert one_sided["detector_threshold_bounded"] == pytest.approx(0.9)
    assert all(np.isnan(one_sided[f"detector_{k}"]) for k in ("auc", "recall_bounded", "precision_bounded"))
    all_won = jax.device_get(imagined_check.detector_separation(peaks, jnp.ones(10, bool)))
    assert all(np.isnan(v) for v in all_won.values())
    with pytest.raises(ValueError, match="max_false_success must be in"):
        imagined_check.detector_separation(peaks, real, max_false_success=1.0)


@functools.cache
def _executed_steps():
    """One GRPO step on the toy world paid by the toy environment, with its detector ``never`` and with it
    ``always`` firing, from the check's designed starts: ``(state, {detector: (new_state, metrics)})``. Both run
    here, one after the other, whichever test asks first, so that nothing a test between them changes can make
    the step trace twice; the second starts from the state placed where the step placed the first one's (the
    step is not donated, so the results stay readable)."""
    graphdef, params, sim, start, env_starts = _designed(EXEC)
    step = grpo.make_grpo_step(graphdef, EXEC, env=ToyEnv(EXEC.success_threshold), donate=False)
    state, out = grpo.init_state(params, EXEC), {}
    for detector, reward in (("never", NEVER), ("always", ALWAYS)):
        new_state, metrics = step(state, (sim, reward, start, env_starts), jax.random.key(3))
        out[detector] = (new_state, jax.device_get(metrics))
        state = jax.device_put(state, jax.tree.map(lambda x: x.sharding, new_state))
    return state, out


def _executed_step(detector: str):
    """``(state, new_state, metrics)`` of :func:`_executed_steps` for ``detector`` (``never`` or ``always``)."""
    state, out = _executed_steps()
    return (state, *out[detector])


def test_an_executed_reward_pays_what_the_environment_says_whatever_the_detector():
    state, moved, never = _executed_step("never")
    _, _, always = _executed_step("always")
    # the detector stops nothing: the same rollouts, paid the same by the environment
    assert 0.0 < never["success_rate"] < 1.0 and never["success_rate"] == always["success_rate"]
    assert never["kept_fraction"] > 0 and never["kept_fraction"] == always["kept_fraction"]
    assert never["detector_success"] == 0.0 and always["detector_success"] == 1.0
    assert always["detector_false_success"] == 1.0 and never["detector_false_success"] == 0.0
    assert never["detector_agreement"] == pytest.approx(1 - never["success_rate"])
    assert never["real_rollouts"] == EXEC.grpo.rollout_batch * EXEC.grpo.group_size  # 3 starts x 4 executed
    # a detector that scores every frame alike ranks no outcome above the other, at any threshold
    for metrics in (never, always):
        assert metrics["detector_auc"] == pytest.approx(0.5)
        assert metrics["detector_recall_bounded"] == 0.0 and np.isnan(metrics["detector_precision_bounded"])
    changed = jax.tree.leaves(jax.tree.map(lambda a, b: bool(np.any(np.asarray(a) != np.asarray(b))),
                                           state.params, moved.params))
    assert any(changed), "a mixed group moved the policy"


def test_outcomes_by_start_count_each_bin_and_refuse_bad_edges():
    """Counts per bin of the start's step (the last bin open above, an empty bin 0), real successes and the
    detector's verdicts among them; edges must start at 0 and rise."""
    steps = [0, 23, 24, 60, 200, 47]
    said = [True, False, True, True, True, False]
    real = [True, True, False, False, True, False]
    out = jax.device_get(imagined_check.outcomes_by_start(steps, said, real, edges=(0, 24, 48, 96)))
    assert {k: float(v) for k, v in out.items()} == {
        "start_a0_rollouts": 2.0, "start_a0_real": 2.0, "start_a0_said": 1.0, "start_a0_said_real": 1.0,
        "start_a24_rollouts": 2.0, "start_a24_real": 0.0, "start_a24_said": 1.0, "start_a24_said_real": 0.0,
        "start_a48_rollouts": 1.0, "start_a48_real": 0.0, "start_a48_said": 1.0, "start_a48_said_real": 0.0,
        "start_a96_rollouts": 1.0, "start_a96_real": 1.0, "start_a96_said": 1.0, "start_a96_said_real": 1.0}
    assert set(imagined_check.outcomes_by_start([5], [True], [True])) == {
        f"start_a{a}_{k}" for a in imagined_check.START_STEP_EDGES for k in ("rollouts", "real", "said", "said_real")}
    truth = jax.device_get(imagined_check.outcomes_by_start(steps, None, real, edges=(0, 24, 48, 96)))
    assert {k: float(v) for k, v in truth.items()} == {k: float(v) for k, v in out.items() if "said" not in k}
    for bad in ((), (1, 24), (0, 24, 24)):
        with pytest.raises(ValueError, match="edges must start at 0 and rise"):
            imagined_check.outcomes_by_start([0], [True], [True], edges=bad)


def test_an_executed_step_given_its_starts_steps_counts_its_outcomes_by_them():
    """With each start's step in the batch, the executed step counts its trajectories by where their starts stand:
    a group's trajectories all in its start's bin, the real successes adding up to the step's success rate and
    the detector's verdicts to its; without them it logs no such count (the other tests' steps)."""
    graphdef, params, sim, start, env_starts = _designed(EXEC)
    step = grpo.make_grpo_step(graphdef, EXEC, env=ToyEnv(EXEC.success_threshold), donate=False)
    start_steps = jnp.asarray([5, 30, 200], jnp.int32)  # one start per bin of 0, 24 and 96
    _, metrics = step(grpo.init_state(params, EXEC), (sim, ALWAYS, start, env_starts, start_steps), jax.random.key(3))
    metrics = jax.device_get(metrics)
    g, n = EXEC.grpo.group_size, EXEC.grpo.rollout_batch * EXEC.grpo.group_size
    counts = {a: metrics[f"start_a{a}_rollouts"] for a in imagined_check.START_STEP_EDGES}
    assert counts == {0: g, 24: g, 48: 0, 72: 0, 96: g}
    real = sum(metrics[f"start_a{a}_real"] for a in imagined_check.START_STEP_EDGES)
    assert real == pytest.approx(metrics["success_rate"] * n)
    assert all(0 <= metrics[f"start_a{a}_real"] <= counts[a] for a in counts)
    # start 1 (bin 24) is the one near its target: its group succeeds most
    assert metrics["start_a24_real"] >= 1 and metrics["start_a24_real"] >= max(metrics["start_a0_real"],
                                                                               metrics["start_a96_real"])
    assert all(metrics[f"start_a{a}_said"] == counts[a] for a in counts)  # a detector that always fires
    assert all(metrics[f"start_a{a}_said_real"] == metrics[f"start_a{a}_real"] for a in counts)
    assert "start_a0_rollouts" not in _executed_step("always")[2]


def test_a_step_whose_detector_figures_are_undefined_is_still_finite():
    """An executed step's detector figures are NaN by definition where an outcome is missing; that must not stop
    the run as a non-finite update does (the GRPO loop's finite test), while a NaN loss still does."""
    from sword_jax.rl.grpo_loop import grpo_metrics_finite

    nan = jnp.float32(jnp.nan)
    metrics = {"loss": jnp.float32(0.5), **{k: nan for k in imagined_check.UNDEFINED_AS_NAN}}
    assert bool(grpo_metrics_finite(metrics))
    assert not bool(grpo_metrics_finite(dict(metrics, loss=nan)))
    assert not bool(grpo_metrics_finite(dict(metrics, detector_agreement=nan)))
    _, _, never = _executed_step("never")  # the toy step's own undefined precision at the bound
    assert np.isnan(never["detector_precision_bounded"]) and bool(grpo_metrics_finite(never))


def test_every_detector_figure_that_can_be_undefined_is_listed_as_such():
    """Whatever figure the executed step's detector functions return NaN for when an outcome is missing (every
    trajectory real successes, every one a real failure, nothing scored above the cut) is in UNDEFINED_AS_NAN, which
    the GRPO loop's finite test leaves out; a figure added there that can be NaN must be listed, or a run stops."""
    peaks = jnp.asarray([[0.1, 0.9], [0.2, 0.3], [0.8, 0.7], [0.4, 0.1]], jnp.float32)
    cases = {"mixed": [True, False, True, False], "all real successes": [True] * 4,
             "all real failures": [False] * 4}
    undefined = set()
    for name, real in cases.items():
        real = jnp.asarray(real)
        figures = {**imagined_check.detector_metrics(jnp.asarray([True, True, False, False]), real),
                   **imagined_check.detector_separation(peaks, real, max_false_success=0.0)}
        nan = {k for k, v in figures.items() if np.isnan(float(v))}
        if name == "mixed":
            assert not nan, f"figures undefined on mixed outcomes: {sorted(nan)}"
        undefined |= nan
    flat = imagined_check.detector_separation(jnp.zeros((4, 2), jnp.float32), jnp.asarray([True, False, True, False]))
    undefined |= {k for k, v in flat.items() if np.isnan(float(v))}  # every score alike: nothing paid at the cut
    assert undefined and undefined <= set(imagined_check.UNDEFINED_AS_NAN), sorted(
        undefined - set(imagined_check.UNDEFINED_AS_NAN))
    assert set(imagined_check.UNDEFINED_AS_NAN) <= undefined  # and nothing listed that is always defined


def test_an_executed_reward_is_refused_without_its_environment_outside_mjx_or_with_a_branching_refresh():
    graphdef, _ = build_policy(EXEC, seed=0)
    with pytest.raises(ValueError, match="needs env="):
        grpo.make_grpo_step(graphdef, EXEC)
    for bad, what in ((dataclasses.replace(EXEC, env=EnvConfig(backend="cpu")), "backend=mjx"),
                      (dataclasses.replace(EXEC, refresh=RefreshConfig(every=5, budget=64)),
                       "no refresh that branches"),
                      (dataclasses.replace(EXEC, imagined=dataclasses.replace(EXEC.imagined, confirm_success=True)),
                       "confirm_success=false")):
        with pytest.raises(ValueError, match=what):
            bad.validate()
    with pytest.raises(ValueError, match="detector|executed"):
        ImaginedConfig(reward="oracle").validate()
    # a refresh from the keyframes (no branch) keeps their recorded states, so the executed reward may refresh
    dataclasses.replace(EXEC, refresh=RefreshConfig(every=5, budget=64, branch=False)).validate()
    # the run's identity names what pays it only when it is not the detector
    assert grpo_run_id(EXEC, seed=0, simulator="world_model")["rl.imagined.reward"] == "executed"
    assert "rl.imagined.reward" not in grpo_run_id(CFG, seed=0, simulator="world_model")


# ---- where the closed loop through the simulator leaves the real one ----

def test_execute_observed_keeps_the_real_frame_at_each_decisions_end():
    env = ToyEnv(CFG.success_threshold)
    starts = jnp.asarray([[0.0, 0.0, 0.3, 0.0], [0.1, -0.2, -0.5, 0.4], [0.0, 0.5, 0.0, 0.0]])
    actions = jax.random.uniform(jax.random.key(1), (3, 6, 7), minval=-1.0, maxval=1.0).at[:, :, 0].set(1.0)
    lengths = jnp.asarray([6, 4, 2])
    first, frames = jax.jit(lambda s, a, n: imagined_check.execute_observed(env, s, a, n, every=2, rows=2))(
        starts, actions, lengths)
    np.testing.assert_array_equal(first, imagined_check.execute_open_loop(env, starts, actions, lengths))
    assert frames.shape == (2, 3, 8, 8, 3)
    state, _ = env.reset(starts)
    for i in range(6):  # the frame after actions 1, 3 and 5: decisions 0, 1, 2 of two actions each
        state, obs, _ = env.step(state, actions[:, i])
        if i % 2:
            np.testing.assert_allclose(frames[:, i // 2], obs["frames"][:2], atol=1e-6)
    with pytest.raises(ValueError, match="every=4 must divide"):
        imagined_check.execute_observed(env, starts, actions, lengths, every=4, rows=2)
    with pytest.raises(ValueError, match="rows=4"):
        imagined_check.execute_observed(env, starts, actions, lengths, every=2, rows=4)


def _lagging(sim):
    """``sim`` shown one step late: each step returns the frames of the step before (the start frame first)."""
    def init_fn(params, start):
        inner = sim.init_fn(params, start)
        return inner, jnp.repeat(toy_render(inner, sim.frame_size)[None], sim.frames_per_step, axis=0)

    def step_fn(params, state, chunk, key):
        inner, shown = state
        inner, frames = sim.step_fn(params, inner, chunk, key)
        return (inner, frames), shown

    return dataclasses.replace(sim, init_fn=init_fn, step_fn=step_fn,
                               observe_fn=lambda params, state: sim.observe_fn(params, state[0]))


def _shifted(sim, shift):
    """``sim`` with every frame it returns brightened by ``shift`` (not clipped): faithful dynamics seen through
    a decoder that adds ``shift``."""
    def step_fn(params, state, chunk, key):
        state, frames = sim.step_fn(params, state, chunk, key)
        return state, frames + shift

    return dataclasses.replace(sim, step_fn=step_fn)


def _fidelity(step_size, lag=False, figures=("frame_error", "action_gap"), round_trip=None, shift=0.0,
              read_state=None):
    """The closed-loop figures of the designed toy starts in a toy simulator moving ``step_size`` a step (shown a
    step late with ``lag``, its frames brightened by ``shift``), checked against the toy environment (``STEP``),
    with ``round_trip`` given to the check."""
    graphdef, params, _, start, env_starts = _designed(CFG)
    sim = toy_simulator(frame_size=8, step_size=step_size, chunk_len=CFG.chunk_len)
    sim = _lagging(sim) if lag else sim
    sim = _shifted(sim, shift) if shift else sim
    g = CFG.grpo.group_size

    def go(key):
        rollout = imagined_rollout(graphdef, params, sim, NEVER, start, CFG, key=key, group_size=g)
        actions, lengths = imagined_check.executed_actions(rollout, CFG.action_bins)
        _, frames = imagined_check.execute_observed(ToyEnv(CFG.success_threshold), jnp.repeat(env_starts, g, axis=0),
                                                    actions, lengths, every=rollout.tokens.shape[2], rows=8)
        return imagined_check.closed_loop_fidelity(graphdef, params, rollout, frames, image_size=CFG.image_size,
                                                   action_bins=CFG.action_bins, round_trip=round_trip,
                                                   read_state=read_state)

    out = jax.device_get(jax.jit(go)(jax.random.key(2)))
    c = CFG.imagined.max_chunks
    # the VAE's share only with a round trip, the state readouts only with a probe; without them the keys of before
    vae = ("frame_error_vae", "action_gap_vae", "sharpness_vae") if round_trip is not None else ()
    probe = ("ee_cm", "bowl_cm", "gripper_agree", "ee_motion_cm", "bowl_motion_cm") if read_state is not None else ()
    probe += ("ee_cm_vae", "bowl_cm_vae", "gripper_agree_vae") if read_state is not None and vae else ()
    assert sorted(out) == sorted([f"closed_loop_{what}_{k}" for k in range(1, c)
                                  for what in ("frame_error", "action_gap", "frame_error_prev", "action_gap_prev",
                                               "motion", "sharpness") + vae + probe])
    return [[out[f"closed_loop_{what}_{k}"] for k in range(1, c)] for what in figures]


# 13 s on 2 cores; the default run checks a simulator equal to the environment leaves no gap in
# test_an_executed_step_logs_its_closed_loop_and_is_paid_the_same_without_it (the toy simulator there).
@pytest.mark.slow
def test_a_simulator_equal_to_the_environment_leaves_no_closed_loop_gap():
    frame_error, action_gap = _fidelity(STEP)
    np.testing.assert_allclose(frame_error, 0.0, atol=1e-5)
    np.testing.assert_allclose(action_gap, 0.0, atol=1e-6)


def test_a_simulator_a_decision_late_matches_the_real_frame_a_decision_earlier():
    """Shown a step late, the simulator's frame is the real one of the decision before: its error against that
    frame is 0, its error against the current one is the real motion, which the faithful simulator also reports."""
    error, prev, gap_prev, motion = _fidelity(STEP, lag=True, figures=("frame_error", "frame_error_prev",
                                                                      "action_gap_prev", "motion"))
    np.testing.assert_allclose(prev, 0.0, atol=1e-5)
    np.testing.assert_allclose(gap_prev, 0.0, atol=1e-6)
    assert min(motion) > 1e-3, motion  # the real scene moves every decision
    np.testing.assert_allclose(error, motion, atol=1e-5)
    faithful_error, faithful_prev, faithful_motion = _fidelity(STEP, figures=("frame_error", "frame_error_prev",
                                                                               "motion"))
    np.testing.assert_allclose(faithful_error, 0.0, atol=1e-5)
    np.testing.assert_allclose(faithful_prev, faithful_motion, atol=1e-5)


def test_an_identity_round_trip_leaves_no_vae_share():
    error, gap = _fidelity(STEP, figures=("frame_error_vae", "action_gap_vae"), round_trip=lambda f: f)
    np.testing.assert_array_equal(error, 0.0)
    np.testing.assert_array_equal(gap, 0.0)


def _designed_probe(frames):
    """A stand-in state probe: the end effector is the frame's mean colour, the bowl twice it, the gripper closed
    (0.01 m) where the red channel's mean is above 0.5 (metres, the probe's 7 values)."""
    mean = jnp.mean(frames, axis=(1, 2))
    gripper = jnp.where(mean[:, :1] > 0.5, 0.01, 0.08)
    return jnp.concatenate([mean, gripper, 2.0 * mean], axis=1)


def test_the_state_readout_places_the_gap_in_the_arm_or_the_bowl():
    """Read by a designed probe: a faithful simulator leaves no gap in the arm, the bowl or the gripper; one a
    decision late is off by exactly the real motion the readout sees; one whose frames are brightened by 0.1 reads
    every channel 0.1 higher (the arm sqrt(3) x 10 cm off, the bowl twice that)."""
    ee, bowl, agree, ee_motion, bowl_motion = _fidelity(
        STEP, figures=("ee_cm", "bowl_cm", "gripper_agree", "ee_motion_cm", "bowl_motion_cm"),
        read_state=_designed_probe)
    np.testing.assert_allclose(ee, 0.0, atol=1e-3)
    np.testing.assert_allclose(bowl, 0.0, atol=1e-3)
    np.testing.assert_array_equal(agree, 1.0)
    assert min(ee_motion) > 1e-2, ee_motion  # the real scene's readout moves every decision
    np.testing.assert_allclose(bowl_motion, 2.0 * np.asarray(ee_motion), rtol=1e-4)
    late, late_motion = _fidelity(STEP, lag=True, figures=("ee_cm", "ee_motion_cm"), read_state=_designed_probe)
    np.testing.assert_allclose(late, late_motion, rtol=1e-4, atol=1e-4)
    shifted = _fidelity(STEP, figures=("ee_cm", "bowl_cm"), shift=0.1, read_state=_designed_probe)
    np.testing.assert_allclose(shifted[0], 10.0 * np.sqrt(3.0), rtol=1e-4)
    np.testing.assert_allclose(shifted[1], 20.0 * np.sqrt(3.0), rtol=1e-4)


def test_the_state_readout_on_the_round_trip_is_the_floor_of_a_faithful_simulator_behind_that_decoder():
    """A faithful simulator whose frames come out brightened by 0.1, and a round trip that brightens the real frames
    by the same 0.1: the designed probe reads the round trip exactly as far off as the simulator's frames (the arm
    sqrt(3) x 10 cm, the bowl twice that), so the whole readout gap is the floor; an identity round trip has none."""
    ee, bowl, ee_vae, bowl_vae = _fidelity(STEP, figures=("ee_cm", "bowl_cm", "ee_cm_vae", "bowl_cm_vae"), shift=0.1,
                                           round_trip=lambda f: f + 0.1, read_state=_designed_probe)
    np.testing.assert_allclose(ee_vae, 10.0 * np.sqrt(3.0), rtol=1e-4)
    np.testing.assert_allclose(bowl_vae, 20.0 * np.sqrt(3.0), rtol=1e-4)
    np.testing.assert_allclose(ee, ee_vae, rtol=1e-4)
    np.testing.assert_allclose(bowl, bowl_vae, rtol=1e-4)
    ee_vae, agree_vae = _fidelity(STEP, figures=("ee_cm_vae", "gripper_agree_vae"), round_trip=lambda f: f,
                                  read_state=_designed_probe)
    np.testing.assert_allclose(ee_vae, 0.0, atol=1e-4)
    np.testing.assert_array_equal(agree_vae, 1.0)


def test_a_decoder_that_shifts_the_frames_is_the_whole_gap_of_a_faithful_simulator():
    """A simulator with the environment's dynamics whose frames come out brightened by 0.1, and a round trip that
    brightens the real frames by the same 0.1: the VAE's share is the shift's frame error, and it is the whole
    closed-loop gap (frame error and greedy action gap alike), read as a decoder, not dynamics, problem."""
    shift = 0.1
    error, gap, vae_error, vae_gap, motion = _fidelity(
        STEP, figures=("frame_error", "action_gap", "frame_error_vae", "action_gap_vae", "motion"),
        round_trip=lambda f: f + shift, shift=shift)
    np.testing.assert_allclose(vae_error, shift, atol=1e-6)  # the shift's frame error at the policy's size
    np.testing.assert_allclose(error, vae_error, atol=1e-6)
    np.testing.assert_allclose(gap, vae_gap, atol=1e-6)
    assert min(motion) > 1e-3  # the scene moves: the figures are of real frames that differ decision by decision
    # a round trip through the same shift beside a simulator that drifts: the VAE's share stays the shift's
    drift_error, drift_vae = _fidelity(3 * STEP, figures=("frame_error", "frame_error_vae"),
                                       round_trip=lambda f: f + shift, shift=shift)
    np.testing.assert_allclose(drift_vae, shift, atol=1e-6)
    assert max(abs(a - b) for a, b in zip(drift_error, drift_vae)) > 1e-3, "the drift is the dynamics' share"


def _box_blur(frames):
    """Each pixel the mean of its 3 x 3 neighbourhood (wrapping round): the same scene with its finest detail gone."""
    padded = jnp.pad(frames, [(0, 0)] * (frames.ndim - 3) + [(1, 1), (1, 1), (0, 0)], mode="wrap")
    h, w = frames.shape[-3:-1]
    return sum(padded[..., i:i + h, j:j + w, :] for i in range(3) for j in range(3)) / 9.0


def test_sharpness_is_one_for_the_same_detail_and_falls_with_a_blur():
    board = (np.indices((16, 16)).sum(0) % 2).astype(np.float32)[..., None].repeat(3, -1)  # a checkerboard
    frames = jnp.stack([jnp.asarray(board), jnp.asarray(board) * 0.5 + 0.25])
    assert float(imagined_check.high_frequency_energy(frames[0])) == pytest.approx(16.0, rel=1e-6)  # (4 x +-1)^2
    np.testing.assert_allclose(imagined_check.sharpness_ratio(frames, frames), 1.0)
    np.testing.assert_allclose(imagined_check.sharpness_ratio(frames + 0.1, frames), 1.0, rtol=1e-5)  # brightness
    # half the contrast is a quarter of the energy; a 3 x 3 blur of a checkerboard leaves a ninth of its amplitude
    assert float(imagined_check.sharpness_ratio(frames[1], frames[0])) == pytest.approx(0.25, rel=1e-5)
    assert float(imagined_check.sharpness_ratio(_box_blur(frames[0]), frames[0])) == pytest.approx(1 / 81, rel=1e-4)
    flat = jnp.full((8, 8, 3), 0.3)
    assert float(imagined_check.sharpness_ratio(flat, flat)) == pytest.approx(1.0)
    assert float(imagined_check.sharpness_ratio(flat, frames[0])) < 1e-6


def test_a_faithful_simulator_is_as_sharp_as_the_real_frames_and_a_blurring_decoder_is_not():
    """The closed loop's sharpness: 1 at every decision for a simulator equal to the environment, and for a round
    trip that only brightens; below 1 for a round trip that blurs (the VAE's floor of it), the simulator's own 1."""
    sharp, sharp_vae = _fidelity(STEP, figures=("sharpness", "sharpness_vae"), round_trip=lambda f: f + 0.1)
    np.testing.assert_allclose(sharp, 1.0, rtol=1e-4)
    np.testing.assert_allclose(sharp_vae, 1.0, rtol=1e-3)
    sharp, blurred = _fidelity(STEP, figures=("sharpness", "sharpness_vae"), round_trip=_box_blur)
    np.testing.assert_allclose(sharp, 1.0, rtol=1e-4)
    assert max(blurred) < 0.9, blurred


def test_a_simulators_round_trip_runs_in_slices_at_its_frame_size():
    sim = toy_simulator(frame_size=8, chunk_len=4)
    with pytest.raises(ValueError, match="no round trip"):
        sim.round_trip(jnp.zeros((2, 8, 8, 3)))
    seen = []

    def halve(params, frames):
        seen.append(frames.shape)
        return frames * 0.5

    frames = jax.random.uniform(jax.random.key(0), (7, 8, 8, 3))
    whole = sim.replace(round_trip_fn=halve)
    np.testing.assert_allclose(whole.round_trip(frames), frames * 0.5)
    sliced = sim.replace(round_trip_fn=halve, max_slice=3)  # 3 slices of 3, the last padded
    np.testing.assert_allclose(jax.jit(sliced.round_trip)(frames), frames * 0.5)
    assert seen[0] == (7, 8, 8, 3) and seen[-1] == (3, 8, 8, 3)
    flat = jnp.full((2, 16, 16, 3), 0.4)  # frames of another size are resized to the simulator's first
    np.testing.assert_allclose(whole.round_trip(flat), jnp.full((2, 8, 8, 3), 0.2), atol=1e-6)


def test_a_simulator_that_moves_too_far_drifts_from_the_real_frames_decision_by_decision():
    frame_error, action_gap = _fidelity(3 * STEP)
    assert all(e > 1e-3 for e in frame_error), frame_error
    assert frame_error[-1] > frame_error[0], frame_error  # the drift grows with the decisions
    assert max(action_gap) > 0.0, "the policy reads the drifted frames differently"


def test_an_executed_step_logs_its_closed_loop_and_is_paid_the_same_without_it():
    _, _, logged = _executed_step("never")
    c = EXEC.imagined.max_chunks
    for k in range(1, c):  # the toy simulator equals the toy environment
        assert logged[f"closed_loop_frame_error_{k}"] == pytest.approx(0.0, abs=1e-5)
        assert logged[f"closed_loop_action_gap_{k}"] == pytest.approx(0.0, abs=1e-6)
    assert not any("_vae_" in k for k in logged), "the toy simulator has no round trip of real frames"
    # a simulator with a round trip (here the identity) logs the VAE's share too: none
    graphdef, params, sim, start, env_starts = _designed(EXEC)
    step = grpo.make_grpo_step(graphdef, EXEC, env=ToyEnv(EXEC.success_threshold), donate=False)
    _, with_trip = step(grpo.init_state(params, EXEC), (sim.replace(round_trip_fn=lambda p, f: f), NEVER, start,
                                                        env_starts), jax.random.key(3))
    with_trip = jax.device_get(with_trip)
    for k in range(1, c):
        assert with_trip[f"closed_loop_frame_error_vae_{k}"] == 0.0
        assert with_trip[f"closed_loop_action_gap_vae_{k}"] == 0.0
    assert with_trip["loss"] == pytest.approx(logged["loss"]), "the round trip is measured, not trained on"
    off = dataclasses.replace(EXEC, imagined=dataclasses.replace(EXEC.imagined, fidelity_trajectories=0))
    graphdef, params, sim, start, env_starts = _designed(off)
    step = grpo.make_grpo_step(graphdef, off, env=ToyEnv(off.success_threshold), donate=False)
    _, plain = step(grpo.init_state(params, off), (sim, NEVER, start, env_starts), jax.random.key(3))
    plain = jax.device_get(plain)
    assert not any(k.startswith("closed_loop") for k in plain)
    assert plain["success_rate"] == logged["success_rate"] and plain["loss"] == pytest.approx(logged["loss"])
    with pytest.raises(ValueError, match="fidelity_trajectories"):
        ImaginedConfig(fidelity_trajectories=-1).validate()


# ---- rl.imagined.reward=calibrated: paid by execution first, then by the detector at the threshold that set ----

CAL = dataclasses.replace(EXEC, imagined=dataclasses.replace(EXEC.imagined, reward="calibrated", calibrate_steps=1))


def test_the_calibrated_threshold_sits_just_above_the_median_cut():
    assert grpo.calibrated_threshold([0.2, float("nan"), 0.6, 0.4]) == np.nextafter(np.float32(0.4), np.float32(1))
    assert grpo.calibrated_threshold([0.0]) == np.finfo(np.float32).tiny  # never a subnormal a device flushes to 0
    with pytest.raises(ValueError, match="none of the 2 steps paid by execution had a real failure"):
        grpo.calibrated_threshold([float("nan")] * 2)


def test_a_calibrated_reward_pays_by_execution_then_by_the_detector_at_the_threshold_it_set():
    """rl.imagined.reward=calibrated with one calibration step on the toy world: step 1 is the executed step (the
    environment pays, the detector's bounded cut is logged); step 2 is the detector's step at the threshold just
    above that cut, the same step as one built with that threshold; a step resumed after the calibration reads the
    cut from the run's records and pays alike; without them it is refused by name."""
    graphdef, params, sim, start, env_starts = _designed(CAL)
    env, detector = ToyEnv(CAL.success_threshold), toy_reward_model()
    batch = (sim, detector, start, env_starts)
    state = grpo.init_state(params, CAL)
    step = grpo.make_calibrated_step(graphdef, CAL, env=env, donate=False)
    first_state, first = step(state, batch, jax.random.key(3))
    first = jax.device_get(first)
    assert {"detector_auc", "detector_threshold_bounded", "detector_success"} <= set(first)
    assert not np.isnan(first["detector_threshold_bounded"]), "the designed starts give both real outcomes"
    threshold = grpo.calibrated_threshold([first["detector_threshold_bounded"]])
    second_state, second = step(first_state, batch, jax.random.key(3))
    second = jax.device_get(second)
    assert second["detector_threshold"] == np.float32(threshold) and "detector_success" not in second
    by_hand = grpo.make_grpo_step(graphdef, dataclasses.replace(
        CAL, success_threshold=threshold, imagined=dataclasses.replace(CAL.imagined, reward="detector",
                                                                       calibrate_steps=0)), donate=False)
    placed = jax.device_put(first_state, jax.tree.map(lambda x: x.sharding, second_state))
    hand_state, hand = by_hand(placed, batch, jax.random.key(3))
    assert {k: v for k, v in second.items() if k != "detector_threshold"} == jax.device_get(hand)
    # resumed after the calibration step: its cut from the records, the same step
    resumed = grpo.make_calibrated_step(graphdef, CAL, env=env, donate=False,
                                        history=lambda: [{"step": 1, **{k: float(v) for k, v in first.items()}}])
    again_state, again = resumed(placed, batch, jax.random.key(3))
    assert jax.device_get(again) == second
    for a, b in zip(jax.tree.leaves(again_state.params), jax.tree.leaves(second_state.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    lost = grpo.make_calibrated_step(graphdef, CAL, env=env, donate=False)
    with pytest.raises(ValueError, match=r"resumed after steps \[1\] paid by execution, but its records hold only"):
        lost(placed, batch, jax.random.key(3))


def test_a_calibrated_reward_is_refused_without_its_steps_or_by_the_plain_step():
    with pytest.raises(ValueError, match="calibrate_steps .* must be >= 1 with rl.imagined.reward=calibrated"):
        dataclasses.replace(CAL, imagined=dataclasses.replace(CAL.imagined, calibrate_steps=0)).validate()
    with pytest.raises(ValueError, match="calibrate_steps .* and 0 otherwise"):
        dataclasses.replace(EXEC, imagined=dataclasses.replace(EXEC.imagined, calibrate_steps=2)).validate()
    with pytest.raises(ValueError, match="reward=calibrated pays imagined actions by executing them on MJX"):
        dataclasses.replace(CAL, env=EnvConfig(backend="cpu")).validate()
    graphdef, _ = build_policy(CAL, seed=0)
    with pytest.raises(ValueError, match="build its step with make_calibrated_step"):
        grpo.make_grpo_step(graphdef, CAL, env=ToyEnv(CAL.success_threshold))
    with pytest.raises(ValueError, match="reward must be calibrated"):
        grpo.make_calibrated_step(graphdef, EXEC, env=ToyEnv(EXEC.success_threshold))
    run_id = grpo_run_id(CAL, seed=0, simulator="world_model")
    assert run_id["rl.imagined.calibrate_steps"] == 1 and run_id["rl.refresh.max_false_success"] == 0.05
    assert "rl.imagined.calibrate_steps" not in grpo_run_id(EXEC, seed=0, simulator="world_model")
