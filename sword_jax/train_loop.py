"""The step loop of every trainer (VAE, world model, SFT, reward model, GRPO): resume, late metrics, checkpoints.

:func:`run_steps` drives a jitted ``step(state, batch, key) -> (state, metrics)`` whose batch is a
pure function of the step (``batch_at(step)``, e.g. drawn from ``rng.stream_rng(seed, name, step)``),
so the train state alone (params, optimizer state, step, the latent cache) is all an exact resume
needs. With a checkpoint directory it resumes from the newest checkpoint there and saves one every
``checkpoint_every`` steps and at the end, through :class:`~sword_jax.checkpoint.Checkpointer`
(with ``checkpoint_meta(step)``'s JSON facts, e.g. the data position, RNG root and config). ``place``
puts each host batch on the mesh (global arrays) on the loop's thread.

The host reads a log step's metrics after the next step was dispatched, so the device never waits
on it. Every step's metrics go through a small device-side check that remembers the first step
with a non-finite value; it is read with the metrics and before each checkpoint, so a checkpoint
is written only once its step's loss was read finite, and a non-finite loss stops the run with
:class:`NonFiniteLoss` naming the step, the last good checkpoint left as it was (``on_nonfinite="skip"``
goes on instead, for a step that skips a non-finite update itself).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from sword_jax import checkpoint, cli
from sword_jax import sharding as shd
from sword_jax.prefetch import prefetched

StepFn = Callable[[Any, Any, jax.Array], tuple[Any, dict[str, jax.Array]]]


class NonFiniteLoss(FloatingPointError):
    """A step's loss (or gradient norm, or another metric) was non-finite; the run stopped."""


class AnotherRunsCheckpoint(ValueError):
    """The checkpoint directory holds a checkpoint of another run (its ``run_id`` differs)."""


@dataclasses.dataclass
class LoopResult:
    """What :func:`run_steps` ends with.

    Attributes:
      state: the final train state.
      metrics: the last step's metrics (device arrays; empty when no step ran).
      history: one ``report`` point per log step of the whole run (restored ones included).
      first_step: steps already done when this call started (> 0 after a resume).
    """

    state: Any
    metrics: dict[str, jax.Array]
    history: list[dict[str, Any]]
    first_step: int


def all_finite(metrics: dict[str, jax.Array]) -> jax.Array:
    """True when every floating metric is finite (the default finite test of :func:`run_steps`)."""
    finite = jnp.bool_(True)
    for value in jax.tree.leaves(metrics):
        if jnp.issubdtype(value.dtype, jnp.floating):
            finite = finite & jnp.all(jnp.isfinite(value))
    return finite


@functools.partial(jax.jit, static_argnames="metrics_finite")
def _note_nonfinite(first_bad: jax.Array, step: jax.Array, metrics: dict[str, jax.Array], *,
                    metrics_finite: Callable[[dict[str, jax.Array]], jax.Array] = all_finite) -> jax.Array:
    """``first_bad``, or ``step`` if it is still -1 and ``metrics_finite(metrics)`` is False."""
    return jnp.where((first_bad < 0) & ~metrics_finite(metrics), step, first_bad).astype(jnp.int32)


def differing_keys(saved: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """The top-level keys (config sections) whose values differ between two run descriptions, sorted."""
    return sorted(k for k in set(saved) | set(current) if saved.get(k) != current.get(k))


def _check_same_run(name: str, directory: str, saved: Any, current: dict[str, Any] | None) -> None:
    if current is None or saved == current:
        return
    differ = differing_keys(saved if isinstance(saved, dict) else {}, current)
    raise AnotherRunsCheckpoint(f"{name}: the checkpoint in {directory} was made by another run (differs in "
                                f"{differ}); use a new work dir or remove it")


def run_steps(
    step: StepFn,
    state: Any,
    batch_at: Callable[[int], Any],
    *,
    key: jax.Array,
    steps: int,
    log_every: int,
    name: str,
    report: Callable[[int, dict[str, float], Any, float], dict[str, Any]],
    observe: Callable[[Any], Any] | None = None,
    checkpoint_dir: str | None = None,
    checkpoint_every: int = 1,
    run_id: dict[str, Any] | None = None,
    log: Callable[[str], Any] = print,
    on_start: Callable[[int, Any], Any] | None = None,
    at_checkpoint: Callable[[int, Any, list[dict[str, Any]]], Any] | None = None,
    place: Callable[[Any], Any] | None = None,
    checkpoint_meta: Callable[[int], dict[str, Any]] | None = None,
    keep_checkpoints: int = 2,
    metrics_finite: Callable[[dict[str, jax.Array]], jax.Array] = all_finite,
    on_nonfinite: str = "stop",
    settle: bool = False,
    on_first_step: Callable[[], Any] | None = None,
    on_history: Callable[[list[dict[str, Any]]], Any] | None = None,
    stop_requested: Callable[[], bool] | None = cli.stop_requested,
) -> LoopResult:
    """Runs steps ``first_step .. steps - 1`` (0-based) of ``step`` from ``state``.

    Args:
      step: the jitted step; it may donate its state (or any callable of that signature, e.g. GRPO's
        rollout in the C engine followed by its jitted update).
      state: the initial train state (its structure and shardings are what a checkpoint restores into).
      batch_at: the batch of a 0-based step, a pure function of it (made one step ahead on a thread).
      key: the root key passed to every step (which folds in its own step counter).
      steps: total steps of the run.
      log_every: steps between log points (the last step is one too).
      name: the trainer's name in messages (``"SFT"``, ``"reward model"``).
      report: ``report(step_done, metrics, observed, eta_s) -> point``, called one step late with host
        values; logs the point and returns what goes into the history.
      observe: ``observe(state) -> device pytree`` dispatched on a log step's state before the next
        step may donate it (e.g. held-out metrics); read with that step's metrics.
      checkpoint_dir: where checkpoints live; None = no checkpoints and no resume.
      checkpoint_every: steps between checkpoints (the last step is always saved).
      run_id: JSON-able facts a resumed run must share with the checkpoint (seed, batch size, ...); compared
        as JSON gives them back (a tuple equals the list the checkpoint stored).
      log: where the resume line goes.
      on_start: ``on_start(first_step, state) -> state``, called once after any resume and before the first
        step; the loop runs from the state it returns (GRPO settles it, forgets evaluations a killed run
        recorded after its checkpoint, and evaluates step 0 of a fresh run).
      at_checkpoint: ``at_checkpoint(step_done, state, history) -> state | None`` at every checkpoint step
        (every ``checkpoint_every`` steps and the last; also without a checkpoint directory), once that step's
        metrics were read finite and before its checkpoint is written, with the run's history up to that step
        (GRPO evaluates the policy and writes the history there). A state it returns replaces the loop's
        (GRPO's exploitation guard rolls the policy back); None keeps it.
      place: ``place(host_batch) -> batch`` on the loop's thread before the step (e.g. global arrays
        with the step's input shardings); None = the batch as ``batch_at`` made it.
      checkpoint_meta: ``checkpoint_meta(step_done) -> dict`` of further JSON facts saved with each
        checkpoint (data position, RNG root, config); they may not use the loop's own keys.
      keep_checkpoints: how many checkpoints stay (the newest).
      metrics_finite: ``metrics_finite(metrics) -> bool scalar``, traced: whether a step was finite
        (default: every floating metric is, see :func:`all_finite`).
      on_nonfinite: ``"stop"`` raises :class:`NonFiniteLoss`; ``"skip"`` goes on (for a step that
        leaves its state unchanged when non-finite) and keeps saving checkpoints.
      settle: pass the state (initial or restored) through :func:`sword_jax.sharding.settle` before the
        first step, so a step with explicit shardings traces once.
      on_first_step: called once the first step of this call has finished (the loop waits for it),
        e.g. to log the compile time apart from the step rate.
      on_history: ``on_history(history)`` after every log step's point joins the history (restored points
        included), e.g. to keep it on disk so that a run killed between checkpoints leaves it (GRPO).
      stop_requested: read after each step is dispatched (default: the process's stop request,
        :func:`sword_jax.cli.stop_requested`, which ``SIGUSR1`` sets under :func:`sword_jax.cli.run`); once it
        says yes, that step is read, treated as a checkpoint step (``at_checkpoint``, then the checkpoint) and
        :class:`~sword_jax.cli.StopRequested` is raised: the same call later resumes there. Read in
        single-process runs only (processes would see it at different steps); None = never.

    Raises:
      NonFiniteLoss: a step's metrics held a non-finite value (the message names the 0-based step and
        the last good checkpoint).
      sword_jax.cli.StopRequested: a stop was requested (``stop_requested``); the message names the step
        checkpointed.
      ValueError: the checkpoint in ``checkpoint_dir`` is from another run (``run_id``: an
        :class:`AnotherRunsCheckpoint`, or structure), or ``on_nonfinite`` is neither ``"stop"`` nor ``"skip"``.
      sword_jax.checkpoint.CheckpointInUse: another live process writes ``checkpoint_dir``
        (:class:`~sword_jax.checkpoint.WriterLock`, held by process 0 for the whole call).
    """
    if on_nonfinite not in ("stop", "skip"):
        raise ValueError(f"{name}: on_nonfinite must be 'stop' or 'skip', got {on_nonfinite!r}")
    if run_id is not None:  # as a checkpoint's JSON gives it back (tuples as lists), so a resume compares equal
        run_id = json.loads(json.dumps(run_id))
    # one writer per run: a second process started on the same checkpoint directory is refused here
    lock = checkpoint.WriterLock(checkpoint_dir, name) if checkpoint_dir and jax.process_index() == 0 else None
    ckpt, first_step, history, batches = None, 0, [], None
    try:
        ckpt = checkpoint.Checkpointer(checkpoint_dir, max_to_keep=keep_checkpoints) if checkpoint_dir else None
        if ckpt is not None and ckpt.latest_step() is not None:
            state, meta = ckpt.restore(checkpoint.abstract_like(state))
            _check_same_run(name, ckpt.directory, meta.get("run"), run_id)
            first_step, history = int(meta["step"]), list(meta.get("history", []))  # none before this loop
            log(f"{name}: resumed from step {first_step} in {ckpt.directory}")
        if settle:
            state = shd.settle(state)
        if on_start is not None:
            state = on_start(first_step, state)
        first_bad = jnp.full((), -1, jnp.int32)
        dispatched, pending, metrics = first_step, None, {}
        start = time.perf_counter()

        def stop_if_nonfinite(bad: jax.Array) -> None:
            bad_step = int(jax.device_get(bad))
            if bad_step >= 0 and on_nonfinite == "stop":
                last = None if ckpt is None else ckpt.latest_step()
                kept = ("no checkpoints (no checkpoint directory)" if ckpt is None else
                        f"last good checkpoint: {'none' if last is None else f'step {last}'} in {ckpt.directory}")
                raise NonFiniteLoss(f"{name}: non-finite loss or gradient at step {bad_step} (0-based); "
                                    f"stopped after step {dispatched}; {kept}")

        def read(done: int, step_metrics: dict, observed: Any, bad: jax.Array) -> None:
            stop_if_nonfinite(bad)
            host = {k: float(v) for k, v in jax.device_get(step_metrics).items()}
            eta = (time.perf_counter() - start) / max(dispatched - first_step, 1) * (steps - done)
            history.append(report(done, host, jax.device_get(observed), eta))
            if on_history is not None:
                on_history(history)

        stoppable, stopping = stop_requested is not None and jax.process_count() == 1, False
        batches = prefetched(batch_at, range(first_step, steps))
        for i, batch in enumerate(batches, start=first_step):
            state, metrics = step(state, batch if place is None else place(batch), key)
            first_bad = _note_nonfinite(first_bad, i, metrics, metrics_finite=metrics_finite)
            dispatched = i + 1
            stopping = stoppable and dispatched < steps and stop_requested()
            if on_first_step is not None and i == first_step:
                jax.block_until_ready(metrics)
                on_first_step()
            if pending is not None:  # the previous log step: the device already has this step queued
                read(*pending)
                pending = None
            if dispatched % log_every == 0 or dispatched == steps or stopping:
                pending = (dispatched, metrics, observe(state) if observe else None, first_bad)
            boundary = dispatched % checkpoint_every == 0 or dispatched == steps or stopping
            if boundary and (ckpt is not None or at_checkpoint is not None):
                if pending is not None:
                    read(*pending)
                    pending = None
                stop_if_nonfinite(first_bad)  # only a step read finite is saved
                if at_checkpoint is not None:
                    replaced = at_checkpoint(dispatched, state, history)
                    state = state if replaced is None else replaced
                if ckpt is not None:
                    extra = checkpoint_meta(dispatched) if checkpoint_meta is not None else {}
                    ckpt.save(dispatched, state, {**extra, "step": dispatched, "history": history, "run": run_id})
            if stopping:
                break
        if pending is not None:
            read(*pending)
        stop_if_nonfinite(first_bad)
        if stopping:
            kept = ("no checkpoint (no checkpoint directory)" if ckpt is None
                    else f"checkpoint of step {dispatched} in {ckpt.directory}; the same command resumes from it")
            raise cli.StopRequested(f"{name}: stopped on request after step {dispatched} of {steps}; {kept}")
    finally:
        try:
            if batches is not None:
                batches.close()
            if ckpt is not None:
                ckpt.close()
        finally:
            if lock is not None:
                lock.release()
    return LoopResult(state, metrics, history, first_step)
