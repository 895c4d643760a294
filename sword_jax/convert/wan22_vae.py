"""Official Wan 2.2 VAE (``WanVAE_`` state dict) -> :class:`sword_jax.vae.model.WanVAE` state.

The key map is derived from the JAX module tree (each JAX parameter path has exactly one official
key), then checked both ways: a key missing from the file or an unexpected key in it is an error
naming the key, as is any shape mismatch. ``run_reference_cases`` runs the reference vectors
(``vae_*.npz`` with ``video``/``mu``) of a directory through the port and returns
:class:`sword_jax.convert.CaseResult` rows.
"""

from __future__ import annotations

import glob
import os
from typing import Any

import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.convert import CaseResult
from sword_jax.convert.safetensors_io import CheckpointError, read_config, read_safetensors, torch_to_jax_layout
from sword_jax.vae import api
from sword_jax.vae.config import VAEConfig
from sword_jax.vae.model import default_latent_stats, set_conv_impl

_RES_BLOCK = {"norm1": "residual.0", "conv1": "residual.2", "norm2": "residual.3", "conv2": "residual.6",
              "shortcut": "shortcut"}
_ATTN = {("norm", "gamma"): "norm.gamma", ("qkv_kernel",): "to_qkv.weight", ("qkv_bias",): "to_qkv.bias",
         ("proj_kernel",): "proj.weight", ("proj_bias",): "proj.bias"}
_LEAF = {"kernel": "weight", "bias": "bias", "gamma": "gamma"}


def config_from_official(official: dict[str, Any], *, compute_dtype: str = "float32") -> VAEConfig:
    """Maps ``WanVAE_`` constructor arguments (safetensors metadata ``config``) to a :class:`VAEConfig`."""
    required = ("dim", "z_dim", "dim_mult", "num_res_blocks", "temperal_downsample")
    missing = [k for k in required if k not in official]
    if missing:
        raise CheckpointError(f"VAE config lacks {missing} (got {sorted(official)})")
    if official.get("attn_scales", []):
        raise CheckpointError(f"VAE attn_scales {official['attn_scales']} unsupported (Wan 2.2 uses [])")
    cfg = VAEConfig(
        z_dim=int(official["z_dim"]),
        dim=int(official["dim"]),
        dec_dim=int(official.get("dec_dim", 256)),  # the class default; the wrapper never passes it
        dim_mult=tuple(int(m) for m in official["dim_mult"]),
        num_res_blocks=int(official["num_res_blocks"]),
        temporal_downsample=tuple(bool(t) for t in official["temperal_downsample"]),
        compute_dtype=compute_dtype,
    )
    cfg.validate()
    return cfg


def _official_key(path: tuple, cfg: VAEConfig) -> str:
    """The official state-dict key of one JAX parameter path."""
    names = [str(p) for p in path]

    def res_block(prefix: str, rest: list[str]) -> str:
        return f"{prefix}{_RES_BLOCK[rest[0]]}.{_LEAF[rest[1]]}"

    def resample(prefix: str, rest: list[str]) -> str:
        if rest[0] == "time_conv":
            return f"{prefix}time_conv.{_LEAF[rest[1]]}"
        return f"{prefix}resample.1.{'weight' if rest[0] == 'conv_kernel' else 'bias'}"

    def middle(prefix: str, rest: list[str]) -> str:
        if rest[0] == "attn":
            return f"{prefix}1.{_ATTN[tuple(rest[1:])]}"
        return res_block(f"{prefix}{0 if rest[0] == 'res0' else 2}.", rest[1:])

    def coder(side: str, rest: list[str]) -> str:
        group, blocks = ("downsamples", cfg.num_res_blocks) if side == "encoder" else ("upsamples", cfg.num_res_blocks + 1)
        head = rest[0]
        if head == "conv1":
            return f"{side}.conv1.{_LEAF[rest[1]]}"
        if head == "middle":
            return middle(f"{side}.middle.", rest[1:])
        if head == "head_norm":
            return f"{side}.head.0.gamma"
        if head == "head_conv":
            return f"{side}.head.2.{_LEAF[rest[1]]}"
        if head == group:
            level = rest[1]
            if rest[2] == group:
                return res_block(f"{side}.{group}.{level}.{group}.{rest[3]}.", rest[4:])
            if rest[2] == "resample":
                return resample(f"{side}.{group}.{level}.{group}.{blocks}.", rest[3:])
        raise KeyError(".".join(names))

    if names[0] in ("encoder", "decoder"):
        return coder(names[0], names[1:])
    if names[0] in ("conv1", "conv2"):
        return f"{names[0]}.{_LEAF[names[1]]}"
    raise KeyError(".".join(names))


def key_map(cfg: VAEConfig) -> dict[str, tuple]:
    """Official key -> JAX parameter path, for every parameter of the VAE built from ``cfg``."""
    params = nnx.state(api.abstract_vae(cfg), nnx.Param)
    mapping = {}
    for path, _ in nnx.to_flat_state(params):
        mapping[_official_key(tuple(path), cfg)] = tuple(path)
    return mapping


def convert_state_dict(
    tensors: dict[str, np.ndarray], cfg: VAEConfig, *, latent_mean=None, latent_inv_std=None,
) -> tuple[nnx.GraphDef, nnx.State]:
    """Official ``WanVAE_`` tensors -> ``(graphdef, state)`` of :class:`WanVAE` (float32).

    Args:
      tensors: official key -> numpy array (PyTorch layouts).
      cfg: the architecture (see :func:`config_from_official`).
      latent_mean, latent_inv_std: per-channel normalisation (default: the module's, i.e. the
        official Wan 2.2 constants when ``z_dim == 48``).

    Raises:
      CheckpointError: missing/unexpected keys or shape mismatches, each named.
    """
    graphdef, abstract = nnx.split(api.abstract_vae(cfg))
    mapping = key_map(cfg)
    missing = sorted(set(mapping) - set(tensors))
    unexpected = sorted(set(tensors) - set(mapping))
    if missing or unexpected:
        raise CheckpointError(
            f"VAE state dict does not match the config {cfg}: missing {missing[:8]}"
            f"{'...' if len(missing) > 8 else ''} ({len(missing)}), unexpected {unexpected[:8]}"
            f"{'...' if len(unexpected) > 8 else ''} ({len(unexpected)})"
        )
    by_path = {path: key for key, path in mapping.items()}
    flat = []
    for path, variable in nnx.to_flat_state(abstract):
        path = tuple(path)
        if path in by_path:
            key = by_path[path]
            value = torch_to_jax_layout(key, tensors[key], tuple(variable.shape)).astype(np.float32)
            if not np.isfinite(value).all():
                raise CheckpointError(f"{key}: contains NaN/Inf")
        elif path[-1] == "latent_mean" and latent_mean is not None:
            value = _stat("latent_mean", latent_mean, variable.shape)
        elif path[-1] == "latent_inv_std" and latent_inv_std is not None:
            value = _stat("latent_inv_std", latent_inv_std, variable.shape)
        else:
            value = None  # a non-parameter keeps the module's default (filled below)
        flat.append((path, variable, value))
    default_mean, default_inv_std = default_latent_stats(cfg.z_dim)
    values = []
    for path, variable, value in flat:
        if value is None:
            value = default_mean if path[-1] == "latent_mean" else default_inv_std
        values.append((path, variable.replace(jnp.asarray(value))))
    return graphdef, nnx.from_flat_state(values)


def _stat(name: str, value, shape) -> np.ndarray:
    array = np.asarray(value, np.float32).reshape(-1)
    if array.shape != tuple(shape):
        raise CheckpointError(f"{name}: {array.shape} values, the VAE has {tuple(shape)} latent channels")
    return array


def load_vae(
    path: str, *, latent_norm_path: str | None = None, compute_dtype: str = "float32",
) -> tuple[nnx.GraphDef, nnx.State, VAEConfig]:
    """Loads an official-format VAE safetensors file (config in metadata) -> ``(graphdef, state, cfg)``.

    ``latent_norm_path``: optional npz with ``mean`` and ``inv_std`` (or ``std``) arrays.
    """
    tensors, metadata = read_safetensors(path)
    cfg = config_from_official(read_config(metadata, path), compute_dtype=compute_dtype)
    mean = inv_std = None
    if latent_norm_path:
        with np.load(latent_norm_path) as norm:
            mean = norm["mean"]
            inv_std = norm["inv_std"] if "inv_std" in norm else np.float32(1) / norm["std"].astype(np.float32)
    graphdef, state = convert_state_dict(tensors, cfg, latent_mean=mean, latent_inv_std=inv_std)
    return graphdef, state, cfg


def _to_torch_layout(x) -> np.ndarray:
    return np.moveaxis(np.asarray(x), -1, 1)  # [B, T, H, W, C] -> [B, C, T, H, W]


def _find_weights(ref_dir: str) -> str:
    preferred = os.path.join(ref_dir, "vae_weights.safetensors")
    if os.path.isfile(preferred):
        return preferred
    found = sorted(glob.glob(os.path.join(ref_dir, "vae*.safetensors")))
    if len(found) != 1:
        raise CheckpointError(f"{ref_dir}: expected one vae*.safetensors weights file, found {found}")
    return found[0]


def case_files(ref_dir: str) -> list[str]:
    """The VAE reference case files of ``ref_dir``: ``vae*.npz`` holding ``video`` and ``mu``."""
    cases = []
    for path in sorted(glob.glob(os.path.join(ref_dir, "vae*.npz"))):
        try:
            with np.load(path) as data:
                if "video" in data.files and "mu" in data.files:
                    cases.append(path)
        except Exception as err:  # noqa: BLE001
            raise CheckpointError(f"cannot read reference case {path}: {err}") from err
    return cases


def run_reference_cases(ref_dir: str, *, causal_conv: str = "conv3d", upsample: str = "repeat") -> list[CaseResult]:
    """Runs every VAE reference case of ``ref_dir`` through the JAX port (float32).

    ``causal_conv`` / ``upsample`` pick the convolution forms (``VAEConfig``'s fields of those names).

    Compares ``mu``, ``decoded`` (unclamped decode of the stored ``mu``), ``mu_first_frame_only``,
    ``decoded_first_chunk``, every stored intermediate, and the streaming path (encode in chunks
    1, 4, 4, ...; decode one latent at a time) against ``mu``/``decoded``.
    """
    cases = case_files(ref_dir)
    if not cases:
        return []
    norm_path = os.path.join(ref_dir, "vae_latent_norm.npz")
    graphdef, state, _ = load_vae(_find_weights(ref_dir), latent_norm_path=norm_path if os.path.isfile(norm_path) else None)
    if (causal_conv, upsample) != ("conv3d", "repeat"):
        model = nnx.merge(graphdef, state)
        set_conv_impl(model, causal_conv=causal_conv, upsample=upsample)
        graphdef, state = nnx.split(model)
    results: list[CaseResult] = []
    for path in cases:
        name = os.path.splitext(os.path.basename(path))[0]
        with np.load(path) as data:
            ref = {k: data[k] for k in data.files}
        results.extend(_run_case(name, ref, graphdef, state))
    return results


def _run_case(name: str, ref: dict[str, np.ndarray], graphdef, state) -> list[CaseResult]:
    video = jnp.asarray(np.moveaxis(ref["video"], 1, -1), jnp.float32)  # (B, T, H, W, 3)
    latents_ref = jnp.asarray(np.moveaxis(ref["mu"], 1, -1), jnp.float32)
    outputs: dict[str, Any] = {
        "mu": api.encode(graphdef, state, video, check_values=False),
        "decoded": api.decode(graphdef, state, latents_ref, check_values=False),
    }
    if "mu_first_frame_only" in ref:
        outputs["mu_first_frame_only"] = api.encode(graphdef, state, video[:, :1], check_values=False)
    if "decoded_first_chunk" in ref:
        outputs["decoded_first_chunk"] = api.decode(graphdef, state, latents_ref[:, :1], check_values=False)
    taps = api.reference_taps(graphdef, state, video, latents_ref)
    outputs.update({k: v for k, v in taps.items() if k in ref})
    results = [CaseResult.compare(name, key, _to_torch_layout(value), ref[key]) for key, value in outputs.items()]
    results.extend(_streaming_results(name, ref, graphdef, state, video, latents_ref))
    return results


def _streaming_results(name, ref, graphdef, state, video, latents_ref) -> list[CaseResult]:
    b, t, h, w, _ = video.shape
    cache = api.init_encode_cache(graphdef, state, b, h, w)
    pieces, start = [], 0
    for stop in [1, *range(5, t + 1, 4)]:
        latents, cache = api.encode_chunk(graphdef, state, video[:, start:stop], cache, check_values=False)
        pieces.append(latents)
        start = stop
    mu_streamed = jnp.concatenate(pieces, axis=1)
    cache = api.init_decode_cache(graphdef, state, b, latents_ref.shape[2], latents_ref.shape[3])
    frames = []
    for i in range(latents_ref.shape[1]):
        out, cache = api.decode_chunk(graphdef, state, latents_ref[:, i:i + 1], cache, check_values=False)
        frames.append(out)
    decoded_streamed = jnp.concatenate(frames, axis=1)
    return [
        CaseResult.compare(name, "mu[streamed 1,4,4..]", _to_torch_layout(mu_streamed), ref["mu"]),
        CaseResult.compare(name, "decoded[streamed 1 latent/chunk]", _to_torch_layout(decoded_streamed), ref["decoded"]),
    ]

