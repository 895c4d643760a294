"""Typed experiment configs: one module per experiment, each with tiny / small / paper variants.

``configs.get("sword:tiny")`` returns a validated ``ExperimentConfig``;
``configs.from_argv(argv)`` reads ``--config NAME:VARIANT`` plus dotted overrides.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Sequence

from configs.base import ExperimentConfig
from configs.cli import ArgumentParser, ConfigError, apply_overrides, format_config, to_dict

EXPERIMENTS = ("sword", "cache_ablation")
DEFAULT = "sword:tiny"


def get(name: str = DEFAULT) -> ExperimentConfig:
    """Returns the config ``experiment:variant`` (variant defaults to tiny), validated."""
    experiment, _, variant = name.partition(":")
    if experiment not in EXPERIMENTS:
        raise ConfigError(f"unknown experiment {experiment!r}; known: {', '.join(EXPERIMENTS)}")
    module = importlib.import_module(f"configs.{experiment}")
    try:
        cfg = module.get(variant or "tiny")
    except KeyError as err:
        raise ConfigError(str(err.args[0])) from None
    return cfg.validate()


def variants() -> dict[str, tuple[str, ...]]:
    """Each experiment's variant names, for help texts."""
    out = {}
    for experiment in EXPERIMENTS:
        module = importlib.import_module(f"configs.{experiment}")
        out[experiment] = tuple(module.VARIANTS)
    return out


def from_argv(argv: Sequence[str], default: str = DEFAULT) -> tuple[ExperimentConfig, list[str]]:
    """Parses ``--config NAME`` and dotted overrides; returns (config, remaining non-config args).

    Arguments that do not start with a config section name are returned untouched so entry
    points can read their own flags. ``--print-config`` prints the resolved config (every
    dotted key with its value) and exits with status 0, as ``--help`` does.
    """
    argv = list(argv)
    name = default
    print_config = False
    rest: list[str] = []
    overrides: list[str] = []
    fields = ExperimentConfig.__dataclass_fields__
    scalars = {name for name, f in fields.items() if not dataclasses.is_dataclass(f.default)}
    sections = set(fields)
    index = 0
    while index < len(argv):
        arg = argv[index]
        if arg == "--config" and index + 1 < len(argv):
            name = argv[index + 1]
            index += 2
            continue
        if arg.startswith("--config="):
            name = arg.split("=", 1)[1]
            index += 1
            continue
        if arg == "--print-config":
            print_config, index = True, index + 1
            continue
        key = arg[2:].split("=", 1)[0] if arg.startswith("--") else ""
        # "--model.dim=8" and "--seed 3" are config overrides; a bare "--model X" is an entry point's own flag.
        if ("." in key and key.split(".")[0] in sections) or key in scalars:
            if "=" in arg or index + 1 >= len(argv):
                overrides.append(arg)
            else:
                overrides.extend([arg, argv[index + 1]])
                index += 1
        elif arg.startswith("--") and "." in key:
            raise ConfigError(f"unknown config key {key!r}; sections are: {', '.join(sorted(sections))}")
        else:
            rest.append(arg)
        index += 1
    cfg = apply_overrides(get(name), overrides)
    try:
        cfg = cfg.validate()
    except ConfigError:
        raise
    except ValueError as err:  # an impossible setting given on the command line is a usage error
        raise ConfigError(str(err)) from None
    if print_config:
        print(format_config(cfg, name))
        raise SystemExit(0)
    return cfg, rest


__all__ = ["ExperimentConfig", "ArgumentParser", "ConfigError", "get", "from_argv", "apply_overrides",
           "format_config", "to_dict", "variants"]
