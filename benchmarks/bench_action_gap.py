"""A scale for the closed-loop action gap: how far the policy's greedy actions move when a real frame is seen
blurred, dimmer, brighter or noisy, and when the scene moves on by one decision.

GRPO in the world model logs per decision ``closed_loop_action_gap_k``
(:func:`sword_jax.rl.imagined_check.closed_loop_fidelity`): the mean absolute difference of the policy's greedy
actions on the world model's frame and on the real frame the same actions reach. ``benchmarks.bench_policy_view``
measured what the views of :data:`~benchmarks.bench_policy_view.VIEWS` cost in success (blur and noise nothing, a
20% change of brightness 9-13 points); this benchmark measures the action gap each view causes, so the world
model's gap can be placed between harmless and harmful.

The policy runs greedily on MuJoCo's C engine (:class:`sim.lockstep.LockstepEnvs`, the JAX renderer) from each
task's first evaluation states, from rest, in the mode GRPO in the world model trains: its "missing proprio" input,
``rl.imagined_actions_per_decision`` actions a decision, no ensembling. The frame it reads at each of its first
``--decisions`` decisions is kept (:func:`policy_frames`). Each kept frame is then seen through every view
(:func:`~benchmarks.bench_policy_view.degrade`, at the environment's resolution) and the gap to the real frame is
computed as ``closed_loop_fidelity`` computes it (:func:`view_gaps`: the same resize, greedy decoding and executed
actions, the mean over actions and dimensions), with the frame error at the policy's size in [0, 1], the world
model's ``closed_loop_frame_error_k``. The same two figures between consecutive decisions' real frames of an
episode say how far one decision of real motion moves the policy. Intervals are 95% bootstraps over episodes (an
episode's frames are not independent)::

    python -m benchmarks.bench_action_gap --config sword:small --policy runs/p/policy_d50.npz \\
        --episodes-per-task 3 --decisions 12 --out runs/action_gap \\
        --rl.imagined.execute_steps=4 --rl.grpo.temperature=0.5

With ``--vae DIR`` (the checkpoint ``train.grpo --vae`` takes) the table adds the view ``vae``: each kept frame
encoded by that VAE as a still keyframe and decoded back, in [0, 1] as the world model's simulator decodes it
(:func:`sword_jax.rl.world_model_sim.vae_round_trip`): the floor of the closed-loop gap that GRPO logs as
``closed_loop_action_gap_vae_k`` beside ``closed_loop_action_gap_k``, the gap a world model with faithful dynamics
would still cause through that VAE.

With ``--lag-episodes-per-task N`` it also measures what one decision of lag costs in real success: whole
episodes from rest, sampled at ``rl.grpo.temperature``, once reading the real frames and once reading at each
decision the frame of the decision before (:class:`LaggedEnvs`: a simulator that shows the scene a decision
late, or does not move it), on the same evaluation states. ``--lag-proprio true,missing`` measures it once per
proprio input: whether a policy that reads the arm's true (or dead-reckoned) state still needs the current frame.

With ``--lag-keyframe-steps N --demos FILE`` it measures that cost where GRPO's rollouts start: the start states
of ground-truth GRPO's first N steps from the demonstrations' keyframes (the config's batch, group size and
keyframe window; the same draws ``bench_policy grpo`` makes at the seed), each rolled out for the learned
simulator's horizon on real and on late frames, sampled, proprio missing, and counted by the start's step in its
demonstration (:func:`lag_by_start`): the by-start figure of a simulator a decision late, to set beside the world
model's (``bench_grpo_reward_source`` ``by_start``).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Bool, Float, Int, UInt8

from benchmarks.bench_policy_view import PARAMETER_NAMES, VIEW_COLUMNS, VIEWS, degrade, policy_parser
from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic
from sword_jax.rl.env_rollout import run_policy
from sword_jax.rl.imagined_check import greedy_actions
from sword_jax.rl.policy import resize_frames

# the VAE round trip needs a trained VAE (--vae) and the lag an episode's history (--lag-episodes-per-task)
GAP_VIEWS = tuple(v for v in VIEWS if v not in ("vae", "lag_1"))
VAE_VIEW = "vae"
BATCH = 32  # frames per compiled gap call (the last batch padded, so one shape compiles)
RESAMPLES = 2000


class _LockstepView:
    """Lockstep environments (:mod:`sword_jax.rl.env_rollout`'s protocol) whose returned frames pass through
    :meth:`_seen` (``first``: the reset's); everything else is the inner environments'."""

    def __init__(self, envs: Any):
        self.envs = envs

    @property
    def n(self) -> int:
        return self.envs.n

    @property
    def language(self) -> list[str]:
        return self.envs.language

    def reset(self, *episodes: Any) -> dict[str, np.ndarray]:
        obs = self.envs.reset(*episodes)
        return dict(obs, frames=self._seen(np.asarray(obs["frames"]), first=True))

    def step(self, actions: np.ndarray) -> dict[str, np.ndarray]:
        obs = self.envs.step(actions)
        return dict(obs, frames=self._seen(np.asarray(obs["frames"]), first=False))

    def _seen(self, frames: np.ndarray, *, first: bool) -> np.ndarray:
        raise NotImplementedError


class FrameKeeper(_LockstepView):
    """Lockstep environments that keep every frame they return, the reset's first: ``frames[k]`` is what the
    policy reads at decision ``k``."""

    def __init__(self, envs: Any):
        super().__init__(envs)
        self.frames: list[np.ndarray] = []

    def _seen(self, frames: np.ndarray, *, first: bool) -> np.ndarray:
        if first:
            self.frames = []
        self.frames.append(frames)
        return frames


class LaggedEnvs(_LockstepView):
    """Lockstep environments whose policy reads, at each decision, the frame of the decision before (at the
    first, the start frame again); proprio, success and the physics are the environment's."""

    def __init__(self, envs: Any):
        super().__init__(envs)
        self.held: np.ndarray | None = None

    def _seen(self, frames: np.ndarray, *, first: bool) -> np.ndarray:
        shown = frames if first else self.held
        self.held = frames
        return shown


class LateEnvs(_LockstepView):
    """Lockstep environments whose policy reads, at each decision, the frame ``lag`` actions before the decision's
    end: a decision's ``k`` actions run as its first ``k - lag`` (whose frame is shown) and its last ``lag``. Proprio,
    success, the executed count and the physics are the environment's after all ``k``. ``lag`` from 1 to ``k - 1``
    (``k`` is :class:`LaggedEnvs`)."""

    def __init__(self, envs: Any, lag: int):
        if lag < 1:
            raise ValueError(f"LateEnvs: lag must be >= 1 action, got {lag}")
        super().__init__(envs)
        self.lag = lag

    def _seen(self, frames: np.ndarray, *, first: bool) -> np.ndarray:
        return frames  # the reset's frame is the start's; step shows its own

    def step(self, actions: np.ndarray) -> dict[str, np.ndarray]:
        k = actions.shape[1]
        if self.lag >= k:
            raise ValueError(f"LateEnvs: a lag of {self.lag} actions needs decisions of more actions, got {k}")
        shown = self.envs.step(actions[:, : k - self.lag])
        out = self.envs.step(actions[:, k - self.lag:])  # episodes done in the first part execute nothing more
        return dict(out, frames=shown["frames"], success=np.asarray(shown["success"]) | np.asarray(out["success"]),
                    executed=np.asarray(shown["executed"]) + np.asarray(out["executed"]))


def lag_success(act: Any, params: Any, envs: Any, rl: Any, *, max_steps: int, tasks: Sequence[int], key: jax.Array,
                proprio: str = "missing", reckoning: Any = None) -> dict[str, Any]:
    """Whole episodes in ``envs`` sampled at ``rl.grpo.temperature``, reading the real frames (``real``) and the
    frames of the decision before (``lag_1``, :class:`LaggedEnvs`), with the same key; their success
    (:func:`~sword_jax.rl.policy_success.success_summary`) and the difference lag - real with its 95% interval.

    ``proprio``: what the policy reads as proprio (:func:`~sword_jax.rl.env_rollout.run_policy`): ``missing`` (the
    mode GRPO in the world model trains), ``true`` (the environment's, current even when the frame is late) or
    ``reckoned`` (integrated from the actions with ``reckoning``, what the learned simulator can report)."""
    from sword_jax.rl.env_rollout import difference_interval
    from sword_jax.rl.policy_success import success_summary

    out = {}
    for name, seen in (("real", envs), ("lag_1", LaggedEnvs(envs))):
        start = time.time()
        rollout = run_policy(act, params, seen, rl, key=key, greedy=False, max_steps=max_steps, record=False,
                             proprio=proprio, reckoning=reckoning)
        out[name] = success_summary(np.asarray(rollout.success), tasks, time.time() - start)
    real, lag = out["real"], out["lag_1"]
    out["difference"] = {"mean": lag["mean"] - real["mean"],
                         "ci95": list(difference_interval(real["successes"], real["episodes"], lag["successes"],
                                                          lag["episodes"]))}
    return out


def lag_by_start(act: Any, params: Any, envs: Any, rl: Any, *, draws: Sequence[tuple[list, np.ndarray]],
                 horizon: int, key: jax.Array, late_actions: Sequence[int] = ()) -> dict[str, Any]:
    """Rollouts from keyframes as ground-truth GRPO draws them (``draws``: per GRPO step, its start states and each
    one's step in its demonstration, :func:`sim.grpo_env.keyframe_env_draw`), ``horizon``
    actions sampled at ``rl.grpo.temperature`` with the policy's "missing proprio" input and
    ``rl.env.execute_steps`` actions a decision, each read once on the real frames and once a decision late
    (:class:`LaggedEnvs`), with the same key per step. Their successes counted by the start's step
    (:func:`~sword_jax.rl.imagined_check.outcomes_by_start`, summed over the steps): ``{"real": bins, "lag_1":
    bins}``, each bin ``{"from_step", "rollouts", "real"}``; with ``late_actions`` also ``late_<j>_actions`` for each
    ``j``, read ``j`` actions late (:class:`LateEnvs`). The by-start figure of a simulator whose frames are late, to
    set beside the world model's (``bench_grpo_reward_source`` ``by_start``)."""
    from sword_jax.rl.imagined_check import START_STEP_EDGES, outcomes_by_start

    views = [("real", envs), ("lag_1", LaggedEnvs(envs)), *((f"late_{j}_actions", LateEnvs(envs, j))
                                                            for j in late_actions)]
    totals = {name: {lower: [0, 0] for lower in START_STEP_EDGES} for name, _ in views}
    for step, (starts, steps) in enumerate(draws, start=1):
        for name, seen in views:
            rollout = run_policy(act, params, seen, rl, key=jax.random.fold_in(key, step), greedy=False,
                                 max_steps=horizon, episodes=starts, record=False, proprio="missing")
            counted = outcomes_by_start(jnp.asarray(steps), None, jnp.asarray(rollout.success, bool))
            for lower in START_STEP_EDGES:
                totals[name][lower][0] += int(counted[f"start_a{lower}_rollouts"])
                totals[name][lower][1] += int(counted[f"start_a{lower}_real"])
    return {name: [{"from_step": lower, "rollouts": n, "real": hits} for lower, (n, hits) in bins.items()]
            for name, bins in totals.items()}


def policy_frames(act: Any, params: Any, envs: Any, rl: Any, *, decisions: int, key: jax.Array
                  ) -> tuple[UInt8[np.ndarray, "n d h w 3"], Bool[np.ndarray, "n d"], Any]:
    """Runs the policy greedily in ``envs`` for ``decisions`` decisions of ``rl.env.execute_steps`` actions, its
    proprio marked missing; returns ``(frames, taken, rollout)``: the environment's frame it read at each decision
    (repeated after an episode ended), whether the episode took that decision, and
    :func:`~sword_jax.rl.env_rollout.run_policy`'s rollout."""
    keeper = FrameKeeper(envs)
    rollout = run_policy(act, params, keeper, rl, key=key, greedy=True, max_steps=decisions * rl.env.execute_steps,
                         proprio="missing")
    kept = keeper.frames[:decisions]
    kept += [kept[-1]] * (decisions - len(kept))  # every episode ended early: the rollout's valid marks the rest
    return np.stack(kept, axis=1), np.asarray(rollout.valid[:, :decisions]) > 0, rollout


def view_gaps(policy: Any, frames: UInt8[Array, "n h w 3"], instruction_tokens: Int[Array, "n l"],
              proprio: Float[Array, "n p"], proprio_valid: Float[Array, " n"], views: Float[Array, "v c"], *,
              key: jax.Array, image_size: int, executed: int, action_bins: int,
              round_trip: Callable[[Array], Array] | None = None
              ) -> tuple[Float[Array, "n ea"], Float[Array, "v n"], Float[Array, "v n"]]:
    """``(real_actions [n, executed x A], frame_error [V, n], action_gap [V, n])`` of real ``frames`` seen
    through each row of ``views`` (:data:`~benchmarks.bench_policy_view.VIEWS`' columns; view ``i``'s noise from
    ``fold_in(key, i)``): the greedy actions on the real frames
    (:func:`~sword_jax.rl.imagined_check.greedy_actions`), and per view and frame the mean absolute difference
    of the two frames at the policy's size and of the two greedy actions, as
    :func:`~sword_jax.rl.imagined_check.closed_loop_fidelity` measures them.

    ``round_trip`` (frames in [0, 1] -> the same, e.g. :func:`sword_jax.rl.world_model_sim.vae_round_trip`) is
    what the views whose VAE column is 1 show: the frame at the environment's resolution, round-tripped, not
    rounded to levels (as the world model's frames are not). Without it that column is not read."""
    n = frames.shape[0]

    def greedy(small):
        return greedy_actions(policy, small, instruction_tokens, proprio, proprio_valid, executed=executed,
                              action_bins=action_bins)

    real = resize_frames(frames, image_size)
    real_actions = greedy(real)

    def one_view(view_and_index):
        view, index = view_and_index
        seen = degrade(frames, jnp.broadcast_to(view, (n, VIEW_COLUMNS)), jax.random.fold_in(key, index))
        seen = seen.astype(jnp.float32) / jnp.float32(255.0)
        if round_trip is not None:  # only the VAE view pays for the round trip
            seen = jax.lax.cond(view[3] > 0, round_trip, lambda f: f, seen)
        seen = resize_frames(seen, image_size)
        return (jnp.mean(jnp.abs(seen - real), axis=(1, 2, 3)),
                jnp.mean(jnp.abs(greedy(seen) - real_actions), axis=-1))

    frame_error, action_gap = jax.lax.map(one_view, (views.astype(jnp.float32), jnp.arange(views.shape[0])))
    return real_actions, frame_error, action_gap


def consecutive(real_actions: Float[np.ndarray, "n d ea"], small: Float[np.ndarray, "n d s s 3"],
                taken: Bool[np.ndarray, "n d"]) -> tuple[np.ndarray, np.ndarray]:
    """``(frame_error, action_gap)``, each ``[n, d - 1]``: between an episode's real frames at decisions ``k``
    and ``k + 1`` (at the policy's size) and between the greedy actions on them; NaN where the episode did not
    take decision ``k + 1``."""
    both = taken[:, 1:] & taken[:, :-1]
    frame_error = np.abs(small[:, 1:] - small[:, :-1]).mean(axis=(2, 3, 4))
    action_gap = np.abs(real_actions[:, 1:] - real_actions[:, :-1]).mean(axis=-1)
    return np.where(both, frame_error, np.nan), np.where(both, action_gap, np.nan)


def summarize(values: Float[np.ndarray, "n d"], *, seed: int = 0, resamples: int = RESAMPLES) -> dict[str, Any]:
    """Mean of ``values`` (episodes x decisions, NaN where there is none), its 95% bootstrap interval over
    episodes (the mean over the resampled episodes' frames), the count and the mean per decision (None where
    no episode has one)."""
    present = ~np.isnan(values)
    sums, counts = np.where(present, values, 0.0).sum(1), present.sum(1)
    if counts.sum() == 0:
        return {"mean": None, "ci95": None, "frames": 0, "per_decision": [None] * values.shape[1]}
    picks = np.random.default_rng(seed).integers(0, len(values), (resamples, len(values)))
    with np.errstate(invalid="ignore"):
        means = sums[picks].sum(1) / counts[picks].sum(1)
        per_decision = np.where(present, values, 0.0).sum(0) / present.sum(0)
    means = means[np.isfinite(means)]
    return {"mean": round(float(sums.sum() / counts.sum()), 5),
            "ci95": [round(float(q), 5) for q in np.percentile(means, [2.5, 97.5])], "frames": int(counts.sum()),
            "per_decision": [None if np.isnan(m) else round(float(m), 5) for m in per_decision]}


def parse_views(text: str, *, vae: bool = False) -> list[str]:
    """The comma list ``text`` as view names, each one of :data:`GAP_VIEWS` (else ``ValueError``); with ``vae``
    (a VAE was given) the view ``vae`` too, added at the end if ``text`` does not name it."""
    views = [v for v in text.split(",") if v]
    known = GAP_VIEWS + ((VAE_VIEW,) if vae else ())
    unknown = [v for v in views if v not in known]
    if unknown or not views:
        why = ""
        if VAE_VIEW in unknown:
            why = " (the view vae round-trips the frames through a trained VAE: give it with --vae)"
        elif "lag_1" in unknown:
            why = " (the lag costs success, measured by --lag-episodes-per-task)"
        raise ValueError(f"--views must name some of {', '.join(known)}, got {views}{why}")
    return views + ([VAE_VIEW] if vae and VAE_VIEW not in views else [])


def measure(graphdef: Any, params: Any, frames: np.ndarray, taken: np.ndarray, rollout: Any, views: Sequence[str], *,
            rl: Any, seed: int, vae: tuple[Any, Any] | None = None) -> dict[str, np.ndarray]:
    """Every taken frame through every view, the policy ``(graphdef, params)``, in compiled batches of
    :data:`BATCH`: ``real_actions [n, d, eA]``, ``frame_error`` and ``action_gap`` ``[V, n, d]`` (NaN where no
    frame), and the real frames at the policy's size, ``small [n, d, s, s, 3]``. ``vae``: the VAE
    ``(graphdef, state)`` whose round trip the view ``vae`` shows (its weights an argument of the compiled call)."""
    from sword_jax.rl.world_model_sim import vae_round_trip

    n, d = taken.shape
    rows, cols = np.nonzero(taken)
    table = jnp.asarray([VIEWS[v] for v in views], jnp.float32)
    if VAE_VIEW in views and vae is None:
        raise ValueError("measure: the view vae needs the VAE (vae=)")
    vae_graphdef, vae_state = vae if vae is not None else (None, None)

    @jax.jit
    def gaps(params, vae_state, frames, tokens, proprio, proprio_valid, key):
        round_trip = vae_round_trip(vae_graphdef, vae_state) if vae_state is not None else None
        return view_gaps(nnx.merge(graphdef, params), frames, tokens, proprio, proprio_valid, table, key=key,
                         image_size=rl.image_size, executed=rl.env.execute_steps, action_bins=rl.action_bins,
                         round_trip=round_trip)

    tokens = np.asarray(rollout.instruction_tokens)
    proprio, proprio_valid = np.asarray(rollout.proprio), np.asarray(rollout.proprio_valid)
    real_actions = np.full((n, d, rl.env.execute_steps * rl.action_dim), np.nan, np.float32)
    frame_error = np.full((len(views), n, d), np.nan, np.float32)
    action_gap = np.full((len(views), n, d), np.nan, np.float32)
    root = jax.random.key(seed)
    for b, lo in enumerate(range(0, len(rows), BATCH)):
        idx = np.arange(lo, lo + BATCH) % len(rows)
        r, c = rows[idx], cols[idx]
        out = jax.device_get(gaps(params, vae_state, frames[r, c], tokens[r], proprio[r, c], proprio_valid[r, c],
                                  jax.random.fold_in(root, b)))
        keep = min(BATCH, len(rows) - lo)
        r, c = r[:keep], c[:keep]
        real_actions[r, c] = out[0][:keep]
        frame_error[:, r, c], action_gap[:, r, c] = out[1][:, :keep], out[2][:, :keep]
    small = np.asarray(jax.jit(resize_frames, static_argnums=1)(frames, rl.image_size))
    return {"real_actions": real_actions, "frame_error": frame_error, "action_gap": action_gap, "small": small}


def keyframe_lag(cfg: Any, rl: Any, graphdef: Any, params: Any, *, demos: Sequence[str], steps: int,
                 late_actions: Sequence[int] = (), workers: int = 0) -> dict:
    """:func:`lag_by_start` on the start states of ground-truth GRPO's first ``steps`` steps from the keyframes of
    ``demos`` (``cfg.rl``'s batch, group size and keyframe window; the same draws as ``train.grpo`` and
    ``bench_policy grpo`` make at ``cfg.seed``), each rolled out for the learned simulator's horizon; the bins with
    their real success on real and on late frames and the share the late frames kept, printed and returned.
    ``workers``: processes the C engine steps in (0 = this one; the outcomes are the same)."""
    from sim import grpo_env
    from sim.dataset import read_dataset
    from sim.lockstep import LockstepEnvs
    from sword_jax.rl import data as rl_data
    from sword_jax.rl.env_rollout import make_act_fns

    keyframes = rl_data.load_episodes(list(demos), read=read_dataset)
    draws = [grpo_env.keyframe_env_draw(keyframes, cfg.rl, seed=cfg.seed, step=step) for step in range(steps)]
    horizon = min(grpo_env.keyframe_horizon(cfg.rl), cfg.sim.max_steps)
    start = time.time()
    with LockstepEnvs(draws[0][0], resolution=cfg.sim.resolution, max_steps=horizon, workers=workers) as envs:
        bins = lag_by_start(make_act_fns(graphdef, rl), params, envs, rl, draws=draws, horizon=horizon,
                            key=jax.random.key(cfg.seed), late_actions=late_actions)
    for i, real in enumerate(bins["real"]):
        if real["rollouts"]:
            lates = [("a decision" if name == "lag_1" else f"{name.split('_')[1]} action(s)", counted[i])
                     for name, counted in bins.items() if name != "real"]
            print(f"[gap] from step {real['from_step']}+: {real['rollouts']} rollouts, real frames "
                  f"{real['real'] / real['rollouts']:.3f}" + "".join(
                      f", {name} late {b['real'] / b['rollouts']:.3f}"
                      + (f" (kept {100 * b['real'] / real['real']:.0f}%)" if real["real"] else "")
                      for name, b in lates), flush=True)
    return {"mode": f"sampled at T {rl.grpo.temperature}, proprio missing, {rl.env.execute_steps} actions a decision, "
                    f"{horizon} actions from keyframes (fractions {cfg.rl.imagined.keyframe_from}-"
                    f"{cfg.rl.imagined.keyframe_fraction} of each demonstration)",
            "steps": steps, "starts_per_step": cfg.rl.grpo.rollout_batch, "group_size": cfg.rl.grpo.group_size,
            "late_actions": list(late_actions),
            "demos": list(demos), "seconds": round(time.time() - start, 1), **bins}


def main(argv: Sequence[str] | None = None) -> dict:
    import configs

    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, rest = configs.from_argv(argv, default="sword:small")
    parser = policy_parser(__doc__, episodes_per_task=3, views=GAP_VIEWS, results="action_gap.json")
    parser.add_argument("--decisions", type=int, default=12, help="decisions kept per episode, from rest")
    parser.add_argument("--vae", default="", help="VAE checkpoint directory (train_vae; a pipeline's vae_run/vae): "
                        "adds the view vae, the frames' round trip through it")
    parser.add_argument("--lag-episodes-per-task", type=int, default=0,
                        help="also the real success of whole episodes read with one decision of lag (0 = off)")
    parser.add_argument("--lag-proprio", default="missing",
                        help="comma list of true, reckoned, missing: the lag measured with the policy reading that "
                        "proprio (reckoned: the policy's .reckoning.json beside it)")
    parser.add_argument("--lag-keyframe-steps", type=int, default=0,
                        help="also the lag's cost by the start's step: the start states of this many ground-truth "
                        "GRPO steps from keyframes (--demos), each rolled out on real and on late frames (0 = off)")
    parser.add_argument("--demos", action="append", default=[],
                        help="demonstrations with recorded states (LIBERO-layout HDF5) for --lag-keyframe-steps")
    parser.add_argument("--lag-late-actions", default="",
                        help="with --lag-keyframe-steps, also these lags in actions (comma list, each 1 to a "
                        "decision's actions - 1): the frame that many actions before the decision's end")
    parser.add_argument("--lag-workers", type=int, default=0,
                        help="with --lag-keyframe-steps: processes the C engine steps in (0 = this one)")
    args = parser.parse_args(rest)
    if args.lag_workers < 0:
        raise SystemExit(f"bench_action_gap: --lag-workers must be >= 0, got {args.lag_workers}")
    try:
        late_actions = [int(x) for x in args.lag_late_actions.split(",") if x]
    except ValueError:
        raise SystemExit(f"bench_action_gap: --lag-late-actions must be a comma list of ints, got "
                         f"{args.lag_late_actions!r}") from None
    k = cfg.rl.imagined_actions_per_decision
    if any(not 1 <= j < k for j in late_actions) or len(set(late_actions)) < len(late_actions) or (
            late_actions and not args.lag_keyframe_steps):
        raise SystemExit(f"bench_action_gap: --lag-late-actions needs --lag-keyframe-steps and distinct lags from 1 "
                         f"to {k - 1} (a decision is {k} actions), got {args.lag_late_actions!r}")
    if args.lag_keyframe_steps < 0 or bool(args.lag_keyframe_steps) != bool(args.demos):
        raise SystemExit(f"bench_action_gap: --lag-keyframe-steps (>= 1) and --demos go together, got "
                         f"{args.lag_keyframe_steps} and {len(args.demos)} demonstration files")
    missing = [d for d in args.demos if not os.path.isfile(d)]
    if missing:
        raise SystemExit(f"bench_action_gap: no such demonstration file: {', '.join(missing)}")
    try:
        views = parse_views(args.views, vae=bool(args.vae))
    except ValueError as err:
        raise SystemExit(f"bench_action_gap: {err}") from None
    lag_proprio = [m for m in args.lag_proprio.split(",") if m]
    if not lag_proprio or set(lag_proprio) - {"true", "reckoned", "missing"} or len(set(lag_proprio)) < len(lag_proprio):
        raise SystemExit(f"bench_action_gap: --lag-proprio must list some of true, reckoned, missing once each, got "
                         f"{args.lag_proprio!r}")
    reckoning_file = os.path.splitext(args.policy)[0] + ".reckoning.json"  # where bench_policy sft saves it
    if "reckoned" in lag_proprio and not os.path.isfile(reckoning_file):
        raise SystemExit(f"bench_action_gap: --lag-proprio reckoned needs the policy's reckoning {reckoning_file}")
    if args.episodes_per_task < 1 or args.decisions < 1 or args.lag_episodes_per_task < 0:
        raise SystemExit(f"bench_action_gap: --episodes-per-task and --decisions must be >= 1 and "
                         f"--lag-episodes-per-task >= 0, got {args.episodes_per_task}, {args.decisions} and "
                         f"{args.lag_episodes_per_task}")

    from sim import tasks as sim_tasks
    from sim.lockstep import LockstepEnvs
    from sword_jax.load import experiment_vae
    from sword_jax.rl.env_rollout import make_act_fns
    from sword_jax.rl.params_io import load_params_npz
    from sword_jax.rl.policy import build_policy

    start = time.time()
    execution = dataclasses.replace(cfg.rl.env, execute_steps=cfg.rl.imagined_actions_per_decision,
                                    action_ensemble=False)  # the learned simulator's, without sampling
    rl = dataclasses.replace(cfg.rl, env=execution)
    graphdef, params = build_policy(rl, seed=cfg.seed)
    params = load_params_npz(args.policy, params)
    episodes = sim_tasks.evaluation_episodes(list(cfg.sim.tasks), args.episodes_per_task)
    with LockstepEnvs(episodes, resolution=cfg.sim.resolution, max_steps=cfg.sim.max_steps) as envs:
        frames, taken, rollout = policy_frames(make_act_fns(graphdef, rl), params, envs, rl, decisions=args.decisions,
                                               key=jax.random.key(cfg.seed))
    episode_seconds = time.time() - start
    vae = experiment_vae(cfg, args.vae) if args.vae else None
    out = measure(graphdef, params, frames, taken, rollout, views, rl=rl, seed=cfg.seed, vae=vae)
    frame_consecutive, gap_consecutive = consecutive(out["real_actions"], out["small"], taken)
    results = {
        "policy": args.policy, "config": cfg.name, "argv": argv, "device": str(jax.devices()[0].device_kind),
        "mode": f"greedy, proprio missing, {rl.env.execute_steps} actions a decision, no ensembling, from rest, "
                f"the frames read at the first {args.decisions} decisions (C engine, JAX renderer)",
        "episodes": len(episodes), "frames": int(taken.sum()), "decisions": args.decisions,
        "success_within_decisions": float(np.mean(rollout.success)),
        "interval": f"95% bootstrap over episodes ({RESAMPLES} resamples)",
        **({"vae": args.vae} if args.vae else {}),
        "views": {view: {"parameters": dict(zip(PARAMETER_NAMES, VIEWS[view])),
                         "action_gap": summarize(out["action_gap"][i], seed=cfg.seed),
                         "frame_error": summarize(out["frame_error"][i], seed=cfg.seed)}
                  for i, view in enumerate(views)},
        "consecutive_decisions": {"action_gap": summarize(gap_consecutive, seed=cfg.seed),
                                  "frame_error": summarize(frame_consecutive, seed=cfg.seed)},
    }
    if args.lag_episodes_per_task:
        lag_episodes = sim_tasks.evaluation_episodes(list(cfg.sim.tasks), args.lag_episodes_per_task)
        from sword_jax.rl.proprio_reckoning import load_reckoning

        reckoning = load_reckoning(reckoning_file) if "reckoned" in lag_proprio else None
        by_proprio = {}
        with LockstepEnvs(lag_episodes, resolution=cfg.sim.resolution, max_steps=cfg.sim.max_steps) as envs:
            for mode in lag_proprio:
                lag = lag_success(make_act_fns(graphdef, rl), params, envs, rl, max_steps=cfg.sim.max_steps,
                                  tasks=[t for t, _ in lag_episodes], key=jax.random.key(cfg.seed), proprio=mode,
                                  reckoning=reckoning)
                lag["mode"] = (f"sampled at T {rl.grpo.temperature}, proprio {mode}, {rl.env.execute_steps} actions a "
                               f"decision, {cfg.sim.max_steps} actions from rest")
                by_proprio[mode] = lag
                print(f"[gap] success over {lag['real']['episodes']} episodes, proprio {mode}: real "
                      f"{lag['real']['mean']:.3f}, a decision late {lag['lag_1']['mean']:.3f} "
                      f"({lag['difference']['mean']:+.3f} [{lag['difference']['ci95'][0]:+.3f}, "
                      f"{lag['difference']['ci95'][1]:+.3f}])", flush=True)
        results["lag"] = by_proprio[lag_proprio[0]]  # the first mode listed (missing by default)
        if len(lag_proprio) > 1:
            results["lag_by_proprio"] = by_proprio
    if args.lag_keyframe_steps:
        results["lag_by_start"] = keyframe_lag(cfg, rl, graphdef, params, demos=args.demos,
                                               steps=args.lag_keyframe_steps, late_actions=late_actions,
                                               workers=args.lag_workers)
    results["seconds"] = {"episodes": round(episode_seconds, 1), "all": round(time.time() - start, 1)}
    print(f"[gap] {results['frames']} frames of {len(episodes)} episodes, {results['seconds']['all']}s; "
          f"greedy action gap and frame error (mean [95% interval])", flush=True)
    rows = [(v, r["action_gap"], r["frame_error"]) for v, r in results["views"].items()]
    rows.append(("next decision", *results["consecutive_decisions"].values()))
    for name, gap, error in rows:
        if gap["frames"]:
            print(f"[gap] {name:<14} gap {gap['mean']:.4f} [{gap['ci95'][0]:.4f}, {gap['ci95'][1]:.4f}]  "
                  f"frame error {error['mean']:.4f} [{error['ci95'][0]:.4f}, {error['ci95'][1]:.4f}]  "
                  f"({gap['frames']} frames)", flush=True)
    os.makedirs(args.out, exist_ok=True)
    write_json_atomic(os.path.join(args.out, "action_gap.json"), results)
    return results


if __name__ == "__main__":
    cli.run(main)
