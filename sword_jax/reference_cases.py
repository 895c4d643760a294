"""Comparing a port's outputs with the outputs of the reference implementation it ports.

The converters (:mod:`sword_jax.convert`) and the metric networks' check (:mod:`sword_jax.metrics.verify`)
report one :class:`CaseResult` per compared output array, so their command lines
(``train.convert_wan22``, ``train.verify_metrics``) print and threshold them the same way.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class CaseResult:
    """Comparison of one output of one reference case against the JAX port.

    Attributes:
      case: the case name, e.g. ``"vae_case"`` or ``"dit_ti2v_i2v"`` (file stem).
      output: the array compared, e.g. ``"mu"`` or ``"out_0"``.
      max_abs: largest absolute difference ``max |ours - ref|``.
      max_rel: largest difference relative to the reference's scale,
        ``max |ours - ref| / max(max |ref|, 1e-6)``.
      shape: the compared array's shape.
    """

    case: str
    output: str
    max_abs: float
    max_rel: float
    shape: tuple[int, ...]

    @staticmethod
    def compare(case: str, output: str, ours, ref) -> "CaseResult":
        """Builds a result from two arrays of the same shape (numpy or jax, any float dtype)."""
        import numpy as np

        ours_np = np.asarray(ours, dtype=np.float64)
        ref_np = np.asarray(ref, dtype=np.float64)
        if ours_np.shape != ref_np.shape:
            raise ValueError(f"{case}:{output}: shape {ours_np.shape} differs from reference {ref_np.shape}")
        diff = np.abs(ours_np - ref_np)
        max_abs = float(diff.max()) if diff.size else 0.0
        if not np.isfinite(ours_np).all():
            max_abs = float("inf")
        scale = max(float(np.abs(ref_np).max()) if ref_np.size else 0.0, 1e-6)
        return CaseResult(case, output, max_abs, max_abs / scale, tuple(ref_np.shape))
