"""Writing a file (JSON, JSON lines, text) so that a reader (or a run killed mid-write) sees the old file or the new one,
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


def write_text_atomic(path: str, text: str) -> str:
    """Writes ``text`` to ``path`` atomically (a temporary file per process beside it, flushed to disk,
    renamed over it) and returns ``path``."""
    tmp = f"{path}.tmp.{os.getpid()}"  # per process: two writers never share a temporary file
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def write_json_atomic(path: str, payload: Any, *, sort_keys: bool = False) -> str:
    """Writes ``payload`` as indented JSON to ``path`` atomically (values JSON cannot hold go through
    :func:`json_default`) and returns ``path``."""
    return write_text_atomic(path, json.dumps(payload, indent=1, sort_keys=sort_keys, default=json_default))


def write_jsonl_atomic(path: str, rows: Any) -> str:
    """Writes one JSON object per line to ``path`` atomically and returns ``path``."""
    return write_text_atomic(path, "".join(json.dumps(row, default=json_default) + "\n" for row in rows))
