"""VAE section of the experiment config (owned by sword_jax.vae)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class VAEConfig:
    """Wan 2.2-style causal video VAE (defaults: the official full-size VAE).

    Attributes:
      z_dim: latent channels.
      dim: encoder base width (official 160).
      dec_dim: decoder base width (official 256).
      dim_mult: width multipliers per resolution level.
      num_res_blocks: residual blocks per level.
      temporal_downsample: which levels halve time (two of them: temporal x4).
      checkpoint: optional path to official Wan 2.2 VAE safetensors; empty trains from scratch.
      compute_dtype: 'float32' or 'bfloat16'.
    """

    z_dim: int = 48
    dim: int = 160
    dec_dim: int = 256
    dim_mult: tuple[int, ...] = (1, 2, 4, 4)
    num_res_blocks: int = 2
    temporal_downsample: tuple[bool, ...] = (False, True, True)
    checkpoint: str = ""
    compute_dtype: str = "float32"
    train_steps: int = 1000
    learning_rate: float = 1e-4
    kl_weight: float = 1e-6
    batch_size: int = 8

    def validate(self) -> None:
        if self.z_dim <= 0 or self.dim <= 0 or self.dec_dim <= 0:
            raise ValueError(f"vae: z_dim/dim/dec_dim must be positive, got {self.z_dim}/{self.dim}/{self.dec_dim}")
        if len(self.temporal_downsample) != len(self.dim_mult) - 1:
            raise ValueError(
                f"vae.temporal_downsample needs {len(self.dim_mult) - 1} entries (one per down level), "
                f"got {len(self.temporal_downsample)}"
            )
