"""Flow matching: Wan's shift, noising, targets, clean estimates, loss on the future only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.world_model import flow
from sword_jax.world_model.config import FlowConfig


def test_shift_matches_wan_formula():
    s = jnp.array([0.0, 0.25, 0.5, 1.0], jnp.float32)
    np.testing.assert_allclose(flow.shift_sigma(s, 1.0), s, rtol=1e-6)
    expected = 5.0 * np.array([0.0, 0.25, 0.5, 1.0]) / (1.0 + 4.0 * np.array([0.0, 0.25, 0.5, 1.0]))
    np.testing.assert_allclose(flow.shift_sigma(s, 5.0), expected, rtol=1e-6)
    sig = flow.sampling_sigmas(4, 3.0)
    assert sig.shape == (5,) and float(sig[0]) == 1.0 and float(sig[-1]) == 0.0
    assert np.all(np.diff(np.asarray(sig)) < 0)
    with pytest.raises(ValueError, match="num_steps"):
        flow.sampling_sigmas(0, 3.0)


def test_training_sigmas_shifted_and_in_range(key):
    cfg = FlowConfig(shift=5.0)
    sig = np.asarray(flow.sample_sigmas(4096, cfg, key=key))
    assert sig.min() > 0 and sig.max() <= 1.0
    # shift 5 pushes mass to high noise: median of shifted U(0,1) is 5*0.5/3 = 0.833
    assert abs(np.median(sig) - 2.5 / 3.0) < 0.03


@pytest.mark.parametrize("prediction", ["velocity", "epsilon"])
def test_perfect_prediction_recovers_clean_latents(prediction, keys):
    cfg = FlowConfig(prediction=prediction)
    x0 = jax.random.normal(keys[0], (3, 2, 2, 2, 4))
    noise = jax.random.normal(keys[1], x0.shape)
    sigma = jnp.array([0.1, 0.5, 0.9], jnp.float32)
    x_t = flow.add_noise(x0, noise, sigma)
    s = sigma[:, None, None, None, None]
    np.testing.assert_allclose(x_t, (1 - s) * x0 + s * noise, rtol=1e-6, atol=1e-6)
    perfect = flow.target(x0, noise, cfg)
    np.testing.assert_allclose(flow.to_clean(perfect, x_t, s, cfg), x0, atol=1e-5)
    np.testing.assert_allclose(flow.to_velocity(perfect, x_t, s, cfg), noise - x0, atol=1e-4)


def test_noisy_segment_keeps_conditioning_clean(keys):
    cfg = FlowConfig()
    latents = jax.random.normal(keys[0], (2, 4, 2, 2, 3))
    noise = jax.random.normal(keys[1], (2, 2, 2, 2, 3))
    sigma = jnp.array([0.3, 0.7], jnp.float32)
    model_in, timesteps = flow.noisy_segment(latents, noise, sigma, 2, cfg)
    np.testing.assert_array_equal(model_in[:, :2], latents[:, :2])
    np.testing.assert_allclose(model_in[:, 2:], flow.add_noise(latents[:, 2:], noise, sigma))
    np.testing.assert_allclose(timesteps, [[0, 0, 300, 300], [0, 0, 700, 700]], rtol=1e-6)


def test_loss_covers_future_only(keys):
    cfg = FlowConfig()
    latents = jax.random.normal(keys[0], (2, 4, 2, 2, 3))
    noise = jax.random.normal(keys[1], (2, 2, 2, 2, 3))
    prediction = jax.random.normal(keys[2], latents.shape)
    loss = flow.flow_loss(prediction, latents, noise, 2, cfg)
    changed_cond = prediction.at[:, :2].set(100.0)
    assert float(flow.flow_loss(changed_cond, latents, noise, 2, cfg)) == float(loss)
    expected = np.mean((np.asarray(prediction[:, 2:]) - (np.asarray(noise) - np.asarray(latents[:, 2:]))) ** 2)
    np.testing.assert_allclose(loss, expected, rtol=1e-5)
    assert float(flow.flow_loss(changed_cond.at[:, 3].add(1.0), latents, noise, 2, cfg)) != float(loss)
