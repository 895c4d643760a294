"""Dotted command-line overrides for frozen dataclass configs: ``--model.num_layers=4``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import typing
from collections.abc import Sequence
from typing import Any

from sword_jax.cli import ArgumentParser as _BaseParser
from sword_jax.cli import UsageError


class ConfigError(UsageError):
    """A bad config key or value; the message names the key (a usage error: exit status 2)."""


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
    renamed = getattr(type(cfg), "renamed_fields", {})  # a section's keys of earlier versions -> their new paths
    if head not in names and head in renamed:
        raise ConfigError(f"{full} is now {_prefix}{renamed[head]}")
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


def flatten(cfg: Any, prefix: str = "") -> dict[str, Any]:
    """Every leaf of a config as ``{"section.key": value}``, in field order."""
    out: dict[str, Any] = {}
    for field in dataclasses.fields(cfg):
        value = getattr(cfg, field.name)
        if dataclasses.is_dataclass(value):
            out.update(flatten(value, f"{prefix}{field.name}."))
        else:
            out[prefix + field.name] = value
    return out


def _format_value(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        if all(isinstance(v, (int, float, str)) and not isinstance(v, bool) for v in value):
            return ",".join(str(v) for v in value)
        return json.dumps(value, default=list)
    return str(value)


def format_config(cfg: Any, name: str = "") -> str:
    """The config as ``--key=value`` lines that can be pasted back on a command line."""
    lines = [f"# {name}" if name else f"# {getattr(cfg, 'name', type(cfg).__name__)}"]
    lines += [f"--{key}={_format_value(value)}" for key, value in flatten(cfg).items()]
    return "\n".join(lines)


def config_help(experiments: dict[str, Sequence[str]], default: str) -> str:
    """The ``--config`` help: ``sword:tiny|small|paper, cache_ablation:...``."""
    return ("experiment config NAME:VARIANT, one of " + "; ".join(
        f"{name}:{'|'.join(variants)}" for name, variants in experiments.items()) + f" (default {default}); "
        "a cache_ablation design takes a size prefix, e.g. cache_ablation:small-tf")


class ArgumentParser(_BaseParser):
    """An entry point's parser that also documents the experiment config in ``--help``.

    ``configs.from_argv`` consumes ``--config``, ``--print-config`` and the dotted overrides
    before this parser sees the rest; the arguments here are for ``--help``.
    """

    def __init__(self, *args: Any, **kwargs: Any):
        import configs

        super().__init__(*args, **kwargs)
        group = self.add_argument_group(
            "configuration", "Any config key can be set as --SECTION.KEY=VALUE, e.g. --model.num_layers=4 "
                             "--trainer.steps=100; --print-config lists every key with its value.")
        group.add_argument("--config", metavar="NAME:VARIANT", default=argparse.SUPPRESS,
                           help=config_help(configs.variants(), configs.DEFAULT))
        group.add_argument("--workdir", metavar="DIR", default=argparse.SUPPRESS,
                           help="where checkpoints, metrics and results go (the config's workdir)")
        group.add_argument("--print-config", action="store_true", default=argparse.SUPPRESS,
                           help="print every config key (--section.key=value, after overrides) and exit")
