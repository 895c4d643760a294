"""Sim section of the experiment config (owned by sim)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """LIBERO-Spatial-like MuJoCo environments."""

    backend: str = "cpu"  # cpu (MuJoCo C engine) | mjx
    resolution: int = 128
    episodes_per_task: int = 2
    tasks: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 8, 9)
    max_steps: int = 220
    settle_steps: int = 10
    expert_noise: float = 0.0
    wrist_camera: bool = False

    def validate(self) -> None:
        if self.backend not in ("cpu", "mjx"):
            raise ValueError(f"sim.backend must be cpu|mjx, got {self.backend!r}")
        if self.resolution % 16:
            raise ValueError(f"sim.resolution must be a multiple of 16, got {self.resolution}")
        for task in self.tasks:
            if not 0 <= task <= 9:
                raise ValueError(f"sim.tasks: task ids are 0-9, got {task}")
