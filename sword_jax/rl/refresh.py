"""Keeping the learned simulator honest while GRPO moves the policy: refresh it on the policy's real episodes.

GRPO inside a world model that never sees the moving policy's consequences learns what the simulator and
its success detector call success (measured on `small`: real success fell in all six world-model slices
while imagined success rose). Peers refit the model on the evolving policy's own rollouts (WoVR's PACE,
WMPO, MBPO) and branch short imagined rollouts from real states (MBPO). A :class:`Refresher` does this
every ``rl.refresh.every`` GRPO steps (:class:`~sword_jax.rl.config.RefreshConfig`):

1. **Collect** ``rl.refresh.episodes`` real episodes of the current policy (``collect``, e.g. MJX through
   :func:`~sword_jax.rl.scan_rollout.record_episodes`), within the run's budget of real episodes.
2. **Measure** before changing anything: the new episodes' actions replayed open loop in the simulator
   GRPO trained in, scored by its detector: ``replay`` (false and missed success, imagined success by
   horizon), what the exploitation guard (:mod:`sword_jax.rl.sim_guard`) judges.
3. **World model**: fine-tuned on the run's training latents plus every refresh's episodes so far, its
   DLB cache refreshed (a new cache over the new dataset, its schedule run again over the fine-tune). With
   ``rl.refresh.closed_loop_starts``, a share of every batch's rows are segments of its own closed loop set against
   reality (:mod:`~sword_jax.rl.closed_loop`: the policy's imagined trajectories from keyframe starts, their actions
   executed for real), every 8th trajectory's held out and measured before and after (the record's
   ``closed_loop``).
4. **Detector**: fine-tuned on the real frames (the task's success predicate as label) and on the new
   world model's replays of the real episodes labelled with their real outcome
   (:func:`~sword_jax.rl.sim_agreement.replay_labels`); its threshold is then set on replays of held-out
   episodes, over as many actions as GRPO's imagined rollouts run (``rl.refresh.calibrate_over``), so that
   at most ``max_false_success`` of their real failures are imagined successes
   (:func:`~sword_jax.rl.sim_agreement.calibrate_threshold`) or so that it separates their real outcomes
   best (``rl.refresh.calibration=separation``), applied as a logit shift
   (:func:`~sword_jax.rl.reward_model.shifted_reward_model`). Precision and recall are reported on the
   held-out episodes' imagined and real frames, and on their real frames at the run's threshold with the
   detector before and after the fine-tune (``real_frames_run_threshold``).
5. **Branch**: the next imagined rollouts start from the new real episodes' states, every phase before
   their success (``rl.refresh.branch``).

Every start this encodes from real frames (the branch starts, the replays' starts) is encoded as
``rl.imagined.start_encoding`` says, as GRPO's own keyframe starts are.

Each refresh is saved under ``<directory>/step_XXXXXX`` (world model, detector, shift, the round's latents
and real episodes, a ``record.json`` written last), so a resumed GRPO run loads the refresh its
checkpoint followed (:meth:`Refresher.at`) and ends as an uninterrupted one does; a refresh already on
disk is loaded, not recollected.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax import sharding as shd
from sword_jax.atomic_write import write_json_atomic
from sword_jax.rl import data as rl_data
from sword_jax.rl import sim_agreement
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel
from sword_jax.rl.policy import resize_frames
from sword_jax.rl.reward_model import (detector_report, make_detector_step, score_episodes, shifted_reward_model,
                                      threshold_shift, train_detector)
from sword_jax.rl.rollout import success_runs
from sword_jax.rl.scan_rollout import RecordedEpisodes
from sword_jax.rng import stream_key, stream_rng, stream_seed


@functools.partial(jax.jit, static_argnums=1)
def _resized_uint8(frames: jax.Array, size: int) -> jax.Array:
    return jnp.clip(jnp.round(resize_frames(frames, size) * 255.0), 0, 255).astype(jnp.uint8)


def detector_sized(frames: np.ndarray, size: int) -> np.ndarray:
    """uint8 episodes ``[n, T, H, W, 3]`` at ``size x size``, the success detector's input size (the resize it
    applies to every frame, :func:`~sword_jax.rl.policy.resize_frames`, done once and stored as uint8)."""
    if frames.shape[2:4] == (size, size):
        return frames
    return np.stack([np.asarray(_resized_uint8(episode, size)) for episode in frames])


@dataclasses.dataclass(frozen=True)
class RealEpisodes:
    """Real episodes of fixed length ``T`` recorded whole (host arrays).

    Attributes:
      frames: ``[n, T + 1, H, W, 3]`` uint8, frame ``t`` seen before action ``t``.
      proprio: ``[n, T + 1, P]``.
      actions: ``[n, T, A]`` executed.
      success: ``[n, T]`` bool, the success predicate after action ``t``.
      instructions: the ``n`` instructions.
      tasks: ``[n]`` task ids.
    """

    frames: np.ndarray
    proprio: np.ndarray
    actions: np.ndarray
    success: np.ndarray
    instructions: tuple[str, ...]
    tasks: np.ndarray

    def __post_init__(self):
        n, t = self.actions.shape[:2]
        if self.frames.shape[:2] != (n, t + 1) or self.frames.dtype != np.uint8 or self.success.shape != (n, t):
            raise ValueError(f"RealEpisodes: frames [n, T + 1, H, W, 3] uint8 and success [n, T] for actions "
                             f"{self.actions.shape}, got {self.frames.shape} {self.frames.dtype}, {self.success.shape}")
        if len(self.instructions) != n or self.tasks.shape != (n,):
            raise ValueError("RealEpisodes: one instruction and task per episode")

    @classmethod
    def from_recorded(cls, rec: RecordedEpisodes, instructions, tasks) -> "RealEpisodes":
        return cls(np.asarray(rec.frames, np.uint8), np.asarray(rec.proprio, np.float32),
                   np.asarray(rec.actions, np.float32), np.asarray(rec.success, bool), tuple(instructions),
                   np.asarray(tasks, np.int64))

    @property
    def num(self) -> int:
        return int(self.actions.shape[0])

    @property
    def solved(self) -> np.ndarray:
        """``[n]`` whether the task was solved at some action (the episode's real outcome)."""
        return self.success.any(axis=1)

    @property
    def lengths(self) -> np.ndarray:
        """``[n]`` actions up to and including the first success (``T`` where none): the episode as an
        evaluation that stops at success would have run it."""
        t = self.actions.shape[1]
        return np.where(self.solved, np.argmax(self.success, axis=1) + 1, t).astype(np.int64)

    def episode_set(self) -> rl_data.EpisodeSet:
        """Every frame before an action, with the success predicate of the state each frame shows."""
        n, t = self.actions.shape[:2]
        frame_success = np.concatenate([np.zeros((n, 1), bool), self.success[:, :-1]], axis=1)
        return rl_data.EpisodeSet(frames=self.frames[:, :t], actions=self.actions, proprio=self.proprio[:, :t],
                                  lengths=np.full(n, t, np.int64), success=self.solved,
                                  instructions=self.instructions, frame_success=frame_success, tasks=self.tasks)

    def branch_set(self) -> rl_data.EpisodeSet:
        """The states before each episode's first success, where imagined rollouts may branch off."""
        return dataclasses.replace(self.episode_set(), lengths=self.lengths)

    def traced(self, head_steps: int) -> sim_agreement.TracedEpisodes:
        """The episodes as :mod:`~sword_jax.rl.sim_agreement` replays them: stopped at their first success."""
        lengths = self.lengths
        actions = np.where(np.arange(self.actions.shape[1])[None, :, None] < lengths[:, None, None], self.actions, 0.0)
        return sim_agreement.TracedEpisodes(self.frames[:, : head_steps + 1], self.proprio[:, : head_steps + 1],
                                            actions.astype(np.float32), lengths, self.solved, self.instructions)

    def subset(self, idx: np.ndarray) -> "RealEpisodes":
        return RealEpisodes(self.frames[idx], self.proprio[idx], self.actions[idx], self.success[idx],
                            tuple(self.instructions[i] for i in idx), self.tasks[idx])

    def save(self, path: str) -> None:
        np.savez(path, frames=self.frames, proprio=self.proprio, actions=self.actions, success=self.success,
                 instructions=np.asarray(self.instructions), tasks=self.tasks)

    @classmethod
    def load(cls, path: str) -> "RealEpisodes":
        with np.load(path) as f:
            return cls(f["frames"], f["proprio"], f["actions"], f["success"], tuple(str(s) for s in f["instructions"]),
                       f["tasks"])


Collect = Callable[[Any, int, int], RealEpisodes]  # (policy params, GRPO step, episodes) -> real episodes


def _save_tree(path: str, tree: Any) -> None:
    np.savez(path, *[np.asarray(x) for x in jax.tree.leaves(jax.device_get(tree))])


def _load_tree(path: str, like: Any) -> Any:
    leaves, treedef = jax.tree.flatten(like)
    with np.load(path) as f:
        loaded = [f[f"arr_{i}"] for i in range(len(leaves))]
    for old, new in zip(leaves, loaded):
        if np.shape(old) != new.shape:
            raise ValueError(f"refresh: a saved array has shape {new.shape}, the model's {np.shape(old)} ({path})")
    placed = [jax.device_put(new.astype(np.asarray(old).dtype if not isinstance(old, jax.Array) else old.dtype),
                             old.sharding if isinstance(old, jax.Array) else None) for old, new in zip(leaves, loaded)]
    return jax.tree.unflatten(treedef, placed)


def stratified_split(outcome: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """``[n]`` bool: ``fraction`` of the successes and of the failures (at least one of each where there are
    two or more), drawn by ``rng``."""
    outcome = np.asarray(outcome, bool)
    mask = np.zeros(outcome.shape, bool)
    for value in (True, False):
        idx = np.flatnonzero(outcome == value)
        take = int(round(fraction * idx.size))
        if idx.size >= 2:
            take = min(max(take, 1), idx.size - 1)
        mask[rng.permutation(idx)[:take]] = True
    return mask


def finetune_world_model(cfg: Any, wm_state: tuple[Any, Any], dataset: Any, *, steps: int, learning_rate: float,
                         seed: int, mesh=None, log: Callable[[str], Any] = print,
                         compiled: dict | None = None, given: Any = None,
                         given_share: float = 0.0) -> tuple[tuple[Any, Any], dict]:
    """``steps`` world-model steps from ``wm_state`` (``(params, buffers)``) on ``dataset``
    (:class:`~sword_jax.world_model.data.LatentDataset`), at a constant ``learning_rate`` after a short
    warmup, fresh AdamW moments and, with DLB, a fresh cache whose schedule runs over the fine-tune.
    ``compiled``: a dict kept between calls; the compiled step is stored there and reused while the
    dataset's shape stays the same (a refresh's fine-tunes then compile once).

    ``given``: segments whose context is given (:class:`~sword_jax.rl.closed_loop.ClosedLoopSegments`, the world
    model's own closed loop against reality); ``given_share`` of every batch's rows (at least one, at most all but
    one) are drawn from them (with replacement, a function of (seed, step)) in place of the dataset's, trained on
    as they are (the ``given_context`` rows of the train step: no cache read or write). Returns
    ``((params, buffers), last metrics)``."""
    from sword_jax.dit.action_dit import WorldModel
    from sword_jax.train_loop import run_steps
    from sword_jax.world_model import data as wm_data
    from sword_jax.world_model import train_step as wm_step
    from sword_jax.world_model.train_state import create_train_state

    mesh = shd.make_mesh(cfg.mesh) if mesh is None else mesh
    rules = cfg.mesh.rules
    warmup = min(cfg.trainer.warmup_steps, max(steps // 10, 1))
    trainer = dataclasses.replace(cfg.trainer, steps=steps, learning_rate=learning_rate, warmup_steps=warmup,
                                  lr_schedule="constant", ema_decay=0.0, log_every=max(steps // 4, 1))
    cache = (dataclasses.replace(cfg.cache, schedule_steps=steps, warmup_steps=min(cfg.cache.warmup_steps, warmup))
             if cfg.cache.enabled else cfg.cache)
    k, f = cfg.data.context_frames // cfg.vae.temporal_factor, cfg.data.predict_frames // cfg.vae.temporal_factor
    graphdef, state, shardings = create_train_state(lambda: WorldModel(cfg.model, rngs=nnx.Rngs(seed)), trainer, cache,
                                                    dataset.shape, mesh, rules)
    params, buffers = wm_state
    state = state.replace(params=jax.device_put(params, shardings.params),
                          buffers=jax.device_put(buffers, shardings.buffers))
    sampler = wm_data.SegmentSampler(dataset.shape[0], dataset.shape[1], k, f, cfg.data.batch_size, seed=seed)
    loader = wm_data.SegmentLoader(dataset, sampler, k, f, mesh, rules)
    host_batch_at, place, batch_shardings = loader.host_batch_at, loader.place, loader.shardings
    if given is not None:
        host_batch_at, batch_shardings = given_rows(loader, given, given_share, seed=seed)
        place = lambda batch: shd.to_global(batch, batch_shardings, loader.rows,  # noqa: E731
                                            loader.sampler.batch_size)
    compiled = {} if compiled is None else compiled
    signature = (tuple(dataset.shape), given is not None)
    if compiled.get("shape") != signature:
        step_fn = wm_step.make_train_step(graphdef, flow_cfg=cfg.flow, trainer_cfg=trainer, cache_cfg=cache,
                                          num_context=k, num_episodes=dataset.shape[0])
        compiled.update(shape=signature,
                        step=wm_step.compile_train_step(step_fn, shardings, batch_shardings, mesh, rules))
    step = compiled["step"]

    def report(done, metrics, _observed, _eta):
        log(f"world model refresh step {done}/{steps} loss {metrics.get('loss', float('nan')):.4f}")
        return {"step": done, **metrics}

    result = run_steps(step, state, host_batch_at, key=shd.put(jax.random.key(seed), shd.replicated(mesh)),
                       steps=steps, log_every=trainer.log_every, name="world model refresh", report=report,
                       place=place, settle=True, log=log, metrics_finite=wm_step.step_was_finite)
    return (result.state.params, result.state.buffers), (result.history[-1] if result.history else {})


def given_rows(loader: Any, given: Any, share: float, *, seed: int) -> tuple[Callable[[int], dict], dict]:
    """``(host_batch_at, shardings)`` of ``loader``'s batches with their last ``round(share x batch)`` rows taken
    from ``given`` (:class:`~sword_jax.rl.closed_loop.ClosedLoopSegments`) and flagged ``given_context``; which
    segment fills which row is a function of (seed, step), so a fine-tune's batches are the same wherever it runs."""
    batch = loader.sampler.batch_size
    count = int(round(share * batch))
    if given.num < 1 or not 1 <= count <= batch - 1:
        raise ValueError(f"world model fine-tune: given segments take {share} of {batch} rows ({count}); they need "
                         f"at least one row and leave at least one to the dataset, and at least one segment "
                         f"(got {given.num})")
    example = loader.host_batch_at(0)
    if (given.latents.shape[1:], given.actions.shape[1:]) != (example["latents"].shape[1:],
                                                              example["actions"].shape[1:]):
        raise ValueError(f"world model fine-tune: given segments {given.latents.shape[1:]} / {given.actions.shape[1:]} "
                         f"do not match the dataset's {example['latents'].shape[1:]} / {example['actions'].shape[1:]}")
    shardings = dict(loader.shardings, given_context=loader.shardings["episode"])
    held = loader.rows
    flagged = np.arange(batch)[held] >= batch - count

    def host_batch_at(step: int) -> dict[str, np.ndarray]:
        out = loader.host_batch_at(step)
        pick = stream_rng(seed, "refresh/given_rows", step).integers(0, given.num, batch)[held][flagged]
        out["latents"][flagged] = given.latents[pick]
        out["actions"][flagged] = given.actions[pick]
        out["given_context"] = flagged.copy()
        return out

    return host_batch_at, shardings


def segment_fit(cfg: Any, wm_state: tuple[Any, Any], latents: np.ndarray, actions: np.ndarray, *, seed: int,
                batch: int = 32, compiled: dict | None = None) -> dict[str, float]:
    """The world model's fixed-noise flow loss and the relative squared error of the future it samples in
    ``flow.sample_steps`` Euler steps from each segment's own context, over segments ``latents [M, 1 + k + p, ...]``
    with their ``actions`` (:func:`~sword_jax.world_model.heldout.make_measure`, in batches of ``batch`` whose noise
    levels span the training distribution's quantiles; the means weighted by the batches' sizes). The noise is fixed
    by ``seed``, so two world models are measured on the same draws. ``compiled``: a dict kept between calls, where
    the jitted measurement is kept (a refresh's measurements then trace it once per batch shape)."""
    from sword_jax.dit.action_dit import WorldModel
    from sword_jax.world_model.heldout import make_measure

    if latents.shape[0] < 1:
        raise ValueError("segment_fit: no segments")
    n_steps = cfg.flow.sample_steps
    compiled = {} if compiled is None else compiled
    if "measure" not in compiled:
        k = cfg.data.context_frames // cfg.vae.temporal_factor
        graphdef = nnx.split(nnx.eval_shape(lambda: WorldModel(cfg.model, rngs=nnx.Rngs(0))), nnx.Param, ...)[0]
        compiled["measure"] = jax.jit(make_measure(graphdef, cfg.flow, k, (n_steps,), with_other_actions=False))
    measure = compiled["measure"]
    params, buffers = wm_state
    root = stream_key(jax.random.key(seed), "refresh/segment_fit")
    total = {"loss": 0.0, "sample_error": 0.0}
    for i in range(0, latents.shape[0], batch):
        seg = {"latents": jnp.asarray(latents[i:i + batch], jnp.float32),
               "actions": jnp.asarray(actions[i:i + batch], jnp.float32)}
        out = jax.device_get(measure(params, buffers, seg, jax.random.fold_in(root, i)))
        size = seg["latents"].shape[0]
        total["loss"] += float(out["loss"]) * size
        total["sample_error"] += float(out[f"sample_error_{n_steps}"]) * size
    return {name: value / latents.shape[0] for name, value in total.items()}


def first_success(scores: np.ndarray, lengths: np.ndarray, threshold: float, success_frames: int = 1) -> np.ndarray:
    """``[E]`` the frame at which each replay first completes ``success_frames`` consecutive frames scoring
    ``>= threshold`` within its first ``lengths`` frames (the imagined-success rule,
    :func:`~sword_jax.rl.rollout.success_runs`), -1 where it never does."""
    scores, lengths = np.asarray(scores), np.asarray(lengths)
    hit = (scores >= threshold) & (np.arange(scores.shape[1])[None] < lengths[:, None])
    reached = np.asarray(success_runs(jnp.asarray(hit))) >= success_frames
    return np.where(reached.any(1), reached.argmax(1), -1)


def separation(entry: dict[str, Any]) -> float | None:
    """Imagined success among real successes minus among real failures, of one horizon's entry of
    :func:`~sword_jax.rl.sim_agreement.success_by_horizon` (None where a group is empty)."""
    win, loss = entry["real_success"]["rate"], entry["real_failure"]["rate"]
    return None if win is None or loss is None else float(win - loss)


def choose_horizon(by_horizon: dict[str, dict[str, Any]], horizons: tuple[int, ...], min_separation: float
                   ) -> tuple[int, dict[str, float | None], bool]:
    """The longest of ``horizons`` whose separation (imagined success by then among real successes minus
    among real failures, :func:`~sword_jax.rl.sim_agreement.success_by_horizon`'s entries) is at least
    ``min_separation``; when none is, the one that separates best (the longest of equals), since a horizon
    too short for any task to be solved pays no reward at all; the shortest when no separation is known.
    Returns ``(horizon, every candidate's separation (None where a group is empty), trusted)``."""
    seps = {str(h): separation(by_horizon[str(h)]) for h in horizons}
    known = [h for h in horizons if seps[str(h)] is not None]
    trusted = [h for h in known if seps[str(h)] >= min_separation]
    if trusted:
        return max(trusted), seps, True
    if not known:
        return min(horizons), seps, False
    best = max(seps[str(h)] for h in known)
    return max(h for h in known if seps[str(h)] == best), seps, False


def calibrate_held_out(scores: np.ndarray, lengths: np.ndarray, solved: np.ndarray, over: list[int | None],
                       conf: Any, success_frames: int) -> tuple[float, dict[str, Any], dict[str, Any] | None]:
    """The refreshed detector's threshold from its scores ``[E, T]`` of held-out replays (real outcomes
    ``solved``, at least one failure), set by ``conf.calibration`` over each of ``over`` (actions, ``None``:
    the whole replay; :func:`~sword_jax.rl.sim_agreement.calibrate_replays`). With several horizons (the
    run's first refresh) each is read at its own threshold and the one :func:`choose_horizon` takes sets it.

    Returns ``(threshold, the record's calibration, {str(h): imagined success by h among real successes and
    failures at h's threshold} with several horizons, else None)``. Separation needs both outcomes: without
    a held-out success the false-success bound sets it."""
    mode = conf.calibration if solved.any() else "false_success"
    per = sim_agreement.calibrate_replays(scores, lengths, solved, horizons=over, calibration=mode,
                                          max_false_success=conf.max_false_success, success_frames=success_frames)
    picked, candidates = over[0], None
    if len(over) > 1:
        candidates = {key: sim_agreement.success_by_horizon(
            solved, first_success(scores, lengths, c["threshold"], success_frames), horizons=(h,))[key]
            for h, (key, c) in zip(over, per.items())}
        picked = choose_horizon(candidates, tuple(over), conf.min_separation)[0]
    chosen = per["all" if picked is None else str(picked)]
    report = {**{key: chosen[key] for key in ("false_success", "missed_success", "imagined_success", "separation")},
              "rule": mode, "over_actions": picked, "roc": chosen["roc"],
              "thresholds": {key: c["threshold"] for key, c in per.items()}}
    return chosen["threshold"], report, candidates


class Refresher:
    """The refreshes of one GRPO run (module docstring).

    Args:
      cfg: the experiment config (world model, data, DLB, mesh, seed); ``cfg.rl`` is not read, ``rl`` is.
      rl: the run's RL config (``rl.refresh``, the detector, the imagined-success rule).
      wm_state: the world model's ``(params, buffers)`` at the start of the run.
      make_simulator: ``wm_state -> LearnedSimulator`` (the VAE bound in).
      encode: ``(first_frames, history) -> start latents`` (:func:`~sword_jax.rl.world_model_sim.encode_history`).
      encode_prefix: ``(prefix, latent_index) -> start latents`` (:func:`~sword_jax.rl.world_model_sim.encode_prefix`),
        which ``rl.imagined.start_encoding=prefix`` needs (:func:`~sword_jax.rl.data.prefix_encoder`): the branch
        starts and the replays of real episodes are then encoded from each episode's frame 0 on, as GRPO's own
        starts; with ``window`` it is not used.
      encode_frames: ``frames [n, F, H, W, 3] in [0, 1] -> latents [n, L, h, w, c]``: the training latents
        of the world model (the VAE's encoder as the run's latents were made).
      detector: ``(graphdef, params)`` of the success detector at the start of the run.
      base: the world model's training latents (:class:`~sword_jax.world_model.data.LatentDataset`).
      collect: ``collect(policy params, step, n) -> RealEpisodes``.
      directory: where the refreshes are saved.
      verify: with ``rl.refresh.verify_starts``, ``verify(policy params, simulator, reward model, step, decisions)
        -> report`` (:func:`~sword_jax.pipeline.grpo_refresh.make_verify`): the policy's imagined groups of
        ``decisions`` decisions, their actions executed in the real environment; ``report["episodes"]`` of them.
      closed_loop: with ``rl.refresh.closed_loop_starts``, ``closed_loop(policy params, simulator, reward model,
        step, decisions) -> (segments, report)`` (:func:`~sword_jax.pipeline.grpo_refresh.make_closed_loop`): the
        policy's closed loop in the simulator against reality (:class:`~sword_jax.rl.closed_loop.ClosedLoopSegments`),
        which the world model's fine-tune mixes into its batches; ``report["episodes"]`` real executions.
    """

    def __init__(self, cfg: Any, rl: Any, *, wm_state: Any, make_simulator: Callable[[Any], LearnedSimulator],
                 encode: Callable[..., Any], encode_frames: Callable[[np.ndarray], np.ndarray],
                 detector: tuple[Any, Any], base: Any, collect: Collect, directory: str, mesh=None,
                 log: Callable[[str], Any] = print, verify: Callable[..., dict] | None = None,
                 closed_loop: Callable[..., tuple[Any, dict]] | None = None,
                 encode_prefix: Callable[..., Any] | None = None):
        rl.refresh.validate()
        if not rl.refresh.every:
            raise ValueError("Refresher: rl.refresh.every is 0 (refresh off)")
        if rl.refresh.verify_starts and verify is None:
            raise ValueError("Refresher: rl.refresh.verify_starts needs verify= (the real environment the imagined "
                             "rollouts' actions are executed in)")
        if rl.refresh.closed_loop_starts and closed_loop is None:
            raise ValueError("Refresher: rl.refresh.closed_loop_starts needs closed_loop= (the real environment the "
                             "closed loop's actions are executed in)")
        self.verify, self.closed_loop = verify, closed_loop
        self.cfg, self.rl, self.conf = cfg, rl, rl.refresh
        self.make_simulator, self.encode, self.encode_frames = make_simulator, encode, encode_frames
        self.encode_prefix = rl_data.prefix_encoder(rl.imagined.start_encoding, encode_prefix, "the refresh")
        self.mesh = shd.make_mesh(cfg.mesh) if mesh is None else mesh
        # the world model's fine-tune batch splits over this mesh (its loader refuses otherwise): checked before GRPO
        # runs rather than at the first refresh
        shd.check_batch_divides(shd.batch_sharding(self.mesh, 1, cfg.mesh.rules), cfg.data.batch_size,
                                "data.batch_size")
        self.det_graphdef, self.det_params = detector[0], jax.device_put(detector[1], shd.replicated(self.mesh))
        self.initial = (wm_state, self.det_params)
        self.wm_state, self.shift = wm_state, 0.0
        # one reward model whose params change (new closures would make every compiled step trace again)
        self._reward_model = shifted_reward_model(self.det_graphdef, self.det_params, 0.0)
        self.base, self.collect, self.directory, self.log = base, collect, directory, log
        self.tf = cfg.vae.temporal_factor
        self.k = cfg.data.context_frames // self.tf
        self.window = cfg.data.episode_frames
        self.rounds: list[tuple[np.ndarray, np.ndarray]] = []  # each refresh's (latents, actions) so far
        self.branch: rl_data.EpisodeSet | None = None
        self.used, self.loaded, self.records = 0, None, []
        self._wm_compiled: dict = {}  # the world model's fine-tune step, compiled once
        self._fit_compiled: dict = {}  # the closed loop's held-out measurement, traced once per batch shape
        self._det_compiled = make_detector_step(self.det_graphdef, rl, mesh=self.mesh)
        settle = rl.imagined.eval_replay_settle_steps
        self._replay_fn = jax.jit(lambda sim, rm, start, actions, lengths, key, record: sim_agreement.replay_actions(
            sim, rm, start, actions, lengths, success_threshold=rl.success_threshold, key=key, settle_steps=settle,
            success_frames=rl.imagined.success_frames, record_frames=record), static_argnums=(6,))
        os.makedirs(directory, exist_ok=True)

    # ---- what GRPO reads -------------------------------------------------------------------------------
    def simulator(self) -> LearnedSimulator:
        return self.make_simulator(self.wm_state)

    def reward_model(self) -> RewardModel:
        return self._reward_model.replace(params={"net": self.det_params, "shift": jnp.asarray(self.shift, jnp.float32)})

    def _calibration_horizons(self) -> list[int | None]:
        """The actions of each held-out replay the detector's threshold is set over (``rl.refresh.calibrate_over``):
        the whole replay (``[None]``), or as many as GRPO's imagined rollouts run: the run's horizon once chosen,
        every candidate at the first refresh, else ``max_chunks x execute_steps``."""
        conf, imagined, chosen = self.conf, self.rl.imagined, self.horizon()
        if conf.calibrate_over == "episode":
            return [None]
        if chosen is not None:
            return [chosen]
        if conf.horizons:
            return list(conf.horizons)
        return [imagined.max_chunks * imagined.execute_steps]

    def horizon(self) -> int | None:
        """The imagined rollouts' length in actions chosen by the run's first refresh (``rl.refresh.horizons``),
        None when it chose none."""
        return next((r["horizon"]["actions"] for r in self.records if "horizon" in r), None)

    def decisions(self) -> int:
        """Decisions of an imagined rollout at the run's horizon (:meth:`horizon`), ``rl.imagined.max_chunks``
        before one is chosen."""
        horizon = self.horizon()
        return self.rl.imagined.max_chunks if horizon is None else horizon // self.rl.imagined_actions_per_decision

    def paused(self) -> bool:
        """With ``rl.refresh.pause_untrusted``: whether the refresh the steps follow found the simulator not
        separating real successes from real failures at the run's horizon (its ``trust``); GRPO then leaves
        the policy as it is until a refresh trusts the simulator again."""
        if not self.conf.pause_untrusted:
            return False
        made = [r for r in self.records if r["step"] <= self.loaded and not r.get("skipped")]  # the models in use
        return bool(made and "trust" in made[-1] and not made[-1]["trust"]["trusted"])

    def due(self, step: int) -> bool:
        return step % self.conf.every == 0

    def branch_pick(self, step: int, count: int) -> dict[str, Any] | None:
        """``count`` start states of step ``step`` branched from the latest refresh's real episodes (every
        latent-aligned frame before their success; a function of (seed, step)), or None without branching. With
        ``rl.imagined.start_encoding=prefix`` each carries its episode from frame 0 (``prefix``, ``latent_index``)."""
        if not self.conf.branch or self.branch is None:
            return None
        prefix_latents = (None if self.encode_prefix is None else rl_data.prefix_latents_for(
            self.branch, max_fraction=1.0, num_context=self.k, frames_per_latent=self.tf))
        return rl_data.keyframe_starts(self.branch, count, stream_rng(self.cfg.seed, "grpo/branch", step),
                                       max_fraction=1.0, num_context=self.k, frames_per_latent=self.tf,
                                       prefix_latents=prefix_latents)

    # ---- persistence -------------------------------------------------------------------------------------
    def _dir(self, step: int) -> str:
        return os.path.join(self.directory, f"step_{step:06d}")

    def done_steps(self) -> list[int]:
        out = []
        for name in os.listdir(self.directory):
            if name.startswith("step_") and os.path.exists(os.path.join(self.directory, name, "record.json")):
                out.append(int(name[len("step_"):]))
        return sorted(out)

    def at(self, step: int) -> None:
        """Makes the models those of the latest refresh at or before ``step`` (a resumed run's state)."""
        done = [s for s in self.done_steps() if s <= step]
        want = done[-1] if done else None
        if want == self.loaded:
            return
        self.wm_state, self.det_params = self.initial
        self.shift, self.rounds, self.branch, self.used, self.records = 0.0, [], None, 0, []
        for s in done:  # every refresh's latents; the models and episodes only of the last one that made them
            self._load(s, models=False)
        last = next((r["step"] for r in reversed(self.records) if not r.get("skipped")), None)
        if last is not None:
            self._load_models(last)
        self.loaded = want

    def _load(self, step: int, *, models: bool = True) -> dict:
        d = self._dir(step)
        with open(os.path.join(d, "record.json")) as f:
            record = json.load(f)
        self.used = int(record["real_episodes_used"])
        self.records.append(record)
        if record.get("skipped"):
            return record
        with np.load(os.path.join(d, "latents.npz")) as f:
            self.rounds.append((f["latents"], f["actions"]))
        if models:
            self._load_models(step)
        return record

    def _load_models(self, step: int) -> None:
        """The world model, detector, threshold shift and branch episodes a refresh saved."""
        d = self._dir(step)
        self.wm_state = _load_tree(os.path.join(d, "world_model.npz"), self.wm_state)
        self.det_params = _load_tree(os.path.join(d, "detector.npz"), self.det_params)
        self.shift = float(next(r for r in self.records if r["step"] == step)["detector"]["shift"])
        self.branch = RealEpisodes.load(os.path.join(d, "episodes.npz")).branch_set()

    # ---- one refresh ---------------------------------------------------------------------------------
    def refresh(self, step: int, policy_params: Any) -> dict[str, Any]:
        """The refresh at GRPO step ``step`` with the current policy (module docstring); returns its record
        (also ``<directory>/step_XXXXXX/record.json``). One saved already is loaded instead."""
        self.at(step - 1)  # the models as the steps before this one trained in
        if step in self.done_steps():
            record = self._load(step)
            self.loaded = step
            return record
        t0 = time.perf_counter()
        conf = self.conf
        k = conf.group_size
        d = self._dir(step)
        shutil.rmtree(d, ignore_errors=True)  # a killed refresh's leftovers
        os.makedirs(d)
        # 0. before anything changes: the policy's imagined groups in the simulator GRPO trained in, checked in reality
        verified = self._verify(step, policy_params)
        checked = {"verify": verified} if verified is not None else {}
        n = min(conf.episodes, conf.budget - self.used) // k * k  # whole groups
        # the closed loop's executions only from what the refresh's own episodes leave of the budget
        given, looped = self._closed_loop(step, policy_params, reserve=n if n >= 2 else None)
        if looped is not None:
            checked["closed_loop"] = looped
        if n < 2:
            record = {"step": step, "skipped": f"the budget of {conf.budget} real episodes is spent",
                      "real_episodes": 0, "real_episodes_used": self.used, **checked}
            write_json_atomic(os.path.join(d, "record.json"), record)
            self.records.append(record)
            self.loaded = step
            self.log(f"refresh at step {step}: skipped ({record['skipped']})")
            return record
        real = self.collect(policy_params, step, n)
        self.used += real.num
        solved = real.solved
        key = jax.random.fold_in(jax.random.key(self.cfg.seed), step)
        # 1. before anything changes: the simulator GRPO trained in, on the policy's new real episodes
        before = self._replay_report(real, self.simulator(), self.reward_model(), jax.random.fold_in(key, 1))
        # 2. the world model, on its training latents and every refresh's episodes
        latents = self._latents(real)
        self.rounds.append(latents)
        train_given, fit = given, None
        trajectories = int(given.trajectory.max()) + 1 if given is not None else 0
        if trajectories >= 2:  # every 8th trajectory's segments held out: the fine-tune's effect where it did not train
            held = given.trajectory % 8 == (7 if trajectories >= 8 else trajectories - 1)
            train_given, held_out = given.subset(~held), given.subset(held)
            fit = {"held_out_trajectories": int(np.unique(held_out.trajectory).size),
                   "before": self._segment_fit(held_out, step)}
        wm_metrics = self._finetune_world_model(step, train_given)
        if fit is not None:
            fit["after"] = self._segment_fit(held_out, step)
            checked["closed_loop"]["fit"] = fit
            said = lambda part: (f"{fit['before'][part]['sample_error']:.4f} -> "  # noqa: E731
                                 f"{fit['after'][part]['sample_error']:.4f}" if fit["before"][part] else "none")
            self.log(f"refresh at step {step}: the world model's sample error on held-out closed-loop segments "
                     f"{said('closed_loop')} (its own context), {said('first_decision')} (the real start's); on its "
                     f"training segments {said('training')}")
        # 3. the detector, on real frames and on the new world model's replays of the real episodes
        rng = stream_rng(self.cfg.seed, "refresh/split", step)
        calibrate = stratified_split(solved, conf.calibrate_fraction, rng)
        detector = self._refresh_detector(step, real, calibrate, jax.random.fold_in(key, 2))
        self.branch = real.branch_set()
        horizon = {}
        by_horizon = detector.get("imagined_success_by_horizon")
        if conf.horizons and by_horizon and not any("horizon" in r for r in self.records):
            # the run's first calibrated refresh chooses (among thresholds set per candidate horizon, if it did)
            chosen, seps, trusted = choose_horizon(detector.get("candidates") or by_horizon, tuple(conf.horizons),
                                                   conf.min_separation)
            horizon = {"horizon": {"actions": chosen, "separation": seps, "min_separation": conf.min_separation,
                                   "trusted": trusted}}
        chosen = horizon["horizon"]["actions"] if horizon else self.horizon()
        if chosen is not None and by_horizon and str(chosen) in by_horizon:
            # every calibrated refresh: does the simulator still separate real outcomes at the run's horizon?
            sep = separation(by_horizon[str(chosen)])
            horizon["trust"] = {"actions": chosen, "separation": sep,
                                "trusted": sep is not None and sep >= conf.min_separation}
        record = {"step": step, "real_episodes": real.num, **horizon, "real_episodes_used": self.used,
                  "budget": conf.budget, "real_success": float(solved.mean()), "replay": before, **checked,
                  "world_model": {"steps": conf.world_model_steps, "training_episodes": int(self.base.latents.shape[0]),
                                  "real_episodes": int(sum(r[0].shape[0] for r in self.rounds)),
                                  "last": {k: float(v) for k, v in wm_metrics.items() if np.isscalar(v)}},
                  "detector": detector, "seconds": round(time.perf_counter() - t0, 1)}
        _save_tree(os.path.join(d, "world_model.npz"), self.wm_state)
        _save_tree(os.path.join(d, "detector.npz"), self.det_params)
        np.savez(os.path.join(d, "latents.npz"), latents=latents[0], actions=latents[1])
        real.save(os.path.join(d, "episodes.npz"))
        write_json_atomic(os.path.join(d, "record.json"), record)  # last: the refresh is complete
        self.records.append(record)
        self.loaded = step
        fs = before["false_success"]
        within = before.get("within_group")
        within = (f"; within its groups it separated real outcomes by {within['all']['separation']:+.2f} "
                  f"({within['mixed_real_groups']} of {within['groups']} groups mixed)"
                  if within and within["all"]["separation"] is not None else "")
        self.log(f"refresh at step {step}: {real.num} real episodes (used {self.used}/{conf.budget}), real success "
                 f"{solved.mean():.3f}; before it the simulator called {fs['rate'] if fs['rate'] is not None else 'n/a'} "
                 f"of {fs['of']} real failures successes{within}; detector threshold {detector['threshold']:.4f} "
                 f"({record['seconds']} s)")
        return record

    def _verify(self, step: int, policy_params: Any) -> dict[str, Any] | None:
        """``rl.refresh.verify_starts``'s check of the policy's imagined groups (None when off); its real
        executions count against the budget, and a budget that cannot pay for them skips it."""
        conf = self.conf
        if not conf.verify_starts:
            return None
        count = conf.verify_starts * self.rl.grpo.group_size
        if conf.budget - self.used < count:
            return {"skipped": f"{count} real executions exceed what is left of the budget of {conf.budget}"}
        t0 = time.perf_counter()
        out = self.verify(policy_params, self.simulator(), self.reward_model(), step, self.decisions())
        self.used += int(out["episodes"])
        out["seconds"] = round(time.perf_counter() - t0, 1)
        fs, pr = out["false_success"], out["precision"]
        within = out.get("within_group", {}).get("all", {}).get("separation")
        self.log(f"refresh at step {step}: the policy's {out['episodes']} imagined rollouts executed for real: "
                 f"imagined success {out['imagined_success']:.3f}, real {out['real_success']:.3f}; "
                 f"{pr['rate'] if pr['rate'] is not None else 'n/a'} of {pr['of']} imagined successes real, "
                 f"{fs['rate'] if fs['rate'] is not None else 'n/a'} of {fs['of']} real failures paid"
                 + (f", within groups {within:+.2f}" if within is not None else "") + f" ({out['seconds']} s)")
        return out

    def _closed_loop(self, step: int, policy_params: Any, *, reserve: int | None
                     ) -> tuple[Any, dict[str, Any] | None]:
        """``rl.refresh.closed_loop_starts``'s segments of the policy's closed loop in the simulator GRPO trained in,
        against reality (None, None when off); their executions count against the budget, after the ``reserve``
        episodes the refresh collects (None: the refresh collects none and fine-tunes nothing, so neither is this
        run), and a budget that cannot pay for them skips them."""
        conf = self.conf
        if not conf.closed_loop_starts:
            return None, None
        count = conf.closed_loop_starts * self.rl.grpo.group_size
        if reserve is None or conf.budget - self.used - reserve < count:
            return None, {"skipped": f"{count} real executions exceed what the refresh's own episodes leave of the "
                                     f"budget of {conf.budget}"}
        t0 = time.perf_counter()
        segments, out = self.closed_loop(policy_params, self.simulator(), self.reward_model(), step, self.decisions())
        self.used += int(out["episodes"])
        out = dict(out, segments=segments.num, share=conf.closed_loop_share, seconds=round(time.perf_counter() - t0, 1))
        drift = out.get("latent_drift_by_decision") or [float("nan")]
        self.log(f"refresh at step {step}: the policy's closed loop, {out['episodes']} trajectories executed for "
                 f"real: {segments.num} segments; latent drift {drift[0]:.4f} after the first decision, "
                 f"{drift[-1]:.4f} after the last ({out['seconds']} s)")
        return segments, out

    def _segment_fit(self, held_out: Any, step: int) -> dict[str, dict[str, float] | None]:
        """:func:`segment_fit` of the current world model on held-out closed-loop segments (the first decision's,
        whose context is the real start's, apart from the later ones', whose context is the world model's own) and on
        fixed segments of its training latents (what the fine-tune must not lose)."""
        from sword_jax.world_model.heldout import fixed_segments

        p = self.cfg.data.predict_frames // self.tf
        seed = self.cfg.seed + step
        episodes, starts = fixed_segments(self.base, 128, self.k, p, stream_seed(self.cfg.seed, "refresh/fit", step))
        training = self.base.segment(episodes, starts, self.k, p)
        out: dict[str, dict[str, float] | None] = {}
        for name, mask in (("first_decision", held_out.decision == 0), ("closed_loop", held_out.decision > 0)):
            part = held_out.subset(mask)
            out[name] = (dict(segment_fit(self.cfg, self.wm_state, part.latents, part.actions, seed=seed,
                                          compiled=self._fit_compiled), segments=part.num) if part.num else None)
        fitted = segment_fit(self.cfg, self.wm_state, training["latents"], training["actions"], seed=seed,
                             compiled=self._fit_compiled)
        out["training"] = dict(fitted, segments=int(training["latents"].shape[0]))
        return out

    def _latents(self, real: RealEpisodes) -> tuple[np.ndarray, np.ndarray]:
        w = self.window
        if real.actions.shape[1] < w:
            raise ValueError(f"refresh: episodes of {real.actions.shape[1]} actions are shorter than the world model's "
                             f"training windows (data.episode_frames={w}); raise rl.refresh.episode_steps")
        frames = real.frames[:, :w].astype(np.float32) / np.float32(255.0)
        return np.asarray(self.encode_frames(frames), np.float32), real.actions[:, :w].astype(np.float32)

    def _finetune_world_model(self, step: int, given: Any = None) -> dict:
        from sword_jax.world_model.data import LatentDataset

        real_latents = np.concatenate([r[0] for r in self.rounds])
        real_actions = np.concatenate([r[1] for r in self.rounds])
        # as many of the policy's episodes (every refresh's so far, drawn with replacement) as training
        # latents: half of the fine-tune's segments show what the moving policy really did, and the dataset
        # keeps one shape, so every refresh reuses the compiled step
        e = self.base.latents.shape[0]
        pick = stream_rng(self.cfg.seed, "refresh/world_model_mix", step).integers(0, real_latents.shape[0], e)
        latents = np.concatenate([self.base.latents, real_latents[pick]])
        actions = np.concatenate([self.base.actions, real_actions[pick]])
        self.wm_state, metrics = finetune_world_model(
            self.cfg, self.wm_state, LatentDataset(latents, actions), steps=self.conf.world_model_steps,
            learning_rate=self.conf.world_model_learning_rate, seed=self.cfg.seed + 1 + step, mesh=self.mesh,
            log=self.log, compiled=self._wm_compiled, given=given, given_share=self.conf.closed_loop_share)
        return metrics

    def _replay(self, real: RealEpisodes, sim, rm, key, *, record: bool):
        traced = real.traced(self.tf * self.k)
        start, actions, lengths = sim_agreement.replay_starts(
            traced, self.encode, num_context=self.k, frames_per_latent=self.tf, proprio_dim=self.rl.proprio_dim,
            max_instruction_bytes=self.rl.policy.max_instruction_bytes, encode_prefix=self.encode_prefix)
        settle = self.rl.imagined.eval_replay_settle_steps
        actions = np.pad(actions, ((0, 0), (0, settle), (0, 0)))
        lengths = np.maximum(lengths, 1)
        mesh = self.mesh
        sim, rm = jax.device_put((sim, rm), shd.shardings_on((sim, rm), mesh))
        start, actions, lengths, key = jax.device_put((start, jnp.asarray(actions), jnp.asarray(lengths), key),
                                                      shd.replicated(mesh))
        out = self._replay_fn(sim, rm, start, actions, lengths, key, record)
        return jax.device_get(out), lengths

    def _replay_report(self, real: RealEpisodes, sim, rm, key) -> dict[str, Any]:
        out, _ = self._replay(real, sim, rm, key, record=False)
        imagined = np.asarray(out.success, bool)
        report = sim_agreement.agreement(real.solved, imagined)
        report["imagined_success_by_horizon"] = sim_agreement.success_by_horizon(real.solved,
                                                                                 np.asarray(out.first_success))
        if self.conf.group_size > 1:  # the collected episodes come in groups sharing a start state
            run = self.horizon()  # and the run's own horizons
            own = (*self.conf.horizons, *([run] if run is not None else []))
            horizons = tuple(sorted({*sim_agreement.HORIZON_SWEEP, *own}))
            report["within_group"] = sim_agreement.within_group_separation(
                real.solved, np.asarray(out.first_success), self.conf.group_size, horizons=horizons,
                scores=np.asarray(out.scores))
        return report

    def _refresh_detector(self, step: int, real: RealEpisodes, calibrate: np.ndarray, key) -> dict[str, Any]:
        conf, rl = self.conf, self.rl
        out, lengths = self._replay(real, self.simulator(), self.reward_model(), key, record=True)
        frames = np.asarray(out.frames)
        e, t = frames.shape[:2]
        settle = rl.imagined.eval_replay_settle_steps
        replayed = rl_data.EpisodeSet(frames=frames, actions=np.zeros((e, t, rl.action_dim), np.float32),
                                      proprio=np.zeros((e, t, rl.proprio_dim), np.float32),
                                      lengths=(lengths + settle).astype(np.int64), success=real.solved,
                                      instructions=real.instructions)
        replay_labels = sim_agreement.replay_labels(replayed, lengths, rl.reward_model.positive_tail)
        real_set = real.episode_set()
        if frames.shape[2:4] != real_set.frames.shape[2:4]:  # e.g. the light decoder's frames at the policy's size
            # both sources at the detector's input size, so its batches mix them (it resizes every frame to it anyway)
            replayed = dataclasses.replace(replayed, frames=detector_sized(frames, rl.detector_image_size))
            real_set = dataclasses.replace(real_set, frames=detector_sized(real_set.frames, rl.detector_image_size))
        real_labels = rl_data.success_labels(real_set, rl.reward_model.positive_tail, "state")
        train = np.flatnonzero(~calibrate)
        sources = []
        train_real = real_set.subset(train)
        if (real_labels[train] == 0).any():
            sources.append((train_real, real_labels[train], 1.0 - conf.replay_share))
        train_replay = replayed.subset(train)
        if (replay_labels[train] == 0).any() and conf.replay_share > 0:
            sources.append((train_replay, replay_labels[train], conf.replay_share))
        total = sum(share for *_, share in sources)
        sources = [(a, b, share / total) for a, b, share in sources if share > 0]

        def batch_at(s):
            return rl_data.sample_mixed_reward_batch(sources, rl.reward_model.batch_size,
                                                     stream_rng(self.cfg.seed, "refresh/detector", step, s))

        held = np.flatnonzero(calibrate)
        real_held = real_set.subset(held)

        def scorer(params: Any) -> Callable[[Any], Any]:
            """The detector ``params``' frame scores, unshifted (no calibrated threshold applied)."""
            net = self._reward_model.replace(params={"net": params, "shift": jnp.zeros((), jnp.float32)})
            return functools.partial(jax.jit(net.score_fn), net.params)

        # the detector as it came into this refresh, on the held-out real frames at the run's threshold: what the
        # fine-tune below changes
        k = rl.imagined.success_frames  # every report reads the frames as the imagined-success rule does
        before = (detector_report(score_episodes(scorer(self.det_params), real_held.frames), real_held,
                                  rl.success_threshold, success_frames=k) if held.size else None)
        metrics = {}
        if sources:
            state, metrics = train_detector(self.det_graphdef, self.det_params, rl, batch_at,
                                            key=jax.random.fold_in(key, 3), steps=conf.detector_steps,
                                            log=lambda line: None, mesh=self.mesh, compiled=self._det_compiled)
            self.det_params = state.params
        score = scorer(self.det_params)
        out_report: dict[str, Any] = {"loss": float(metrics.get("loss", np.nan)), "train_episodes": int(train.size),
                                      "calibration_episodes": int(held.size)}
        if held.size == 0:  # too few episodes of each outcome to hold any out: the run's threshold stays
            self.shift = 0.0
            out_report.update(calibration="no held-out episode: threshold kept", threshold=float(rl.success_threshold),
                              shift=0.0)
            return out_report
        scores = score_episodes(score, frames[held])
        solved_held = real.solved[held]
        if (~solved_held).any():
            threshold, out_report["calibration"], candidates = calibrate_held_out(
                scores, replayed.lengths[held], solved_held, self._calibration_horizons(), conf, k)
            if candidates:
                out_report["candidates"] = candidates
        else:  # no real failure to bound: keep the run's threshold
            threshold = rl.success_threshold
            out_report["calibration"] = "no real failure among the calibration episodes: threshold kept"
        self.shift = threshold_shift(threshold, rl.success_threshold)
        fire = scores >= threshold
        labels = replay_labels[held]
        truth, labelled = labels == 1, labels >= 0
        tp = float((fire & truth & labelled).sum())
        out_report["imagined_frames"] = {"precision": tp / max(float((fire & labelled).sum()), 1.0),
                                         "recall": tp / max(float(truth.sum()), 1.0)}
        real_scores = score_episodes(score, real_held.frames)  # scored once, read at both thresholds
        out_report["real_frames"] = detector_report(real_scores, real_held, threshold, success_frames=k)
        # the same real frames at the run's threshold, before and after this refresh's fine-tune: whether the
        # fine-tune on replays kept the detector's judgement of real scenes, apart from the calibrated threshold
        out_report["real_frames_run_threshold"] = {"before": before,
                                                   "after": detector_report(real_scores, real_held,
                                                                            rl.success_threshold, success_frames=k)}
        out_report.update(threshold=float(threshold), shift=float(self.shift))
        out_report["imagined_success_by_horizon"] = sim_agreement.success_by_horizon(
            solved_held, first_success(scores, replayed.lengths[held], threshold, k),
            horizons=tuple(conf.horizons) or sim_agreement.HORIZON_SWEEP)
        return out_report
