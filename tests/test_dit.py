"""WanDiT parity with the official Wan 2.2 TI2V model (reference vectors) and converter checks."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import sword_jax
from sword_jax.convert import wan22_dit
from sword_jax.dit.layers import rope_split, rope_table, timestep_sinusoid


def _ref(shared_dir):
    return os.path.join(shared_dir, "reference", "wan22")


@pytest.fixture(scope="module")
def reference_results(shared_dir):
    return wan22_dit.run_reference_cases(_ref(shared_dir))


def test_reference_cases_match_official(reference_results):
    by_name = {(r.case, r.output): r for r in reference_results}
    # every case's final outputs and the key intermediates are compared
    for case in ("dit_ti2v_i2v", "dit_ti2v_t2v", "dit_batch2_padded"):
        for output in ("out_0", "time_emb", "block0_out", "head_out"):
            assert (case, output) in by_name, f"{case}:{output} not compared"
    assert ("dit_batch2_padded", "out_1") in by_name
    for output in ("sinusoid", "time_proj", "text_emb", "tokens_in", "patch_embed_0", "block1_out",
                   "block0_sa_q_roped", "block0_sa_k_roped", "block0_sa_attn", "block0_cross_attn_out"):
        assert ("dit_ti2v_i2v", output) in by_name, output
    for result in reference_results:
        assert result.max_abs < 1e-4, result
    # the sinusoid is float64-accurate (plain float32 would be off by ~5e-6 here)
    assert by_name[("dit_ti2v_i2v", "sinusoid")].max_abs < 1e-6
    assert by_name[("dit_rope_freqs", "freqs_real_imag")].max_abs < 1e-12


def test_rope_split_and_table(shared_dir):
    assert rope_split(128) == (22, 21, 21)  # TI2V-5B: 44/42/42 real dims
    assert rope_split(16) == (4, 2, 2)
    with np.load(os.path.join(_ref(shared_dir), "dit_rope_freqs.npz")) as data:
        ref, split = data["freqs_real_imag"], data["split"]
    assert tuple(split) == rope_split(2 * ref.shape[1])
    table = rope_table(2 * ref.shape[1])[: ref.shape[0]]
    np.testing.assert_allclose(np.stack([table.real, table.imag], -1), ref, atol=1e-12)


def test_sinusoid_matches_float64():
    t = np.concatenate([np.linspace(0, 1000, 97), [999.75, 250.5, 731.25, 1.0e-3]]).astype(np.float32)
    half = 128
    omega = np.power(10000.0, -np.arange(half) / half)
    angle = t.astype(np.float64)[:, None] * omega
    ref = np.concatenate([np.cos(angle), np.sin(angle)], axis=1)
    ours = np.asarray(jax.jit(lambda x: timestep_sinusoid(x, 256))(jnp.asarray(t)))
    assert np.abs(ours - ref).max() < 2e-6
    naive = np.asarray(jnp.concatenate([jnp.cos(t[:, None] * omega.astype(np.float32)),
                                        jnp.sin(t[:, None] * omega.astype(np.float32))], 1))
    assert np.abs(naive - ref).max() > 1e-5  # the compensated path is what buys the accuracy


def test_frame_timestep_call_matches_per_token_reference(shared_dir):
    """WanDiT.__call__ (one t per latent frame, grouped modulation) reproduces the i2v case."""
    cfg, graphdef, state = wan22_dit.load_official(
        os.path.join(_ref(shared_dir), "dit_weights.safetensors"), compute_dtype="float32")
    with np.load(os.path.join(_ref(shared_dir), "dit_ti2v_i2v.npz")) as data:
        x, context, out, t = data["x_0"], data["context_0"], data["out_0"], data["t"]
    grid = (x.shape[1], x.shape[2] // 2, x.shape[3] // 2)
    frame_t = t.reshape(1, *grid)[:, :, 0, 0]  # (1, F): 0 for the clean first frame
    assert frame_t[0, 0] == 0 and frame_t[0, 1] > 0
    latents = jnp.asarray(x).transpose(1, 2, 3, 0)[None]
    fn = jax.jit(lambda s, *a: nnx.merge(graphdef, s)(*a))
    ours = fn(state, latents, jnp.asarray(frame_t), jnp.asarray(context)[None])
    np.testing.assert_allclose(np.asarray(ours[0]).transpose(3, 0, 1, 2), out, atol=1e-4, rtol=1e-4)
    assert ours.shape == (1, x.shape[1], x.shape[2], x.shape[3], 48)


def _write(path, tensors, config):
    from safetensors.numpy import save_file

    save_file(tensors, str(path), metadata={"config": json.dumps(config)})


@pytest.fixture(scope="module")
def official(shared_dir):
    return wan22_dit.read_safetensors(os.path.join(_ref(shared_dir), "dit_weights.safetensors"))


def test_load_official_layouts(official):
    tensors, metadata = official
    path_cfg = json.loads(metadata["config"])
    flat = wan22_dit.official_to_state(tensors, wan22_dit.config_from_official(path_cfg))
    q = tensors["blocks.1.self_attn.q.weight"]
    np.testing.assert_array_equal(flat[("blocks", "self_attn", "q", "kernel")][1], q.T)
    conv = tensors["patch_embedding.weight"]  # (dim, c, pt, ph, pw)
    np.testing.assert_array_equal(flat[("patch_kernel",)][0, 1, 0, 5], conv[:, 5, 0, 1, 0])
    np.testing.assert_array_equal(flat[("blocks", "modulation")][0], tensors["blocks.0.modulation"][0])


def test_converter_rejects_bad_checkpoints(official, tmp_path):
    tensors, metadata = official
    config = json.loads(metadata["config"])
    missing = {k: v for k, v in tensors.items() if k != "blocks.1.ffn.0.bias"}
    _write(tmp_path / "missing.safetensors", missing, config)
    with pytest.raises(KeyError, match="blocks.1.ffn.0.bias"):
        wan22_dit.load_official(str(tmp_path / "missing.safetensors"))
    _write(tmp_path / "fewer_layers.safetensors", tensors, dict(config, num_layers=1))
    with pytest.raises(ValueError, match="beyond num_layers"):
        wan22_dit.load_official(str(tmp_path / "fewer_layers.safetensors"))
    wrong = dict(tensors, **{"head.modulation": np.zeros((1, 3, config["dim"]), np.float32)})
    _write(tmp_path / "wrong.safetensors", wrong, config)
    with pytest.raises(ValueError, match="head.modulation"):
        wan22_dit.load_official(str(tmp_path / "wrong.safetensors"))
    _write(tmp_path / "window.safetensors", tensors, dict(config, window_size=[4, 4]))
    with pytest.raises(ValueError, match="window_size"):
        wan22_dit.load_official(str(tmp_path / "window.safetensors"))
    (tmp_path / "corrupt.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="corrupt.safetensors"):
        wan22_dit.load_official(str(tmp_path / "corrupt.safetensors"))


def test_load_released_directory_with_bf16_shards(official, tmp_path):
    """A released checkpoint layout: config.json + several safetensors shards, bf16 tensors."""
    import ml_dtypes
    from safetensors.numpy import save_file

    tensors, metadata = official
    keys = sorted(tensors)
    half = len(keys) // 2
    for i, part in enumerate((keys[:half], keys[half:])):
        save_file({k: tensors[k].astype(ml_dtypes.bfloat16) for k in part},
                  str(tmp_path / f"diffusion_pytorch_model-0000{i + 1}-of-00002.safetensors"))
    config = dict(json.loads(metadata["config"]), _class_name="WanModel")
    (tmp_path / "config.json").write_text(json.dumps(config))
    cfg, _, state = wan22_dit.load_official(str(tmp_path))
    assert cfg.dim == config["dim"] and cfg.num_layers == config["num_layers"]
    kernel = state["blocks"]["ffn_0"]["kernel"].get_value()
    assert kernel.dtype == jnp.float32
    ref = tensors["blocks.1.ffn.0.weight"].T
    np.testing.assert_allclose(np.asarray(kernel[1]), ref, rtol=1e-2, atol=1e-2)
    (tmp_path / "config.json").unlink()
    with pytest.raises(sword_jax.CheckpointError, match="config.json"):  # the one checkpoint error type
        wan22_dit.load_official(str(tmp_path))


def test_runner_detects_cases_by_content(shared_dir, tmp_path):
    """Cases are found by their arrays, not file names; a lone padded sample with its own grid works."""
    import shutil

    ref = _ref(shared_dir)
    shutil.copy(os.path.join(ref, "dit_weights.safetensors"), tmp_path / "dit_model.safetensors")
    with np.load(os.path.join(ref, "dit_batch2_padded.npz")) as data:
        np.savez(tmp_path / "dit_single_padded.npz", x_0=data["x_1"], context_0=data["context_1"],
                 out_0=data["out_1"], t=data["t"][1:], seq_len=data["seq_len"], seq_lens=data["seq_lens"][1:],
                 grid_sizes=data["grid_sizes"][1:], time_emb=data["time_emb"][1:])
    results = wan22_dit.run_reference_cases(str(tmp_path))
    assert {r.output for r in results} == {"out_0", "time_emb"}
    assert all(r.max_abs < 1e-4 for r in results), results
