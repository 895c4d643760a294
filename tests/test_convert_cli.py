"""``python -m train.convert_wan22 verify DIR``: passes on the reference, fails on corrupted copies."""

import os
import subprocess
import sys

import numpy as np
import pytest
from safetensors import safe_open
from safetensors.numpy import save_file

from sword_jax.convert import wan22
from train import convert_wan22

REF = "reference/wan22"


def _vae_copy(src: str, dst: str, *, perturb: str | None = None, truncate: bool = False) -> str:
    os.makedirs(dst, exist_ok=True)
    for name in ("vae_case.npz", "vae_latent_norm.npz"):
        os.symlink(os.path.join(src, name), os.path.join(dst, name))
    with safe_open(os.path.join(src, "vae_weights.safetensors"), framework="np") as handle:
        metadata = handle.metadata()
        tensors = {k: handle.get_tensor(k) for k in handle.keys()}
    if perturb is not None:
        tensors[perturb] = tensors[perturb] + np.float32(0.05)
    path = os.path.join(dst, "vae_weights.safetensors")
    save_file(tensors, path, metadata=metadata)
    if truncate:
        data = open(path, "rb").read()
        open(path, "wb").write(data[: len(data) // 2])
    return dst


@pytest.mark.slow  # 70 s on 2 cores; test_vae checks the same parity, the perturbed case below the command line
def test_verify_vae_reference_passes(shared_dir, tmp_path, capsys):
    good = _vae_copy(os.path.join(shared_dir, REF), str(tmp_path / "good"))
    assert convert_wan22.main(["verify", good]) == 0
    out = capsys.readouterr().out
    assert "vae_case:mu " in out and "vae_case:decoded " in out and "largest errors" in out
    assert "[wan22_dit] skipped" in out


@pytest.mark.slow
def test_verify_shared_dir_passes(shared_dir, capsys):
    """The whole shared directory: VAE and (when its converter exists) DiT cases."""
    assert convert_wan22.main(["verify", os.path.join(shared_dir, REF)]) == 0
    assert "vae_case:decoded " in capsys.readouterr().out


def test_verify_fails_on_perturbed_weight(shared_dir, tmp_path, capsys):
    bad = _vae_copy(os.path.join(shared_dir, REF), str(tmp_path / "bad"),
                    perturb="decoder.upsamples.1.upsamples.0.residual.2.bias")
    assert wan22.verify(bad) == 1
    out = capsys.readouterr()
    assert "FAIL" in out.out and "vae_case:decoded" in out.out
    assert "vae_case:mu " in out.out  # the encoder is untouched: mu still passes


def test_verify_fails_on_truncated_file(shared_dir, tmp_path, capsys):
    bad = _vae_copy(os.path.join(shared_dir, REF), str(tmp_path / "trunc"), truncate=True)
    assert wan22.verify(bad) == 1
    assert "cannot read safetensors" in capsys.readouterr().err


def test_verify_missing_or_empty_dir(tmp_path, capsys):
    assert convert_wan22.main(["verify", str(tmp_path / "nope")]) == 2
    assert "not found" in capsys.readouterr().err
    assert wan22.verify(str(tmp_path)) == 2
    assert "no reference cases" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_subprocess_exit_code(shared_dir):
    proc = subprocess.run([sys.executable, "-m", "train.convert_wan22", "verify", os.path.join(shared_dir, REF)],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
