"""The shared optimizer builder reproduces each trainer's previous optimizer exactly.

Each reference below is the chain the trainer built inline before ``sword_jax.optim`` existed.
Learning rates and updates are compared bit for bit, under the strict promotion the tests run in.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import configs
from sword_jax import optim
from sword_jax.rl import data as rl_data
from sword_jax.rl import grpo
from sword_jax.rl.policy import trainable_mask
from sword_jax.rl.reward_model import build_detector, make_detector_optimizer, make_detector_step, train_detector
from sword_jax.rl.sft import make_sft_optimizer, sft_schedule
from sword_jax.vae.train import make_optimizer as vae_optimizer
from sword_jax.world_model.config import TrainerConfig
from sword_jax.world_model.train_state import learning_rate_schedule as world_model_schedule
from sword_jax.world_model.train_state import make_optimizer as world_model_optimizer

VARIANTS = ("tiny", "small", "paper")


def _params():
    """A policy-like tree: two weights and the stored proprio statistics (not decayed by SFT)."""
    rng = np.random.default_rng(0)
    return {name: jnp.asarray(rng.normal(size=shape), jnp.float32)
            for name, shape in {"w": (3, 4), "b": (4,), "proprio_mean": (2,), "proprio_std": (2,)}.items()}


def _grads(scale):
    rng = np.random.default_rng(1)
    return {k: jnp.asarray(scale * rng.normal(size=v.shape), jnp.float32) for k, v in _params().items()}


def _old_world_model_schedule(cfg: TrainerConfig):
    warmup = optax.linear_schedule(0.0, cfg.learning_rate, max(cfg.warmup_steps, 1))
    if cfg.lr_schedule == "cosine":
        after = optax.cosine_decay_schedule(cfg.learning_rate, max(cfg.steps - cfg.warmup_steps, 1),
                                            alpha=cfg.lr_end_fraction)
    else:
        after = optax.constant_schedule(cfg.learning_rate)
    return after if cfg.warmup_steps == 0 else optax.join_schedules([warmup, after], [cfg.warmup_steps])


def _old_world_model_optimizer(cfg: TrainerConfig):
    parts = [optax.clip_by_global_norm(cfg.grad_clip)] if cfg.grad_clip > 0 else []
    parts.append(optax.adamw(_old_world_model_schedule(cfg), b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps,
                             weight_decay=cfg.weight_decay))
    return optax.chain(*parts)


def _old_vae_optimizer(cfg):
    adamw = optax.adamw(cfg.learning_rate, b1=0.9, b2=0.99, weight_decay=cfg.weight_decay)
    return optax.chain(optax.clip_by_global_norm(cfg.grad_clip), adamw) if cfg.grad_clip > 0 else adamw


def _old_sft_optimizer(schedule):
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=1e-4, mask=trainable_mask))


def _old_sft_schedule(cfg, total_steps):
    steps = max(int(total_steps), 1)
    warmup = min(cfg.sft.warmup_steps, steps // 10)
    peak = cfg.sft.learning_rate
    return optax.warmup_cosine_decay_schedule(0.0, peak, warmup, steps, end_value=peak * cfg.sft.lr_end_fraction)


def _old_update_inside(tx, grads, opt_state, params):
    """GRPO's former ``apply_optimizer`` (SFT and the reward model imported it)."""
    with jax.numpy_dtype_promotion("standard"):
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
    return params, opt_state


def _old_update_outside(tx, grads, opt_state, params):
    """The VAE and world-model steps: only ``tx.update`` under standard promotion."""
    with jax.numpy_dtype_promotion("standard"):
        updates, opt_state = tx.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def _assert_same_updates(new_tx, old_tx, old_update, *, same_layout=True):
    """Three updates (the first clipped where clipping is on) are bit-identical, and so are the states."""
    params_new = params_old = _params()
    state_new, state_old = jax.jit(new_tx.init)(params_new), jax.jit(old_tx.init)(params_old)
    if same_layout:
        assert jax.tree.structure(state_new) == jax.tree.structure(state_old)
    new_step = jax.jit(lambda g, s, p: optim.apply_optimizer(new_tx, g, s, p)[1:])
    old_step = jax.jit(lambda g, s, p: old_update(old_tx, g, s, p))
    for scale in (10.0, 0.01, 1.0):  # step 0 of a warm-up has rate 0: the later steps move the weights
        state_new, params_new = new_step(_grads(scale), state_new, params_new)
        params_old, state_old = old_step(_grads(scale), state_old, params_old)
        for name in params_old:
            np.testing.assert_array_equal(np.asarray(params_new[name]), np.asarray(params_old[name]), err_msg=name)
    assert not np.array_equal(np.asarray(params_new["w"]), np.asarray(_params()["w"]))
    for new_leaf, old_leaf in zip(jax.tree.leaves(state_new), jax.tree.leaves(state_old), strict=True):
        np.testing.assert_array_equal(np.asarray(new_leaf), np.asarray(old_leaf))


def _schedule_values(schedule, steps):
    at = jax.jit(lambda step: optim.learning_rate_at(schedule, step))
    return np.asarray([at(jnp.int32(s)) for s in steps])


def _old_schedule_values(schedule, steps):
    def at(step):
        with jax.numpy_dtype_promotion("standard"):
            return jnp.asarray(schedule(step), jnp.float32)

    at = jax.jit(at)
    return np.asarray([at(jnp.int32(s)) for s in steps])


def _probe_steps(warmup, total):
    return sorted({0, 1, max(warmup - 1, 0), warmup, warmup + 1, (warmup + total) // 2, total - 1, total, total + 5})


@pytest.mark.parametrize("variant", VARIANTS)
def test_world_model_optimizer_is_unchanged(variant):
    base = configs.get(f"sword:{variant}").trainer
    for cfg in (base, dataclasses.replace(base, lr_schedule="cosine"), dataclasses.replace(base, warmup_steps=0),
                dataclasses.replace(base, grad_clip=0.0, lr_schedule="cosine", warmup_steps=0)):
        steps = _probe_steps(cfg.warmup_steps, cfg.steps)
        np.testing.assert_array_equal(_schedule_values(world_model_schedule(cfg), steps),
                                      _old_schedule_values(_old_world_model_schedule(cfg), steps))
        _assert_same_updates(world_model_optimizer(cfg), _old_world_model_optimizer(cfg), _old_update_outside)


def test_world_model_schedule_pinned_values():
    cfg = configs.get("sword:tiny").trainer  # lr 1e-3, 2 warm-up steps, constant after
    np.testing.assert_array_equal(_schedule_values(world_model_schedule(cfg), [0, 1, 2, 19]),
                                  np.float32([0.0, 5e-4, 1e-3, 1e-3]))
    cosine = dataclasses.replace(cfg, lr_schedule="cosine")  # to 0.1 of the peak at step 20
    np.testing.assert_allclose(_schedule_values(world_model_schedule(cosine), [11, 20, 30]),
                               [0.55e-3, 1e-4, 1e-4], rtol=1e-6)


@pytest.mark.parametrize("variant", VARIANTS)
def test_vae_optimizer_is_unchanged(variant):
    cfg = configs.get(f"sword:{variant}").vae
    _assert_same_updates(vae_optimizer(cfg), _old_vae_optimizer(cfg), _old_update_outside)
    # without clipping the state is now a one-part chain (was bare AdamW): same numbers, new layout
    no_clip = dataclasses.replace(cfg, grad_clip=0.0, weight_decay=0.05)
    _assert_same_updates(vae_optimizer(no_clip), _old_vae_optimizer(no_clip), _old_update_outside, same_layout=False)


@pytest.mark.parametrize("variant", VARIANTS)
def test_grpo_optimizer_is_unchanged(variant):
    cfg = configs.get(f"sword:{variant}").rl
    old = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(cfg.grpo.learning_rate, weight_decay=0.0))
    _assert_same_updates(grpo.make_optimizer(cfg), old, _old_update_inside)


@pytest.mark.parametrize("variant", VARIANTS)
def test_sft_optimizer_is_unchanged(variant):
    cfg = configs.get(f"sword:{variant}").rl
    for total in (cfg.sft.steps, 1, 7, 60):  # short runs have no warm-up (steps // 10 caps it)
        steps = _probe_steps(min(cfg.sft.warmup_steps, total // 10), total)
        np.testing.assert_array_equal(_schedule_values(sft_schedule(cfg, total), steps),
                                      _old_schedule_values(_old_sft_schedule(cfg, total), steps))
    schedule = sft_schedule(cfg, cfg.sft.steps)
    _assert_same_updates(make_sft_optimizer(schedule), _old_sft_optimizer(_old_sft_schedule(cfg, cfg.sft.steps)),
                         _old_update_inside)


def test_sft_masks_weight_decay_on_the_stored_statistics():
    """With a zero gradient only weight decay moves a parameter: the statistics must stay put."""
    tx = make_sft_optimizer(optax.constant_schedule(1e-2))
    params = _params()
    zero = jax.tree.map(jnp.zeros_like, params)
    _, _, moved = optim.apply_optimizer(tx, zero, tx.init(params), params)
    for name in ("proprio_mean", "proprio_std"):
        np.testing.assert_array_equal(np.asarray(moved[name]), np.asarray(params[name]))
    assert not np.array_equal(np.asarray(moved["w"]), np.asarray(params["w"]))


@pytest.mark.parametrize("variant", VARIANTS)
def test_reward_model_optimizer_is_unchanged(variant):
    cfg = configs.get(f"sword:{variant}").rl
    old = optax.adamw(cfg.reward_model.learning_rate, weight_decay=1e-4)
    # now a one-part chain (was bare AdamW); the reward model's optimizer state is never saved
    _assert_same_updates(make_detector_optimizer(cfg), old, _old_update_inside, same_layout=False)


def _reward_batches(cfg, poison_at=None):
    """``batch_at(step)``: class-balanced batches of brightening frames; step ``poison_at``'s holds a NaN frame."""
    e, t = 4, 12
    level = np.linspace(0, 255, t).astype(np.uint8)
    frames = np.broadcast_to(level[None, :, None, None, None], (e, t, 8, 8, 3)).copy()
    frames[2:] //= 3
    episodes = rl_data.EpisodeSet(frames, np.zeros((e, t, 7), np.float32), np.zeros((e, t, 4), np.float32),
                                  np.full(e, t), np.array([True, True, False, False]), ("a", "b", "a", "b"))
    labels = rl_data.success_labels(episodes, positive_tail=3)

    def batch_at(step):
        batch = rl_data.sample_reward_batch(episodes, labels, 8, np.random.default_rng(step))
        if step == poison_at:
            batch = dict(batch, frames=np.asarray(batch["frames"], np.float32) / 255.0)
            batch["frames"][0, 0, 0, 0] = np.nan
        return batch

    return batch_at


def test_reward_model_stops_on_a_non_finite_loss_naming_the_step():
    tiny = configs.get("sword:tiny").rl
    cfg = dataclasses.replace(tiny, image_size=8, reward_model=dataclasses.replace(tiny.reward_model, width=4))
    graphdef, params = build_detector(cfg)
    with pytest.raises(FloatingPointError, match=r"reward model: non-finite loss or gradient at step 3 \(0-based\)"):
        train_detector(graphdef, params, cfg, _reward_batches(cfg, poison_at=3), key=jax.random.key(0), steps=10,
                       log=lambda line: None)
    graphdef, params = build_detector(cfg)  # the step donates its state: fresh parameters
    state, metrics = train_detector(graphdef, params, cfg, _reward_batches(cfg), key=jax.random.key(0), steps=10,
                                    log=lambda line: None)
    assert int(state.first_nonfinite_step) == -1 and float(metrics["finite"]) == 1.0


def test_reward_model_skips_the_poisoned_update():
    tiny = configs.get("sword:tiny").rl
    cfg = dataclasses.replace(tiny, image_size=8, reward_model=dataclasses.replace(tiny.reward_model, width=4))
    graphdef, params = build_detector(cfg)
    init, step = make_detector_step(graphdef, cfg)
    batch_at = _reward_batches(cfg, poison_at=1)
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
