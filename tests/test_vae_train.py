"""VAE training from scratch: the loss falls on synthetic moving squares; sharded step keeps shardings."""

import jax
import numpy as np
import pytest

from sword_jax import sharding
from sword_jax.vae import tiny_config, train


def test_moving_squares_in_range_and_moving():
    video = train.moving_squares(key=jax.random.key(0), batch=2, frames=5, size=32)
    assert video.shape == (2, 5, 32, 32, 3)
    assert float(video.min()) >= -1.0 and float(video.max()) <= 1.0
    assert float(np.abs(np.asarray(video[:, 0]) - np.asarray(video[:, 4])).max()) > 0.1


def test_training_loss_falls():
    cfg = tiny_config(z_dim=8, learning_rate=3e-3, kl_weight=1e-4)
    graphdef, state = train.init_train_state(cfg, key=jax.random.key(0))
    step = train.make_train_step(graphdef, cfg)
    root = jax.random.key(1)
    video = train.moving_squares(key=root, batch=2, frames=5, size=32)
    losses = []
    for _ in range(25):
        state, metrics = step(state, {"video": video}, root)
        losses.append(metrics["loss"])
    losses = [float(x) for x in losses]
    assert int(state.step) == 25
    assert all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.5 * losses[0], losses
    assert float(metrics["kl"]) > 0 and float(metrics["grad_norm"]) > 0


@pytest.mark.slow
def test_sharded_step_keeps_shardings():
    cfg = tiny_config(z_dim=8, dim=16, dec_dim=16)
    mesh = sharding.make_mesh(sharding.MeshConfig(data=2, fsdp=4))
    graphdef, state = train.init_train_state(cfg, key=jax.random.key(0), mesh=mesh)
    kernel = state.params["decoder"]["conv1"]["kernel"]
    assert kernel.value.sharding.spec[-1] == "fsdp"
    step = train.make_train_step(graphdef, cfg, state=state, mesh=mesh)
    video = train.moving_squares(key=jax.random.key(1), batch=8, frames=5, size=32)
    for _ in range(2):
        state, metrics = step(state, {"video": video}, jax.random.key(2))
    assert np.isfinite(float(metrics["loss"]))
    assert state.params["decoder"]["conv1"]["kernel"].value.sharding.spec[-1] == "fsdp"
