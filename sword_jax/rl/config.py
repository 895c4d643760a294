"""RL section of the experiment config (owned by sword_jax.rl)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class RLConfig:
    """Policy, reward model and GRPO settings."""

    group_size: int = 8
    clip_low: float = 0.2
    clip_high: float = 0.28
    kl_coef: float = 0.0
    learning_rate: float = 1e-5
    grpo_steps: int = 10
    max_chunks: int = 8
    success_threshold: float = 0.9
    sft_steps: int = 200
    reward_model_steps: int = 200

    def validate(self) -> None:
        if self.group_size < 2:
            raise ValueError(f"rl.group_size must be >= 2 for group-normalised advantages, got {self.group_size}")
        if not 0.0 < self.success_threshold <= 1.0:
            raise ValueError(f"rl.success_threshold must be in (0, 1], got {self.success_threshold}")
