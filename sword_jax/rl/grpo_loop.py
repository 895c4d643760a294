"""The GRPO run: steps through :func:`sword_jax.train_loop.run_steps`, an evaluation and a checkpoint every
``rl.grpo.eval_every`` steps, one success curve that never runs ahead of the checkpoint after a resume.

Whatever the simulator (the toy, the learned world model, the C-engine environments), a GRPO run is a
step ``step(state, batch, key) -> (state, metrics)`` whose batch, the step's start states, is a pure
function of the step (``batch_at``), so the train state (:class:`~sword_jax.rl.grpo.GRPOState`) is all an
exact resume needs: a run killed at any point and rerun in its work dir ends bit-identical to an
uninterrupted one. The step need not be one jitted function (in the real environments it rolls out in
the C engine, then applies the jitted update). The per-step history so far is written to
``<workdir>/train_history.jsonl`` after every step (so a run killed at any point leaves it, its closed-loop
record included). At step 0 of a fresh run, every ``rl.grpo.eval_every`` steps and at the last one, once the
step's loss was read finite, the policy is evaluated, the point is appended to
``<workdir>/success_curve.{json,png}``, then the state is checkpointed under ``<workdir>/checkpoints`` with the
run's identity and the history. A resume drops the curve's points after the checkpoint and writes the history
from the checkpoint's (what a killed run recorded before it could save), so they are recomputed, never
duplicated; a checkpoint of another run (another seed, simulator, learning rate ...) is refused, naming the
keys that differ.

Each step's wall time goes to ``<workdir>/step_times.jsonl`` (``step``, ``step_s``: from the previous step's
metrics read to this one's, evaluations left out; with ``frames_per_chunk``, ``imagined_frames`` and
``imagined_frames_per_s``: the frames the simulator rendered for the step's ``B x G`` rollouts over its
time, the groups ``rl.imagined.oversample`` rolls out beyond the update's included), apart from the
history, which stays bit-identical across a resume. The first step after a start or resume includes
compilation.

In a job of several processes every process runs the loop (the steps and checkpoints are global
computations) and takes the same decisions; only process 0 writes the curve, the history and the step times.

With ``rl.imagined.guard_margin > 0`` and evaluations that replay real episodes in the learned simulator
(their ``replay`` entry; with ``rl.imagined.guard_on=verify`` their ``verify`` entry, the refresh's check of the
policy's own imagined groups executed for real), the exploitation guard
(:class:`~sword_jax.rl.sim_guard.FalseSuccessGuard`) judges
every evaluation: when the replay's false-success rate exceeds step 0's by more than the margin, the policy
and its optimizer state go back to the last evaluation that passed (the last checkpoint, kept on the host),
the step counter goes on, and the point records the rollback (``guard``). A resumed run takes the baseline
from step 0's point and the restored checkpoint as the last state that passed, so it rolls back exactly as
an uninterrupted run does.

With ``rl.refresh.real_guard_margin > 0`` and evaluations that refresh the simulator on real episodes of the
current policy (their ``refresh`` entry), the real-success guard (:class:`~sword_jax.rl.sim_guard.RealSuccessGuard`)
judges every evaluation too: when a refresh's real success falls below step 0's by more than the margin, the
policy rolls back the same way. Either guard tripping rolls it back; the point's ``guard`` keeps the
false-success guard's verdict at its top level and the real-success guard's under ``real_success``. A resumed
run takes that baseline from the first judged ``refresh`` entry of the curve's points.
"""

from __future__ import annotations

import dataclasses
import json
import operator
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax

from sword_jax import sharding as shd
from sword_jax.atomic_write import write_jsonl_atomic
from sword_jax.rl.config import RLConfig
from sword_jax.rl.imagined_check import UNDEFINED_AS_NAN
from sword_jax.rl.policy_success import SuccessCurve
from sword_jax.rl.sim_guard import FalseSuccessGuard, RealSuccessGuard
from sword_jax.train_loop import LoopResult, StepFn, all_finite, run_steps

# RL config keys (paths under ``rl``) that shape a GRPO run's train state: a resumed run must share them with
# its checkpoint. Left out: grpo.steps (a run may be extended), the evaluation's settings, the SFT and
# reward-model knobs. The real-success guard's keys enter only when it is on (grpo_run_id).
GRPO_RUN_KEYS = ("grpo.group_size", "grpo.clip_low", "grpo.clip_high", "grpo.kl_coef", "grpo.learning_rate",
                 "grpo.ppo_epochs", "grpo.minibatches", "grpo.max_sample_rounds", "grpo.min_mixed_fraction",
                 "env.backend", "imagined.max_chunks", "chunk_len", "action_dim", "action_bins",
                 "success_threshold", "grpo.filter_groups", "grpo.success_bonus", "imagined.return_rule",
                 "grpo.loss_norm", "grpo.temperature", "policy.width", "policy.layers", "policy.heads",
                 "policy.max_instruction_bytes", "image_size", "proprio_dim", "policy.proprio_encoding",
                 "env.execute_steps", "imagined.execute_steps", "imagined.proprio", "imagined.success_frames",
                 "imagined.shared_group_noise", "env.proprio", "env.starts", "imagined.keyframe_fraction",
                 "grpo.update_microbatch", "grpo.rollout_batch", "imagined.guard_margin",
                 "imagined.guard_min_failures", "imagined.confirm_success")

REAL_GUARD_KEYS = ("refresh.real_guard_margin", "refresh.real_guard_min_episodes")

# evaluate(step, params) -> (curve point, extra entries stored beside it)
Evaluate = Callable[[int, Any], tuple[dict[str, Any], dict[str, Any]]]


def grpo_metrics_finite(metrics: dict[str, Any]) -> Any:
    """Whether a GRPO step was finite: every floating metric but those NaN by definition where an outcome is
    missing (:data:`~sword_jax.rl.imagined_check.UNDEFINED_AS_NAN`, e.g. the detector's false successes in a step
    whose trajectories all succeeded for real), which must not stop a run as a non-finite update would."""
    return all_finite({k: v for k, v in metrics.items() if k not in UNDEFINED_AS_NAN})


def grpo_run_id(rl: RLConfig, *, seed: int, simulator: str, **facts: Any) -> dict[str, Any]:
    """The identity a resumed GRPO run must share with its checkpoint (``run_steps``' ``run_id``).

    Args:
      rl: the run's RL config (``GRPO_RUN_KEYS`` enter as ``rl.<key>``).
      seed: the experiment seed (start states and sampling keys derive from it).
      simulator: ``toy``, ``world_model`` or ``env``.
      **facts: more facts under their config names, e.g. ``**{"sim.tasks": (0, 1)}``.
    """
    # the decoder enters only when it is not the default, so runs from before it was a setting still resume
    decoder = {"rl.imagined.decoder": rl.imagined.decoder} if rl.imagined.decoder != "full" else {}
    # likewise the real-success guard, which enters only when it is on
    keys = GRPO_RUN_KEYS + (REAL_GUARD_KEYS if rl.refresh.real_guard_margin > 0 else ())
    # and the learned simulator's oversampling, only when it is on
    oversample = {"rl.imagined.oversample": rl.imagined.oversample} if rl.imagined.oversample != 1 else {}
    # and the skip of under-filled batches, only when it is on
    skip = {"rl.grpo.min_mixed_groups": rl.grpo.min_mixed_groups} if rl.grpo.min_mixed_groups else {}
    # and what the exploitation guard reads, only when it is not the replay
    guard_on = {"rl.imagined.guard_on": rl.imagined.guard_on} if rl.imagined.guard_on != "replay" else {}
    # and what pays the imagined trajectories, only when it is not the detector
    reward = {"rl.imagined.reward": rl.imagined.reward} if rl.imagined.reward != "detector" else {}
    if rl.imagined.reward == "calibrated":  # and then the steps and the bound that set the detector's threshold
        reward.update({"rl.imagined.calibrate_steps": rl.imagined.calibrate_steps,
                       "rl.refresh.max_false_success": rl.refresh.max_false_success})
    # and the advantages' scale, only when it is not the group std
    scale = {"rl.grpo.scale_by_std": False} if not rl.grpo.scale_by_std else {}
    # and the shuffled-returns control, only when it is on
    shuffle = {"rl.grpo.shuffle_returns": True} if rl.grpo.shuffle_returns else {}
    # and the value that closes short rollouts, only when it is on
    value = ({f"rl.value.{f.name}": getattr(rl.value, f.name) for f in dataclasses.fields(rl.value)}
             if rl.value.episodes else {})
    # and the keyframes' lower bound, only when it is above the first keyframe
    keyframe_from = {"rl.imagined.keyframe_from": rl.imagined.keyframe_from} if rl.imagined.keyframe_from else {}
    return {"seed": seed, "simulator": simulator, **{f"rl.{k}": operator.attrgetter(k)(rl) for k in keys},
            **decoder, **oversample, **skip, **guard_on, **reward, **scale, **shuffle, **value, **keyframe_from,
            **facts}


def train_grpo(
    step: StepFn,
    state: Any,
    batch_at: Callable[[int], Any],
    *,
    key: jax.Array,
    rl: RLConfig,
    workdir: str,
    evaluate: Evaluate,
    run_id: dict[str, Any],
    progress: Callable[[dict[str, float], float], str],
    curve_label: str = "GRPO in the learned simulator",
    log: Callable[[str], Any] = print,
    frames_per_chunk: int = 0,
    place: Callable[[Any], Any] | None = None,
) -> tuple[LoopResult, list[dict[str, Any]]]:
    """Runs GRPO steps up to ``rl.grpo.steps`` from ``state``, resuming from ``<workdir>/checkpoints``.

    Args:
      step: ``step(state, batch, key) -> (state, metrics)``; it may donate its state.
      state: the initial :class:`~sword_jax.rl.grpo.GRPOState` (its shardings are what a resume restores into).
      batch_at: the batch of a 0-based step (its start states), a pure function of the step.
      key: the root key passed to every step (which folds in ``state.step``).
      rl: the RL config (``grpo_steps``, ``eval_every``).
      workdir: where the checkpoints and the success curve live.
      evaluate: ``evaluate(step_done, params) -> (point, extra)`` for the success curve.
      run_id: the run's identity (:func:`grpo_run_id`).
      progress: ``progress(point, eta_s) -> line``, the log line of a step (``point``: its metrics and ``step``).
      curve_label: the success curve's title.
      log: where progress and resume lines go.
      frames_per_chunk: frames the simulator renders per imagined chunk (0: not a learned simulator): its
        ``frames_per_step``, the executed actions' frames; with the step's ``mean_chunks`` metric (its
        ``mean_chunks_sampled`` with ``rl.imagined.oversample > 1``: every rolled-out trajectory's, over
        ``rl.imagined_starts_per_step x G`` of them) it gives ``step_times.jsonl``'s imagined frames per second.
      place: ``place(host_batch) -> batch`` before each step (:func:`~sword_jax.train_loop.run_steps`; e.g. the
        global start states assembled from each process's rows); None = the batch as ``batch_at`` made it.

    Returns:
      ``(loop result, success-curve points)``; the result's history holds every step's metrics of the run.

    Raises:
      sword_jax.train_loop.NonFiniteLoss: a non-finite loss or gradient (the last good checkpoint is kept).
      ValueError: the checkpoint in the work dir is another run's.
    """
    writes = jax.process_index() == 0
    curve = SuccessCurve(workdir, label=curve_label, writes=writes)
    # every rolled-out trajectory's frames, the oversampled groups the update leaves out included
    times = StepTimes(workdir, rl.imagined_starts_per_step * rl.grpo.group_size * frames_per_chunk, writes=writes)
    false_guard = (FalseSuccessGuard(rl.imagined.guard_margin, min_failures=rl.imagined.guard_min_failures)
                   if rl.imagined.guard_margin > 0 else None)
    real_guard = (RealSuccessGuard(rl.refresh.real_guard_margin, min_episodes=rl.refresh.real_guard_min_episodes)
                  if rl.refresh.real_guard_margin > 0 else None)
    # each guard that is on, the evaluation entry it judges and its name in the log
    guards = [(g, entry, name) for g, entry, name in ((false_guard, rl.imagined.guard_on, "exploitation guard"),
                                                      (real_guard, "refresh", "real-success guard")) if g is not None]
    passed: dict[str, Any] = {}  # the last state the guards passed, on the host, and its step

    def keep_passed(done: int, state: Any) -> None:
        passed.update(step=done, params=jax.device_get(state.params), opt_state=jax.device_get(state.opt_state))

    def roll_back(state: Any) -> Any:
        like = jax.tree.map(lambda x: x.sharding, (state.params, state.opt_state))
        params, opt_state = jax.device_put((passed["params"], passed["opt_state"]), like)
        return dataclasses.replace(state, params=params, opt_state=opt_state)

    def record(done: int, state: Any) -> Any:
        point, extra = evaluate(done, state.params)
        restored = None
        if guards:
            verdict: dict[str, Any] = {}
            tripped = []
            for g, entry, name in guards:
                decision = g.observe(extra.get(entry))
                if g is false_guard:
                    verdict.update(trip=decision.trip, false_success=decision.rate, baseline=decision.baseline,
                                   reason=decision.reason)
                else:
                    verdict["real_success"] = {"trip": decision.trip, "rate": decision.rate,
                                               "baseline": decision.baseline, "reason": decision.reason}
                if decision.trip:
                    tripped.append((name, decision.reason))
            if tripped:
                restored = roll_back(state)
                verdict["rolled_back_to"] = passed["step"]
                for name, reason in tripped:
                    log(f"GRPO step {done}: {name} tripped ({reason}); policy rolled back to step {passed['step']}")
            else:
                keep_passed(done, state)
            extra = dict(extra, guard=verdict)
        curve.add(done, point, **extra)
        return restored

    def at_checkpoint(done: int, state: Any, _history: list[dict[str, Any]]) -> Any:  # on disk already (on_history)
        restored = record(done, state)
        times.save()
        times.restart()  # the evaluation is not the next step's time
        return restored

    def on_start(first_step: int, state: Any) -> Any:
        # every array committed to its device, as a restored state's are: a resumed run then compiles the
        # same program as a fresh one (a cache hit), and the step's input types = output types (one trace)
        # (parameters loaded from a file arrive as numpy arrays, which have no sharding: the default device's)
        state = shd.settle(jax.device_put(state, jax.tree.map(
            lambda x: x.sharding if isinstance(x, jax.Array) else jax.devices()[0], state)))
        curve.drop_after(first_step)
        if first_step == 0:
            record(0, state)
        elif guards:  # as the uninterrupted run stood after this checkpoint
            for g, entry, _ in guards:
                for p in curve.points:
                    if p["step"] <= first_step and g.baseline is None:
                        g.observe(p.get(entry))
            at = next((p for p in curve.points if p["step"] == first_step), {}).get("guard", {})
            keep_passed(at.get("rolled_back_to", first_step), state)  # a rolled-back checkpoint holds that state
        times.drop_after(first_step)  # the clock starts at the first step, the evaluation before it left out
        return state

    def report(done: int, metrics: dict[str, float], _: Any, eta: float) -> dict[str, float]:
        point = {"step": done, **metrics}
        times.add(done, metrics.get("mean_chunks_sampled", metrics.get("mean_chunks")))
        log(progress(point, eta))
        return point

    result = run_steps(step, state, batch_at, key=key, steps=rl.grpo.steps, log_every=1, name="GRPO", report=report,
                       metrics_finite=grpo_metrics_finite,
                       checkpoint_dir=os.path.join(workdir, "checkpoints"), checkpoint_every=rl.grpo.eval_every,
                       run_id=run_id, log=log, on_start=on_start, at_checkpoint=at_checkpoint, place=place,
                       on_history=(lambda history: save_history(workdir, history)) if writes else None)
    if writes:
        save_history(workdir, result.history)  # also when no step ran (a finished run resumed, zero steps)
    times.save()
    return result, curve.points


class StepTimes:
    """Each GRPO step's wall time, kept in ``<workdir>/step_times.jsonl`` (module docstring).

    ``frames_per_chunk_batch``: frames rendered per imagined chunk across the step's rollouts (``B x G x``
    frames per chunk; 0: no imagined frames). A step's time runs from the previous :meth:`add` (or
    :meth:`restart`) to its own. ``writes=False`` or no ``workdir``: :meth:`save` writes nothing (without a
    ``workdir`` the rows are kept only in memory, e.g. ``benchmarks.bench_grpo_step``'s)."""

    def __init__(self, workdir: str | None, frames_per_chunk_batch: int = 0, *, writes: bool = True):
        self.path = os.path.join(workdir, "step_times.jsonl") if workdir else None
        self.per_chunk, self.writes = frames_per_chunk_batch, writes and self.path is not None
        self.rows: list[dict[str, float]] = []
        if self.path and os.path.exists(self.path):
            with open(self.path) as f:
                self.rows = [json.loads(line) for line in f if line.strip()]
        self.last = time.perf_counter()

    def restart(self) -> None:
        self.last = time.perf_counter()

    def drop_after(self, step: int) -> None:
        """Forgets steps after ``step`` (a resumed run times them again) and restarts the clock."""
        self.rows = [r for r in self.rows if r["step"] <= step]
        self.restart()

    def add(self, step: int, mean_chunks: float | None) -> dict[str, float]:
        now = time.perf_counter()
        row = {"step": step, "step_s": now - self.last}
        if self.per_chunk and mean_chunks is not None:
            row["imagined_frames"] = self.per_chunk * mean_chunks
            row["imagined_frames_per_s"] = row["imagined_frames"] / max(row["step_s"], 1e-9)
        self.rows = [r for r in self.rows if r["step"] != step] + [row]
        self.last = now
        return row

    def save(self) -> None:
        if self.writes:
            write_jsonl_atomic(self.path, self.rows)


def read_history(workdir: str) -> list[dict[str, Any]]:
    """The rows of ``<workdir>/train_history.jsonl``; none where it is not there."""
    path = os.path.join(workdir, "train_history.jsonl")
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def save_history(workdir: str, history: Sequence[dict[str, Any]]) -> None:
    """``<workdir>/train_history.jsonl``: the run's per-step metrics, restored steps included (replaced
    atomically, so a run killed while writing leaves the previous checkpoint's)."""
    write_jsonl_atomic(os.path.join(workdir, "train_history.jsonl"), history)
