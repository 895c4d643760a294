"""Writing a JSON file so that a reader (or a run killed mid-write) sees the old file or the new one,
never a torn one: the text goes to a temporary file beside it, is flushed to disk, then renamed over it."""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Any


def json_default(value: Any) -> Any:
    """Arrays and numpy scalars as lists / numbers, dataclasses as dicts, anything else as its string."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return str(value)


def write_json_atomic(path: str, payload: Any, *, sort_keys: bool = False) -> str:
    """Writes ``payload`` as indented JSON to ``path`` atomically (values JSON cannot hold go through
    :func:`json_default`) and returns ``path``."""
    tmp = f"{path}.tmp.{os.getpid()}"  # per process: two writers never share a temporary file
    try:
        with open(tmp, "w") as f:
            json.dump(payload, f, indent=1, sort_keys=sort_keys, default=json_default)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path
