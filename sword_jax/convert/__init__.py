"""Converters from official Wan 2.2 PyTorch checkpoints to sword-jax states, and reference checks.

Submodules:
  ``safetensors_io``: reading safetensors files (tensors as numpy, the ``config`` metadata JSON).
  ``wan22_vae``: official ``WanVAE_`` state dict -> :mod:`sword_jax.vae` state; VAE reference cases.
  ``wan22_dit``: official ``WanModel`` state dict -> :mod:`sword_jax.dit` state; DiT reference cases.
  ``wan22``: every converter's reference cases of a directory, checked and tabulated (the command
    line ``python -m train.convert_wan22 verify DIR``).

Every ``run_reference_cases(ref_dir)`` returns a list of :class:`CaseResult`, one per compared
output array (:mod:`sword_jax.reference_cases`), so ``wan22`` can print and threshold them uniformly.
"""

from __future__ import annotations

from sword_jax.reference_cases import CaseResult

__all__ = ["CaseResult"]
