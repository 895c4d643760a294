"""GRPO: advantages and loss against hand-computed numbers, clipping, and learning on a toy simulator."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import data as rl_data
from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.rollout import Rollout, expand_groups, imagined_rollout


def test_group_advantages_hand_computed():
    returns = jnp.asarray([[1.0, 0.0, 0.0, 1.0], [2.0, 2.0, 2.0, 2.0], [3.0, 1.0, 2.0, 2.0]])
    adv, keep = grpo.group_advantages(returns, eps=0.0)
    # group 0: mean 0.5, population std 0.5; group 1: no signal (filtered);
    # group 2: mean 2, std sqrt(0.5)
    s = math.sqrt(0.5)
    expected = np.array([[1, -1, -1, 1], [0, 0, 0, 0], [1 / s, -1 / s, 0, 0]], np.float32)
    np.testing.assert_allclose(np.asarray(adv), expected, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(keep), [1.0, 0.0, 1.0])
    _, keep_all = grpo.group_advantages(returns, filter_groups=False)
    np.testing.assert_array_equal(np.asarray(keep_all), [1.0, 1.0, 1.0])
    # Dr. GRPO: centred, not scaled, so a spread of 0.02 stays 100 times smaller than a spread of 2
    centred, keep_c = grpo.group_advantages(jnp.asarray([[2.0, 0.0], [0.11, 0.09], [1.0, 1.0]]), scale_by_std=False)
    np.testing.assert_allclose(np.asarray(centred), [[1, -1], [0.01, -0.01], [0, 0]], rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(keep_c), [1.0, 1.0, 0.0])
    scaled, _ = grpo.group_advantages(jnp.asarray([[2.0, 0.0], [0.11, 0.09]]))
    np.testing.assert_allclose(np.asarray(scaled), [[1, -1], [1, -1]], rtol=1e-3)  # what the std makes of them


def _random_rollout(cfg, rng, returns=None, groups=2):
    """``groups`` groups of random frames, tokens and behaviour log-probs, every chunk valid; ``returns`` default to
    uniform draws."""
    n, c, t, a = groups * cfg.grpo.group_size, cfg.imagined.max_chunks, cfg.chunk_len, cfg.action_dim
    frames, proprio = rng.random((n, c, 8, 8, 3)), rng.normal(size=(n, c, 4))
    tokens, noise = rng.integers(0, cfg.action_bins, (n, c, t, a)), rng.normal(size=(n, c, t, a))
    return Rollout(
        obs_frames=jnp.asarray(frames, jnp.float32), proprio=jnp.asarray(proprio), proprio_valid=jnp.ones((n, c)),
        instruction_tokens=jnp.asarray(tokenize_instructions(["pick it"] * n, 32)), tokens=jnp.asarray(tokens, jnp.int32),
        log_probs=jnp.asarray(-np.log(cfg.action_bins) + 0.3 * noise, jnp.float32), valid=jnp.ones((n, c)),
        rewards=jnp.zeros((n, c)), scores=jnp.zeros((n, c)), success=jnp.zeros((n,), bool),
        returns=jnp.asarray(rng.random(n) if returns is None else returns, jnp.float32), frames=jnp.zeros((0,)))


def test_the_update_reads_scale_by_std():
    """grpo_gradients with rl.grpo.scale_by_std: returns shrunk 100-fold give the same gradient under the std
    (GRPO) and a 100-fold smaller one without it (Dr. GRPO)."""
    with pytest.raises(ValueError, match="rl.grpo.scale_by_std"):
        GRPOConfig(scale_by_std="no").validate()
    base = _toy_cfg(ppo_epochs=1, max_chunks=2, group_size=4)
    graphdef, params = build_policy(base, seed=0)
    rollout = _random_rollout(base, np.random.default_rng(3))
    grads = {}
    for by_std in (True, False):
        cfg = dataclasses.replace(base, grpo=dataclasses.replace(base.grpo, scale_by_std=by_std))
        fn = jax.jit(lambda p, b, cfg=cfg: grpo.grpo_gradients(graphdef, cfg, p, b)[2])
        grads[by_std] = [fn(params, rollout._replace(returns=rollout.returns * k)) for k in (1.0, 0.01)]
    for by_std, factor in ((True, 1.0), (False, 0.01)):
        full, shrunk = grads[by_std]
        scale = max(float(np.abs(np.asarray(x)).max()) for x in jax.tree.leaves(full))
        for x, y in zip(jax.tree.leaves(full), jax.tree.leaves(shrunk)):
            np.testing.assert_allclose(np.asarray(y), factor * np.asarray(x), rtol=0, atol=2e-3 * factor * scale)


def test_grpo_loss_hand_computed():
    cfg = RLConfig(grpo=GRPOConfig(clip_low=0.2, clip_high=0.28))
    # two trajectories, 2 chunks, 1 action x 1 dim; trajectory 1 is done after chunk 0
    old = jnp.log(jnp.asarray([[0.5, 0.5], [0.5, 0.5]], jnp.float32))[:, :, None, None]
    new = jnp.log(jnp.asarray([[0.6, 0.75], [0.3, 0.9]], jnp.float32))[:, :, None, None]
    adv = jnp.asarray([1.0, -1.0])
    valid = jnp.asarray([[1.0, 1.0], [1.0, 0.0]])
    keep = jnp.ones((2,))
    loss, metrics = grpo.grpo_loss(new, old, None, adv, valid, keep, cfg)
    # traj 0 (A=+1): ratios 1.2 (inside) and 1.5 (clipped to 1.28): losses -1.2, -1.28 -> mean -1.24
    # traj 1 (A=-1): ratio 0.6 -> -min(-0.6, -0.8) = 0.8; chunk 1 masked -> 0.8
    np.testing.assert_allclose(float(loss), (-1.24 + 0.8) / 2, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["clip_fraction"]), 2 / 3, rtol=1e-5)  # 1.5 (A>0) and 0.6 (A<0)
    token_cfg = RLConfig(grpo=GRPOConfig(loss_norm="token"))
    loss_tok, _ = grpo.grpo_loss(new, old, None, adv, valid, keep, token_cfg)
    np.testing.assert_allclose(float(loss_tok), (-1.2 - 1.28 + 0.8) / 3, rtol=1e-5)
    # KL (k3) to a reference equal to the old policy
    kl_cfg = RLConfig(grpo=GRPOConfig(kl_coef=0.5))
    loss_kl, m_kl = grpo.grpo_loss(new, old, old, adv, valid, keep, kl_cfg)
    k3 = lambda p_new: 0.5 / p_new - math.log(0.5 / p_new) - 1  # noqa: E731
    kl_vals = [k3(0.6), k3(0.75), k3(0.3)]
    expected = ((-1.2 + 0.5 * kl_vals[0] - 1.28 + 0.5 * kl_vals[1]) / 2 + 0.8 + 0.5 * kl_vals[2]) / 2
    np.testing.assert_allclose(float(loss_kl), expected, rtol=1e-5)
    np.testing.assert_allclose(float(m_kl["kl"]), sum(kl_vals) / 3, rtol=1e-5)


@pytest.mark.parametrize(
    "ratio, advantage, zero_grad",
    [(1.5, 1.0, True), (1.1, 1.0, False), (0.5, 1.0, False),  # A > 0: clipped only above 1 + 0.28
     (0.5, -1.0, True), (0.9, -1.0, False), (1.5, -1.0, False)],  # A < 0: clipped only below 1 - 0.2
)
def test_clipping_zeroes_gradient_on_the_right_side(ratio, advantage, zero_grad):
    def loss(new_lp):
        out, _ = grpo.clipped_token_loss(new_lp, jnp.float32(0.0), jnp.float32(advantage), clip_low=0.2, clip_high=0.28)
        return out

    g = float(jax.grad(loss)(jnp.log(jnp.float32(ratio))))
    if zero_grad:
        assert g == 0.0
    else:
        assert abs(g) > 0.1, g
        assert np.sign(g) == -np.sign(advantage)  # descent raises log-prob iff A > 0


def _toy_cfg(max_chunks=3, **grpo_kw):
    grpo_cfg = {"group_size": 8, "learning_rate": 1e-2, "ppo_epochs": 2, **grpo_kw}
    return RLConfig(image_size=8, action_bins=8, proprio_dim=4,
                    policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
                    grpo=GRPOConfig(**grpo_cfg), imagined=ImaginedConfig(max_chunks=max_chunks))


# A learning property (35 s on 2 cores); the default run keeps GRPO's learning in tests/test_rl_policy_learning.py
# (the ground-truth update raises the success rate on MuJoCo) and its update rules in the designed-batch tests here.
@pytest.mark.slow
def test_grpo_improves_policy_on_toy_simulator():
    """The toy reward depends on the action (move toward the text's goal): GRPO must raise it. The step runs
    with rl.imagined.confirm_success: the toy world is noiseless, so a second imagination confirms every
    success (the rule's effect on noise-made successes: test_sim_agreement)."""
    base = _toy_cfg()
    cfg = dataclasses.replace(base, imagined=dataclasses.replace(base.imagined, confirm_success=True))
    graphdef, params = build_policy(cfg, seed=0)
    sim, reward_model = toy_simulator(frame_size=8, step_size=0.08), toy_reward_model()
    tokens = jnp.asarray(tokenize_instructions(["pick up the black bowl on the plate", "put the bowl on the stove"], 32))
    eval_start = expand_groups(toy_start_states(jnp.tile(tokens, (8, 1)), key=jax.random.key(7), frame_size=8), 4)

    @jax.jit
    def evaluate(params):
        out = imagined_rollout(graphdef, params, sim, reward_model, eval_start, cfg, key=jax.random.key(3))
        return jnp.mean(out.returns)

    # both evaluations take parameters committed to one device: the step's mesh placement of its parameters
    # (or uncommitted ones) would make evaluate compile twice
    device = jax.devices()[0]
    before = float(evaluate(jax.device_put(params, device)))
    state = grpo.init_state(params, cfg)
    step = grpo.make_grpo_step(graphdef, cfg)
    for i in range(12):
        start = toy_start_states(tokens, key=jax.random.key(100 + i), frame_size=8)
        state, metrics = step(state, (sim, reward_model, start), jax.random.key(0))
        assert float(metrics["unconfirmed_fraction"]) == 0.0
        assert float(metrics["imagined_success_unconfirmed"]) == float(metrics["success_rate"])
    assert np.isfinite(float(metrics["loss"]))
    after = float(evaluate(jax.device_put(state.params, device)))
    assert after > before + 0.2, (before, after)


def test_a_non_finite_batch_skips_the_update():
    """A NaN behaviour log-prob makes the loss non-finite: the update is skipped, so NaN never reaches a
    checkpoint. (NaN returns alone are already harmless: their group has no finite spread and is filtered.)"""
    from sword_jax.rl.rollout import Rollout

    cfg = _toy_cfg(ppo_epochs=1, max_chunks=2)
    graphdef, params = build_policy(cfg, seed=0)
    n, c, t, a = cfg.grpo.group_size, cfg.imagined.max_chunks, cfg.chunk_len, cfg.action_dim
    rng = np.random.default_rng(0)
    tokens = jnp.asarray(tokenize_instructions(["pick up the black bowl"] * n, 32))
    rollout = Rollout(
        obs_frames=jnp.asarray(rng.random((n, c, 8, 8, 3)), jnp.float32), proprio=jnp.zeros((n, c, 4)),
        proprio_valid=jnp.ones((n, c)), instruction_tokens=tokens,
        tokens=jnp.asarray(rng.integers(0, cfg.action_bins, (n, c, t, a)), jnp.int32),
        log_probs=jnp.full((n, c, t, a), -np.log(cfg.action_bins), jnp.float32), valid=jnp.ones((n, c)),
        rewards=jnp.zeros((n, c)), scores=jnp.zeros((n, c)), success=jnp.zeros((n,), bool),
        returns=jnp.asarray(rng.random(n), jnp.float32), frames=jnp.zeros((0,)))
    update = jax.jit(lambda s, b: grpo.grpo_update(graphdef, cfg, s, b))
    state = grpo.init_state(params, cfg)
    new_state, metrics = update(state, rollout._replace(log_probs=rollout.log_probs.at[0].set(jnp.nan)))
    assert float(metrics["finite"]) == 0.0
    for old, new in zip(jax.tree.leaves(state.params), jax.tree.leaves(new_state.params)):
        np.testing.assert_array_equal(np.asarray(old), np.asarray(new))
    good_state, metrics = update(state, rollout)
    assert float(metrics["finite"]) == 1.0
    assert any(not np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree.leaves(state.params), jax.tree.leaves(good_state.params)))


ONE_MIXED = (1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0)  # two groups of 4: the first mixed, the second all failures
TWO_MIXED = (1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0)
NONE_MIXED = (0.0,) * 8


@pytest.fixture(scope="module")
def designed():
    """A tiny policy and a rollout of two groups of 4 whose returns each test sets (the policy is built once:
    its eager initialisation costs as much as a compile)."""
    from sword_jax.rl.rollout import Rollout

    cfg = _toy_cfg(ppo_epochs=1, max_chunks=2, group_size=4)
    graphdef, params = build_policy(cfg, seed=0)
    n, c, t, a = 2 * cfg.grpo.group_size, cfg.imagined.max_chunks, cfg.chunk_len, cfg.action_dim
    rng = np.random.default_rng(2)
    rollout = Rollout(
        obs_frames=jnp.asarray(rng.random((n, c, 8, 8, 3)), jnp.float32),
        proprio=jnp.asarray(rng.normal(size=(n, c, 4)), jnp.float32), proprio_valid=jnp.ones((n, c)),
        instruction_tokens=jnp.asarray(tokenize_instructions(["pick up the black bowl"] * n, 32)),
        tokens=jnp.asarray(rng.integers(0, cfg.action_bins, (n, c, t, a)), jnp.int32),
        log_probs=jnp.full((n, c, t, a), -np.log(cfg.action_bins), jnp.float32), valid=jnp.ones((n, c)),
        rewards=jnp.zeros((n, c)), scores=jnp.zeros((n, c)), success=jnp.zeros((n,), bool),
        returns=jnp.asarray(ONE_MIXED, jnp.float32), frames=jnp.zeros((0,)))
    return cfg, graphdef, params, rollout


def _with_min_mixed(cfg, groups):
    return dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, min_mixed_groups=groups))


def _leaves_equal(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b),
                                                                          strict=True))


def test_too_few_mixed_groups_apply_no_update(designed):
    """rl.grpo.min_mixed_groups: a batch with fewer mixed groups leaves the parameters and the optimizer state
    exactly as they were (the step still counts); at the threshold the batch updates."""
    cfg, graphdef, params, rollout = designed
    state = grpo.init_state(params, cfg)
    update = jax.jit(lambda s, b: grpo.grpo_update(graphdef, _with_min_mixed(cfg, 2), s, b))
    skipped, metrics = update(state, rollout)
    assert _leaves_equal(skipped.params, state.params) and _leaves_equal(skipped.opt_state, state.opt_state)
    assert int(skipped.step) == int(state.step) + 1
    assert float(metrics["skipped_update"]) == 1.0 and float(metrics["mixed_groups"]) == 1.0
    assert float(metrics["update_norm"]) == 0.0 and float(metrics["grad_norm"]) > 0.0  # the gradient was there
    two, metrics = update(state, rollout._replace(returns=jnp.asarray(TWO_MIXED, jnp.float32)))
    assert float(metrics["skipped_update"]) == 0.0 and float(metrics["mixed_groups"]) == 2.0
    assert not _leaves_equal(two.params, state.params)

    one, metrics = jax.jit(lambda s, b: grpo.grpo_update(graphdef, _with_min_mixed(cfg, 1), s, b))(state, rollout)
    assert float(metrics["skipped_update"]) == 0.0 and float(metrics["mixed_groups"]) == 1.0
    assert float(metrics["update_norm"]) > 0.0
    assert not _leaves_equal(one.params, state.params) and not _leaves_equal(one.opt_state, state.opt_state)


def test_min_mixed_groups_0_updates_as_before_the_option(designed):
    """rl.grpo.min_mixed_groups=0 (the default) is the update without the option: bitwise the optimizer applied
    to the objective's gradient, and a batch without any mixed group still takes its (zero-gradient) Adam step."""
    from sword_jax import optim

    cfg, graphdef, params, rollout = designed
    assert GRPOConfig().min_mixed_groups == 0
    state = grpo.init_state(params, cfg)
    update = jax.jit(lambda s, b: grpo.grpo_update(graphdef, _with_min_mixed(cfg, 0), s, b))
    off, metrics = update(state, rollout)
    default, _ = jax.jit(lambda s, b: grpo.grpo_update(graphdef, cfg, s, b))(state, rollout)
    assert _leaves_equal(off.params, default.params) and _leaves_equal(off.opt_state, default.opt_state)
    assert float(metrics["skipped_update"]) == 0.0 and float(metrics["mixed_groups"]) == 1.0

    @jax.jit
    def reference(params, opt_state, batch):  # one on-policy step: the optimizer on the objective's gradient
        loss, _, grads = grpo.grpo_gradients(graphdef, cfg, params, batch)
        return optim.apply_finite_update(grpo.grpo_optimizer(cfg), loss, grads, opt_state, params)[1:3]

    opt_state, new_params = reference(state.params, state.opt_state, rollout)
    assert _leaves_equal(off.params, new_params) and _leaves_equal(off.opt_state, opt_state)
    assert not _leaves_equal(off.params, state.params)

    none, metrics = update(state, rollout._replace(returns=jnp.asarray(NONE_MIXED, jnp.float32)))
    assert float(metrics["mixed_groups"]) == 0.0 and float(metrics["skipped_update"]) == 0.0
    assert not _leaves_equal(none.opt_state, state.opt_state)  # Adam counted the step


@pytest.mark.parametrize("groups", [-1, 1.5, True])
def test_min_mixed_groups_must_be_a_count(groups):
    with pytest.raises(ValueError, match=r"rl\.grpo\.min_mixed_groups must be an int >= 0"):
        _with_min_mixed(RLConfig(), groups).validate()


def test_min_mixed_groups_enters_the_run_identity_only_when_on():
    """A resumed run must skip as its checkpoint's did; off, the identity is the one runs from before the
    option saved, so they still resume."""
    from sword_jax.rl.grpo_loop import grpo_run_id

    assert "rl.grpo.min_mixed_groups" not in grpo_run_id(RLConfig(), seed=0, simulator="toy")
    assert grpo_run_id(_with_min_mixed(RLConfig(), 2), seed=0, simulator="toy")["rl.grpo.min_mixed_groups"] == 2
    # the shuffled-returns control likewise: a control run never resumes as a plain one
    assert "rl.grpo.shuffle_returns" not in grpo_run_id(RLConfig(), seed=0, simulator="toy")
    control = RLConfig(grpo=GRPOConfig(shuffle_returns=True))
    assert grpo_run_id(control, seed=0, simulator="toy")["rl.grpo.shuffle_returns"] is True


@pytest.mark.parametrize("loss_norm,kl_coef", [("trajectory", 0.0),
                                               pytest.param("token", 0.1, marks=pytest.mark.slow)])  # CI time
def test_micro_batched_update_equals_the_whole_batch_update(loss_norm, kl_coef):
    """rl.grpo.update_microbatch sums the gradients of micro-batches of trajectories; the token weights come
    from the whole batch, so the update (and its metrics) match the one-shot update."""
    from sword_jax.rl.rollout import Rollout

    cfg = _toy_cfg(ppo_epochs=1, max_chunks=2, group_size=4, loss_norm=loss_norm, kl_coef=kl_coef)
    graphdef, params = build_policy(cfg, seed=0)
    n, c, t, a = 2 * cfg.grpo.group_size, cfg.imagined.max_chunks, cfg.chunk_len, cfg.action_dim
    rng = np.random.default_rng(1)
    valid = np.ones((n, c), np.float32)
    valid[1, 1:] = 0.0
    valid[5, 1:] = 0.0  # trajectories of different lengths
    rollout = Rollout(
        obs_frames=jnp.asarray(rng.random((n, c, 8, 8, 3)), jnp.float32), proprio=jnp.asarray(rng.normal(size=(n, c, 4))),
        proprio_valid=jnp.ones((n, c)),
        instruction_tokens=jnp.asarray(tokenize_instructions(["pick up the black bowl"] * n, 32)),
        tokens=jnp.asarray(rng.integers(0, cfg.action_bins, (n, c, t, a)), jnp.int32),
        log_probs=jnp.asarray(-np.log(cfg.action_bins) + 0.3 * rng.normal(size=(n, c, t, a)), jnp.float32),
        valid=jnp.asarray(valid), rewards=jnp.zeros((n, c)), scores=jnp.zeros((n, c)), success=jnp.zeros((n,), bool),
        returns=jnp.asarray(rng.random(n), jnp.float32), frames=jnp.zeros((0,)))
    results = {}
    for micro in (0, 2):
        mcfg = dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, update_microbatch=micro))
        results[micro] = jax.jit(lambda p, b, mcfg=mcfg: grpo.grpo_gradients(graphdef, mcfg, p, b, ref_params=p))(
            params, rollout._replace(log_probs=rollout.log_probs))
    whole_loss, whole_metrics, whole_grads = results[0]
    scale = max(float(np.abs(np.asarray(x)).max()) for x in jax.tree.leaves(whole_grads))
    assert scale > 0
    for micro in (2,):
        loss, metrics, grads = results[micro]
        np.testing.assert_allclose(float(loss), float(whole_loss), rtol=1e-5, atol=1e-7)
        for x, y in zip(jax.tree.leaves(whole_grads), jax.tree.leaves(grads)):
            np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=0, atol=1e-5 * scale)
        for k in ("clip_fraction", "kl", "ratio_mean", "kept_fraction"):
            np.testing.assert_allclose(float(metrics[k]), float(whole_metrics[k]), rtol=1e-5, atol=1e-7)
    # the micro-batched objective is grpo_loss's
    from sword_jax.rl.grpo import _rollout_log_probs

    @jax.jit  # eager op-by-op dispatch of the policy's forward pass takes several times longer
    def direct_loss(params, rollout):
        adv, keep = grpo.group_advantages(rollout.returns.reshape(-1, cfg.grpo.group_size))
        ref = _rollout_log_probs(graphdef, params, rollout)
        return grpo.grpo_loss(ref, rollout.log_probs, ref, adv.reshape(-1), rollout.valid,
                              jnp.repeat(keep, cfg.grpo.group_size), cfg)[0]

    direct = direct_loss(params, rollout)
    np.testing.assert_allclose(float(whole_loss), float(direct), rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="update_microbatch"):
        odd = dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, update_microbatch=3))
        grpo.grpo_update(graphdef, odd, grpo.init_state(params, cfg), rollout)


def test_behaviour_nll_is_the_mean_sampled_token_nll_over_valid_chunks():
    """The logged behaviour-policy NLL averages -log p of the sampled tokens over valid chunks only,
    every trajectory counted (kept groups or not)."""
    n, c, t, a = 2, 3, 2, 1
    log_probs = -np.arange(1, n * c * t * a + 1, dtype=np.float32).reshape(n, c, t, a)
    valid = np.array([[1, 1, 0], [1, 0, 0]], np.float32)
    zeros = np.zeros((n, c), np.float32)
    batch = Rollout(obs_frames=np.zeros((n, c, 1, 1, 3), np.float32), proprio=np.zeros((n, c, 8), np.float32),
                         proprio_valid=zeros, instruction_tokens=np.zeros((n, 4), np.int32),
                         tokens=np.zeros((n, c, t, a), np.int32), log_probs=log_probs, valid=valid, rewards=zeros,
                         scores=zeros, success=np.zeros(n, bool), returns=np.zeros(n, np.float32),
                         frames=np.zeros((0,), np.float32))
    # valid tokens: trajectory 0 chunks 0-1 -> 1, 2, 3, 4; trajectory 1 chunk 0 -> 7, 8
    expected = (1 + 2 + 3 + 4 + 7 + 8) / 6
    assert float(grpo.behaviour_nll(jax.tree.map(jnp.asarray, batch))) == pytest.approx(expected)


def test_sampled_tokens_carry_the_tempered_log_probs_whose_score_has_zero_mean():
    """At temperature T the sampler draws from softmax(z / T) and returns those log-probs, and the
    update differentiates the same ones: their score has zero mean under the samples, so a batch
    whose rewards ignore the actions moves the policy nowhere on average. The untempered score the
    update used before drifts by p_T - p_1 (the collapse at T = 0.7 in the README, issue 17)."""
    from sword_jax.rl.policy import sample_chunk, sampling_log_probs, token_log_probs

    temperature, bins = 0.6, 12
    logits = 2.0 * jax.random.normal(jax.random.key(0), (bins,))
    tokens, logp = sample_chunk(jnp.broadcast_to(logits, (20000, bins)), key=jax.random.key(1),
                                temperature=temperature)
    p_t, p_1 = jax.nn.softmax(logits / temperature), jax.nn.softmax(logits)
    np.testing.assert_allclose(np.asarray(logp), np.asarray(jnp.log(p_t)[tokens]), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.bincount(np.asarray(tokens), minlength=bins) / tokens.size, np.asarray(p_t),
                               atol=0.015)

    def mean_score(log_prob_fn):  # E_{a ~ p_T}[d log p(a) / d logits], exactly
        scores = jax.vmap(lambda a: jax.grad(lambda z: log_prob_fn(z, a))(logits))(jnp.arange(bins))
        return np.asarray(jnp.einsum("a,ab->b", p_t, scores))

    np.testing.assert_allclose(mean_score(lambda z, a: sampling_log_probs(z, a, temperature)), 0.0, atol=1e-6)
    drift = mean_score(token_log_probs)
    np.testing.assert_allclose(drift, np.asarray(p_t - p_1), atol=1e-6)
    assert np.abs(drift).max() > 0.05


def test_the_update_scores_rollouts_at_their_sampling_temperature():
    """A rollout sampled at T = 0.5: the update's recomputed log-probs are the behaviour log-probs
    (ratio exactly 1 before the step), not the untempered policy's."""
    from sword_jax.rl.grpo import _rollout_log_probs

    cfg = _toy_cfg(max_chunks=2, temperature=0.5)
    graphdef, params = build_policy(cfg, seed=0)
    sim, reward_model = toy_simulator(frame_size=8, step_size=0.08), toy_reward_model()
    tokens = jnp.asarray(tokenize_instructions(["pick up the black bowl"], 32))
    start = expand_groups(toy_start_states(jnp.tile(tokens, (2, 1)), key=jax.random.key(7), frame_size=8),
                          cfg.grpo.group_size)
    # jitted: eager op-by-op dispatch of the rollout and the update takes several times longer
    rollout = jax.jit(lambda p, s, r, st, k: imagined_rollout(graphdef, p, s, r, st, cfg, key=k))(
        params, sim, reward_model, start, jax.random.key(3))
    mask = np.asarray(rollout.valid, bool)
    log_probs = jax.jit(lambda p, r, temperature: _rollout_log_probs(graphdef, p, r, temperature),
                        static_argnums=(2,))
    recomputed = np.asarray(log_probs(params, rollout, 0.5))[mask]
    np.testing.assert_allclose(recomputed, np.asarray(rollout.log_probs)[mask], rtol=1e-4, atol=1e-4)
    untempered = np.asarray(log_probs(params, rollout, 1.0))[mask]
    assert np.abs(untempered - recomputed).mean() > 0.1
    _, metrics, _ = jax.jit(lambda p, r: grpo.grpo_gradients(graphdef, cfg, p, r))(params, rollout)
    assert float(metrics["ratio_mean"]) == pytest.approx(1.0, abs=1e-4)


def test_minibatch_updates_move_the_ratio_and_bind_the_clip_on_a_designed_batch():
    """One pass in one step: the ratio is 1 and nothing is clipped (REINFORCE). Four minibatch steps over
    two passes: from the second step on the policy that scores a minibatch moved, so the ratio leaves
    1 and, with a large step, the clip binds; every step is counted and the metrics are their means."""
    from sword_jax.rl.grpo import _rollout_log_probs

    cfg = _toy_cfg(ppo_epochs=1, max_chunks=2, group_size=4)
    cfg = dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, learning_rate=3e-2, update_microbatch=0))
    graphdef, params = build_policy(cfg, seed=0)
    n, c, t, a = 4 * cfg.grpo.group_size, cfg.imagined.max_chunks, cfg.chunk_len, cfg.action_dim
    rng = np.random.default_rng(2)
    rollout = Rollout(
        obs_frames=jnp.asarray(rng.random((n, c, 8, 8, 3)), jnp.float32), proprio=jnp.asarray(rng.normal(size=(n, c, 4))),
        proprio_valid=jnp.ones((n, c)),
        instruction_tokens=jnp.asarray(tokenize_instructions(["pick up the black bowl"] * n, 32)),
        tokens=jnp.asarray(rng.integers(0, cfg.action_bins, (n, c, t, a)), jnp.int32),
        log_probs=jnp.zeros((n, c, t, a)), valid=jnp.ones((n, c)), rewards=jnp.zeros((n, c)), scores=jnp.zeros((n, c)),
        success=jnp.zeros((n,), bool), returns=jnp.asarray(np.tile([2.0, 0.0, 0.0, 0.0], n // 4), jnp.float32),
        frames=jnp.zeros((0,)))
    # sampled by this policy (jitted, as the update: eager dispatch takes several times longer)
    rollout = rollout._replace(log_probs=jax.jit(lambda p, r: _rollout_log_probs(graphdef, p, r))(params, rollout))
    one = jax.jit(lambda s, b: grpo.grpo_update(graphdef, cfg, s, b))(
        grpo.init_state(jax.tree.map(jnp.copy, params), cfg), rollout)[1]
    assert float(one["updates"]) == 1.0
    assert float(one["clip_fraction"]) == 0.0 and abs(float(one["ratio_mean"]) - 1.0) < 1e-5
    many_cfg = dataclasses.replace(cfg, grpo=dataclasses.replace(cfg.grpo, minibatches=4, ppo_epochs=2))
    state, many = jax.jit(lambda s, b, k: grpo.grpo_update(graphdef, many_cfg, s, b, k))(
        grpo.init_state(jax.tree.map(jnp.copy, params), many_cfg), rollout, jax.random.key(0))
    assert float(many["updates"]) == 8.0 and int(state.step) == 1
    assert float(many["clip_fraction"]) > 0.0 and abs(float(many["ratio_mean"]) - 1.0) > 1e-3
    with pytest.raises(ValueError, match="minibatches"):
        dataclasses.replace(cfg.grpo, minibatches=3).validate()


def test_shared_group_noise_is_one_draw_per_group():
    """rl.imagined.shared_group_noise: the simulator's noise keys are equal within a group and differ across
    groups; greedy members of a group from one start then see the same frames, while per-trajectory
    noise makes them differ."""
    from sword_jax.rl.rollout import simulator_keys

    cfg = _toy_cfg(group_size=4)
    shared = dataclasses.replace(cfg, imagined=dataclasses.replace(cfg.imagined, shared_group_noise=True))
    data = jax.random.key_data(simulator_keys(jax.random.key(0), 8, shared)).reshape(2, 4, -1)
    assert bool(jnp.all(data == data[:, :1])) and not bool(jnp.all(data[0] == data[1]))
    own = jax.random.key_data(simulator_keys(jax.random.key(0), 8, cfg)).reshape(8, -1)
    assert len({tuple(np.asarray(k)) for k in own}) == 8
    with pytest.raises(ValueError, match="whole groups"):
        simulator_keys(jax.random.key(0), 6, shared)
    graphdef, params = build_policy(cfg, seed=0)
    sim, reward_model = toy_simulator(frame_size=8, noise=0.05), toy_reward_model()
    tokens = jnp.asarray(tokenize_instructions(["pick up the black bowl"], 32))
    start = expand_groups(toy_start_states(jnp.tile(tokens, (2, 1)), key=jax.random.key(1), frame_size=8), 4)
    start = start._replace(frame=jnp.broadcast_to(start.frame[:1], start.frame.shape),
                           proprio=jnp.broadcast_to(start.proprio[:1], start.proprio.shape))
    frames = {}
    for name, c in (("shared", shared), ("own", cfg)):
        out = imagined_rollout(graphdef, params, sim, reward_model, start, c, key=jax.random.key(2), greedy=True,
                               record_frames=True)
        frames[name] = np.asarray(out.frames).reshape((2, 4) + out.frames.shape[1:])
    assert np.array_equal(frames["shared"][:, 0], frames["shared"][:, 3]) and not np.array_equal(
        frames["shared"][0], frames["shared"][1])
    assert not np.array_equal(frames["own"][:, 0], frames["own"][:, 3])


def test_a_process_makes_only_its_rows_of_the_start_states():
    """In a job of several processes each makes only its rows of a step's start states (the toy's draws,
    the keyframe windows): each row equals the whole batch's, whichever rows are asked for."""
    from tests.support.rl import brightening_episodes

    tokens = jnp.asarray(tokenize_instructions(["a", "b", "c", "d", "e", "f"], 16))
    whole = toy_start_states(tokens, key=jax.random.key(3), frame_size=8)
    for rows in (np.array([0, 1, 2]), np.array([3, 4, 5]), np.array([1, 4])):
        part = toy_start_states(tokens, key=jax.random.key(3), frame_size=8, rows=rows)
        for got, want in zip(jax.tree.leaves(part), jax.tree.leaves(whole)):
            assert got.shape[0] == len(rows)
            np.testing.assert_array_equal(got, np.asarray(want)[rows])

    episodes = brightening_episodes()
    whole = rl_data.keyframe_starts(episodes, 6, np.random.default_rng(5))
    part = rl_data.keyframe_starts(episodes, 6, np.random.default_rng(5), rows=np.array([4, 5]))
    assert part["instructions"] == [whole["instructions"][i] for i in (4, 5)]
    for name in ("frame", "first_frame", "history", "actions", "proprio"):
        np.testing.assert_array_equal(part[name], whole[name][[4, 5]], err_msg=name)


@pytest.mark.slow  # a control of the toy run; the toy run itself stays in the default run
def test_shuffled_returns_keep_each_groups_values_and_lose_their_assignment():
    """rl.grpo.shuffle_returns (the noise-only control): every group keeps its returns (so its spread and whether it
    is mixed), assigned to its trajectories by the key; without a key it is refused."""
    returns = jnp.asarray(np.arange(64, dtype=np.float32).reshape(8, 8))
    a = grpo.shuffle_within_groups(returns, jax.random.key(0))
    b = grpo.shuffle_within_groups(returns, jax.random.key(1))
    np.testing.assert_array_equal(np.sort(np.asarray(a), axis=1), np.asarray(returns))
    assert not np.array_equal(np.asarray(a), np.asarray(returns)) and not np.array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="needs the update's key"):
        grpo.shuffle_within_groups(returns, None)
    with pytest.raises(ValueError, match="rl.grpo.shuffle_returns"):
        GRPOConfig(shuffle_returns=1).validate()
    # in the update: the same mixed groups, another gradient than the unshuffled one
    base = _toy_cfg(ppo_epochs=1, max_chunks=2, group_size=4)
    graphdef, params = build_policy(base, seed=0)
    rollout = _random_rollout(base, np.random.default_rng(5), returns=[2, 0, 0, 0, 2, 2, 0, 0])
    out = {}
    for shuffle in (False, True):
        cfg = dataclasses.replace(base, grpo=dataclasses.replace(base.grpo, shuffle_returns=shuffle))
        state, metrics = grpo.grpo_update(graphdef, cfg, grpo.init_state(params, cfg), rollout, jax.random.key(3))
        out[shuffle] = (state, metrics)
    assert float(out[True][1]["mixed_groups"]) == float(out[False][1]["mixed_groups"]) == 2.0
    moved = [float(jnp.abs(x - y).max()) for x, y in zip(jax.tree.leaves(out[True][0].params),
                                                          jax.tree.leaves(out[False][0].params))]
    assert max(moved) > 0
