"""Metric networks vs the reference PyTorch outputs (the command line is ``python -m train.verify_metrics DIR``).

Driven by ``DIR/manifest.json`` (see ``shared/reference/metrics/README.md``): for every network and
case listed there, the weight files are read with the torch-free reader, the inputs run through the
JAX networks / Frechet code, and every output array is compared as ``max|got - ref| / max|ref|``.
:func:`run` prints one line per output; an output fails when it exceeds the manifest's tolerance
(default 1e-4). Unknown networks in the manifest raise (nothing is silently skipped). Parity needs
float32 matmuls at full precision: the caller sets ``jax_default_matmul_precision`` to ``highest``.
"""

from __future__ import annotations

import json
import os
import time
from typing import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.reference_cases import CaseResult
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.flolpips import flow_weighted_lpips
from sword_jax.metrics.frechet import frechet_distance_from_features
from sword_jax.metrics.networks import build_i3d, build_inception, build_lpips
from sword_jax.metrics.preprocess import fvd_preprocess


def _nhwc(array: np.ndarray) -> jax.Array:
    """NCHW / NCTHW -> channels-last float32."""
    array = np.asarray(array).astype(np.float32)
    return jnp.asarray(np.moveaxis(array, 1, -1))


def _jit(module: nnx.Module, fn: Callable) -> Callable:
    graphdef, state = nnx.split(module)
    compiled = jax.jit(lambda state, *args: fn(nnx.merge(graphdef, state), *args))
    return lambda *args: compiled(state, *args)


def _lpips_cases(root: str, name: str, spec: dict) -> Iterator[CaseResult]:
    net = "vgg" if "vgg" in name else "alex"
    weights = spec["weights"]
    config = EvalConfig(lpips_net=net, lpips_weights=os.path.join(root, weights["backbone"]),
                        lpips_lin_weights=os.path.join(root, weights["lin"]))
    module = build_lpips(config).module
    forward = {flag: _jit(module, lambda m, a, b, flag=flag: m(a, b, normalize=flag)) for flag in (False, True)}
    for case in spec["cases"]:
        data = np.load(os.path.join(root, case["file"]))
        stem = f"{name}/{os.path.splitext(os.path.basename(case['file']))[0]}"
        total, res = forward[bool(data["normalize"])](_nhwc(data["in0"]), _nhwc(data["in1"]))
        got = {"lpips": total, **{f"res_{k}": r for k, r in enumerate(res)}}
        for out in case["outputs"]:
            yield CaseResult.compare(stem, out, np.reshape(np.asarray(got[out]), data[out].shape), data[out])
    flo = spec.get("flolpips")
    if flo:
        data = np.load(os.path.join(root, flo["file"]))
        score = _jit(module, flow_weighted_lpips)(_nhwc(data["frames_ref"]), _nhwc(data["frames_dis"]), _nhwc(data["flow_diff"]))
        for out in flo["outputs"]:
            yield CaseResult.compare(f"{name}/flolpips", out, score, data[out])


def _fid_cases(root: str, name: str, spec: dict) -> Iterator[CaseResult]:
    module = build_inception(EvalConfig(inception_weights=os.path.join(root, spec["weights"]["inception"]))).module
    forward = _jit(module, lambda m, x: m(x))
    for case in spec["cases"]:
        data = np.load(os.path.join(root, case["file"]))
        stem = f"{name}/{os.path.splitext(os.path.basename(case['file']))[0]}"
        got = {"pool3": forward(_nhwc(data["images"]))}
        for out in case["outputs"]:
            yield CaseResult.compare(stem, out, got[out], data[out])
    if spec.get("frechet"):
        data = np.load(os.path.join(root, spec["frechet"]))
        prefixes = sorted({k[: -len("_fd")] for k in data.files if k.endswith("_fd")})
        for prefix in prefixes:
            got = frechet_distance_from_features(data[f"{prefix}_act1"], data[f"{prefix}_act2"])
            yield CaseResult.compare(f"{name}/frechet", prefix, np.float64(got), data[f"{prefix}_fd"])


def _i3d_cases(root: str, name: str, spec: dict) -> Iterator[CaseResult]:
    module = build_i3d(EvalConfig(i3d_weights=os.path.join(root, spec["weights"]["i3d"]))).module
    forward = _jit(module, lambda m, x: {k: v for k, v in m.endpoints(x).items() if k in ("logits", "features")})
    for case in spec["cases"]:
        data = np.load(os.path.join(root, case["file"]))
        stem = f"{name}/{os.path.splitext(os.path.basename(case['file']))[0]}"
        if "video01" in data.files:
            clip = fvd_preprocess(_nhwc(data["video01"]))
        else:
            clip = _nhwc(data["clip_f16"])
        out = forward(clip)
        # ours (N, T', h, w, C) -> torch (N, C, T', h, w), then the reference's squeezes.
        got = {k: np.moveaxis(np.asarray(v), -1, 1) for k, v in out.items()}
        got["preprocessed_sample0_frame0"] = np.moveaxis(np.asarray(clip[0, 0]), -1, 0)
        got["preprocessed_sample0_frame_last"] = np.moveaxis(np.asarray(clip[0, -1]), -1, 0)
        for key in case["outputs"]:
            ref = data[key]
            if got[key].size != ref.size:
                raise ValueError(f"{stem}:{key}: got {got[key].shape}, reference {ref.shape}")
            yield CaseResult.compare(stem, key, got[key].reshape(ref.shape), ref)
    if spec.get("frechet"):
        data = np.load(os.path.join(root, spec["frechet"]))
        real, fake = data["feats_real"], data["feats_fake"]
        checks = {"fvd_stylegan_v": (fake, real, False), "fvd_unbiased_cov": (fake, real, True),
                  "fvd_common_metrics_styleganv": (fake, real, True), "fvd_stylegan_v_self": (real, real, False)}
        for key, (a, b, unbiased) in checks.items():
            if key in data.files:
                got = frechet_distance_from_features(a, b, unbiased=unbiased)
                if key.endswith("_self"):  # ~0: compare on the scale of the real distance
                    scale = float(data["fvd_stylegan_v"])
                    yield CaseResult(f"{name}/frechet", key, abs(got - float(data[key])), abs(got - float(data[key])) / scale, ())
                else:
                    yield CaseResult.compare(f"{name}/frechet", key, np.float64(got), data[key])


RUNNERS = {"lpips_alex": _lpips_cases, "lpips_vgg": _lpips_cases, "fid_inception": _fid_cases, "i3d": _i3d_cases}


def run(directory: str) -> tuple[list[CaseResult], float]:
    """Runs every case of ``directory``'s manifest; returns the results and the tolerance."""
    manifest_path = os.path.join(directory, "manifest.json")
    if not os.path.isfile(manifest_path):
        raise FileNotFoundError(f"no manifest.json in {directory}")
    with open(manifest_path) as f:
        manifest = json.load(f)
    tolerance = float(manifest.get("tolerance", {}).get("rel", 1e-4))
    unknown = sorted(set(manifest["networks"]) - set(RUNNERS))
    if unknown:
        raise ValueError(f"manifest lists networks this verifier does not know: {unknown}")
    results: list[CaseResult] = []
    for name, spec in manifest["networks"].items():
        start = time.time()
        for result in RUNNERS[name](directory, name, spec):
            results.append(result)
            flag = "ok  " if result.max_rel <= tolerance else "FAIL"
            print(f"{flag} {result.case:28s} {result.output:34s} max_abs={result.max_abs:.3e} max_rel={result.max_rel:.3e}", flush=True)
        print(f"     ({name}: {time.time() - start:.1f} s)", flush=True)
    return results, tolerance


def summary(results: list[CaseResult], tolerance: float) -> tuple[str, int]:
    """The closing line of a run (largest relative error, pass or fail) and how many outputs failed."""
    worst = max(results, key=lambda r: r.max_rel)
    failed = [r for r in results if not r.max_rel <= tolerance]
    line = (f"{len(results)} outputs, largest relative error {worst.max_rel:.3e} ({worst.case}:{worst.output}); "
            f"tolerance {tolerance:.0e}: {'FAILED ' + str(len(failed)) if failed else 'all passed'}")
    return line, len(failed)
