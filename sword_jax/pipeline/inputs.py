"""Hashes of the inputs the slices of a comparison (``train.compare``) share, and where and with what code a slice ran.

Every hash is sha256 over named arrays (name, dtype, shape, little-endian C-order bytes), so the same
data or parameters give the same hash on any machine, whatever file layout holds them. A slice
records these; ``train.compare merge`` refuses slices whose hashes disagree.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the checkout


DATA_HASH_KEYS = ("actions", "executed_actions", "rewards", "obs/agentview_rgb", "obs/eye_in_hand_rgb")


def hash_arrays(named: Iterable[tuple[str, np.ndarray]]) -> str:
    """sha256 over each array's name, dtype, shape and C-order bytes, in the order given."""
    digest = hashlib.sha256()
    for name, array in named:
        array = np.ascontiguousarray(array)
        digest.update(f"{name}|{array.dtype.newbyteorder('<').str}|{array.shape}|".encode())
        digest.update(array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes())
    return digest.hexdigest()


def hash_episodes(path: str) -> str:
    """Hash of an expert HDF5's arrays that reach the models (actions, rewards, frames), demo by demo.

    The file's bytes are not hashed: HDF5 stores timestamps and chunk layouts that differ between
    writes of the same data.
    """
    import h5py

    with h5py.File(path, "r") as f:
        data = f["data"]
        demos = sorted(data, key=lambda name: int(name.rsplit("_", 1)[-1]))
        return hash_arrays((f"{demo}/{key}", data[demo][key][()])
                           for demo in demos for key in DATA_HASH_KEYS if key in data[demo])


def hash_npz(path: str) -> str:
    """Hash of the numeric arrays of an ``.npz`` file; strings (metadata such as the source paths) are left out."""
    with np.load(path) as npz:
        arrays = {name: npz[name] for name in sorted(npz.files)}
    return hash_arrays((name, array) for name, array in arrays.items() if array.dtype.kind in "biufc")


def _hash_tree(tree) -> str:
    import jax

    leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
    return hash_arrays((jax.tree_util.keystr(path), np.asarray(leaf)) for path, leaf in leaves)


def hash_vae(cfg, path: str) -> str:
    """Hash of the VAE's parameters: the trained checkpoint as saved, or the official weights as loaded."""
    if not cfg.vae.checkpoint:
        return hash_checkpoint(path)
    from flax import nnx

    from sword_jax.load import load_vae_params

    _, state = load_vae_params(cfg.vae, path)
    return _hash_tree(nnx.to_pure_dict(state))


def hash_checkpoint(path: str) -> str:
    """Hash of the arrays in an orbax parameter checkpoint (reward model, policy), restored as saved."""
    from sword_jax import checkpoint

    ckpt = checkpoint.Checkpointer(path)
    try:
        tree, _ = ckpt.restore(None)
    finally:
        ckpt.close()
    return _hash_tree(tree)


def cached_hash(cache_dir: str | None, kind: str, path: str, compute) -> str:
    """``compute()``, remembered in ``cache_dir`` for ``(kind, path)`` as long as the path's size and
    modification time stay (a stage's outputs are written once). Slices that adopted the same shared
    stages then hash each input once between them; ``None``: no cache."""
    if not cache_dir or not os.path.exists(path):  # nothing to stamp: computed every time
        return compute()
    import json

    from sword_jax.atomic_write import write_json_atomic

    stat = os.stat(path)
    stamp = {"kind": kind, "path": os.path.abspath(path), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
    entry = os.path.join(cache_dir, hashlib.sha256(json.dumps(stamp, sort_keys=True).encode()).hexdigest()[:24] + ".json")
    try:
        with open(entry) as f:
            saved = json.load(f)
        if {k: saved.get(k) for k in stamp} == stamp:
            return saved["hash"]
    except (OSError, ValueError, KeyError):
        pass
    digest = compute()
    os.makedirs(cache_dir, exist_ok=True)
    write_json_atomic(entry, {**stamp, "hash": digest}, sort_keys=True)
    return digest


def shared_hashes(cfg, stages: dict, *, cache_dir: str | None = None) -> dict[str, str]:
    """Hashes of the shared inputs a slice used, keyed so that equal keys must hold equal hashes.

    Latents depend on the augmentation setting, so their key names it. Parameters saved as ``.npz``
    (the probe) are hashed array by array, orbax directories (reward model, policy) as restored.
    ``cache_dir``: remember each file's hash there (:func:`cached_hash`).
    """
    def cached(kind, path, compute):
        return cached_hash(cache_dir, kind, path, compute)

    hashes = {}
    if "data" in stages:
        for split in ("train", "heldout"):
            path = stages["data"][split]["path"]
            hashes[f"data/{split}"] = cached("episodes", path, lambda: hash_episodes(path))
        hashes["data"] = hashlib.sha256((hashes["data/train"] + hashes["data/heldout"]).encode()).hexdigest()
    if stages.get("policy_data", {}).get("path"):
        path = stages["policy_data"]["path"]
        hashes["data/policy_rollouts"] = cached("episodes", path, lambda: hash_episodes(path))
    if "vae" in stages:
        path = stages["vae"]["path"]
        hashes["vae"] = cached(f"vae:{cfg.vae.checkpoint}", path, lambda: hash_vae(cfg, path))
    if "latents" in stages:
        path = stages["latents"]["path"]
        hashes[f"latents[augment={'on' if cfg.augment.enabled else 'off'}]"] = cached("npz", path, lambda: hash_npz(path))
    for stage in ("probe", "reward_model", "sft_policy"):
        path = stages.get(stage, {}).get("path")
        if path and path.endswith(".npz"):
            hashes[stage] = cached("npz", path, lambda: hash_npz(path))
        elif path:
            hashes[stage] = cached("checkpoint", path, lambda: hash_checkpoint(path))
    return hashes


def code_version() -> dict:
    """The git commit (and whether tracked files differ from it) and a hash of the Python sources."""
    import subprocess

    version: dict = {"commit": None, "dirty": None}
    try:
        git = ["git", "-C", REPO]
        version["commit"] = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True,
                                           check=True, timeout=20).stdout.strip()
        version["dirty"] = bool(subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"],
                                               capture_output=True, text=True, check=True, timeout=20).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        pass  # a copy of the tree without .git: the source hash still names the code
    digest = hashlib.sha256()
    for top in ("configs", "sim", "sword_jax", "train"):
        for root, dirs, files in os.walk(os.path.join(REPO, top)):
            dirs[:] = sorted(d for d in dirs if not d.startswith((".", "__")))
            for name in sorted(f for f in files if f.endswith(".py")):
                path = os.path.join(root, name)
                digest.update(os.path.relpath(path, REPO).encode())
                with open(path, "rb") as f:
                    digest.update(hashlib.sha256(f.read()).digest())
    version["source_hash"] = digest.hexdigest()
    return version


def device_info() -> dict:
    import jax

    devices = jax.devices()
    return {"platform": devices[0].platform, "kind": devices[0].device_kind, "count": len(devices),
            "jax": jax.__version__}
