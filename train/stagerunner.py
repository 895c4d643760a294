"""Resumable stages for the pipeline entry point.

Each stage writes ``<workdir>/stages/<name>.json`` (atomically) when it finishes; a rerun skips
finished stages and reuses their recorded results. The config a workdir was made with is stored in
``<workdir>/config.json``; resuming with a different config is refused, naming the keys that differ.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable
from typing import Any

from configs.cli import to_dict


@dataclasses.dataclass(frozen=True)
class Stage:
    name: str
    run: Callable[["Context"], dict[str, Any]]
    description: str = ""


@dataclasses.dataclass
class Context:
    """What stages share: the config, the work dir and finished stages' results."""

    cfg: Any
    workdir: str
    results: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    cfg_name: str = "sword:tiny"  # experiment:variant the config came from (for the report)
    overrides: list[str] = dataclasses.field(default_factory=list)  # its dotted overrides (for the report)
    is_main: bool = True  # process 0

    def path(self, *parts: str) -> str:
        """A file under the work dir; its folder is made."""
        full = os.path.join(self.workdir, *parts)
        os.makedirs(os.path.dirname(full), exist_ok=True)
        return full

    def stage_dir(self, *parts: str) -> str:
        """A folder under the work dir (made), e.g. the work dir a stage's trainer writes into."""
        full = os.path.join(self.workdir, *parts)
        os.makedirs(full, exist_ok=True)
        return full

    def cfg_in(self, workdir: str, **sections) -> Any:
        """The pipeline's config with ``workdir`` (and whole sections in ``sections``) replaced: what a
        stage hands an entry point's ``run``."""
        return dataclasses.replace(self.cfg, workdir=workdir, **sections)


def write_json_atomic(path: str, payload: Any) -> None:
    tmp = f"{path}.tmp.{os.getpid()}"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=1, sort_keys=True, default=_json_default)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):
        return value.tolist()
    if dataclasses.is_dataclass(value):
        return dataclasses.asdict(value)
    return str(value)


def _diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = sorted(set(a) | set(b))
        return [d for k in keys for d in _diff(a.get(k), b.get(k), f"{prefix}{k}.")]
    return [] if a == b else [prefix.rstrip(".")]


def check_workdir_config(cfg: Any, workdir: str) -> None:
    """Stores the config on first use; refuses a different one later (names differing keys)."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, "config.json")
    current = to_dict(cfg)
    if os.path.exists(path):
        with open(path) as f:
            stored = json.load(f)
        differing = [k for k in _diff(stored, current) if k != "workdir"]
        if differing:
            raise ValueError(
                f"{workdir} was made with a different config (keys: {', '.join(differing[:12])}); "
                "use a new --workdir, or --restart to discard that run's stages"
            )
        return
    write_json_atomic(path, current)


def run_stages(stages: list[Stage], ctx: Context, *, only: set[str] | None = None, log=print) -> dict[str, Any]:
    """Runs the stages in order, skipping finished ones; returns every stage's results."""
    for index, stage in enumerate(stages):
        marker = ctx.path("stages", f"{stage.name}.json")
        if os.path.exists(marker):
            with open(marker) as f:
                ctx.results[stage.name] = json.load(f)["results"]
            log(f"[{index + 1}/{len(stages)}] {stage.name}: done earlier, skipped")
            continue
        if only is not None and stage.name not in only:
            raise RuntimeError(f"stage {stage.name!r} has not run yet and is not among --only {sorted(only)}")
        log(f"[{index + 1}/{len(stages)}] {stage.name}: {stage.description}")
        start = time.perf_counter()
        results = stage.run(ctx)
        seconds = time.perf_counter() - start
        ctx.results[stage.name] = {**results, "seconds": round(seconds, 2)}
        write_json_atomic(marker, {"stage": stage.name, "results": ctx.results[stage.name]})
        log(f"[{index + 1}/{len(stages)}] {stage.name}: finished in {seconds:.1f} s")
    return ctx.results


def cpu_workers() -> int:
    """Worker processes for C-engine work (data generation, real-environment evaluation): all cores
    but two, at most 14; 0 = in this process. Results do not depend on it (episodes are independent)."""
    return min(14, max(0, (os.cpu_count() or 1) - 2))
