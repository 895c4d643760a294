"""Resumable stages: what the pipeline (``python -m train.pipeline``) and the comparison run.

Each stage writes ``<workdir>/stages/<name>.json`` (atomically) when it finishes; a rerun skips
finished stages and reuses their recorded results. The config a workdir was made with is stored in
``<workdir>/config.json``; resuming with a different config is refused, naming the keys that differ.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import time
from collections.abc import Callable, Sequence
from typing import Any

from configs.cli import to_dict
from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic


@dataclasses.dataclass(frozen=True)
class Stage:
    """One resumable step. ``needs``: the stages whose results it reads when they are part of the run
    (a stage left out with ``--skip`` is not waited for); they decide what may run side by side."""

    name: str
    run: Callable[["Context"], dict[str, Any]]
    description: str = ""
    needs: tuple[str, ...] = ()


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

def _diff(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = sorted(set(a) | set(b))
        return [d for k in keys for d in _diff(a.get(k), b.get(k), f"{prefix}{k}.")]
    return [] if a == b else [prefix.rstrip(".")]


def _added_at_default(cfg: Any, stored: dict, key: str) -> bool:
    """Whether dotted ``key`` is absent from a stored config and holds its field's default in ``cfg``: a setting
    added after that run was made, at the value that keeps the behaviour it ran with."""
    node, value = stored, cfg
    for part in key.split("."):
        if not isinstance(node, dict) or not dataclasses.is_dataclass(value):
            return False
        if part not in node:
            field = next((f for f in dataclasses.fields(value) if f.name == part), None)
            if field is None or field.default is dataclasses.MISSING:
                return False
            return getattr(value, part) == field.default
        node, value = node[part], getattr(value, part, None)
    return False


def _scoring_keys() -> frozenset[str]:
    from sword_jax.metrics.config import EvalConfig

    return frozenset(f"eval.{name}" for name in EvalConfig.scoring_fields)


def check_workdir_config(cfg: Any, workdir: str) -> None:
    """Stores the config on first use; refuses a different one later (names differing keys). A setting that the
    stored config lacks (added since) counts as equal when it holds its default. How the evaluation scores
    (``EvalConfig.scoring_fields``, read by the evaluate stage alone) may change until that stage has run: the stored
    config then takes the new values; once it has run they are refused with the rest."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, "config.json")
    current = to_dict(cfg)
    if os.path.exists(path):
        with open(path) as f:
            stored = json.load(f)
        differing = [k for k in _diff(stored, current) if k != "workdir" and not _added_at_default(cfg, stored, k)]
        evaluated = os.path.exists(os.path.join(workdir, "stages", "evaluate.json"))
        if differing and not evaluated and set(differing) <= _scoring_keys():
            write_json_atomic(path, current, sort_keys=True)  # the evaluation, not yet run, scores as now asked
            return
        if differing:
            scored = [k for k in differing if k in _scoring_keys()] if evaluated else []
            hint = (f"; the evaluation already ran with the stored {', '.join(scored)} (python -m "
                    "train.evaluate_world_model scores the run's world model with other settings)" if scored else "")
            raise ValueError(
                f"{workdir} was made with a different config (keys: {', '.join(differing[:12])}){hint}; "
                "use a new --workdir, or --restart to discard that run's stages"
            )
        return
    write_json_atomic(path, current, sort_keys=True)


def _marker(ctx: Context, name: str) -> str:
    return ctx.path("stages", f"{name}.json")


def _load_finished(ctx: Context, name: str) -> bool:
    """Reads a finished stage's recorded results into ``ctx.results``; False if it has not finished."""
    marker = _marker(ctx, name)
    if not os.path.exists(marker):
        return False
    with open(marker) as f:
        ctx.results[name] = json.load(f)["results"]
    return True


def check_needs(stages: list[Stage], ctx: Context, only: set[str] | None) -> None:
    """Refuses an ``--only`` set one of whose stages needs a stage of this run that has neither
    finished nor been named in it (naming both)."""
    if only is None:
        return
    names = {s.name for s in stages}
    for stage in stages:
        if stage.name not in only or os.path.exists(_marker(ctx, stage.name)):
            continue
        for need in stage.needs:
            if need in names and need not in only and not os.path.exists(_marker(ctx, need)):
                raise RuntimeError(f"stage {stage.name!r} needs {need!r}, which has not run yet and is not among "
                                   f"--only {sorted(only)}")


def run_stages(stages: list[Stage], ctx: Context, *, only: set[str] | None = None, log=print) -> dict[str, Any]:
    """Runs the stages in order, skipping finished ones (and, with ``only``, those not named in it,
    which are left for a later run); returns every finished stage's results."""
    check_needs(stages, ctx, only)
    for index, stage in enumerate(stages):
        if _load_finished(ctx, stage.name):
            log(f"[{index + 1}/{len(stages)}] {stage.name}: done earlier, skipped")
            continue
        if only is not None and stage.name not in only:
            continue
        log(f"[{index + 1}/{len(stages)}] {stage.name}: {stage.description}")
        start = time.perf_counter()
        results = stage.run(ctx)
        seconds = time.perf_counter() - start
        ctx.results[stage.name] = {**results, "seconds": round(seconds, 2)}
        write_json_atomic(_marker(ctx, stage.name), {"stage": stage.name, "results": ctx.results[stage.name]},
                          sort_keys=True)
        log(f"[{index + 1}/{len(stages)}] {stage.name}: finished in {seconds:.1f} s")
    return ctx.results


def run_stages_parallel(stages: list[Stage], ctx: Context, launch: Callable[[Stage], subprocess.Popen], *,
                        max_running: int = 2, poll_s: float = 1.0, log=print) -> dict[str, Any]:
    """Runs the unfinished stages each in its own process, a stage as soon as the stages of this run
    it ``needs`` have finished, at most ``max_running`` at a time, in list order where several are
    ready (e.g. the VAE trains while the policy is cloned and rolled out).

    ``launch(stage)`` starts the process that runs ``stage`` and writes its marker (``train.pipeline
    --parallel`` re-invokes itself with ``--only STAGE``). A stage counts as finished when its
    process exits 0 and its marker exists. When one fails, no new stage starts; those running are
    waited for (what they finish is kept, as with any finished stage) and then ``RuntimeError``
    names the failed stages. Results do not depend on the schedule: a stage reads only its needs.

    A stop request (:func:`sword_jax.cli.request_stop`, ``SIGUSR1`` under ``cli.run``) is passed on once to every
    running stage (each checkpoints its step in flight and exits ``cli.STOPPED_EXIT``) and starts no more; once they
    have ended, :class:`~sword_jax.cli.StopRequested` names the stages stopped and those not started (the same
    command resumes them). Failed stages still raise ``RuntimeError``, which names the stopped ones as well.
    """
    if max_running < 1:
        raise ValueError(f"max_running must be >= 1, got {max_running}")
    names = [s.name for s in stages]
    index = {name: i for i, name in enumerate(names)}
    pending = []
    for stage in stages:
        if _load_finished(ctx, stage.name):
            log(f"[{index[stage.name] + 1}/{len(stages)}] {stage.name}: done earlier, skipped")
        else:
            pending.append(stage)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    failed: list[str] = []
    stopped: list[str] = []
    forwarded = False  # the stop request passed on to the running stages
    while pending or running:
        if (cli.stop_requested() or stopped) and not forwarded:
            forwarded = True
            asked = cli.ask_to_stop(proc for proc, _ in running.values())
            log(f"stop requested: asked {asked} running stage(s) to stop; no more stages start")
        for stage in list(pending):
            if failed or stopped or cli.stop_requested() or len(running) >= max_running:
                break
            if all(need not in index or need in ctx.results for need in stage.needs):
                pending.remove(stage)
                running[stage.name] = (launch(stage), time.perf_counter())
                log(f"[{index[stage.name] + 1}/{len(stages)}] {stage.name}: started ({stage.description})")
        if not running:
            break  # a failure stopped the rest (a cycle cannot happen: needs are checked against the order)
        time.sleep(poll_s)
        for name, (proc, start) in list(running.items()):
            code = proc.poll()
            if code is None:
                continue
            del running[name]
            if code == 0 and _load_finished(ctx, name):
                log(f"[{index[name] + 1}/{len(stages)}] {name}: finished in {time.perf_counter() - start:.1f} s")
            elif code == cli.STOPPED_EXIT:
                stopped.append(name)
                log(f"[{index[name] + 1}/{len(stages)}] {name}: stopped on request (resumes)")
            else:
                failed.append(name)
                log(f"[{index[name] + 1}/{len(stages)}] {name}: FAILED (exit code {code})")
    left = [s.name for s in pending]
    if failed:
        raise RuntimeError(f"stage(s) {', '.join(failed)} failed"
                           + (f"; stopped on request: {', '.join(stopped)}" if stopped else "")
                           + (f"; not started: {', '.join(left)}" if left else ""))
    if stopped or (cli.stop_requested() and left):
        raise cli.StopRequested(f"stopped on request: {', '.join(stopped) or 'no stage running'}"
                                + (f"; not started: {', '.join(left)}" if left else "") + "; the same command resumes")
    return ctx.results


def check_order(stages: list[Stage]) -> None:
    """Every stage's needs come earlier in the list (the sequential order is then a valid schedule)."""
    seen: set[str] = set()
    for stage in stages:
        unknown = [n for n in stage.needs if n not in seen]
        if unknown:
            raise ValueError(f"stage {stage.name!r} needs {unknown}, which do not come before it")
        seen.add(stage.name)


def cpu_workers() -> int:
    """Worker processes for C-engine work (data generation, real-environment evaluation): all cores
    but two, at most 14; 0 = in this process. Results do not depend on it (episodes are independent)."""
    return min(14, max(0, (os.cpu_count() or 1) - 2))


def without_flags(argv: Sequence[str], flags: dict[str, bool]) -> list[str]:
    """``argv`` less the given flags (``flag: takes a value``), in ``--flag v`` or ``--flag=v`` form."""
    out, skip_next = [], False
    for arg in argv:
        if skip_next:
            skip_next = False
            continue
        name = arg.split("=", 1)[0]
        if name in flags:
            skip_next = flags[name] and "=" not in arg
            continue
        out.append(arg)
    return out
