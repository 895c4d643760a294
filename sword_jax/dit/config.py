"""Model section of the experiment config: the Wan 2.2 TI2V DiT world model (owned by sword_jax.dit)."""

import dataclasses

REMAT_POLICIES = ("none", "full", "dots", "dots_acts")


# Video frames (= actions) per latent frame after the first: the action DiT groups the actions of each latent
# frame into one token of FRAMES_PER_LATENT x action_dim (Wan 2.2's VAE compresses time by 4). The experiment
# config checks it against the VAE's ``temporal_factor``.
FRAMES_PER_LATENT = 4


@dataclasses.dataclass(frozen=True)
class DiTConfig:
    """Wan 2.2 TI2V diffusion transformer with dual action conditioning.

    Defaults are the official TI2V-5B shapes.
    """

    patch_size: tuple[int, int, int] = (1, 2, 2)
    in_dim: int = 48
    out_dim: int = 48
    dim: int = 3072
    ffn_dim: int = 14336
    freq_dim: int = 256
    num_heads: int = 24
    num_layers: int = 30
    text_dim: int = 4096
    text_len: int = 512
    eps: float = 1e-6
    qk_norm: bool = True
    cross_attn_norm: bool = True
    action_dim: int = 7
    action_cross_attn: bool = True  # actions as cross-attention tokens
    action_adaln: bool = True  # action chunk MLP added to the time embedding
    remat: str = "none"  # one of REMAT_POLICIES (see model._remat_policy)
    scan_layers: bool = True
    compute_dtype: str = "bfloat16"
    param_dtype: str = "float32"
    # dtype of the residual stream between blocks. float32 (default) is the official model; bfloat16
    # halves the memory traffic of the carry and of what remat saves, at a rounding of the stream
    # after every block (each block still adds in float32).
    residual_dtype: str = "float32"
    attention_impl: str = "auto"  # auto | xla | cudnn

    def validate(self) -> None:
        if len(self.patch_size) != 3 or any(int(p) < 1 for p in self.patch_size):
            raise ValueError(f"model.patch_size must be 3 positive ints (t, h, w), got {self.patch_size}")
        for name in ("in_dim", "out_dim", "dim", "ffn_dim", "freq_dim", "num_heads", "num_layers", "text_dim",
                     "text_len", "action_dim"):
            if getattr(self, name) < 1:
                raise ValueError(f"model.{name} must be positive, got {getattr(self, name)}")
        if self.freq_dim % 2:
            raise ValueError(f"model.freq_dim={self.freq_dim} must be even (cos and sin halves)")
        if not 0 < self.eps < 1:
            raise ValueError(f"model.eps must be in (0, 1), got {self.eps}")
        if self.dim % self.num_heads:
            raise ValueError(f"model: num_heads={self.num_heads} does not divide dim={self.dim}")
        if (self.dim // self.num_heads) % 2:
            raise ValueError(f"model: head_dim={self.dim // self.num_heads} must be even for RoPE")
        if self.remat not in REMAT_POLICIES:
            raise ValueError(f"model.remat must be {'|'.join(REMAT_POLICIES)}, got {self.remat!r}")
        if self.attention_impl not in ("auto", "xla", "cudnn"):
            raise ValueError(f"model.attention_impl must be auto|xla|cudnn, got {self.attention_impl!r}")
        for name in ("compute_dtype", "param_dtype", "residual_dtype"):
            if getattr(self, name) not in ("float32", "bfloat16"):
                raise ValueError(f"model.{name} must be float32|bfloat16, got {getattr(self, name)!r}")
