"""Augment section of the experiment config (owned by sword_jax.augment)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class AugmentConfig:
    """Structure-guided style augmentation.

    Attributes:
      enabled: apply augmentation in world-model training. The pipeline trains on pre-encoded
        styled copies per episode (see ``sword_jax.augment.pipeline`` for the measurement behind
        that choice); the per-step augmenter is a library function, not a pipeline mode.
      intensity: in [0, 1], scales every style parameter's departure from the identity.
      styled_copies: styled copies per episode (the raw episode is kept too).
      mixed_fraction: LIBERO-Mixed: share of held-out-styled episodes.
      fov_deg: vertical field of view of the camera (metric texture coordinates from depth);
        used by the VAE's styled clips, the styled copies and LIBERO-Mixed.
      seg_classes: optional ``((group, (ids...)), ...)`` override of the segmentation id groups
        (groups: background, table, robot, objects, fixtures); empty = the renderer's default;
        used wherever ``fov_deg`` is.
    """

    enabled: bool = True
    intensity: float = 1.0
    styled_copies: int = 2
    mixed_fraction: float = 0.5
    fov_deg: float = 45.0
    seg_classes: tuple = ()

    def validate(self) -> None:
        if not 0.0 <= self.intensity <= 1.0:
            raise ValueError(f"augment.intensity must be in [0, 1], got {self.intensity}")
        if self.styled_copies < 0:
            raise ValueError(f"augment.styled_copies must be >= 0, got {self.styled_copies}")
        if not 0.0 <= self.mixed_fraction <= 1.0:
            raise ValueError(f"augment.mixed_fraction must be in [0, 1], got {self.mixed_fraction}")
        if not 5.0 <= self.fov_deg <= 170.0:
            raise ValueError(f"augment.fov_deg must be in [5, 170], got {self.fov_deg}")
        groups = {"background", "table", "robot", "objects", "fixtures"}
        for entry in self.seg_classes:
            if not (isinstance(entry, tuple) and len(entry) == 2 and entry[0] in groups):
                raise ValueError(f"augment.seg_classes entries must be (group in {sorted(groups)}, ids), got {entry!r}")
