"""Every public entry point rejects bad input with an error naming the problem (one test per kind)."""

from __future__ import annotations

import os

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from configs.cli import ConfigError
from sword_jax import checkpoint
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dit.config import DiTConfig
from sword_jax.dlb.config import CacheConfig
from sword_jax import sharding as shd
from sword_jax.world_model import train_state
from sword_jax.world_model.config import TrainerConfig
from sword_jax.world_model.data import LatentDataset

TINY_DIT = DiTConfig(dim=32, ffn_dim=64, freq_dim=32, num_heads=2, num_layers=1, text_dim=16, text_len=8,
                     compute_dtype="float32")


@pytest.fixture(scope="module")
def world_model():
    return WorldModel(TINY_DIT, rngs=nnx.Rngs(0))


@pytest.fixture(scope="module")
def tiny_vae():
    from sword_jax.vae import api as vae_api
    from sword_jax.vae import tiny_config

    return nnx.split(vae_api.create_vae(tiny_config(), key=jax.random.key(0)))


def _wm_inputs(frames=2):
    latents = jnp.zeros((1, frames, 2, 2, 48), jnp.float32)
    timesteps = jnp.zeros((1, frames), jnp.float32)
    actions = jnp.zeros((1, 1 + 4 * (frames - 1), 7), jnp.float32)
    return latents, timesteps, actions


def test_world_model_wrong_shapes(world_model):
    latents, timesteps, actions = _wm_inputs()
    with pytest.raises(ValueError, match="actions"):
        world_model(latents, timesteps, actions[:, :3])
    with pytest.raises(ValueError, match="latents|channels|48"):
        world_model(latents[..., :8], timesteps, actions)


def test_world_model_nan_actions_and_out_of_range_sim_actions(world_model):
    latents, timesteps, actions = _wm_inputs()
    with pytest.raises(ValueError, match="(?i)nan|finite"):
        world_model(latents, timesteps, actions.at[0, 0, 0].set(jnp.nan))
    from sim.gym_env import LiberoSpatialGymEnv

    env = LiberoSpatialGymEnv(task_id=0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(np.full(7, 3.0, np.float32))
    env.close()


def test_vae_frames_not_1_plus_4k_and_range(tiny_vae):
    from sword_jax.vae import api as vae_api

    graphdef, state = tiny_vae
    with pytest.raises(ValueError, match="1 ?\\+ ?4k|1\\+4k"):
        vae_api.encode(graphdef, state, jnp.zeros((1, 4, 32, 32, 3), jnp.float32))
    with pytest.raises(ValueError, match="16"):
        vae_api.encode(graphdef, state, jnp.zeros((1, 5, 24, 24, 3), jnp.float32))
    with pytest.raises(ValueError, match="\\[-1, 1\\]|range"):
        vae_api.encode(graphdef, state, jnp.full((1, 5, 32, 32, 3), 200.0, jnp.float32))


def test_episode_frames_outside_unit_range():
    from sword_jax.augment.episodes import as_episodes

    frames = np.full((1, 2, 8, 8, 3), 2.0, np.float32)
    with pytest.raises(ValueError, match="\\[0, 1\\]"):
        as_episodes({"frames": frames, "depth": None, "seg": None, "actions": np.zeros((1, 2, 7), np.float32),
                     "episode_ids": np.arange(1)}, require_geometry=False)


def test_latent_dataset_nan_and_mismatched_actions():
    latents = np.zeros((2, 3, 2, 2, 48), np.float32)
    with pytest.raises(ValueError, match="NaN"):
        LatentDataset(latents.copy() * np.nan, np.zeros((2, 9, 7), np.float32))
    with pytest.raises(ValueError, match="actions shape"):
        LatentDataset(latents, np.zeros((2, 8, 7), np.float32))


def test_corrupt_and_truncated_hdf5(tmp_path):
    from sim.dataset import DatasetError, read_dataset

    not_hdf5 = tmp_path / "junk.hdf5"
    not_hdf5.write_bytes(b"this is not an HDF5 file" * 10)
    with pytest.raises(DatasetError, match="junk.hdf5"):
        read_dataset(not_hdf5)
    empty = tmp_path / "empty.hdf5"
    with h5py.File(empty, "w") as f:
        f.create_group("data")
    with pytest.raises(DatasetError, match="demo"):
        read_dataset(empty)
    missing = tmp_path / "missing.hdf5"
    with h5py.File(missing, "w") as f:
        f.create_group("data/demo_0").create_dataset("actions", data=np.zeros((3, 7), np.float32))
    with pytest.raises(DatasetError, match="demo_0"):
        read_dataset(missing)


def test_checkpoint_of_other_dataset_size_or_config_is_refused(tmp_path):
    mesh = shd.make_mesh(shd.MeshConfig(data=1), devices=jax.devices()[:1])
    cache_cfg = CacheConfig()
    trainer_cfg = TrainerConfig()

    def state_for(dataset_shape, model_cfg=TINY_DIT):
        return train_state.create_train_state(lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0)), trainer_cfg,
                                              cache_cfg, dataset_shape, mesh)

    _, state, _ = state_for((4, 5, 2, 2, 48))
    ckpt = checkpoint.Checkpointer(str(tmp_path / "ckpt"))
    ckpt.save(1, state, {"step": 1})
    _, other, shardings = state_for((6, 5, 2, 2, 48))  # dataset with more episodes than the cache
    with pytest.raises(ValueError, match="does not match"):
        ckpt.restore(checkpoint.abstract_like(other, shardings))
    wider = DiTConfig(**{**TINY_DIT.__dict__, "dim": 64, "num_heads": 4})
    _, other, shardings = state_for((4, 5, 2, 2, 48), wider)
    with pytest.raises(ValueError, match="does not match"):
        ckpt.restore(checkpoint.abstract_like(other, shardings))
    ckpt.close()
    assert os.path.isdir(tmp_path / "ckpt" / "1"), "a refused restore must leave the checkpoint in place"


def test_unknown_config_key_and_impossible_config():
    with pytest.raises(ConfigError, match="cache.schedul"):
        configs.from_argv(["--cache.schedul=linear"])
    with pytest.raises(ValueError, match="image_size"):
        configs.from_argv(["--data.image_size=40"])
    with pytest.raises(ValueError, match="flow.shift"):
        configs.from_argv(["--flow.shift=nan"])


def test_train_entry_point_rejects_mismatched_latents(tmp_path):
    from train import train_world_model

    path = tmp_path / "latents.npz"
    np.savez(path, latents=np.zeros((2, 9, 4, 4, 48), np.float32), actions=np.zeros((2, 33, 7), np.float32))
    with pytest.raises(SystemExit, match="expects"):
        train_world_model.main(["--config", "sword:tiny", f"--workdir={tmp_path / 'run'}", f"--data.path={path}"])
