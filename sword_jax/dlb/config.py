"""Cache section of the experiment config: Dynamic Latent Bootstrapping (owned by sword_jax.dlb)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class CacheConfig:
    """Dynamic Latent Bootstrapping cache: read schedule and write-back rule.

    Defaults are the paper's best design: linear schedule, direct replacement, write all chunks.
    """

    enabled: bool = True
    schedule: str = "linear"  # linear | warmup_cosine
    read_prob_start: float = 0.0
    read_prob_end: float = 0.5
    schedule_steps: int = 100
    warmup_steps: int = 0
    replacement: str = "direct"  # direct | ema
    ema_rate: float = 0.5
    scope: str = "all"  # single | all
    write_source: str = "train_forward"  # train_forward | sample
    write_sample_steps: int = 2

    def validate(self) -> None:
        if self.schedule not in ("linear", "warmup_cosine"):
            raise ValueError(f"cache.schedule must be linear|warmup_cosine, got {self.schedule!r}")
        if self.replacement not in ("direct", "ema"):
            raise ValueError(f"cache.replacement must be direct|ema, got {self.replacement!r}")
        if self.scope not in ("single", "all"):
            raise ValueError(f"cache.scope must be single|all, got {self.scope!r}")
        for name in ("read_prob_start", "read_prob_end", "ema_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"cache.{name} must be in [0, 1], got {value}")
