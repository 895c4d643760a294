"""Augment section of the experiment config (owned by sword_jax.augment)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
    """Structure-guided style augmentation."""

    enabled: bool = True
    intensity: float = 1.0
    styled_copies: int = 2  # pre-encoded styled copies per episode
    mixed_fraction: float = 0.5  # LIBERO-Mixed: share of held-out-styled episodes

    def validate(self) -> None:
        if not 0.0 <= self.intensity <= 1.0:
            raise ValueError(f"augment.intensity must be in [0, 1], got {self.intensity}")
        if not 0.0 <= self.mixed_fraction <= 1.0:
            raise ValueError(f"augment.mixed_fraction must be in [0, 1], got {self.mixed_fraction}")
