"""Tiny models and builders for the world-model / DLB tests.

``MixerWorldModel`` has the WorldModel call signature but compiles in a blink: a per-frame channel
mix, a context summary of the clean frames, a timestep feature and an action-chunk term. The
real DiT is used where the test is about the model (loss falls, entry point, rollout finiteness).
``ProbeWorldModel`` records every input it is called with through ``jax.debug.callback``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax import sharding as shd
from sword_jax.dit.action_dit import action_chunks
from sword_jax.dlb.config import CacheConfig
from sword_jax.world_model import data, train_state, train_step
from sword_jax.world_model.config import FlowConfig, TrainerConfig

CHANNELS = 8
LATENT_HW = 2


class MixerWorldModel(nnx.Module):
    def __init__(self, channels: int = CHANNELS, action_dim: int = 7, *, rngs: nnx.Rngs):
        init = nnx.initializers.normal(0.3)
        with nnx.use_eager_sharding(False):
            self._make(init, channels, action_dim, rngs)

    def _make(self, init, channels, action_dim, rngs):
        self.frame_mix = nnx.Param(init(rngs.params(), (channels, channels)), out_sharding=(None, "embed"))
        self.context_mix = nnx.Param(init(rngs.params(), (channels, channels)), out_sharding=("embed", None))
        self.time_mix = nnx.Param(init(rngs.params(), (2, channels)))
        self.action_mix = nnx.Param(init(rngs.params(), (4 * action_dim, channels)))

    def __call__(self, latents, timesteps, actions):
        clean = (timesteps == 0).astype(jnp.float32)[:, :, None, None, None]
        summary = jnp.sum(latents * clean, axis=1, keepdims=True) / jnp.maximum(
            jnp.sum(clean, axis=1, keepdims=True), 1.0)
        t = timesteps / jnp.float32(1000.0)
        time_feat = jnp.stack([t, jnp.sin(t * jnp.float32(3.0))], axis=-1) @ self.time_mix[...]  # (b, f, c)
        action_feat = action_chunks(actions) @ self.action_mix[...]  # (b, f, c)
        out = latents @ self.frame_mix[...] + summary @ self.context_mix[...]
        return out + (time_feat + action_feat)[:, :, None, None, :]


class ProbeWorldModel(MixerWorldModel):
    """Records the latents and timesteps it sees (host side) on every call."""

    records: list = []

    def __call__(self, latents, timesteps, actions):
        jax.debug.callback(lambda x, t: ProbeWorldModel.records.append((np.asarray(x), np.asarray(t))),
                           latents, timesteps)
        return super().__call__(latents, timesteps, actions)


def tiny_dataset(num_episodes: int = 8, num_latents: int = 6, seed: int = 0) -> data.LatentDataset:
    return data.synthetic_latent_dataset(num_episodes, num_latents, LATENT_HW, LATENT_HW, CHANNELS, seed=seed)


def build(
    *, mesh, cache_cfg: CacheConfig, flow_cfg: FlowConfig = FlowConfig(), trainer_cfg: TrainerConfig | None = None,
    dataset: data.LatentDataset | None = None, batch_size: int = 8, model_cls=MixerWorldModel, seed: int = 0,
    wrap=None,
):
    """(graphdef, state, shardings, step, loader) for the tiny stand-in model on ``mesh``."""
    trainer_cfg = trainer_cfg or TrainerConfig(learning_rate=1e-2, warmup_steps=0)
    dataset = dataset or tiny_dataset()
    graphdef, state, shardings = train_state.create_train_state(
        lambda: model_cls(rngs=nnx.Rngs(seed)), trainer_cfg, cache_cfg, dataset.shape, mesh)
    sampler = data.SegmentSampler(dataset.shape[0], dataset.shape[1], 1, 2, batch_size, seed=seed)
    loader = data.SegmentLoader(dataset, sampler, 1, 2, mesh)
    fn = train_step.make_train_step(graphdef, flow_cfg=flow_cfg, trainer_cfg=trainer_cfg, cache_cfg=cache_cfg,
                                    num_context=1, num_episodes=dataset.shape[0])
    if wrap is not None:
        fn = wrap(fn)
    step = train_step.compile_train_step(fn, shardings, loader.shardings, mesh)
    return graphdef, state, shardings, step, loader


def single_device_mesh():
    return shd.make_mesh(shd.MeshConfig(data=1), devices=jax.devices()[:1])


def full_mesh():
    return shd.make_mesh(shd.MeshConfig(data=-1))
