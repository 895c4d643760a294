"""bench_start_latents: GRPO's start context latents against the whole episode's (tiny random VAE)."""

import jax
import numpy as np
import pytest
from flax import nnx

import configs
from benchmarks import bench_start_latents as bench
from sword_jax import cli


def test_only_the_prefix_encoding_is_the_whole_episodes_latent():
    from sword_jax.vae import api as vae_api

    cfg = configs.get("sword:tiny")
    vae_graphdef, vae_state = nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(1)))
    size = cfg.data.image_size
    frames = np.random.default_rng(0).integers(0, 256, (3, 30, size, size, 3), dtype=np.uint8)
    errors = bench.relative_errors(vae_graphdef, vae_state, frames, np.array([30, 30, 10]), [1, 2, 4, 9])
    assert sorted(errors) == [1, 2, 4]  # no episode reaches past frame 36
    assert errors[4]["prefix"].size == 2 and errors[1]["prefix"].size == 3
    for s, ways in errors.items():
        np.testing.assert_allclose(ways["prefix"], 0.0, atol=1e-3)
        assert ways["still"].min() > 0.01
    # the window is the episode's own first 9 frames at latent 2 only; before (frame 0 repeated) and after it is not
    np.testing.assert_allclose(errors[2]["window"], 0.0, atol=1e-3)
    assert errors[1]["window"].min() > 0.01 and errors[4]["window"].min() > 0.01
    rows = bench.summary(errors)
    assert [r["frame"] for r in rows] == [4, 8, 16] and rows[0]["episodes"] == 3
    assert rows[2]["window"]["max"] == pytest.approx(float(errors[4]["window"].max()))


def test_bad_command_lines_are_refused_by_name(tmp_path):
    base = ["--config", "sword:tiny", "--out", str(tmp_path / "o")]
    (tmp_path / "vae").mkdir()
    with pytest.raises(cli.UsageError, match="--latents"):
        bench.main(base + ["--vae", str(tmp_path / "vae"), "--episodes", "x.h5", "--latents", "0,2"])
    with pytest.raises(cli.UsageError, match="comma list"):
        bench.main(base + ["--vae", str(tmp_path / "vae"), "--episodes", "x.h5", "--latents", "a"])
    with pytest.raises(cli.UsageError, match="--episodes x.h5: no such file"):
        bench.main(base + ["--vae", str(tmp_path / "vae"), "--episodes", "x.h5"])
    with pytest.raises(cli.UsageError, match="--vae .*missing: no such folder"):
        bench.main(base + ["--vae", str(tmp_path / "missing"), "--episodes", "x.h5"])
    with pytest.raises(cli.UsageError, match="at least one --episodes"):
        bench.main(base + ["--vae", str(tmp_path / "vae")])
