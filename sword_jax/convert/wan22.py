"""Checks the Wan 2.2 converters against reference cases (the command line is ``python -m train.convert_wan22``).

:func:`verify` runs every reference case found in a directory (VAE when it has ``vae*`` files:
``vae*.npz`` with ``vae_weights.safetensors``; DiT when it has ``dit*`` files and
``sword_jax.convert.wan22_dit`` exists: its ``run_reference_cases``) through the JAX port in float32,
prints the largest absolute and relative error per output and returns the exit status

* 0 when every output is within tolerance (an output fails when both its max abs error and its
  max error relative to the reference's largest magnitude exceed ``tol``),
* 1 when an output is out of tolerance or a runner raised (corrupt file, config mismatch ...),
* 2 when the directory is missing or holds no reference cases.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import os
import sys
import traceback
from collections.abc import Callable

from sword_jax.convert import CaseResult


# Which files of a directory belong to which converter's format.
_FILE_PREFIX = {"wan22_vae": "vae", "wan22_dit": "dit"}


def _runners() -> list[tuple[str, Callable[[str], list[CaseResult]] | None, str | None]]:
    """(name, run_reference_cases or None, reason when unavailable)."""
    runners = []
    for name in ("wan22_vae", "wan22_dit"):
        module_name = f"sword_jax.convert.{name}"
        if importlib.util.find_spec(module_name) is None:
            runners.append((name, None, "module not present"))
            continue
        module = importlib.import_module(module_name)  # a broken module raises here: reported as failure
        runners.append((name, getattr(module, "run_reference_cases"), None))
    return runners


def _failed(result: CaseResult, tol: float) -> bool:
    if not (math.isfinite(result.max_abs) and math.isfinite(result.max_rel)):
        return True
    return result.max_abs > tol and result.max_rel > tol


def verify(ref_dir: str, tol: float = 1e-4) -> int:
    """Runs all reference cases of ``ref_dir``; prints a table; returns the exit code."""
    if not os.path.isdir(ref_dir):
        print(f"error: reference directory not found: {ref_dir}", file=sys.stderr)
        return 2
    results: list[CaseResult] = []
    errors: list[str] = []
    try:
        runners = _runners()
    except Exception as err:  # noqa: BLE001 - report any import failure of a converter
        traceback.print_exc()
        print(f"error: importing a converter failed: {err}", file=sys.stderr)
        return 1
    for name, run, reason in runners:
        prefix = _FILE_PREFIX[name]
        if run is not None and not any(f.startswith(prefix) for f in os.listdir(ref_dir)):
            run, reason = None, f"no {prefix}* files in {ref_dir}"
        if run is None:
            print(f"[{name}] skipped: {reason}")
            continue
        try:
            found = list(run(ref_dir))
        except Exception as err:  # noqa: BLE001 - corrupt inputs raise many error types
            errors.append(f"[{name}] {type(err).__name__}: {err}")
            continue
        print(f"[{name}] {len(found)} outputs compared")
        results.extend(found)
    if not results and not errors:
        print(f"error: no reference cases found in {ref_dir} (expected vae*.npz / dit*.npz with weights)",
              file=sys.stderr)
        return 2
    if results:
        width = max(len(f"{r.case}:{r.output}") for r in results)
        print(f"{'case:output'.ljust(width)}  {'shape':22s}  {'max_abs':>10s}  {'max_rel':>10s}  status")
        for r in results:
            status = "FAIL" if _failed(r, tol) else "ok"
            print(f"{f'{r.case}:{r.output}'.ljust(width)}  {str(r.shape):22s}  {r.max_abs:10.3e}  {r.max_rel:10.3e}  {status}")
        worst_abs = max(r.max_abs for r in results)
        worst_rel = max(r.max_rel for r in results)
        print(f"largest errors: abs {worst_abs:.3e}, rel {worst_rel:.3e} (tolerance {tol:g})")
    for line in errors:
        print(f"error: {line}", file=sys.stderr)
    failures = [r for r in results if _failed(r, tol)]
    if failures:
        print(f"FAILED: {len(failures)} of {len(results)} outputs above tolerance {tol:g}", file=sys.stderr)
    return 1 if failures or errors else 0
