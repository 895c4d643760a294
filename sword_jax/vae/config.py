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
      checkpoint: optional: a file of official Wan 2.2 VAE weights (safetensors), or the folder of a trained
        sword-jax VAE of this architecture (``train.train_vae``'s, a bundle's ``vae_run/vae``) to reuse; empty
        trains from scratch.
      compute_dtype: 'float32' or 'bfloat16' (activations/convs; params, norms, softmax and losses
        stay float32).
      train_steps, learning_rate, batch_size: VAE training from scratch (sword_jax.vae.train).
      kl_weight: weight of the KL term on the (mu, log_var) posterior.
      l1_weight, l2_weight: weights of the mean absolute / mean squared reconstruction errors.
      perceptual_weight: weight of the optional perceptual term (a callable given to the step).
      weight_decay: AdamW weight decay.
      grad_clip: global-norm gradient clipping (0 disables).
      train_styles: train on raw plus training-style frames (``sword_jax.vae.data``); held-out
        styles (LIBERO-Mixed) never reach the VAE.
      styled_fraction: with ``train_styles``, the share of training clips restyled.
      causal_conv: how the 3x3x3 causal convolutions run: ``conv3d`` (one 3-D convolution) or
        ``conv2d`` (the three time taps stacked as channels, one 2-D convolution per frame). The
        same sums in another order: outputs agree to rounding.
      upsample: the decoder's x2 upsampling conv: ``repeat`` (nearest x2, then the 3x3 conv, as
        the official code) or ``subpixel`` (the same result from the low-resolution frame with 4/9
        of the multiply-adds; agrees to rounding).
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
    l1_weight: float = 1.0
    l2_weight: float = 1.0
    perceptual_weight: float = 0.0
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    train_styles: bool = True
    styled_fraction: float = 0.5
    causal_conv: str = "conv3d"
    upsample: str = "repeat"

    def validate(self) -> None:
        if self.z_dim <= 0 or self.dim <= 0 or self.dec_dim <= 0:
            raise ValueError(f"vae: z_dim/dim/dec_dim must be positive, got {self.z_dim}/{self.dim}/{self.dec_dim}")
        if len(self.temporal_downsample) != len(self.dim_mult) - 1:
            raise ValueError(
                f"vae.temporal_downsample needs {len(self.dim_mult) - 1} entries (one per down level), "
                f"got {len(self.temporal_downsample)}"
            )
        if len(self.dim_mult) < 2 or any(m <= 0 for m in self.dim_mult):
            raise ValueError(f"vae.dim_mult needs >= 2 positive entries, got {self.dim_mult}")
        if self.num_res_blocks < 1:
            raise ValueError(f"vae.num_res_blocks must be >= 1, got {self.num_res_blocks}")
        if self.compute_dtype not in ("float32", "bfloat16"):
            raise ValueError(f"vae.compute_dtype must be 'float32' or 'bfloat16', got {self.compute_dtype!r}")
        if min(self.kl_weight, self.l1_weight, self.l2_weight, self.perceptual_weight, self.weight_decay) < 0:
            raise ValueError("vae: loss weights and weight_decay must be >= 0")
        if self.causal_conv not in ("conv3d", "conv2d"):
            raise ValueError(f"vae.causal_conv must be 'conv3d' or 'conv2d', got {self.causal_conv!r}")
        if self.upsample not in ("repeat", "subpixel"):
            raise ValueError(f"vae.upsample must be 'repeat' or 'subpixel', got {self.upsample!r}")
        if not 0.0 <= self.styled_fraction <= 1.0:
            raise ValueError(f"vae.styled_fraction must be in [0, 1], got {self.styled_fraction}")
        # AvgDown3D / DupUp3D regroup channels: in*factor must divide evenly into out groups.
        enc = [self.dim * m for m in (1, *self.dim_mult)]
        dec = [self.dec_dim * m for m in (self.dim_mult[-1], *self.dim_mult[::-1])]
        levels = len(self.dim_mult)
        for i in range(levels):
            down = i != levels - 1
            factor = (2 if down and self.temporal_downsample[i] else 1) * (4 if down else 1)
            if (enc[i] * factor) % enc[i + 1]:
                raise ValueError(f"vae: encoder level {i}: {enc[i]}*{factor} channels do not split into {enc[i + 1]} groups")
            t_up = down and i < len(self.temporal_downsample) and self.temporal_downsample[::-1][i]
            factor = (2 if t_up else 1) * (4 if down else 1)
            if down and (dec[i + 1] * factor) % dec[i]:
                raise ValueError(f"vae: decoder level {i}: {dec[i + 1]}*{factor} is not a multiple of {dec[i]}")

    @property
    def temporal_factor(self) -> int:
        """Frames per latent frame after the first (4 for the official VAE)."""
        return 2 ** sum(self.temporal_downsample)

    @property
    def spatial_factor(self) -> int:
        """Pixels per latent pixel along H and W (16 for the official VAE: 2x2 patchify, three x2 levels)."""
        return 2 * 2 ** (len(self.dim_mult) - 1)


TEACHER_PRECISIONS = ("fast", "float32")


@dataclasses.dataclass(frozen=True)
class LightDecoderConfig:
    """The light rollout decoder (:mod:`sword_jax.vae.light_decoder`) and its distillation from the VAE's decoder
    (:mod:`sword_jax.vae.light_train`, the pipeline's ``light_decoder`` stage, which runs when
    ``rl.imagined.decoder=light``).

    Attributes:
      frame_size: side of the frames it decodes, in pixels; 0 (default) = ``rl.image_size``, the frames the
        policy and the success detector read. A power-of-two multiple of the latent size
        (``data.image_size / vae.spatial_factor``), at most ``data.image_size``.
      width: channels of its latent-resolution stage; each later stage halves them, down to
        ``max(width / 4, 8)``.
      blocks: memory blocks per stage (each sees its frame and the previous one: causal in time).
      train_steps, learning_rate, batch_size: the distillation (AdamW at a constant rate).
      clip_latents: latents after the first of each training clip: the episode's first latent, then this
        many consecutive latents from a random position, the layout the learned simulator decodes (start
        latent, context, predictions).
      l1_weight, l2_weight: weights of the mean absolute / squared error to the teacher's frames resized to
        ``frame_size`` (as the policy resizes them).
      perceptual_weight: weight of LPIPS (``eval`` section's network) between the two; 0 (default) = off.
      latent_noise: std of Gaussian noise added to a clip's latents before both decoders see them (the world
        model's predictions are not exactly the encoder's latents); 0 (default) = none.
      teacher_precision: how the VAE's decoder runs as the teacher: ``fast`` (bfloat16, sub-pixel upsampling;
        :func:`sword_jax.rl.sim_builder.inference_vae`) or ``float32`` (the exact decode).
      compute_dtype: the light decoder's convolutions while it trains (the simulator runs it in its own
        precision, ``rl.imagined.sim_precision``).
      weight_decay, grad_clip: AdamW weight decay and global-norm clipping (0 disables it).
    """

    frame_size: int = 0
    width: int = 128
    blocks: int = 2
    train_steps: int = 2000
    learning_rate: float = 5e-4
    batch_size: int = 8
    clip_latents: int = 3
    l1_weight: float = 1.0
    l2_weight: float = 1.0
    perceptual_weight: float = 0.0
    latent_noise: float = 0.0
    teacher_precision: str = "fast"
    compute_dtype: str = "float32"
    weight_decay: float = 0.0
    grad_clip: float = 1.0

    def validate(self) -> None:
        if self.frame_size < 0:
            raise ValueError(f"light_decoder.frame_size must be >= 0 (0 = rl.image_size), got {self.frame_size}")
        if self.width < 1 or self.blocks < 1:
            raise ValueError(f"light_decoder.width and light_decoder.blocks must be >= 1, got {self.width} and "
                             f"{self.blocks}")
        if self.train_steps < 1 or self.batch_size < 1 or self.clip_latents < 1:
            raise ValueError(f"light_decoder: train_steps, batch_size and clip_latents must be >= 1, got "
                             f"{self.train_steps}, {self.batch_size}, {self.clip_latents}")
        if not self.learning_rate > 0:
            raise ValueError(f"light_decoder.learning_rate must be > 0, got {self.learning_rate}")
        if min(self.l1_weight, self.l2_weight, self.perceptual_weight, self.latent_noise, self.weight_decay,
               self.grad_clip) < 0:
            raise ValueError("light_decoder: loss weights, latent_noise, weight_decay and grad_clip must be >= 0")
        if self.l1_weight + self.l2_weight + self.perceptual_weight == 0:
            raise ValueError("light_decoder: l1_weight, l2_weight and perceptual_weight are all 0: nothing to learn")
        if self.teacher_precision not in TEACHER_PRECISIONS:
            raise ValueError(f"light_decoder.teacher_precision must be one of {TEACHER_PRECISIONS}, got "
                             f"{self.teacher_precision!r}")
        if self.compute_dtype not in ("float32", "bfloat16"):
            raise ValueError(f"light_decoder.compute_dtype must be 'float32' or 'bfloat16', got {self.compute_dtype!r}")

    def output_size(self, policy_size: int) -> int:
        """The frame side it decodes: ``frame_size``, or the policy's ``policy_size`` when that is 0."""
        return self.frame_size or policy_size

    def geometry(self, *, image_size: int, spatial_factor: int, policy_size: int) -> tuple[int, int]:
        """``(latent size, frame size)``: latents of ``image_size`` frames under a VAE of ``spatial_factor``
        decoded to :meth:`output_size` frames. Raises ValueError when the frame size is not a power-of-two
        multiple of the latent size or exceeds ``image_size`` (the teacher's frames)."""
        latent = image_size // spatial_factor
        frame = self.output_size(policy_size)
        source = (f"light_decoder.frame_size={frame}" if self.frame_size
                  else f"rl.image_size={frame} (light_decoder.frame_size=0)")
        ratio = frame // latent if latent and frame % latent == 0 else 0
        if ratio < 1 or ratio & (ratio - 1):
            raise ValueError(f"{source}: the light decoder upsamples the {latent}x{latent} latents (data.image_size="
                             f"{image_size} over vae.spatial_factor={spatial_factor}) by a power of two; use "
                             f"{', '.join(str(latent * 2 ** k) for k in range(1, 5) if latent * 2 ** k <= image_size)}")
        if frame > image_size:
            raise ValueError(f"{source} exceeds data.image_size={image_size}: the light decoder learns the VAE's "
                             "frames resized down to its size, never up")
        return latent, frame
