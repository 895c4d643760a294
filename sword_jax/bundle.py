"""A trained pipeline's inference weights as a bundle of size-limited parts, to move between machines.

A pipeline run (``train.pipeline``) keeps its world model as the trainer's whole state: parameters, optimizer
state, the DLB cache (``small``: 0.9 GiB with the 8x VAE's latents). What GRPO, evaluation and
:func:`sword_jax.api.load_world_model` read is far less: the world model's inference weights (its EMA where the
run kept one), the VAE and the success detector. :func:`pack` writes exactly those, laid out as a pipeline work
dir, as one tar stream cut into parts of at most ``part_bytes`` (so that each fits a transfer that limits file
sizes) with a manifest (``bundle.json``) of every part's size and SHA-256. :func:`unpack` checks every part
against it, from one folder or several (parts may travel separately), and restores the work dir, which every
loader then reads as it reads the original: ``--world-model <dir>/world_model --vae <dir>/vae_run/vae
--reward <dir>/rl/reward_model``. The weights are the saved float32 arrays, bit for bit.

The world model there holds inference weights only (``params``, the EMA where there was one, and ``buffers``):
it cannot resume training, and says so in its checkpoint's metadata (``meta["bundle"]``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tarfile
import tempfile
from collections.abc import Sequence
from typing import Any, BinaryIO

import jax
import numpy as np

MANIFEST = "bundle.json"
FORMAT = 1
PART = "part-{:04d}"


class BundleError(ValueError):
    """A bundle that cannot be written or read: the message names the part or path."""


class _PartWriter:
    """A binary file object that writes into ``PART`` files of at most ``part_bytes`` each in ``folder``, hashing
    each and the whole stream."""

    def __init__(self, folder: str, part_bytes: int):
        self.folder, self.part_bytes = folder, part_bytes
        self.parts: list[dict[str, Any]] = []
        self.whole = hashlib.sha256()
        self._file: BinaryIO | None = None
        self._hash = hashlib.sha256()
        self._size = 0

    def _next(self) -> None:
        self._close_part()
        name = PART.format(len(self.parts))
        self._file = open(os.path.join(self.folder, name), "wb")
        self.parts.append({"name": name})
        self._hash, self._size = hashlib.sha256(), 0

    def _close_part(self) -> None:
        if self._file is not None:
            self._file.close()
            self.parts[-1].update(bytes=self._size, sha256=self._hash.hexdigest())
            self._file = None

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        while view.nbytes:
            if self._file is None or self._size == self.part_bytes:
                self._next()
            take = view[: self.part_bytes - self._size]
            self._file.write(take)
            self._hash.update(take)
            self.whole.update(take)
            self._size += take.nbytes
            view = view[take.nbytes:]
        return len(data)

    def close(self) -> None:
        self._close_part()


class _PartReader:
    """A binary file object reading the parts of ``manifest`` in order from ``paths`` (name -> path), checking
    each part's size and SHA-256 as it ends."""

    def __init__(self, manifest: dict[str, Any], paths: dict[str, str]):
        self.parts, self.paths = manifest["parts"], paths
        self.index, self._file, self._hash, self._size = -1, None, hashlib.sha256(), 0

    def _advance(self) -> bool:
        if self._file is not None:
            self._file.close()
            part = self.parts[self.index]
            if self._size != part["bytes"] or self._hash.hexdigest() != part["sha256"]:
                raise BundleError(f"bundle: part {part['name']} ({self.paths[part['name']]}) does not match the "
                                  f"manifest ({self._size} bytes read, {part['bytes']} listed, or another SHA-256)")
            self._file = None
        self.index += 1
        if self.index >= len(self.parts):
            return False
        self._file = open(self.paths[self.parts[self.index]["name"]], "rb")
        self._hash, self._size = hashlib.sha256(), 0
        return True

    def read(self, size: int = -1) -> bytes:
        out = bytearray()
        while size < 0 or len(out) < size:
            if self._file is None and not self._advance():
                break
            chunk = self._file.read(1 << 20 if size < 0 else size - len(out))
            if not chunk:
                if not self._advance():
                    break
                continue
            self._hash.update(chunk)
            self._size += len(chunk)
            out += chunk
        return bytes(out)

    def finish(self) -> None:
        """Reads what is left (the checks of every part run only on what was read)."""
        while self.read(1 << 20):
            pass


def _world_model_weights(run_dir: str, step: int | None, staged: str) -> dict[str, Any]:
    """Writes the world model's inference weights of ``run_dir`` (at ``step``, default the newest) as a
    world-model work dir under ``staged``; returns what it wrote."""
    from sword_jax import load
    from sword_jax.checkpoint import Checkpointer
    from sword_jax.dit.config import DiTConfig

    checkpoints = os.path.join(run_dir, "checkpoints")
    step = load.checkpoint_step(checkpoints, step)
    config = load.read_run_config(run_dir, step)
    model_cfg = load.section_from_dict(DiTConfig, config.get("model", {}))
    present = load.saved_keys(checkpoints, step)
    _, (params, buffers), _ = load.load_world_model_params(model_cfg, checkpoints, step=step, use_ema=True)
    weights = "ema_params" if present.get("ema_params") else "params"
    meta = load.read_meta(checkpoints, step)
    meta = {**meta, "config": config, "bundle": {"weights": weights, "inference_only": True}}
    host = lambda tree: jax.tree.map(np.asarray, tree)  # noqa: E731 - device arrays -> numpy
    target = os.path.join(staged, "world_model")
    with Checkpointer(os.path.join(target, "checkpoints"), max_to_keep=None) as writer:
        writer.save(step, {"params": host(params), "buffers": host(buffers)}, meta)
    with open(os.path.join(target, "config.json"), "w") as f:
        json.dump(config, f, indent=1, sort_keys=True)
    count = sum(int(np.prod(np.shape(leaf))) for leaf in jax.tree.leaves(params))
    return {"step": step, "weights": weights, "parameters": count}


def pack(run: str, out: str, *, part_bytes: int, step: int | None = None) -> dict[str, Any]:
    """Writes the inference weights of pipeline work dir ``run`` into ``out`` (new or empty) as parts of at most
    ``part_bytes`` and ``bundle.json``: the world model (its EMA weights where kept, at ``step``, default the
    newest), the VAE (``vae_run/vae``), the success detector (``rl/reward_model``, where the run has one) and
    the run's ``config.json``. Returns the manifest."""
    from sword_jax import load

    if part_bytes < 1 << 16:
        raise BundleError(f"bundle: part_bytes must be at least 64 KiB, got {part_bytes}")
    if os.path.exists(out) and (not os.path.isdir(out) or os.listdir(out)):
        raise BundleError(f"bundle: {out} exists and is not an empty folder; the bundle goes into a new one")
    try:
        run_dir, pipeline, step = load.find_run(run, step)
    except load.CheckpointError as err:
        raise BundleError(f"bundle: {err}") from None
    if pipeline is None:
        raise BundleError(f"bundle: {run} is a world-model work dir without its pipeline's VAE (vae_run/vae); "
                          "pass the pipeline work dir")
    os.makedirs(out, exist_ok=True)
    contents: list[str] = []
    with tempfile.TemporaryDirectory(dir=out) as staged_root:
        staged = os.path.join(staged_root, "run")
        os.makedirs(staged)
        world_model = _world_model_weights(run_dir, step, staged)
        contents.append("world_model")
        shutil.copytree(load.vae_dir(os.path.join(pipeline, "vae_run")), os.path.join(staged, "vae_run", "vae"))
        contents.append("vae_run/vae")
        reward = os.path.join(pipeline, "rl", "reward_model")
        if os.path.isdir(reward):
            shutil.copytree(reward, os.path.join(staged, "rl", "reward_model"))
            contents.append("rl/reward_model")
        if os.path.exists(os.path.join(pipeline, "config.json")):
            shutil.copy(os.path.join(pipeline, "config.json"), os.path.join(staged, "config.json"))
            contents.append("config.json")
        writer = _PartWriter(out, part_bytes)
        with tarfile.open(fileobj=writer, mode="w|") as tar:
            for name in sorted(os.listdir(staged)):
                tar.add(os.path.join(staged, name), arcname=name)
        writer.close()
    manifest = {"format": FORMAT, "source": os.path.abspath(run), "contents": contents, "world_model": world_model,
                "bytes": sum(p["bytes"] for p in writer.parts), "sha256": writer.whole.hexdigest(),
                "parts": writer.parts}
    with open(os.path.join(out, MANIFEST), "w") as f:
        json.dump(manifest, f, indent=1)
    return manifest


def _find_parts(folders: Sequence[str]) -> tuple[dict[str, Any], dict[str, str]]:
    """The manifest and each part's path, from ``folders`` (the manifest in any of them)."""
    manifests = [os.path.join(f, MANIFEST) for f in folders if os.path.exists(os.path.join(f, MANIFEST))]
    if not manifests:
        raise BundleError(f"bundle: no {MANIFEST} in {', '.join(folders)}")
    try:
        with open(manifests[0]) as f:
            manifest = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise BundleError(f"bundle: {manifests[0]} is not a readable manifest: {err}") from None
    if manifest.get("format") != FORMAT or not isinstance(manifest.get("parts"), list):
        raise BundleError(f"bundle: {manifests[0]} is not a bundle manifest of format {FORMAT}")
    paths, missing = {}, []
    for part in manifest["parts"]:
        found = [os.path.join(f, part["name"]) for f in folders if os.path.exists(os.path.join(f, part["name"]))]
        if found:
            paths[part["name"]] = found[0]
        else:
            missing.append(part["name"])
    if missing:
        raise BundleError(f"bundle: parts {', '.join(missing)} of {len(manifest['parts'])} are in none of "
                          f"{', '.join(folders)}")
    return manifest, paths


def unpack(folders: Sequence[str] | str, dest: str) -> dict[str, Any]:
    """Restores the work dir of the bundle whose manifest and parts lie in ``folders`` into ``dest`` (new or
    empty), checking each part's size and SHA-256 first, with the manifest beside it (``dest/bundle.json``: where
    the weights came from). Returns the manifest. Nothing is written when a part is missing or does not match."""
    folders = [folders] if isinstance(folders, str) else list(folders)
    if os.path.exists(dest) and (not os.path.isdir(dest) or os.listdir(dest)):
        raise BundleError(f"bundle: {dest} exists and is not an empty folder; unpack into a new one")
    manifest, paths = _find_parts(folders)
    checker = _PartReader(manifest, paths)
    checker.finish()  # every part checked before anything is written
    parent = os.path.dirname(os.path.abspath(dest))
    os.makedirs(parent, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=parent) as staged:
        with tarfile.open(fileobj=_PartReader(manifest, paths), mode="r|") as tar:
            for member in tar:
                if member.name.startswith(("/", "..")) or ".." in member.name.split("/") or not (
                        member.isfile() or member.isdir()):
                    raise BundleError(f"bundle: member {member.name!r} is not a plain file or folder inside it")
                tar.extract(member, staged, filter="data")
        with open(os.path.join(staged, MANIFEST), "w") as f:  # where the weights came from, kept beside them
            json.dump(manifest, f, indent=1)
        os.makedirs(dest, exist_ok=True)
        for name in os.listdir(staged):
            shutil.move(os.path.join(staged, name), os.path.join(dest, name))
    return manifest


__all__ = ["BundleError", "pack", "unpack", "MANIFEST"]
