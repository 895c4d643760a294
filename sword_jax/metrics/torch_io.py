"""Torch-free readers for PyTorch weight files: ``.pth`` (zip and legacy formats) and safetensors.

A ``torch.save`` file is either
  * the zip format (torch >= 1.6): a stored ZIP archive with one top folder holding ``data.pkl``
    (the pickled object whose tensors are persistent ids pointing at storages) and ``data/<key>``
    (each storage's raw little-endian bytes); or
  * the legacy format (pre-1.6): consecutive pickles -- magic number, protocol version, sys info,
    the object itself, the list of storage keys -- then per key an int64 element count followed by
    the raw bytes.
Both rebuild tensors through ``torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)``.
Safetensors files are read with their metadata (:func:`read_safetensors`). Every failure raises
:class:`sword_jax.checkpoint.CheckpointError`. This module reimplements just enough of that protocol with a restricted ``pickle.Unpickler`` (only
the globals below are resolvable, so a file cannot run arbitrary code) and returns numpy arrays.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import struct
import zipfile
from typing import Any

import numpy as np

from sword_jax.checkpoint import CheckpointError

_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001

_STORAGE_DTYPES = {
    "FloatStorage": np.float32,
    "DoubleStorage": np.float64,
    "HalfStorage": np.float16,
    "BFloat16Storage": "bfloat16",
    "LongStorage": np.int64,
    "IntStorage": np.int32,
    "ShortStorage": np.int16,
    "CharStorage": np.int8,
    "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


WeightFileError = CheckpointError  # a weight file that is missing, corrupt or not in a supported format


class _StorageType:
    """Stands in for ``torch.<Type>Storage`` inside the pickle."""

    def __init__(self, name: str):
        self.name = name
        self.dtype = _STORAGE_DTYPES[name]


class _Storage:
    """A flat typed buffer (one ``data/<key>`` entry)."""

    def __init__(self, array: np.ndarray):
        self.array = array


def _np_dtype(dtype) -> np.dtype:
    if dtype == "bfloat16":
        import ml_dtypes

        return np.dtype(ml_dtypes.bfloat16)
    return np.dtype(dtype)


def _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad=False, backward_hooks=None, *rest):
    del requires_grad, backward_hooks, rest
    flat = storage.array
    itemsize = flat.dtype.itemsize
    size = tuple(int(s) for s in size)
    stride = tuple(int(s) for s in stride)
    if size:
        last = int(storage_offset) + sum((s - 1) * st for s, st in zip(size, stride) if s > 0)
        if any(s == 0 for s in size):
            return np.zeros(size, flat.dtype)
        if last >= flat.size:
            raise WeightFileError(
                f"tensor of size {size}, stride {stride}, offset {storage_offset} overruns its storage of {flat.size}"
            )
    elif int(storage_offset) >= flat.size:
        raise WeightFileError(f"scalar tensor offset {storage_offset} overruns its storage of {flat.size}")
    view = np.lib.stride_tricks.as_strided(
        flat[int(storage_offset) :], shape=size, strides=tuple(st * itemsize for st in stride), writeable=False
    )
    return np.array(view)  # own, contiguous copy


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, *rest):
    del requires_grad, backward_hooks, rest
    return data


class _Unpickler(pickle.Unpickler):
    """Resolves only the torch globals a state dict needs; storages come from ``load_storage``."""

    def __init__(self, file, load_storage):
        super().__init__(file, encoding="latin1")
        self._load_storage = load_storage

    def find_class(self, module: str, name: str) -> Any:
        if module == "torch._utils" and name == "_rebuild_tensor_v2":
            return _rebuild_tensor_v2
        if module == "torch._utils" and name == "_rebuild_parameter":
            return _rebuild_parameter
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if module == "torch" and name == "Size":
            return tuple
        raise WeightFileError(f"unsupported global {module}.{name} in pickle (only tensor state dicts are read)")

    def persistent_load(self, pid):
        if not isinstance(pid, tuple) or not pid or pid[0] != "storage":
            raise WeightFileError(f"unsupported persistent id {pid!r}")
        storage_type, key, numel = pid[1], str(pid[2]), int(pid[4])  # pid[3]: location, host either way
        return self._load_storage(storage_type, key, numel)


def _read_zip(path: str) -> dict:
    with zipfile.ZipFile(path) as archive:
        names = archive.namelist()
        pkl = [n for n in names if n.endswith("/data.pkl") or n == "data.pkl"]
        if len(pkl) != 1:
            raise WeightFileError(f"{path}: zip file without a single data.pkl (found {pkl})")
        prefix = pkl[0][: -len("data.pkl")]
        byteorder = prefix + "byteorder"
        if byteorder in names and archive.read(byteorder).decode().strip() != "little":
            raise WeightFileError(f"{path}: big-endian torch files are not supported")
        cache: dict[str, _Storage] = {}

        def load_storage(storage_type: _StorageType, key: str, numel: int) -> _Storage:
            if key not in cache:
                entry = f"{prefix}data/{key}"
                if entry not in names:
                    raise WeightFileError(f"{path}: storage entry {entry} missing")
                raw = archive.read(entry)
                dtype = _np_dtype(storage_type.dtype)
                if len(raw) < numel * dtype.itemsize:
                    raise WeightFileError(f"{path}: storage {key} holds {len(raw)} bytes, expected {numel * dtype.itemsize}")
                cache[key] = _Storage(np.frombuffer(raw, dtype=dtype.newbyteorder("<"), count=numel))
            return cache[key]

        return _Unpickler(io.BytesIO(archive.read(pkl[0])), load_storage).load()


def _read_legacy(path: str) -> dict:
    with open(path, "rb") as f:
        data = f.read()
    stream = io.BytesIO(data)

    def plain_load():
        return _Unpickler(stream, lambda *a: None).load()

    try:
        magic = plain_load()
    except Exception as exc:  # noqa: BLE001 - any failure means "not a legacy torch file"
        raise WeightFileError(f"{path}: neither a zip nor a legacy torch file ({exc})") from exc
    if magic != _LEGACY_MAGIC:
        raise WeightFileError(f"{path}: not a torch file (bad magic number {magic!r})")
    protocol = plain_load()
    if protocol != _LEGACY_PROTOCOL:
        raise WeightFileError(f"{path}: legacy torch protocol {protocol} unsupported (expected {_LEGACY_PROTOCOL})")
    sys_info = plain_load()
    if isinstance(sys_info, dict) and not sys_info.get("little_endian", True):
        raise WeightFileError(f"{path}: big-endian legacy torch files are not supported")
    storages: dict[str, _Storage] = {}
    types: dict[str, _StorageType] = {}

    def load_storage(storage_type: _StorageType, key: str, numel: int) -> _Storage:
        if key not in storages:
            storages[key] = _Storage(np.zeros(0, _np_dtype(storage_type.dtype)))  # filled below
            types[key] = storage_type
        return storages[key]

    # Tensors are rebuilt lazily: first unpickle with placeholder storages recorded, then re-read.
    start = stream.tell()
    pending: list = []

    def record(storage_type, key, numel):
        pending.append((storage_type, key, numel))
        return load_storage(storage_type, key, numel)

    class _Recorder(_Unpickler):
        def find_class(self, module, name):
            if module == "torch._utils" and name == "_rebuild_tensor_v2":
                return lambda *args: ("__tensor__", args)
            return super().find_class(module, name)

    _Recorder(stream, record).load()
    keys = _Unpickler(stream, lambda *a: None).load()
    offset = stream.tell()
    for key in keys:
        key = str(key)
        if key not in types:
            raise WeightFileError(f"{path}: storage {key} listed but never referenced")
        if offset + 8 > len(data):
            raise WeightFileError(f"{path}: truncated before storage {key}")
        (numel,) = struct.unpack("<q", data[offset : offset + 8])
        dtype = _np_dtype(types[key].dtype).newbyteorder("<")
        nbytes = numel * dtype.itemsize
        if offset + 8 + nbytes > len(data):
            raise WeightFileError(f"{path}: truncated inside storage {key}")
        storages[key].array = np.frombuffer(data, dtype=dtype, count=numel, offset=offset + 8)
        offset += 8 + nbytes
    stream.seek(start)
    return _Unpickler(stream, load_storage).load()


def load_torch_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads a ``torch.save``-d state dict without torch.

    Args:
      path: a ``.pth``/``.pt`` file in the zip (torch >= 1.6) or legacy (pre-1.6) format.

    Returns:
      ``{key: numpy array}`` in the file's dtypes and PyTorch layouts. Nested dicts (e.g. a
      checkpoint's ``{"state_dict": ...}``) are returned as they are.

    Raises:
      WeightFileError: missing, corrupt or unsupported file.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise WeightFileError(f"weight file not found: {path}")
    try:
        if zipfile.is_zipfile(path):
            obj = _read_zip(path)
        else:
            obj = _read_legacy(path)
    except WeightFileError:
        raise
    except (pickle.UnpicklingError, EOFError, zipfile.BadZipFile, struct.error, KeyError, ValueError) as exc:
        raise WeightFileError(f"{path}: corrupt torch file ({type(exc).__name__}: {exc})") from exc
    if not isinstance(obj, dict):
        raise WeightFileError(f"{path}: expected a state dict, got {type(obj).__name__}")
    return dict(obj)


def read_safetensors(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every tensor of a ``.safetensors`` file as a numpy array (the file's dtypes), plus its string metadata.

    Raises:
      CheckpointError: the file is missing or is not a valid safetensors file.
    """
    from safetensors import safe_open

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise CheckpointError(f"weight file not found: {path}")
    try:
        with safe_open(path, framework="np") as handle:
            metadata = dict(handle.metadata() or {})
            tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    except Exception as exc:  # noqa: BLE001 - safetensors raises several error types
        raise CheckpointError(f"cannot read safetensors file {path}: {exc}") from exc
    return tensors, metadata


def load_safetensors_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads a ``.safetensors`` file into ``{key: numpy array}`` (the file's dtypes)."""
    return read_safetensors(path)[0]


def load_state_dict(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Reads a state dict from ``.safetensors`` or any torch file, by extension then content."""
    path = os.fspath(path)
    if path.endswith(".safetensors"):
        return load_safetensors_file(path)
    return load_torch_file(path)


def as_float32(state: dict[str, np.ndarray], *, prefix: str = "") -> dict[str, np.ndarray]:
    """Float tensors cast to float32 (half files are computed in float32), others dropped.

    ``num_batches_tracked`` and other integer entries do not enter eval-mode math and are dropped.
    An optional ``prefix`` (e.g. ``"module."``) is stripped from keys that carry it.
    """
    out = {}
    for key, value in state.items():
        if not isinstance(value, np.ndarray) or not np.issubdtype(value.dtype, np.floating) and value.dtype.name != "bfloat16":
            continue
        if prefix and key.startswith(prefix):
            key = key[len(prefix) :]
        out[key] = value.astype(np.float32)
    return out
