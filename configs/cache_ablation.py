"""The paper's cache ablation: read schedule x replacement x scope (8 designs) + the WoVR baseline.

Variants: ``<schedule>-<replacement>-<scope>`` on the tiny base (e.g. ``linear-direct-all``),
``tf`` (teacher forcing, DLB off), ``wovr`` (teacher forcing + context noise, no augmentation),
and any of them with a ``small-`` prefix for the one-GPU base.
"""

from __future__ import annotations

import dataclasses
import itertools

from configs import sword
from configs.base import ExperimentConfig

SCHEDULES = ("linear", "warmup_cosine")
REPLACEMENTS = ("direct", "ema")
SCOPES = ("single", "all")
DESIGNS = tuple("-".join(c) for c in itertools.product(SCHEDULES, REPLACEMENTS, SCOPES))
VARIANTS = (*DESIGNS, "tf", "wovr")  # the eight DLB designs and the two teacher-forcing baselines


def _design(base: ExperimentConfig, design: str) -> ExperimentConfig:
    if design == "tf":
        return dataclasses.replace(base, name=f"{base.name}-tf", cache=dataclasses.replace(base.cache, enabled=False))
    if design == "wovr":
        return dataclasses.replace(
            base,
            name=f"{base.name}-wovr",
            cache=dataclasses.replace(base.cache, enabled=False),
            flow=dataclasses.replace(base.flow, context_noise=0.1),
            augment=dataclasses.replace(base.augment, enabled=False),
        )
    schedule, replacement, scope = design.split("-")
    cache = dataclasses.replace(base.cache, enabled=True, schedule=schedule, replacement=replacement, scope=scope)
    return dataclasses.replace(base, name=f"{base.name}-{design}", cache=cache)


def get(variant: str = "linear-direct-all") -> ExperimentConfig:
    size, _, design = variant.partition("-") if variant.startswith(("small-", "tiny-", "paper-")) else ("tiny", "", variant)
    if design not in VARIANTS:
        raise KeyError(f"cache_ablation: unknown variant {variant!r}; designs: {', '.join(VARIANTS)}")
    return _design(sword.get(size), design)
