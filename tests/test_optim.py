"""The shared optimizer builder and each trainer's settings, against AdamW and the schedules
computed from their definitions (numpy, float64) and against hand-computed values."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import configs
from sword_jax import optim
from sword_jax.rl import grpo
from sword_jax.rl.policy import trainable_mask
from sword_jax.rl.reward_model import build_detector, make_detector_optimizer, make_detector_step, train_detector
from sword_jax.rl.sft import make_sft_optimizer, sft_schedule
from sword_jax.vae.train import vae_optimizer
from sword_jax.world_model.train_state import world_model_optimizer, world_model_schedule
from tests.support.rl import reward_batches

VARIANTS = ("tiny", "small", "paper")
GRAD_SCALES = (10.0, 0.01, 1.0)  # the first step is clipped wherever clipping is on


def _params():
    """A policy-like tree: two weights and the stored proprio statistics (not decayed by SFT)."""
    rng = np.random.default_rng(0)
    return {name: jnp.asarray(rng.normal(size=shape), jnp.float32)
            for name, shape in {"w": (3, 4), "b": (4,), "proprio_mean": (2,), "proprio_std": (2,)}.items()}


def _grads(scale):
    rng = np.random.default_rng(1)
    return {k: jnp.asarray(scale * rng.normal(size=v.shape), jnp.float32) for k, v in _params().items()}


def _adamw_reference(rate_at, *, b1, b2, eps, weight_decay, grad_clip=0.0, decayed=lambda name: True):
    """The update of each step (one per ``GRAD_SCALES`` entry), from the algorithm: global-norm clipping
    first, bias-corrected moments, decoupled weight decay scaled by the rate (Loshchilov & Hutter)."""
    params = {k: np.asarray(v, np.float64) for k, v in _params().items()}
    mu = {k: np.zeros_like(v) for k, v in params.items()}
    nu = {k: np.zeros_like(v) for k, v in params.items()}
    updates = []
    for t, scale in enumerate(GRAD_SCALES):
        grads = {k: np.asarray(v, np.float64) for k, v in _grads(scale).items()}
        norm = math.sqrt(sum(float(np.sum(g * g)) for g in grads.values()))
        if grad_clip > 0 and norm > grad_clip:
            grads = {k: g * grad_clip / norm for k, g in grads.items()}
        update = {}
        for k, g in grads.items():
            mu[k] = b1 * mu[k] + (1 - b1) * g
            nu[k] = b2 * nu[k] + (1 - b2) * g * g
            direction = (mu[k] / (1 - b1 ** (t + 1))) / (np.sqrt(nu[k] / (1 - b2 ** (t + 1))) + eps)
            if decayed(k):
                direction = direction + weight_decay * params[k]
            update[k] = -rate_at(t) * direction
            params[k] = params[k] + update[k]
        updates.append(update)
    return updates


def _assert_matches(tx, expected):
    """``tx``'s updates equal ``expected`` step by step (relative to the update, not to the weights, so a
    moment's decay rate or a small weight decay shows)."""
    params = _params()
    state = jax.jit(tx.init)(params)
    step = jax.jit(lambda g, s, p: optim.apply_optimizer(tx, g, s, p))
    for t, scale in enumerate(GRAD_SCALES):
        updates, state, params = step(_grads(scale), state, params)
        for name, value in expected[t].items():
            np.testing.assert_allclose(np.asarray(updates[name]), value, rtol=1e-4, atol=1e-6 * np.abs(value).max(),
                                       err_msg=f"step {t}: {name}")
    assert not np.allclose(np.asarray(params["w"]), np.asarray(_params()["w"]), rtol=0, atol=0)


def _schedule_values(schedule, steps):
    at = jax.jit(lambda step: optim.learning_rate_at(schedule, step))
    return np.asarray([at(jnp.int32(s)) for s in steps])


def _expected_rate(step, *, peak, warmup, kind, total, end_fraction):
    """Linear warm-up from 0, then constant or cosine decay to ``end_fraction * peak`` at ``total``."""
    if step < warmup:
        return peak * step / warmup
    if kind == "constant":
        return peak
    progress = min(step - warmup, max(total - warmup, 1)) / max(total - warmup, 1)
    return peak * (end_fraction + (1 - end_fraction) * 0.5 * (1 + math.cos(math.pi * progress)))


def _probe_steps(warmup, total):
    return sorted({0, 1, max(warmup - 1, 0), warmup, warmup + 1, (warmup + total) // 2, total - 1, total, total + 5})


def test_adamw_reference_matches_hand_computed_first_step():
    """Step 1 of Adam moves each weight by ``rate * (sign(g) + wd * w)`` (eps aside): checked by hand."""
    g = np.asarray(_grads(10.0)["b"], np.float64)
    w = np.asarray(_params()["b"], np.float64)
    norm = math.sqrt(sum(float(np.sum(np.asarray(v, np.float64) ** 2)) for v in _grads(10.0).values()))
    assert norm > 1.0  # so clipping at 1 changes the gradient, not the sign
    tx = optim.make_optimizer(0.1, weight_decay=0.5, grad_clip=1.0)
    params = _params()
    _, _, moved = optim.apply_optimizer(tx, _grads(10.0), tx.init(params), params)
    np.testing.assert_allclose(np.asarray(moved["b"]), w - 0.1 * (np.sign(g) + 0.5 * w), rtol=1e-5)


def test_make_optimizer_is_clipped_adamw():
    rate = lambda t: 3e-2  # noqa: E731
    _assert_matches(optim.make_optimizer(3e-2, weight_decay=0.1, b1=0.8, b2=0.95, eps=1e-6, grad_clip=0.5),
                    _adamw_reference(rate, b1=0.8, b2=0.95, eps=1e-6, weight_decay=0.1, grad_clip=0.5))
    _assert_matches(optim.make_optimizer(3e-2, weight_decay=0.0),
                    _adamw_reference(rate, b1=0.9, b2=0.999, eps=1e-8, weight_decay=0.0))
    with pytest.raises(ValueError, match="grad_clip must be >= 0"):
        optim.make_optimizer(1e-3, weight_decay=0.0, grad_clip=-1.0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_world_model_optimizer_follows_its_config(variant):
    base = configs.get(f"sword:{variant}").trainer
    for cfg in (base, dataclasses.replace(base, lr_schedule="cosine"), dataclasses.replace(base, warmup_steps=0),
                dataclasses.replace(base, grad_clip=0.0, lr_schedule="cosine", warmup_steps=0),
                dataclasses.replace(base, warmup_steps=1, steps=4, lr_schedule="cosine", learning_rate=1e-2)):
        rate = lambda t, cfg=cfg: _expected_rate(t, peak=cfg.learning_rate, warmup=cfg.warmup_steps,  # noqa: E731
                                                  kind=cfg.lr_schedule, total=cfg.steps, end_fraction=cfg.lr_end_fraction)
        steps = _probe_steps(cfg.warmup_steps, cfg.steps)
        # float32 schedule arithmetic: off by a few float32 ulps of the peak rate where the rate is small
        np.testing.assert_allclose(_schedule_values(world_model_schedule(cfg), steps), [rate(s) for s in steps],
                                   rtol=1e-5, atol=1e-6 * cfg.learning_rate)
        _assert_matches(world_model_optimizer(cfg),
                        _adamw_reference(rate, b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps,
                                         weight_decay=cfg.weight_decay, grad_clip=cfg.grad_clip))


def test_world_model_schedule_pinned_values():
    cfg = configs.get("sword:tiny").trainer  # lr 1e-3, 2 warm-up steps, constant after
    np.testing.assert_array_equal(_schedule_values(world_model_schedule(cfg), [0, 1, 2, 19]),
                                  np.float32([0.0, 5e-4, 1e-3, 1e-3]))
    cosine = dataclasses.replace(cfg, lr_schedule="cosine")  # to 0.1 of the peak at step 20
    np.testing.assert_allclose(_schedule_values(world_model_schedule(cosine), [11, 20, 30]),
                               [0.55e-3, 1e-4, 1e-4], rtol=1e-6)


@pytest.mark.parametrize("variant", VARIANTS)
def test_vae_optimizer_is_adamw_b2_0_99_at_a_constant_rate(variant):
    cfg = configs.get(f"sword:{variant}").vae
    for case in (cfg, dataclasses.replace(cfg, grad_clip=0.0, weight_decay=0.05)):
        _assert_matches(vae_optimizer(case),
                        _adamw_reference(lambda t, case=case: case.learning_rate, b1=0.9, b2=0.99, eps=1e-8,
                                         weight_decay=case.weight_decay, grad_clip=case.grad_clip))


@pytest.mark.parametrize("variant", VARIANTS)
def test_grpo_optimizer_clips_at_1_without_weight_decay(variant):
    cfg = configs.get(f"sword:{variant}").rl
    _assert_matches(grpo.grpo_optimizer(cfg),
                    _adamw_reference(lambda t: cfg.grpo.learning_rate, b1=0.9, b2=0.999, eps=1e-8, weight_decay=0.0,
                                     grad_clip=1.0))


@pytest.mark.parametrize("variant", VARIANTS)
def test_sft_schedule_and_optimizer(variant):
    cfg = configs.get(f"sword:{variant}").rl
    for total in (cfg.sft.steps, 1, 7, 60):  # short runs have no warm-up (steps // 10 caps it)
        warmup = min(cfg.sft.warmup_steps, max(total, 1) // 10)
        steps = _probe_steps(warmup, total)
        expected = [_expected_rate(s, peak=cfg.sft.learning_rate, warmup=warmup, kind="cosine", total=max(total, 1),
                                   end_fraction=cfg.sft.lr_end_fraction) for s in steps]
        np.testing.assert_allclose(_schedule_values(sft_schedule(cfg, total), steps), expected, rtol=1e-5,
                                   atol=1e-6 * max(expected))  # float32 arithmetic, as above
    warmup = min(cfg.sft.warmup_steps, cfg.sft.steps // 10)
    rate = lambda t: _expected_rate(t, peak=cfg.sft.learning_rate, warmup=warmup, kind="cosine",  # noqa: E731
                                    total=cfg.sft.steps, end_fraction=cfg.sft.lr_end_fraction)
    _assert_matches(make_sft_optimizer(sft_schedule(cfg, cfg.sft.steps)),
                    _adamw_reference(rate, b1=0.9, b2=0.999, eps=1e-8, weight_decay=1e-4, grad_clip=1.0,
                                     decayed=lambda name: name not in ("proprio_mean", "proprio_std")))


def test_sft_masks_weight_decay_on_the_stored_statistics():
    """With a zero gradient only weight decay moves a parameter: the statistics must stay put."""
    tx = make_sft_optimizer(optax.constant_schedule(1e-2))
    params = _params()
    zero = jax.tree.map(jnp.zeros_like, params)
    _, _, moved = optim.apply_optimizer(tx, zero, tx.init(params), params)
    for name in ("proprio_mean", "proprio_std"):
        np.testing.assert_array_equal(np.asarray(moved[name]), np.asarray(params[name]))
    assert not np.array_equal(np.asarray(moved["w"]), np.asarray(params["w"]))
    assert trainable_mask(params) == {"w": True, "b": True, "proprio_mean": False, "proprio_std": False}


@pytest.mark.parametrize("variant", VARIANTS)
def test_reward_model_optimizer_is_unclipped_adamw(variant):
    cfg = configs.get(f"sword:{variant}").rl
    _assert_matches(make_detector_optimizer(cfg),
                    _adamw_reference(lambda t: cfg.reward_model.learning_rate, b1=0.9, b2=0.999, eps=1e-8,
                                     weight_decay=1e-4))


@pytest.mark.slow  # the shared loop's stop: test_reliability and test_rl_resume (SFT) check it by default
def test_reward_model_stops_on_a_non_finite_loss_naming_the_step():
    tiny = configs.get("sword:tiny").rl
    cfg = dataclasses.replace(tiny, image_size=8, reward_model=dataclasses.replace(tiny.reward_model, width=4))
    graphdef, params = build_detector(cfg)
    with pytest.raises(FloatingPointError, match=r"reward model: non-finite loss or gradient at step 3 \(0-based\)"):
        train_detector(graphdef, params, cfg, reward_batches(cfg, poison_at=3), key=jax.random.key(0), steps=10,
                       log=lambda line: None)
    graphdef, params = build_detector(cfg)  # the step donates its state: fresh parameters
    state, metrics = train_detector(graphdef, params, cfg, reward_batches(cfg), key=jax.random.key(0), steps=10,
                                    log=lambda line: None)
    assert int(state.first_nonfinite_step) == -1 and float(metrics["finite"]) == 1.0


def test_reward_model_skips_the_poisoned_update():
    tiny = configs.get("sword:tiny").rl
    cfg = dataclasses.replace(tiny, image_size=8, reward_model=dataclasses.replace(tiny.reward_model, width=4))
    graphdef, params = build_detector(cfg)
    init, step = make_detector_step(graphdef, cfg)
    batch_at = reward_batches(cfg, poison_at=1)
    state, _ = step(init(params), batch_at(0), jax.random.key(0))
    before = jax.tree.map(np.asarray, state.params)
    state, metrics = step(state, batch_at(1), jax.random.key(0))
    assert float(metrics["finite"]) == 0.0 and not np.isfinite(float(metrics["loss"]))
    assert int(state.first_nonfinite_step) == 1 and int(state.step) == 2
    for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(state.params), strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))
    state, metrics = step(state, batch_at(2), jax.random.key(0))
    assert float(metrics["finite"]) == 1.0 and int(state.first_nonfinite_step) == 1


def test_bfloat16_first_moment_halves_it_and_follows_the_float32_optimizer():
    """trainer.adam_mu_dtype=bfloat16: Adam's first moment is stored in bfloat16 (the second stays
    float32), and 50 steps on a noisy quadratic land where the float32 optimizer does."""
    base = dataclasses.replace(configs.get("sword:tiny").trainer, steps=50, warmup_steps=0, learning_rate=1e-2)
    low = dataclasses.replace(base, adam_mu_dtype="bfloat16")
    target = {k: jnp.ones_like(v) for k, v in _params().items()}

    def run(cfg):
        tx = world_model_optimizer(cfg)
        params = _params()
        state = tx.init(params)
        rng = np.random.default_rng(2)
        for _ in range(cfg.steps):
            grads = {k: params[k] - target[k] + jnp.asarray(0.05 * rng.normal(size=params[k].shape), jnp.float32)
                     for k in params}
            _, state, params = optim.apply_optimizer(tx, grads, state, params)
        return params, state

    full, _ = run(base)
    half, state = run(low)
    adam = next(s for s in jax.tree.leaves(state, is_leaf=lambda s: isinstance(s, optax.ScaleByAdamState))
                if isinstance(s, optax.ScaleByAdamState))
    assert all(x.dtype == jnp.bfloat16 for x in jax.tree.leaves(adam.mu))
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(adam.nu))
    for k in full:
        np.testing.assert_allclose(half[k], full[k], atol=2e-2)
        assert half[k].dtype == jnp.float32
    with pytest.raises(ValueError, match="adam_mu_dtype must be float32\\|bfloat16"):
        dataclasses.replace(base, adam_mu_dtype="float16").validate()
