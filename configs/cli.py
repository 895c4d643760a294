"""Dotted command-line overrides for frozen dataclass configs: ``--model.num_layers=4``."""

from __future__ import annotations

import dataclasses
import json
import typing
from collections.abc import Sequence
from typing import Any


class ConfigError(ValueError):
    """A bad config key or value; the message names the key."""


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _parse_value(key: str, text: str, annotation: Any) -> Any:
    origin = typing.get_origin(annotation)
    try:
        if annotation is bool:
            lowered = text.lower()
            if lowered in ("1", "true", "yes", "on"):
                return True
            if lowered in ("0", "false", "no", "off"):
                return False
            raise ValueError(f"not a boolean: {text!r}")
        if annotation is int:
            return int(text)
        if annotation is float:
            return float(text)
        if annotation is str:
            return text
        if origin is tuple:
            args = typing.get_args(annotation)
            raw = json.loads(text) if text.strip().startswith("[") else [t for t in text.split(",") if t != ""]
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(_parse_value(key, str(v) if not isinstance(v, str) else v, args[0]) for v in raw)
            if len(args) != len(raw):
                raise ValueError(f"expected {len(args)} comma-separated values, got {len(raw)}")
            return tuple(_parse_value(key, str(v) if not isinstance(v, str) else v, a) for v, a in zip(raw, args))
        if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
            for arg in typing.get_args(annotation):
                if arg is type(None):
                    if text.lower() in ("none", "null"):
                        return None
                    continue
                try:
                    return _parse_value(key, text, arg)
                except (ConfigError, ValueError):
                    continue
            raise ValueError(f"does not match {annotation}")
    except (ValueError, json.JSONDecodeError) as err:
        raise ConfigError(f"config key {key!r}: cannot parse {text!r} as {annotation}: {err}") from None
    raise ConfigError(f"config key {key!r}: unsupported field type {annotation}")


def set_path(cfg: Any, dotted: str, text: str, _prefix: str = "") -> Any:
    """Returns a copy of ``cfg`` with the field at ``dotted`` set from its string form."""
    head, _, rest = dotted.partition(".")
    full = _prefix + dotted
    if not dataclasses.is_dataclass(cfg):
        raise ConfigError(f"config key {full!r}: {type(cfg).__name__} has no fields")
    names = {f.name for f in dataclasses.fields(cfg)}
    if head not in names:
        raise ConfigError(
            f"unknown config key {full!r} ({head!r} is not a field of {type(cfg).__name__}; "
            f"known: {', '.join(sorted(names))})"
        )
    current = getattr(cfg, head)
    if rest:
        return dataclasses.replace(cfg, **{head: set_path(current, rest, text, _prefix + head + ".")})
    annotation = _field_types(type(cfg))[head]
    if dataclasses.is_dataclass(current):
        raise ConfigError(f"config key {full!r} is a section; set one of its fields, e.g. --{full}.<field>=...")
    return dataclasses.replace(cfg, **{head: _parse_value(full, text, annotation)})


def apply_overrides(cfg: Any, overrides: Sequence[str]) -> Any:
    """Applies ``--a.b=value`` / ``a.b=value`` / ``--a.b value`` overrides in order."""
    items = list(overrides)
    index = 0
    while index < len(items):
        item = items[index]
        body = item[2:] if item.startswith("--") else item
        if "=" in body:
            key, value = body.split("=", 1)
        elif index + 1 < len(items):
            key, value = body, items[index + 1]
            index += 1
        else:
            raise ConfigError(f"override {item!r} has no value (use --key=value)")
        cfg = _set_checked(cfg, key, value)
        index += 1
    return cfg


def _set_checked(cfg: Any, key: str, value: str) -> Any:
    try:
        return set_path(cfg, key, value)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:
        raise ConfigError(f"config key {key!r}: {err}") from None


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-friendly dict of a config (for logging and checkpoints)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg), default=list))
