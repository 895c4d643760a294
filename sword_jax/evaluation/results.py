"""Evaluation results: metrics per split and model, overall and against horizon."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass
class ModelResult:
    """One model on one split.

    Attributes:
      overall: metric name -> value over the whole horizon.
      curves: metric name -> ``Curve.to_dict()`` (frames, mean, stderr) against horizon.
    """

    overall: dict[str, float]
    curves: dict[str, dict]


@dataclasses.dataclass
class EvalResults:
    """Everything the report shows.

    Attributes:
      metrics: metric names in display order.
      models: ``{split: {model: ModelResult}}``.
      random_weight_networks: metric networks that ran with random weights (the report says so).
      weights: metric network -> weight source.
      settings: free-form settings shown in ``results.json`` (horizon, episodes, seeds).
      vae_floor: ``{split: ModelResult}``, the VAE's encode-decode of the ground truth scored like a
        prediction (:mod:`sword_jax.evaluation.vae_floor`): the error no world model can go below.
      timing: seconds per evaluation stage (``rollout_s``, ``vae_floor_s``, ``metrics_s``,
        ``report_s``, ``total_s``).
    """

    metrics: tuple[str, ...]
    models: dict[str, dict[str, ModelResult]]
    random_weight_networks: list[str] = dataclasses.field(default_factory=list)
    weights: dict[str, str] = dataclasses.field(default_factory=dict)
    settings: dict = dataclasses.field(default_factory=dict)
    vae_floor: dict[str, ModelResult] = dataclasses.field(default_factory=dict)
    timing: dict[str, float] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "metrics": list(self.metrics),
            "random_weight_networks": self.random_weight_networks,
            "weights": self.weights,
            "settings": self.settings,
            "models": {split: {m: dataclasses.asdict(r) for m, r in per.items()} for split, per in self.models.items()},
            "vae_floor": {split: dataclasses.asdict(r) for split, r in self.vae_floor.items()},
            "timing": {name: round(float(seconds), 2) for name, seconds in self.timing.items()},
        }
