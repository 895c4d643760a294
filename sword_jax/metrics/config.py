"""Eval section of the experiment config (owned by sword_jax.metrics)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Long-horizon rollout evaluation and metric weights."""

    horizon_frames: int = 65  # 1 + 4k
    num_episodes: int = 4
    lpips_weights: str = ""  # path; env SWORD_LPIPS_WEIGHTS
    inception_weights: str = ""  # path; env SWORD_INCEPTION_WEIGHTS
    i3d_weights: str = ""  # path; env SWORD_I3D_WEIGHTS

    def validate(self) -> None:
        if (self.horizon_frames - 1) % 4:
            raise ValueError(f"eval.horizon_frames must be of the form 1+4k, got {self.horizon_frames}")
