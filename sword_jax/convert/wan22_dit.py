"""Official Wan 2.2 ``WanModel`` (TI2V) checkpoints -> :class:`sword_jax.dit.model.WanDiT` state.

* ``load_official(path)`` reads a safetensors file with the official ``state_dict()`` key names and
  the constructor config JSON in its metadata field ``config``; Linear ``[out, in]`` kernels are
  transposed to ``[in, out]``, the Conv3d patch embedding ``[dim, c, pt, ph, pw]`` becomes
  channels-last ``(pt, ph, pw, c, dim)``, and per-block keys ``blocks.N.*`` are stacked on the
  leading ``layers`` axis of the scanned block parameters.
* ``load_official_into_world_model(path, cfg)``: a :class:`sword_jax.dit.action_dit.WorldModel`
  whose DiT is the official checkpoint and whose action branches are fresh.
* ``run_reference_cases(ref_dir)`` runs every ``dit_*.npz`` case of a reference directory (the
  official model's inputs, outputs and intermediates) through the port and compares.
"""

from __future__ import annotations

import glob
import json
import os
import re
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.convert import CaseResult
from sword_jax.convert.safetensors_io import CheckpointError, read_config, read_safetensors
from sword_jax.dit.action_dit import ARCH_FIELDS, ActionConditioner, WorldModel
from sword_jax.dit.config import DiTConfig
from sword_jax.dit.layers import timestep_sinusoid
from sword_jax.dit.model import WanDiT

_CONFIG_FIELDS = ("in_dim", "out_dim", "dim", "ffn_dim", "freq_dim", "num_heads", "num_layers", "text_dim",
                  "text_len", "eps", "qk_norm", "cross_attn_norm")

# Official key (with N for the block index) -> JAX path, and the layout change.
_LINEARS = {
    "text_embedding.0": ("text_embedding_0",),
    "text_embedding.2": ("text_embedding_2",),
    "time_embedding.0": ("time_embedding_0",),
    "time_embedding.2": ("time_embedding_2",),
    "time_projection.1": ("time_projection",),
    "head.head": ("head",),
}
_BLOCK_LINEARS = {f"{a}.{p}": (a, p) for a in ("self_attn", "cross_attn") for p in "qkvo"}
_BLOCK_LINEARS.update({"ffn.0": ("ffn_0",), "ffn.2": ("ffn_2",)})


def read_checkpoint(path: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Official tensors and constructor config from a file or a checkpoint directory.

    Args:
      path: a safetensors file whose metadata holds the config JSON under ``config``, or a
        directory as released (``config.json`` + ``*.safetensors`` shards, e.g. Wan2.2-TI2V-5B).

    Returns:
      ``(tensors, config)``; tensors keep their stored dtype (bf16 included).
    """
    if os.path.isdir(path):
        config_path = os.path.join(path, "config.json")
        if not os.path.isfile(config_path):
            raise CheckpointError(f"{path}: checkpoint directory has no config.json")
        with open(config_path) as f:
            config = json.load(f)
        shards = sorted(glob.glob(os.path.join(path, "*.safetensors")))
        if not shards:
            raise CheckpointError(f"{path}: checkpoint directory has no *.safetensors files")
        tensors: dict[str, np.ndarray] = {}
        for shard in shards:
            part, _ = read_safetensors(shard)
            duplicated = set(part) & set(tensors)
            if duplicated:
                raise CheckpointError(f"{shard}: keys also in another shard: {sorted(duplicated)[:4]}")
            tensors.update(part)
        return tensors, config
    tensors, metadata = read_safetensors(path)
    return tensors, read_config(metadata, path)


def config_from_official(official: dict[str, Any], **overrides: Any) -> DiTConfig:
    """Maps the official ``WanModel`` constructor arguments onto a :class:`DiTConfig`."""
    model_type = official.get("model_type", "ti2v")
    if model_type not in ("ti2v", "t2v"):
        raise CheckpointError(f"config: model_type {model_type!r} is not supported (only ti2v / t2v, no image embedding)")
    window = tuple(official.get("window_size", (-1, -1)))
    if window != (-1, -1):
        raise CheckpointError(f"config: window_size {window} is not supported (only global attention (-1, -1))")
    missing = [k for k in _CONFIG_FIELDS + ("patch_size",) if k not in official]
    if missing:
        raise CheckpointError(f"config: official config lacks {missing}")
    fields = {k: official[k] for k in _CONFIG_FIELDS}
    fields["eps"] = float(fields["eps"])
    fields["patch_size"] = tuple(int(p) for p in official["patch_size"])
    fields.update(overrides)
    cfg = DiTConfig(**fields)
    cfg.validate()
    return cfg


def official_to_state(tensors: dict[str, np.ndarray], cfg: DiTConfig) -> dict[tuple[str, ...], np.ndarray]:
    """Official state dict -> flat ``{jax path: array}`` of the :class:`WanDiT` parameters."""
    flat: dict[tuple[str, ...], np.ndarray] = {}
    used: set[str] = set()

    def take(key: str) -> np.ndarray:
        if key not in tensors:
            raise KeyError(f"official checkpoint lacks {key!r}")
        used.add(key)
        return np.asarray(tensors[key], np.float32)

    weight = take("patch_embedding.weight")  # (dim, c, pt, ph, pw)
    flat[("patch_kernel",)] = weight.transpose(2, 3, 4, 1, 0)
    flat[("patch_bias",)] = take("patch_embedding.bias")
    for key, path in _LINEARS.items():
        flat[path + ("kernel",)] = take(f"{key}.weight").T
        flat[path + ("bias",)] = take(f"{key}.bias")
    flat[("head_modulation",)] = _table(take("head.modulation"), "head.modulation", 2, cfg.dim)

    per_block: dict[tuple[str, ...], list[np.ndarray]] = {}
    for n in range(cfg.num_layers):
        entries = {}
        for key, path in _BLOCK_LINEARS.items():
            entries[path + ("kernel",)] = take(f"blocks.{n}.{key}.weight").T
            entries[path + ("bias",)] = take(f"blocks.{n}.{key}.bias")
        if cfg.qk_norm:
            for attn in ("self_attn", "cross_attn"):
                for norm in ("norm_q", "norm_k"):
                    entries[(attn, norm, "scale")] = take(f"blocks.{n}.{attn}.{norm}.weight")
        if cfg.cross_attn_norm:
            entries[("norm3", "scale")] = take(f"blocks.{n}.norm3.weight")
            entries[("norm3", "bias")] = take(f"blocks.{n}.norm3.bias")
        entries[("modulation",)] = _table(take(f"blocks.{n}.modulation"), f"blocks.{n}.modulation", 6, cfg.dim)
        for path, value in entries.items():
            per_block.setdefault(path, []).append(value)
    for path, values in per_block.items():
        flat[("blocks",) + path] = np.stack(values)

    unused = sorted(set(tensors) - used)
    if unused:
        extra_blocks = sorted({m.group(1) for k in unused if (m := re.match(r"blocks\.(\d+)\.", k))}, key=int)
        hint = f" (blocks {extra_blocks} beyond num_layers={cfg.num_layers})" if extra_blocks else ""
        raise CheckpointError(f"official checkpoint has {len(unused)} keys the port does not use{hint}: {unused[:8]}")
    return flat


def _table(value: np.ndarray, key: str, slots: int, dim: int) -> np.ndarray:
    """A ``[1, slots, dim]`` modulation table as ``[slots, dim]``."""
    if value.shape != (1, slots, dim):
        raise CheckpointError(f"{key}: expected shape (1, {slots}, {dim}), got {value.shape}")
    return value[0]


def fill_state(state: nnx.State, flat: dict[tuple[str, ...], np.ndarray], *, strict: bool = True) -> nnx.State:
    """Returns ``state`` with the arrays of ``flat`` put in; shapes must match exactly.

    With ``strict`` every parameter of ``state`` must be provided; otherwise missing ones keep
    their (fresh) values.
    """
    pure = nnx.to_pure_dict(state)
    targets = dict(nnx.to_flat_state(state))
    missing = [p for p in targets if p not in flat]
    if strict and missing:
        raise CheckpointError(f"converted checkpoint lacks parameters {missing[:8]}")
    for path, value in flat.items():
        if path not in targets:
            raise CheckpointError(f"converted parameter {'.'.join(path)} has no place in the JAX model")
        target = targets[path]
        shape = tuple(target.get_value().shape)
        if tuple(value.shape) != shape:
            raise CheckpointError(f"parameter {'.'.join(path)}: checkpoint shape {value.shape} != model shape {shape}")
        node = pure
        for part in path[:-1]:
            node = node[part]
        node[path[-1]] = jnp.asarray(value, target.get_value().dtype)
    nnx.replace_by_pure_dict(state, pure)
    return state


def load_official(path: str, **overrides: Any) -> tuple[DiTConfig, nnx.GraphDef, nnx.State]:
    """Loads an official ``WanModel`` safetensors checkpoint.

    Args:
      path: safetensors file with official key names and a ``config`` JSON metadata entry, or a
        released checkpoint directory (``config.json`` + shards), see :func:`read_checkpoint`.
      **overrides: extra :class:`DiTConfig` fields (e.g. ``compute_dtype="float32"``, ``remat``).

    Returns:
      ``(cfg, graphdef, state)`` of a :class:`WanDiT`.
    """
    tensors, official = read_checkpoint(path)
    cfg = config_from_official(official, **overrides)
    with nnx.use_eager_sharding(False):
        graphdef, state = nnx.split(nnx.eval_shape(lambda: WanDiT(cfg, rngs=nnx.Rngs(0))))
    state = fill_state(state, official_to_state(tensors, cfg))
    return cfg, graphdef, state


def load_official_into_world_model(
    path: str, cfg: DiTConfig | None = None, *, key: jax.Array | None = None
) -> tuple[DiTConfig, nnx.GraphDef, nnx.State]:
    """A :class:`WorldModel` with every shared parameter from an official ``WanModel`` checkpoint.

    Args:
      path: official safetensors checkpoint (config JSON in its metadata) or released
        checkpoint directory (``config.json`` + shards).
      cfg: the world-model config; its architecture fields (dim, heads, layers, ...) must match
        the checkpoint, its other fields (action switches, remat, dtypes) are used as given.
        None: the checkpoint's architecture with default options.
      key: randomness for the fresh action branches (default ``jax.random.key(0)``).

    Returns:
      ``(cfg, graphdef, state)``; the action branches are freshly initialised.
    """
    tensors, official_config = read_checkpoint(path)
    official = config_from_official(official_config)
    if cfg is None:
        cfg = official
    else:
        mismatched = {k: (getattr(cfg, k), getattr(official, k)) for k in ARCH_FIELDS
                      if getattr(cfg, k) != getattr(official, k)}
        if mismatched:
            raise CheckpointError(f"{path}: config fields (given, checkpoint) differ: {mismatched}")
    key = jax.random.key(0) if key is None else key

    with nnx.use_eager_sharding(False):
        graphdef, state = nnx.split(nnx.eval_shape(lambda: WorldModel(cfg, rngs=nnx.Rngs(0))))
        branches = nnx.split(ActionConditioner(cfg, rngs=nnx.Rngs(params=key)))[1]
    flat = {("dit",) + p: v for p, v in official_to_state(tensors, cfg).items()}
    flat.update({("actions",) + tuple(p): v.get_value() for p, v in nnx.to_flat_state(branches)})
    state = fill_state(state, flat)
    return cfg, graphdef, state


# ------------------------------------------------------------------------------------ reference cases


def _run_case(graphdef, state, cfg: DiTConfig, case: dict[str, np.ndarray]):
    """Runs one official call (list of per-sample latents/contexts, per-token t, padding)."""
    model = nnx.merge(graphdef, state)
    pt, ph, pw = cfg.patch_size
    n = len([k for k in case if re.fullmatch(r"x_\d+", k)])
    seq_len = int(case["seq_len"])
    t = jnp.asarray(case["t"], jnp.float32)
    if t.ndim == 1:  # the official model broadcasts a [seq_len] / [1] t over the batch
        t = jnp.broadcast_to(t.reshape(1, -1), (n, seq_len))
    patches, positions, contexts, grids = [], [], [], []
    for i in range(n):
        x = jnp.asarray(case[f"x_{i}"], jnp.float32).transpose(1, 2, 3, 0)[None]  # (1, F, H, W, C)
        grid = (x.shape[1] // pt, x.shape[2] // ph, x.shape[3] // pw)
        tokens = model.patchify(x)[0]
        if tokens.shape[0] > seq_len:
            raise ValueError(f"sample {i}: {tokens.shape[0]} tokens exceed seq_len={seq_len}")
        patches.append(jnp.pad(tokens, ((0, seq_len - tokens.shape[0]), (0, 0))))
        pos = model.grid_positions(1, grid)[0]
        positions.append(jnp.pad(pos, ((0, seq_len - pos.shape[0]), (0, 0))))
        ctx = jnp.asarray(case[f"context_{i}"], jnp.float32)
        contexts.append(jnp.pad(ctx, ((0, cfg.text_len - ctx.shape[0]), (0, 0))))
        grids.append(grid)
    seq_lens = jnp.asarray([g[0] * g[1] * g[2] for g in grids], jnp.int32)
    patches, positions, contexts = jnp.stack(patches), jnp.stack(positions), jnp.stack(contexts)

    def forward(state, patches, positions, t, contexts, seq_lens):
        model = nnx.merge(graphdef, state)
        time_emb = model.embed_time(t)
        text_emb = model.embed_text(contexts)
        head_out, inter = model.forward_tokens(patches, positions, time_emb, text_emb, seq_lens, capture=True)
        inter.update(time_emb=time_emb, text_emb=text_emb, sinusoid=timestep_sinusoid(t, cfg.freq_dim))
        return head_out, inter

    with jax.default_matmul_precision("float32"):
        head_out, inter = jax.jit(forward)(state, patches, positions, t, contexts, seq_lens)
    outputs = {}
    for i, grid in enumerate(grids):
        out = model.unpatchify(head_out[i : i + 1], grid)[0]  # (F, H, W, C)
        outputs[f"out_{i}"] = np.asarray(out).transpose(3, 0, 1, 2)
        # patch embedding of sample i, [dim, F', H', W'] as the official Conv3d output
        tokens = np.asarray(inter["tokens_in"][i, : np.prod(grid)])
        outputs[f"patch_embed_{i}"] = tokens.reshape(*grid, cfg.dim).transpose(3, 0, 1, 2)
    return outputs, {k: np.asarray(v) for k, v in inter.items()}, np.asarray(seq_lens), grids


def run_reference_cases(ref_dir: str, *, weights: str | None = None) -> list[CaseResult]:
    """Runs every ``dit_*.npz`` model case of ``ref_dir`` and compares with the official numbers.

    A case file is any ``dit_*.npz`` holding ``x_0``, ``context_0``, ``t`` and ``seq_len`` (files
    like the RoPE table are checked separately: a ``freqs_real_imag`` array is compared with
    :func:`sword_jax.dit.layers.rope_table`). Outputs ``out_i`` and ``patch_embed_i`` are compared
    whole; ``[B, seq_len, ...]`` intermediates on the valid rows of each sample only.

    Args:
      ref_dir: directory with ``dit_weights.safetensors`` (or ``weights``) and the npz cases.
      weights: override path of the official weights.

    Returns:
      One :class:`CaseResult` per compared array.
    """
    from sword_jax.dit.layers import rope_table

    if weights is None:
        weights = os.path.join(ref_dir, "dit_weights.safetensors")
        if not os.path.isfile(weights):
            candidates = sorted(glob.glob(os.path.join(ref_dir, "dit*.safetensors")))
            if len(candidates) != 1:
                raise CheckpointError(f"{ref_dir}: expected one dit*.safetensors weights file, found {candidates}")
            weights = candidates[0]
    cfg, graphdef, state = load_official(weights, compute_dtype="float32", param_dtype="float32")
    results: list[CaseResult] = []
    for path in sorted(glob.glob(os.path.join(ref_dir, "dit_*.npz"))):
        name = os.path.splitext(os.path.basename(path))[0]
        with np.load(path) as data:
            case = {k: data[k] for k in data.files}
        if "freqs_real_imag" in case:
            ref = case["freqs_real_imag"]
            table = rope_table(cfg.dim // cfg.num_heads)[: ref.shape[0]]
            ours = np.stack([table.real, table.imag], axis=-1)
            results.append(CaseResult.compare(name, "freqs_real_imag", ours, ref))
            continue
        if not {"x_0", "context_0", "t", "seq_len"} <= set(case):
            continue
        outputs, inter, seq_lens, grids = _run_case(graphdef, state, cfg, case)
        for key, ours in (("seq_lens", seq_lens), ("grid_sizes", np.asarray(grids))):
            if key in case and not np.array_equal(np.asarray(case[key]).reshape(ours.shape), ours):
                raise ValueError(f"{name}: reference {key} {case[key].tolist()} != derived {ours.tolist()}")
        seq_len = int(case["seq_len"])
        for key, ref in case.items():
            if key in outputs:
                results.append(CaseResult.compare(name, key, outputs[key], ref))
            elif key in inter:
                ours = inter[key]
                if ours.shape != ref.shape:
                    raise ValueError(f"{name}:{key}: port shape {ours.shape} != reference {ref.shape}")
                if ref.ndim >= 2 and ref.shape[1] == seq_len:  # token rows: compare valid rows only
                    ours = np.concatenate([ours[b, : seq_lens[b]] for b in range(ref.shape[0])])
                    ref = np.concatenate([ref[b, : seq_lens[b]] for b in range(ref.shape[0])])
                results.append(CaseResult.compare(name, key, ours, ref))
    if not results:
        raise CheckpointError(f"{ref_dir}: no dit_*.npz reference cases found")
    return results
