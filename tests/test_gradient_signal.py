"""gradient_signal: the per-group decomposition of GRPO's batch gradient and the signal / alignment statistics
on designed vectors whose expected gradients are known."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from sword_jax.rl import grpo
from sword_jax.rl.gradient_signal import (Setting, bootstrap, first_decisions, gram_matrix, group_gradients,
                                          statistics)
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.rollout import Rollout
from tests.test_grpo import _toy_cfg


def _rollout(cfg, groups, chunks, rng, *, returns, valid):
    n, t, a = groups * cfg.grpo.group_size, cfg.chunk_len, cfg.action_dim
    return Rollout(
        obs_frames=jnp.asarray(rng.random((n, chunks, 8, 8, 3)), jnp.float32),
        proprio=jnp.asarray(rng.normal(size=(n, chunks, 4)), jnp.float32), proprio_valid=jnp.ones((n, chunks)),
        instruction_tokens=jnp.asarray(tokenize_instructions(["pick it"] * n, 32)),
        tokens=jnp.asarray(rng.integers(0, cfg.action_bins, (n, chunks, t, a)), jnp.int32),
        log_probs=jnp.asarray(-np.log(cfg.action_bins) + 0.3 * rng.normal(size=(n, chunks, t, a)), jnp.float32),
        valid=jnp.asarray(valid, jnp.float32), rewards=jnp.zeros((n, chunks)), scores=jnp.zeros((n, chunks)),
        success=jnp.asarray(returns > 0), returns=jnp.asarray(returns, jnp.float32), frames=jnp.zeros((0,)))


@pytest.mark.parametrize("loss_norm", ["trajectory", "token"])
def test_the_groups_gradients_average_to_the_batch_gradient(loss_norm):
    """h.mean(0) is grpo_gradients of the whole batch, whichever way the loss is normalised, with groups of
    unequal length and one group without signal (it contributes zero)."""
    base = _toy_cfg(ppo_epochs=1, max_chunks=3, group_size=4)
    cfg = dataclasses.replace(base, grpo=dataclasses.replace(base.grpo, loss_norm=loss_norm))
    graphdef, params = build_policy(cfg, seed=0)
    rng = np.random.default_rng(0)
    returns = np.array([2, 0, 0, 2, 0, 0, 0, 0, 2, 2, 2, 0], np.float32)  # group 1 has no signal
    valid = np.ones((12, 3))
    valid[0, 2:] = 0  # trajectories of different lengths weigh differently under loss_norm=token
    valid[9, 1:] = 0
    batch = _rollout(cfg, 3, 3, rng, returns=returns, valid=valid)
    h = group_gradients(graphdef, cfg, params, batch)
    whole = ravel_pytree(jax.jit(lambda p, b: grpo.grpo_gradients(graphdef, cfg, p, b)[2])(params, batch))[0]
    assert h.shape == (3, whole.size) and not h[1].any()
    np.testing.assert_allclose(h.mean(0), np.asarray(whole), rtol=1e-4, atol=1e-6 * float(np.abs(whole).max()))


def test_first_decisions_pays_success_within_the_horizon():
    cfg = _toy_cfg(ppo_epochs=1, max_chunks=4, group_size=2)
    valid = np.array([[1, 1, 0, 0], [1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 0]], np.float32)
    batch = _rollout(cfg, 2, 4, np.random.default_rng(1), returns=np.array([2, 2, 0, 2], np.float32), valid=valid)
    short = first_decisions(batch, 2, cfg)
    assert short.valid.shape == (4, 2) and short.tokens.shape[1] == 2
    np.testing.assert_array_equal(np.asarray(short.success), [True, False, False, False])  # ended by decision 2
    np.testing.assert_array_equal(np.asarray(short.returns), [1 + cfg.grpo.success_bonus, 0, 0, 0])
    with pytest.raises(ValueError, match="horizon"):
        first_decisions(batch, 0, cfg)


def _designed(rng, groups, dim, mean, sigma):
    return mean[None, :] + sigma * rng.normal(size=(groups, dim))


def test_statistics_recover_designed_signal_noise_and_alignment():
    rng = np.random.default_rng(0)
    dim, n = 4000, 200
    g = np.zeros(dim)
    g[:10] = 1.0  # |G|^2 = 10
    other = np.zeros(dim)
    other[10:20] = 1.0  # orthogonal to g, same norm
    sigma = 0.1  # noise power 40 per group: signal fraction 10 / 50
    a = _designed(rng, n, dim, g, sigma)
    b = _designed(rng, n, dim, g, sigma)  # the same expected gradient, drawn independently
    c = _designed(rng, n, dim, other, sigma)  # orthogonal
    d = a + 0.0  # scored on the same trajectories as a: unpaired, self-products would inflate the cross term
    zero = sigma * rng.normal(size=(n, dim))  # no expected gradient at all
    vectors = np.concatenate([a, b, c, zero, d - g[None, :]])
    gram = gram_matrix(vectors)
    rows = lambda k: np.arange(k * n, (k + 1) * n)  # noqa: E731
    settings = {"a": Setting(rows(0), "p"), "b": Setting(rows(1)), "c": Setting(rows(2)), "zero": Setting(rows(3)),
                "a_noise": Setting(rows(4), "p")}
    stats = statistics(gram, settings, reference="a", batch_groups=64)
    assert stats["a"]["signal"] == pytest.approx(10.0, rel=0.1)
    assert stats["a"]["noise"] == pytest.approx(40.0, rel=0.05)
    assert stats["a"]["signal_fraction"] == pytest.approx(0.2, rel=0.12)
    assert stats["a"]["cos_at_batch"] == pytest.approx(10 / (10 + 40 / 64), rel=0.05)
    assert stats["b"]["alignment"] == pytest.approx(1.0, abs=0.1)
    assert abs(stats["c"]["alignment"]) < 0.1
    assert abs(stats["zero"]["signal"]) < 0.5 and abs(stats["zero"]["useful"]) < 0.05
    # a_noise is a's noise alone, paired with a: leaving out each group's self-product, it does not align with a
    assert abs(_cross_of(gram, settings["a_noise"], settings["a"])) < 0.5
    unpaired = dataclasses.replace(settings["a_noise"], pairing="")
    assert _cross_of(gram, unpaired, settings["a"]) > 0.1  # what the self-products would have added (40 / n)
    with pytest.raises(ValueError, match="at least 2"):
        statistics(gram, {"a": Setting(rows(0)[:1])}, reference="a", batch_groups=8)
    with pytest.raises(ValueError, match="paired settings"):
        statistics(gram, {"a": Setting(rows(0), "p"), "x": Setting(rows(1)[:5], "p")}, reference="a", batch_groups=8)
    with pytest.raises(ValueError, match="reference"):
        statistics(gram, settings, reference="nope", batch_groups=8)


def _cross_of(gram, a, b):
    from sword_jax.rl.gradient_signal import _cross
    return _cross(gram, a, b)


def test_bootstrap_intervals_cover_the_designed_values():
    rng = np.random.default_rng(1)
    dim, n = 2000, 60
    g = np.zeros(dim)
    g[:5] = 1.0
    vectors = np.concatenate([_designed(rng, n, dim, g, 0.1), _designed(rng, n, dim, g, 0.1),
                              0.1 * rng.normal(size=(n, dim))])
    gram = gram_matrix(vectors)
    settings = {"ref": Setting(np.arange(n)), "same": Setting(np.arange(n, 2 * n)),
                "none": Setting(np.arange(2 * n, 3 * n))}
    ci = bootstrap(gram, settings, reference="ref", batch_groups=16, draws=300)
    lo, hi = ci["ref"]["signal_fraction"]
    assert lo < 5 / 25 < hi  # |G|^2 5, noise 20
    lo, hi = ci["same"]["alignment"]
    assert lo < 1.0 < hi + 0.05
    lo, hi = ci["none"]["signal_fraction"]
    assert lo < 0.0 < hi or lo == -np.inf  # a group drawn twice is not multiplied with its own copy


@pytest.mark.parametrize("argv,message", [
    (["--groups", "1"], "--groups, --rest-groups and --group-size must be >= 2"),
    (["--rest-groups", "1"], "--rest-groups"),
    (["--settings", "short,long"], "--settings names some of"),
    (["--horizon", "0"], "--horizon"),
    (["--demos", "/nonexistent/demos.hdf5"], "no demonstrations at /nonexistent/demos.hdf5"),
])
def test_the_probe_refuses_bad_options_by_name(argv, message, tmp_path):
    from benchmarks import bench_grpo_gradient_signal as bench
    demos = tmp_path / "demos.hdf5"
    demos.write_bytes(b"")
    base = ["--policy", "p.npz", "--demos", str(demos), "--out", str(tmp_path / "out")]
    with pytest.raises(SystemExit, match=message):
        bench.main(base + argv)
