"""The experiment config: one frozen dataclass composed of the library's section configs."""

from __future__ import annotations

import dataclasses

from sim.config import SimConfig
from sword_jax.augment.config import AugmentConfig
from sword_jax.dit.config import FRAMES_PER_LATENT, DiTConfig
from sword_jax.dlb.config import CacheConfig
from sword_jax.metrics.config import EvalConfig
from sword_jax.rl.config import RLConfig
from sword_jax.sharding import MeshConfig
from sword_jax.vae.config import LightDecoderConfig, VAEConfig
from sword_jax.world_model.config import DataConfig, FlowConfig, TrainerConfig


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
    """Everything one run needs. Sections are owned by the library modules that read them."""

    name: str = "sword"
    seed: int = 0
    workdir: str = "runs/sword"
    model: DiTConfig = DiTConfig()
    flow: FlowConfig = FlowConfig()
    vae: VAEConfig = VAEConfig()
    light_decoder: LightDecoderConfig = LightDecoderConfig()
    data: DataConfig = DataConfig()
    cache: CacheConfig = CacheConfig()
    trainer: TrainerConfig = TrainerConfig()
    augment: AugmentConfig = AugmentConfig()
    sim: SimConfig = SimConfig()
    rl: RLConfig = RLConfig()
    eval: EvalConfig = EvalConfig()
    mesh: MeshConfig = MeshConfig()

    def validate(self) -> "ExperimentConfig":
        """Checks each section and the settings that span sections; returns self."""
        for field in dataclasses.fields(self):
            section = getattr(self, field.name)
            if hasattr(section, "validate"):
                section.validate()
        stride = self.vae.spatial_factor
        spatial = stride * self.model.patch_size[1]
        if self.data.image_size % spatial:
            raise ValueError(
                f"data.image_size={self.data.image_size} must be a multiple of {stride}*patch={spatial} "
                f"(VAE stride {stride} times the DiT patch)"
            )
        if self.vae.temporal_factor != FRAMES_PER_LATENT:
            raise ValueError(
                f"vae.temporal_downsample={self.vae.temporal_downsample} compresses time by {self.vae.temporal_factor}, "
                f"but the action DiT groups {FRAMES_PER_LATENT} actions per latent frame (Wan 2.2's VAE: two "
                "temporal downsamples)"
            )
        if self.model.in_dim != self.vae.z_dim or self.model.out_dim != self.vae.z_dim:
            raise ValueError(
                f"model.in_dim/out_dim ({self.model.in_dim}/{self.model.out_dim}) must equal vae.z_dim ({self.vae.z_dim})"
            )
        if self.sim.resolution != self.data.image_size and self.data.path == "":
            raise ValueError(
                f"sim.resolution={self.sim.resolution} differs from data.image_size={self.data.image_size}: "
                "generated episodes would not match the model's frames"
            )
        if (self.eval.horizon_frames - 1) > (self.data.episode_frames - 1):
            raise ValueError(
                f"eval.horizon_frames={self.eval.horizon_frames} exceeds data.episode_frames={self.data.episode_frames}"
            )
        # The policy acts in the world model: its actions are the model's, one chunk per predicted chunk.
        if self.rl.action_dim != self.model.action_dim:
            raise ValueError(
                f"rl.action_dim={self.rl.action_dim} differs from model.action_dim={self.model.action_dim}: "
                "the policy's actions condition the world model"
            )
        if self.rl.chunk_len != self.data.predict_frames:
            raise ValueError(
                f"rl.chunk_len={self.rl.chunk_len} must equal data.predict_frames={self.data.predict_frames} "
                f"({self.vae.temporal_factor} x {self.data.predict_frames // self.vae.temporal_factor} future latents): "
                "the learned simulator predicts one frame per action of a chunk"
            )
        if self.flow.pixel_round_trip and self.data.context_frames > self.data.predict_frames:
            raise ValueError(
                f"flow.pixel_round_trip re-encodes one predicted chunk ({self.data.predict_frames} frames) as the next "
                f"context, which needs data.context_frames={self.data.context_frames} <= data.predict_frames"
            )
        executed = self.rl.imagined.execute_steps or self.rl.chunk_len
        if self.flow.pixel_round_trip and self.data.context_frames > executed:
            raise ValueError(
                f"flow.pixel_round_trip: GRPO's learned simulator re-encodes the {executed} executed frames "
                f"(rl.imagined.execute_steps) as the next context, which needs data.context_frames="
                f"{self.data.context_frames} <= {executed}"
            )
        if self.rl.imagined.decoder == "light":
            self.light_decoder.geometry(image_size=self.data.image_size, spatial_factor=self.vae.spatial_factor,
                                        policy_size=self.rl.image_size)
            if self.flow.pixel_round_trip:
                raise ValueError(
                    "rl.imagined.decoder=light decodes imagined frames with the light decoder, but flow.pixel_round_trip "
                    "re-encodes the VAE's full-resolution frames as the next context; use rl.imagined.decoder=full"
                )
        return self
