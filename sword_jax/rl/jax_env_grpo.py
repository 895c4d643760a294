"""Ground-truth GRPO in a pure JAX environment (MJX on the accelerator), at the batch sizes peers use.

One GRPO step (:meth:`EnvGRPO.step`):

1. **Sampling rounds** (dynamic sampling, DAPO / SimpleVLA-RL / RLinf): ``rl.grpo.rollout_batch`` start
   states (stratified over the tasks by the caller's ``starts_at``), ``group_size`` sampled episodes each,
   all in one compiled :func:`~sword_jax.rl.scan_rollout.scan_rollout`. While fewer than ``rollout_batch``
   of the groups sampled so far have mixed outcomes, another round is sampled, up to
   ``rl.grpo.max_sample_rounds``, unless ``rl.grpo.min_mixed_fraction`` of them already are.
2. **The update batch**: ``rollout_batch`` groups, the mixed ones first (:func:`select_groups`).
3. **The update**: :func:`~sword_jax.rl.grpo.grpo_update` with ``ppo_epochs x minibatches`` gradient steps
   (none when the batch holds fewer than ``rl.grpo.min_mixed_groups`` mixed groups). Its ``mixed_groups`` counts
   the update batch's mixed groups; ``sampled_mixed_groups`` and ``mixed_fraction`` are over every round's.

The start states of round ``r`` of step ``s`` and every sampling key are functions of (seed, s, r), so the
train state is all an exact resume needs (:mod:`sword_jax.rl.grpo_loop`).

Short rollouts (``rl.value``): :func:`start_value` collects real episodes of the starting policy once, fits the
value to them (:mod:`sword_jax.rl.value`) and saves both the fit and the episodes' decisions, which a resumed run
loads; the training rollouts may start at those decisions (:func:`branch_starts`, ``rl.env.starts=branch``), and one
that reaches its horizon without an outcome is paid the value of its final frame. Each step logs where its
advantages came from (:func:`advantage_sources`).

Evaluations (:meth:`EnvGRPO.evaluate`) run the same compiled rollout on the fixed evaluation episodes:
greedy with temporal ensembling (the deployed policy), and sampled at ``rl.grpo.temperature`` (the policy
the update trains), and measure on a fixed set of states how many action tokens' argmax changed since the
start (``flip_rate``) and the mean gap between the best and second-best bin's log-probability
(``top1_margin``): the argmax is what is deployed, and where the top bins nearly tie, small updates flip it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax.rl import grpo
from sword_jax.rl.config import RLConfig
from sword_jax.rl.grpo import UPDATE_KEY_SALT, group_has_signal
from sword_jax.rl.imagined_check import outcomes_by_start
from sword_jax.rl.policy import resize_frames
from sword_jax.rl.policy_success import success_summary
from sword_jax.rl.rollout import Rollout, take_trajectories
from sword_jax.rl.scan_rollout import JaxEnv, scan_rollout
from sword_jax.rl.value import Value, ValueData, decision_samples


def mixed_groups(returns: jax.Array, group_size: int) -> jax.Array:
    """``[B] bool``: the groups of ``returns [B * G]`` whose returns are not all equal."""
    return group_has_signal(returns.reshape(-1, group_size))


def select_groups(rollout: Rollout, group_size: int, groups: int) -> Rollout:
    """The first ``groups`` groups of ``rollout`` in the order: mixed ones, then the rest (each part in
    sampling order). ``rollout`` holds ``>= groups`` groups of ``group_size`` consecutive trajectories."""
    n = rollout.valid.shape[0]
    if n % group_size or n // group_size < groups:
        raise ValueError(f"select_groups: {n} trajectories hold fewer than {groups} groups of {group_size}")
    mixed = mixed_groups(rollout.returns, group_size)
    order = jnp.argsort(jnp.where(mixed, 0, 1), stable=True)[:groups]
    idx = (order[:, None] * group_size + jnp.arange(group_size)[None]).reshape(-1)
    return take_trajectories(rollout, idx)


def _concat(rollouts: Sequence[Rollout]) -> Rollout:
    if len(rollouts) == 1:
        return rollouts[0]
    return jax.tree.map(lambda *xs: xs[0] if xs[0].ndim == 0 or xs[0].shape[0] == 0 else jnp.concatenate(xs), *rollouts)


def advantage_sources(returns: np.ndarray, success: np.ndarray, rl: RLConfig) -> dict[str, float]:
    """Where a batch's advantages come from (``returns``/``success`` ``[B * G]``, group-major): ``return_spread``, the
    groups' mean std of the returns in units of the success return; ``success_advantage_share``, the share of the
    advantages' absolute mass (as the update weighs them, ``rl.grpo.scale_by_std``) in groups where some trajectory
    succeeded and some did not. With success alone every mixed group is such a group (share 1); with a value
    closing the rollouts the rest comes from the value's differences between trajectories."""
    g = rl.grpo.group_size
    grouped = returns.reshape(-1, g).astype(np.float32)
    won = success.reshape(-1, g).astype(bool)
    adv, _ = grpo.group_advantages(jnp.asarray(grouped), filter_groups=rl.grpo.filter_groups,
                                   scale_by_std=rl.grpo.scale_by_std)
    mass = np.abs(np.asarray(adv)).sum(axis=1)
    split = won.any(axis=1) & ~won.all(axis=1)
    total, unit = float(mass.sum()), 1.0 + rl.grpo.success_bonus
    return {"return_spread": float(grouped.std(axis=1).mean()) / (unit if unit else 1.0),
            "success_advantage_share": float(mass[split].sum()) / total if total > 0 else 0.0}


def argmax_probe(graphdef: nnx.GraphDef, params: Any, frames: jax.Array, proprio: jax.Array, tokens: jax.Array,
                 image_size: int) -> tuple[jax.Array, jax.Array]:
    """``(argmax tokens [n, L, A], top-1 margin [n, L, A])`` of the policy on fixed states: the margin is
    ``log p(best bin) - log p(second best)`` at temperature 1."""
    logits = nnx.merge(graphdef, params)(resize_frames(frames, image_size), tokens, proprio)
    logp = jax.nn.log_softmax(logits, axis=-1)
    top2 = jax.lax.top_k(logp, 2)[0]
    return jnp.argmax(logits, axis=-1).astype(jnp.int32), top2[..., 0] - top2[..., 1]


class EnvGRPO:
    """GRPO and its evaluations against a pure JAX environment (module docstring).

    Args:
      graphdef: the policy's graph.
      rl: the RL config (GRPO, chunking, temperature, ensembling).
      env: the environment (:class:`~sword_jax.rl.scan_rollout.JaxEnv`); ``env.reset`` takes ``[n, ...]`` arrays.
      max_steps: the episodes' action limit.
      starts_at: ``starts_at(step, round) -> (starts [B, ...] np, instruction tokens [B, L] np)``: the
        ``rollout_batch`` start states of a sampling round, a pure function of (step, round).
      eval_starts / eval_tokens / eval_tasks: the fixed evaluation episodes (``[E, ...]``, ``[E, L]``, ``[E]``).
      key: the root of every sampling key.
      log: where progress lines go.
      train_max_steps / train_execute_steps / train_proprio: the training rollouts' action limit,
        actions executed per decision and whether the policy reads its proprio (False: its "missing
        proprio" input); default: the evaluation's (``max_steps``, ``rl.env.execute_steps``, True).
        The learned simulator's setting is e.g. 48 actions, 4 per decision, proprio missing.
      value: a fitted success-probability value (``rl.value``, :mod:`sword_jax.rl.value`) that pays the training
        rollouts which reach ``train_max_steps`` with no outcome; evaluations are not affected. Its params are
        an argument of the compiled rollout: :meth:`set_value` swaps them without recompiling.
      start_steps_at: ``start_steps_at(step, round) -> [B]``: each of ``starts_at``'s start states' step in its
        episode (keyframes of demonstrations); each GRPO step then counts its sampled trajectories and their
        real successes by where their starts stood
        (:func:`~sword_jax.rl.imagined_check.outcomes_by_start`, ``start_a<a>_rollouts`` / ``_real``).
    """

    def __init__(self, graphdef: nnx.GraphDef, rl: RLConfig, env: JaxEnv, *, max_steps: int,
                 starts_at: Callable[[int, int], tuple[np.ndarray, np.ndarray]], eval_starts: np.ndarray,
                 eval_tokens: np.ndarray, eval_tasks: Sequence[int], key: jax.Array,
                 log: Callable[[str], Any] = print, train_max_steps: int | None = None,
                 train_execute_steps: int | None = None, train_proprio: bool = True, value: Value | None = None,
                 start_steps_at: Callable[[int, int], np.ndarray] | None = None):
        rl.validate()
        self.graphdef, self.rl, self.env, self.max_steps = graphdef, rl, env, max_steps
        self.starts_at, self.key, self.log = starts_at, key, log
        self.start_steps_at = start_steps_at  # each start's step in its episode (keyframes), as starts_at's
        self.eval_starts, self.eval_tokens = np.asarray(eval_starts), np.asarray(eval_tokens)
        self.eval_tasks = np.asarray(eval_tasks)
        self.batch = rl.grpo.rollout_batch * rl.grpo.group_size  # trajectories per compiled rollout
        self.rollout = jax.jit(self._rollout_impl)
        self.train_max_steps = max_steps if train_max_steps is None else int(train_max_steps)
        if self.train_max_steps < 1:
            raise ValueError(f"EnvGRPO: train_max_steps must be >= 1, got {self.train_max_steps}")
        self.train_rl = rl
        if train_execute_steps is not None and train_execute_steps != rl.env.execute_steps:
            self.train_rl = dataclasses.replace(rl, env=dataclasses.replace(
                rl.env, execute_steps=int(train_execute_steps), action_ensemble=False))
            self.train_rl.validate()
        self.train_proprio = bool(train_proprio)
        self.value = value
        value_fn = None if value is None else value.fn
        same = self.train_max_steps == max_steps and self.train_rl is rl and value is None
        self.train_rollout = self.rollout if same else jax.jit(
            lambda *args: self._rollout_impl(*args, rl=self.train_rl, max_steps=self.train_max_steps, value_fn=value_fn))
        # the sampled policy executed as the training rollouts execute it, for the evaluation's whole episodes
        self.as_trained_rollout = None if self.train_rl is rl else jax.jit(
            lambda *args: self._rollout_impl(*args, rl=self.train_rl))
        self.update = jax.jit(lambda state, batch, key: grpo.grpo_update(graphdef, rl, state, batch, key),
                              donate_argnums=(0,))
        self.select = jax.jit(select_groups, static_argnums=(1, 2))
        self.probe_fn = jax.jit(functools.partial(argmax_probe, graphdef, image_size=rl.image_size))
        self.probe: dict[str, np.ndarray] | None = None
        self.probe_dir, self.reference_tokens = "", None

    def _rollout_impl(self, params, starts, tokens, key, greedy, ensemble, proprio_valid=None, value_params=None, *,
                      rl=None, max_steps=None, value_fn=None, record_states=False):
        return scan_rollout(self.graphdef, params, self.env, starts, tokens, self.rl if rl is None else rl, key=key,
                            greedy=greedy, ensemble=ensemble, max_steps=self.max_steps if max_steps is None else max_steps,
                            proprio_valid=proprio_valid, record_states=record_states,
                            value=None if value_fn is None else Value(fn=value_fn, params=value_params))

    def set_value(self, params: Any) -> None:
        """New params for the value the runner was built with (e.g. a refit); the rollout is not recompiled."""
        if self.value is None:
            raise ValueError("EnvGRPO.set_value: the runner was built without a value")
        self.value = self.value._replace(params=params)

    def value_episodes(self, params: Any, episodes: int, *, max_steps: int, key: jax.Array,
                       starts_at: Callable[[int], tuple[np.ndarray, np.ndarray]]) -> ValueData:
        """``episodes`` real episodes of the policy ``params`` for fitting the value: round ``r = 0, 1, ...`` starts
        ``group_size`` episodes at each of ``starts_at(r)``'s states (only as many of them as the episodes still
        wanted need), sampled and executed as the training rollouts are, each run up to ``max_steps`` actions;
        every decision labelled with its episode's outcome (:func:`~sword_jax.rl.value.decision_samples`), with the
        environment's snapshot there where it has one (the start states of branched rollouts)."""
        if episodes < 1:
            raise ValueError(f"EnvGRPO.value_episodes: episodes must be >= 1, got {episodes}")
        g, record = self.rl.grpo.group_size, hasattr(self.env, "snapshot")
        rollout = jax.jit(lambda *args: self._rollout_impl(*args, rl=self.train_rl, max_steps=max_steps,
                                                           record_states=record))
        parts, have, r = [], 0, 0
        while have < episodes:
            starts, tokens = starts_at(r)
            need = -(-(episodes - have) // g)  # groups still wanted: a large rollout batch rolls out no surplus
            starts, tokens = np.asarray(starts)[:need], np.asarray(tokens)[:need]
            starts, tokens = np.repeat(starts, g, axis=0), np.repeat(tokens, g, axis=0)
            out, stats = rollout(params, jnp.asarray(starts), jnp.asarray(tokens), jax.random.fold_in(key, r), False,
                                 False, self._valid(float(self.train_proprio), starts.shape[0]))
            take = min(episodes - have, starts.shape[0])
            parts.append(decision_samples(np.asarray(out.obs_frames)[:take], np.asarray(out.valid)[:take],
                                          tokens[:take], np.asarray(out.success)[:take],
                                          None if stats.states is None else np.asarray(stats.states)[:take]))
            have, r = have + take, r + 1
        return ValueData.concatenate(parts)

    # ---- training -------------------------------------------------------------------------------------
    def step(self, state: grpo.GRPOState, step: int, key: jax.Array) -> tuple[grpo.GRPOState, dict[str, jax.Array]]:
        """One GRPO step (``batch`` of the loop = the step index); ``key`` is the loop's root key."""
        rl = self.rl
        g, want = rl.grpo.group_size, rl.grpo.rollout_batch
        t0 = time.perf_counter()
        step_key = jax.random.fold_in(key, step)
        rounds, steps_taken, broken, mixed, sampled_success, terminal, start_steps = [], 0, 0, 0, [], [], []
        enough = math.ceil(rl.grpo.min_mixed_fraction * want)
        for r in range(rl.grpo.max_sample_rounds):
            starts, tokens = self.starts_at(step, r)
            starts = np.repeat(np.asarray(starts), g, axis=0)
            tokens = np.repeat(np.asarray(tokens), g, axis=0)
            if self.start_steps_at is not None:
                start_steps.append(np.repeat(np.asarray(self.start_steps_at(step, r)), g))
            rollout, stats = self.train_rollout(state.params, jnp.asarray(starts), jnp.asarray(tokens),
                                                jax.random.fold_in(step_key, r), False, False,
                                                self._valid(float(self.train_proprio)),
                                                *(() if self.value is None else (self.value.params,)))
            if stats.terminal_value is not None:
                cut = ~np.asarray(rollout.success) & ~np.asarray(stats.broken)
                terminal.append(np.asarray(stats.terminal_value)[cut])
            rounds.append(rollout)
            steps_taken += int(jnp.sum(stats.steps))
            broken += int(jnp.sum(stats.broken))
            sampled_success.append(np.asarray(rollout.success))
            mixed += int(jnp.sum(mixed_groups(rollout.returns, g)))
            if mixed >= enough:
                break
        batch = self.select(_concat(rounds), g, want) if len(rounds) > 1 else rounds[0]
        t1 = time.perf_counter()
        state, metrics = self.update(state, batch, jax.random.fold_in(step_key, UPDATE_KEY_SALT))
        jax.block_until_ready(metrics["loss"])
        t2 = time.perf_counter()
        success = np.concatenate(sampled_success)
        extra = {"rollout_success": float(success.mean()), "sample_rounds": float(len(rounds)),
                 "trajectories_sampled": float(success.size), "sampled_mixed_groups": float(mixed),
                 "mixed_fraction": float(mixed) / float(success.size // g),
                 "batch_success": jnp.mean(batch.success.astype(jnp.float32)), "env_steps": float(steps_taken),
                 "broken_episodes": float(broken),
                 "rollout_seconds": t1 - t0, "update_seconds": t2 - t1, "step_seconds": t2 - t0}
        if self.value is not None:  # what the value paid the rollouts that reached their horizon
            cut = np.concatenate(terminal)
            extra.update(truncated_fraction=float(cut.size) / float(success.size),
                         terminal_value=float(cut.mean()) if cut.size else 0.0)
        if start_steps:  # the sampled trajectories counted by where their starts stood
            extra.update(outcomes_by_start(np.concatenate(start_steps), None, success))
        extra.update(advantage_sources(np.asarray(batch.returns), np.asarray(batch.success), rl))
        return state, dict(metrics, **{k: jnp.asarray(v, jnp.float32) for k, v in extra.items()})

    # ---- evaluation -----------------------------------------------------------------------------------
    def _valid(self, value: float, size: int | None = None) -> jax.Array:
        return jnp.full((self.batch if size is None else size,), value, jnp.float32)

    def run_episodes(self, params: Any, *, greedy: bool, ensemble: bool, key: jax.Array,
                     slices: int | None = None, proprio: bool = True, rollout: Any = None) -> tuple[np.ndarray, dict]:
        """The evaluation episodes, in slices of the rollout's batch or of all ``E`` episodes where they are fewer
        (the last slice padded by repeating episodes; ``slices``: only the first this-many): ``(success [E] bool,
        what the first slice recorded)``. A training batch larger than the evaluation runs no padding: 500
        episodes cost 500 trajectories, not a 2,048-trajectory batch. ``rollout``: the compiled rollout to run
        (default the evaluation's, :attr:`rollout`)."""
        rollout_fn = self.rollout if rollout is None else rollout
        e = len(self.eval_starts)
        size = min(self.batch, e)
        success = np.zeros(e, bool)
        first = None
        for lo in list(range(0, e, size))[:slices]:
            idx = np.arange(lo, lo + size) % e
            rollout, _ = rollout_fn(params, jnp.asarray(self.eval_starts[idx]), jnp.asarray(self.eval_tokens[idx]),
                                    jax.random.fold_in(key, lo), greedy, ensemble, self._valid(float(proprio), size))
            hi = min(lo + size, e)
            success[lo:hi] = np.asarray(rollout.success)[: hi - lo]
            if first is None:
                first = {"obs": rollout.obs_frames, "proprio": rollout.proprio, "valid": rollout.valid,
                         "tokens": rollout.instruction_tokens}
        return success, first

    def summarize(self, success: np.ndarray, seconds: float) -> dict[str, Any]:
        """The evaluation episodes' summary, as ``evaluate_in_sim`` gives it (:func:`success_summary`)."""
        return success_summary(success, self.eval_tasks, seconds)

    def set_probe(self, recorded: dict, *, states: int = 1024, stride: int = 10) -> None:
        """Fixes the probe states: every ``stride``-th valid decision of a recorded evaluation slice."""
        valid = np.asarray(recorded["valid"]) > 0
        rows, cols = np.nonzero(valid[:, ::stride])
        cols = cols * stride
        keep = np.linspace(0, len(rows) - 1, min(states, len(rows))).astype(int)
        rows, cols = rows[keep], cols[keep]
        rows, cols = jnp.asarray(rows), jnp.asarray(cols)  # gathered on the device: the slice's frames stay there
        self.probe = {"frames": np.asarray(recorded["obs"][rows, cols]),
                      "proprio": np.asarray(recorded["proprio"][rows, cols]),
                      "tokens": np.asarray(recorded["tokens"][rows])}

    def probe_tokens(self, params: Any) -> tuple[np.ndarray, float]:
        """``(argmax tokens, mean top-1 margin)`` on the probe states."""
        p = self.probe
        tokens, margin = self.probe_fn(params, jnp.asarray(p["frames"]), jnp.asarray(p["proprio"]), jnp.asarray(p["tokens"]))
        return np.asarray(tokens), float(jnp.mean(margin))

    def start_probe(self, initial_params: Any, directory: str) -> None:
        """Fixes the probe states from the initial policy's greedy episodes (the first slice of the
        evaluation episodes) and keeps every evaluation's probe argmax under ``directory``, so a resumed
        run measures its flips against the same states and tokens as an uninterrupted one."""
        _, recorded = self.run_episodes(initial_params, greedy=True, ensemble=self.rl.env.action_ensemble,
                                        key=jax.random.key(0), slices=1)
        self.set_probe(recorded)
        self.probe_dir = directory
        os.makedirs(directory, exist_ok=True)
        self.reference_tokens, _ = self.probe_tokens(initial_params)

    def _probe_file(self, step: int) -> str:
        return os.path.join(self.probe_dir, f"probe_argmax_step{step:06d}.npy")

    def _previous_probe(self, step: int) -> np.ndarray | None:
        saved = (int(f[len("probe_argmax_step"):-len(".npy")]) for f in os.listdir(self.probe_dir)
                 if f.startswith("probe_argmax_step") and f.endswith(".npy"))
        earlier = [s for s in saved if s < step]
        return np.load(self._probe_file(max(earlier))) if earlier else None

    def evaluate(self, params: Any, *, step: int, sampled: bool = True, masked: bool = False,
                 as_trained: bool = False) -> tuple[dict, dict]:
        """Greedy (ensembled when ``rl.env.action_ensemble``) success on the evaluation episodes, with the
        sampled policy's and the probe's figures beside it: ``(point, extra)``. The sampled policy re-plans as the
        evaluation does (``rl.env.execute_steps``, no ensembling). ``masked``: also the sampled policy reading its
        "missing proprio" input (``sampled_proprio_masked``), the mode GRPO in a learned simulator trains.
        ``as_trained``: where the training rollouts execute another number of actions per decision
        (``train_execute_steps``), also the sampled policy executed as they execute it and reading proprio as they
        read it, from the evaluation's starts for its whole episodes (``sampled_as_trained``): the policy GRPO
        optimises, where the other two re-plan every action. Every evaluation runs the same starts with the same
        sampling noise (each policy's key is step 0's): common random numbers, so the gain between two evaluations
        pairs each episode's outcomes (:func:`~sword_jax.rl.env_rollout.gain_interval`). Needs
        :meth:`start_probe`."""
        if self.probe is None:
            raise RuntimeError("EnvGRPO.evaluate: call start_probe(initial_params, directory) first")
        t0 = time.perf_counter()
        success, _ = self.run_episodes(params, greedy=True, ensemble=self.rl.env.action_ensemble, key=jax.random.key(0))
        point = dict(self.summarize(success, time.perf_counter() - t0), where="mjx")
        reference_tokens, previous_tokens = self.reference_tokens, self._previous_probe(step)
        extra: dict[str, Any] = {}

        def sampled_policy(stream: int, **kwargs) -> dict:  # the sampled policy's summary, its own noise per stream
            t1 = time.perf_counter()
            outcome, _ = self.run_episodes(params, greedy=False, ensemble=False,
                                           key=jax.random.fold_in(jax.random.fold_in(self.key, stream), 0), **kwargs)
            return dict(self.summarize(outcome, time.perf_counter() - t1), temperature=self.rl.grpo.temperature)

        if sampled:
            extra["sampled"] = sampled_policy(1 << 20)
        if masked:
            extra["sampled_proprio_masked"] = sampled_policy(1 << 21, proprio=False)
        if as_trained and self.as_trained_rollout is not None:
            extra["sampled_as_trained"] = dict(
                sampled_policy(1 << 22, proprio=self.train_proprio, rollout=self.as_trained_rollout),
                execute_steps=self.train_rl.env.execute_steps, proprio=self.train_proprio)
        tokens, margin = self.probe_tokens(params)
        probe = {"states": int(tokens.shape[0]), "top1_margin": margin,
                 "flip_rate_vs_start": float(np.mean(tokens != reference_tokens))}
        if previous_tokens is not None:
            probe["flip_rate_vs_previous"] = float(np.mean(tokens != previous_tokens))
        np.save(self._probe_file(step), tokens.astype(np.uint8 if self.rl.action_bins <= 256 else np.int32))
        extra["probe"] = probe
        return point, extra


def start_value(runner: EnvGRPO, policy_params: Any, directory: str, *, seed: int, max_steps: int,
                starts_at: Callable[[int], tuple[np.ndarray, np.ndarray]],
                log: Callable[[str], Any] = print) -> tuple[dict[str, Any], ValueData]:
    """Fits ``rl.value`` to ``rl.value.episodes`` real episodes of the starting policy, or, when ``directory``
    holds a finished fit, loads that one (a resumed run pays and branches its rollouts as the uninterrupted run
    did, and collects no episodes again). A runner built with a value (:meth:`EnvGRPO.set_value`) is given the
    fitted params; one built without (``rl.value.bootstrap=false``) keeps paying success alone.

    The episodes are :meth:`EnvGRPO.value_episodes` from ``starts_at(round)`` up to ``max_steps`` actions (the
    episode limit); ``holdout`` of them (whole episodes) are kept out of the fit and report its calibration
    (:func:`~sword_jax.rl.value.calibration`). ``directory`` gets ``value.npz`` (the params), ``decisions.npz``
    (the decisions' snapshots, instructions, labels and the fitted value's prediction, where rollouts branch from)
    and ``value.json`` (the record: real episodes used, their success, the fit's loss, its calibration on fitted
    and held-out decisions). The value network is :func:`~sword_jax.rl.value.build_value`'s for ``rl`` and
    ``seed``, as the runner's value was built.

    Returns ``(record, decisions)``: the decisions without their frames (``frames`` empty).
    """
    from sword_jax.atomic_write import write_json_atomic
    from sword_jax.rl.params_io import load_params_npz, save_params_npz
    from sword_jax.rl.value import as_value, build_value, calibration, fit_value, predict, split_episodes

    rl = runner.rl
    paths = {k: os.path.join(directory, f) for k, f in (("params", "value.npz"), ("decisions", "decisions.npz"),
                                                         ("record", "value.json"))}
    graphdef, fresh = build_value(rl, seed=seed)
    if all(os.path.exists(p) for p in paths.values()):
        import json

        params = load_params_npz(paths["params"], fresh)
        with open(paths["record"]) as f:
            record = json.load(f)
        with np.load(paths["decisions"]) as z:
            decisions = ValueData(np.zeros((len(z["labels"]), 0, 0, 3), np.uint8), z["tokens"], z["labels"],
                                  z["episode"], z["states"], z["predicted"] if "predicted" in z.files else None)
        log(f"value: loaded the fit in {directory} ({record['real_episodes']} real episodes)")
    else:
        t0 = time.perf_counter()
        data = runner.value_episodes(policy_params, rl.value.episodes, max_steps=max_steps,
                                     key=jax.random.fold_in(runner.key, 1 << 22), starts_at=starts_at)
        t1 = time.perf_counter()
        fit, held = split_episodes(data, rl.value.holdout, np.random.default_rng(seed))
        held_out = np.isin(data.episode, held.episode)  # the split, as a mask over ``data``
        outcome = data.labels[np.unique(data.episode, return_index=True)[1]]  # each episode's, from its first decision
        log(f"value: {rl.value.episodes} real episodes ({float(outcome.mean()):.3f} succeeded, {len(data)} decisions, "
            f"{t1 - t0:.0f} s); fitting on {len(np.unique(fit.episode))}, {len(np.unique(held.episode))} held out")
        params, metrics = fit_value(graphdef, fresh, rl, fit, seed=seed, log=log)
        value = as_value(graphdef, params)
        data.predicted = predict(value, data)
        record = {"real_episodes": int(rl.value.episodes), "episode_success": float(outcome.mean()),
                  "decisions": len(data), "fit_episodes": int(len(np.unique(fit.episode))),
                  "held_out_episodes": int(len(np.unique(held.episode))), "loss": metrics["loss"],
                  "fit": calibration(data.predicted[~held_out], fit.labels),
                  "held_out": calibration(data.predicted[held_out], held.labels) if len(held) else None,
                  "collect_seconds": round(t1 - t0, 1), "fit_seconds": round(time.perf_counter() - t1, 1)}
        held_record = record["held_out"]
        if held_record:
            auc = held_record["auc"]
            log(f"value: held-out Brier {held_record['brier']:.4f} (constant {held_record['brier_constant']:.4f}), "
                f"AUC {'n/a' if auc is None else f'{auc:.3f}'}")
        os.makedirs(directory, exist_ok=True)
        save_params_npz(paths["params"], params)
        np.savez(paths["decisions"], tokens=data.tokens, labels=data.labels, episode=data.episode, states=data.states,
                 predicted=data.predicted)
        write_json_atomic(paths["record"], record)  # written last: its presence marks a finished fit
        decisions = dataclasses.replace(data, frames=np.zeros((len(data), 0, 0, 3), np.uint8))
    if runner.value is not None:
        runner.set_value(params)
    return record, decisions


def branch_starts(decisions: ValueData, count: int, rng: np.random.Generator, weighting: str = "uniform"
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` start states branched from recorded decisions (every phase of the episodes before their outcome):
    ``(snapshots [count, f], instruction tokens [count, l])``. ``weighting``: ``uniform`` over the decisions, or
    ``open``, in proportion to ``p (1 - p)`` of the fitted value's success probability ``p`` there (plus 1% of the
    largest weight, so no decision is never drawn): where the outcome is still open, so a group's sampled actions
    can decide it.

    Raises:
      ValueError: decisions recorded without snapshots (an environment without ``snapshot``), none, an unknown
        weighting, or ``open`` without the value's predictions."""
    if len(decisions) == 0 or decisions.states.shape[1] == 0:
        raise ValueError("branch_starts: the recorded decisions hold no environment snapshots to branch from")
    if weighting == "uniform":
        pick = rng.integers(0, len(decisions), count)
    elif weighting == "open":
        if decisions.predicted is None:
            raise ValueError("branch_starts: weighting 'open' needs the fitted value's prediction at each decision")
        p = np.clip(np.asarray(decisions.predicted, np.float64), 0.0, 1.0)
        w = p * (1.0 - p)
        w = w + 0.01 * max(float(w.max()), 1e-12)
        pick = rng.choice(len(decisions), count, p=w / w.sum())
    else:
        raise ValueError(f"branch_starts: weighting must be uniform or open, got {weighting!r}")
    return decisions.states[pick], decisions.tokens[pick]
