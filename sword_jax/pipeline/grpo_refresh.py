"""GRPO in the learned simulator with refreshes (:mod:`sword_jax.rl.refresh`): the run's loop.

Every ``rl.refresh.every`` steps (at an evaluation, step 0 included) the policy is first evaluated in the
ground-truth environments, then the simulator is refreshed on real episodes of the current policy; the
exploitation guard judges the refresh's replay (real episodes the simulator had not seen, in the simulator
GRPO trained in). A GRPO step reads the simulator, the calibrated detector and its start states (branched
from the latest refresh's real episodes) from the refresh its step follows, so a resumed run, which
loads the refreshes from disk, ends as an uninterrupted one does. With ``rl.imagined.reward=executed`` (keyframe
starts, no branch) each imagined trajectory is paid instead by its actions executed from its keyframe's recorded
state, and counted by where the start stood: whether the refreshes make the policy's closed loop in the world
model keep more of what reality pays it.

Nothing here imports a simulator: the environment is a pure JAX one (:class:`~sword_jax.rl.scan_rollout.JaxEnv`,
MJX in ``sim.grpo_refresh``), its start states come from ``collect_starts``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax import sharding as shd
from sword_jax.atomic_write import write_json_atomic
from sword_jax.pipeline.grpo import log, sampled_mixed, start_state
from sword_jax.rl import data as rl_data
from sword_jax.rl import grpo
from sword_jax.rl.grpo_loop import grpo_run_id, train_grpo
from sword_jax.rl.policy import tokenize_instructions
from sword_jax.rl.refresh import RealEpisodes, Refresher
from sword_jax.rl.scan_rollout import JaxEnv, record_episodes
from sword_jax.rng import stream_key, stream_rng

REFRESH_RUN_KEYS = ("every", "episodes", "budget", "episode_steps", "world_model_steps", "world_model_learning_rate",
                    "detector_steps", "replay_share", "calibrate_fraction", "max_false_success", "calibration",
                    "calibrate_over", "branch", "horizons", "min_separation", "pause_untrusted")


def make_collect(graphdef: Any, rl: Any, env: JaxEnv, collect_starts: Callable[[int, int], tuple], *, seed: int,
                 steps: int) -> Callable[[Any, int, int], RealEpisodes]:
    """``collect(params, step, n)``: ``n`` real episodes of the policy (:func:`record_episodes`, sampled at
    ``rl.grpo.temperature``) from ``collect_starts(step, m) -> (env starts, instructions, tasks)``; the
    sampling key is a function of (seed, step). With ``rl.refresh.group_size`` k > 1, ``m = n / k`` starts
    each rolled out k times, consecutive episodes (a group shares its start, not its sampled actions)."""
    record = jax.jit(lambda params, starts, tokens, key: record_episodes(graphdef, params, env, starts, tokens, rl,
                                                                         key=key, steps=steps))
    root = stream_key(jax.random.key(seed), "refresh/collect")
    k = rl.refresh.group_size

    def collect(params, step, n):
        if n % k:
            raise ValueError(f"refresh collect: {n} episodes are not whole groups of rl.refresh.group_size={k}")
        starts, instructions, tasks = collect_starts(step, n // k)
        if k > 1:
            starts = np.repeat(np.asarray(starts), k, axis=0)
            instructions = [text for text in instructions for _ in range(k)]
            tasks = np.repeat(np.asarray(tasks), k)
        tokens = jnp.asarray(tokenize_instructions(list(instructions), rl.policy.max_instruction_bytes))
        rec = record(params, jnp.asarray(starts), tokens, jax.random.fold_in(root, step))
        return RealEpisodes.from_recorded(jax.device_get(rec), instructions, tasks)

    return collect


def run_refreshed(cfg: Any, rl: Any, graphdef: Any, params: Any, workdir: str, *, setup: Any, wm_state: Any,
                  make_simulator: Callable[[Any], Any], encode_frames: Callable[[np.ndarray], np.ndarray],
                  detector: tuple[Any, Any], base: Any, env: JaxEnv, collect_starts: Callable[[int, int], tuple],
                  evaluate_real: Callable[[int, Any], tuple[dict, dict]], max_traces: int,
                  facts: dict[str, Any] | None = None) -> dict:
    """GRPO in the learned simulator with refreshes, resuming from ``workdir``.

    Args:
      setup: the run's :class:`~sword_jax.pipeline.grpo.Setup` (its ``starts`` are the demonstrations'
        keyframes, used until a refresh gives real states to branch from, and its ``encode``, or with
        ``rl.imagined.start_encoding=prefix`` its ``encode_prefix``, encodes every start from real frames).
      wm_state / make_simulator / encode_frames / detector / base: as :class:`~sword_jax.rl.refresh.Refresher` takes them.
      env / collect_starts: the ground-truth environment and ``(step, n) -> (starts, instructions, tasks)``.
      evaluate_real: ``(step, params) -> (point, extra)``, the ground-truth evaluation.
      facts: more identity facts of the run (its tasks, the environment's settings).

    Returns ``{"curve", "workdir", "history", "refreshes", "real_episodes_used", "params"}`` (the final policy).
    """
    rl.validate()
    executed = rl.imagined.reward == "executed"  # each trajectory paid by its actions executed in env
    if executed and setup.env_starts is None:
        raise ValueError("rl.imagined.reward=executed with rl.refresh resets the real environment to the keyframes' "
                         "recorded states: the demonstrations hold no 'states'")
    if rl.refresh.every % rl.grpo.eval_every:
        raise ValueError(f"rl.refresh.every={rl.refresh.every} must be a multiple of rl.grpo.eval_every="
                         f"{rl.grpo.eval_every} (a refresh follows an evaluation)")
    mesh = shd.make_mesh(cfg.mesh)
    steps = rl.refresh.episode_steps or cfg.sim.max_steps
    collect = make_collect(graphdef, rl, env, collect_starts, seed=cfg.seed, steps=steps)
    # rl.imagined.start_encoding=prefix: every start below is encoded from its episode's frame 0 on
    encode_prefix = rl_data.prefix_encoder(rl.imagined.start_encoding, setup.encode_prefix, "GRPO with rl.refresh")
    verify = None
    if rl.refresh.verify_starts:
        verify = make_verify(graphdef, rl, env, collect_starts, setup.encode, seed=cfg.seed,
                             num_context=cfg.data.context_frames // cfg.vae.temporal_factor,
                             frames_per_latent=cfg.vae.temporal_factor, mesh=mesh, encode_prefix=encode_prefix)
    closed_loop = None
    if rl.refresh.closed_loop_starts:
        if setup.env_starts is None or setup.windows is None:
            raise ValueError("rl.refresh.closed_loop_starts executes the closed loop's actions from the keyframes' "
                             "recorded states: the demonstrations hold no 'states'")
        closed_loop = make_closed_loop(graphdef, rl, env, setup, encode_frames, seed=cfg.seed,
                                       frames_per_latent=cfg.vae.temporal_factor,
                                       num_future=cfg.data.predict_frames // cfg.vae.temporal_factor, mesh=mesh)
    refresher = Refresher(cfg, rl, wm_state=wm_state, make_simulator=make_simulator, encode=setup.encode,
                          encode_frames=encode_frames, detector=detector, base=base, collect=collect,
                          directory=os.path.join(workdir, "refresh"), mesh=mesh, log=log, verify=verify,
                          closed_loop=closed_loop, encode_prefix=encode_prefix)
    state = jax.device_put(grpo.init_state(params, rl), shd.replicated(mesh))
    starts_key = stream_key(jax.random.key(cfg.seed), "grpo/starts")
    built: dict[str, Any] = {}
    placed: dict[str, Any] = {}  # the simulator and reward model of the refresh the steps follow, on the mesh

    def step_fn(*args):
        # built at the first step, after the first refresh, which may choose the imagined horizon
        if "fn" not in built:
            run_rl, horizon, decisions = rl, refresher.horizon(), refresher.decisions()
            if horizon is not None:
                run_rl = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, max_chunks=decisions))
                log(f"imagined rollouts of {horizon} actions ({decisions} decisions), chosen by the first refresh")
            built["fn"] = grpo.make_grpo_step(graphdef, run_rl, max_traces=max_traces, mesh=mesh, rules=cfg.mesh.rules,
                                              env=env if executed else None)
        return built["fn"](*args)

    def step(state, index, key):
        refresher.at(index)  # the refresh this step follows (a resumed run loads it)
        pick = refresher.branch_pick(index, rl.imagined_starts_per_step)  # rollout_batch x rl.imagined.oversample
        starts = (setup.starts(jax.random.fold_in(starts_key, index), index) if pick is None
                  else start_state(pick, setup.encode, rl, encode_prefix=encode_prefix))
        if placed.get("refresh", -2) != refresher.loaded:  # once per refresh, not per step: cast and placed
            models = (refresher.simulator(), refresher.reward_model())
            placed.update(refresh=refresher.loaded, models=jax.device_put(models, shd.shardings_on(models, mesh)))
        batch = (*placed["models"], starts)
        if executed:  # the keyframes' recorded states, which the actions are executed from, and their steps
            batch += (setup.env_starts(index),) + ((setup.start_steps(index),) if setup.start_steps else ())
        paused = refresher.paused()
        if paused:  # the simulator failed its trust test: the rollouts run and are logged, the policy stays
            kept = jax.tree.map(jnp.copy, state)  # the step donates the state it is given
            _, metrics = step_fn(state, batch, key)
            state = kept
        else:
            state, metrics = step_fn(state, batch, key)
        return state, dict(metrics, real_episodes_used=jnp.float32(refresher.used), paused=jnp.float32(paused))

    def evaluate(index, params):
        point, extra = evaluate_real(index, params)
        if refresher.due(index):
            if jax.process_index() == 0:  # kept apart first: a run stopped inside the refresh (a deadline) keeps it
                os.makedirs(os.path.join(workdir, "evaluations"), exist_ok=True)
                write_json_atomic(os.path.join(workdir, "evaluations", f"step_{index:06d}.json"),
                                  dict(step=int(index), **point, **extra))
            record = refresher.refresh(index, params)
            extra = dict(extra, refresh=record)
            if "replay" in record:
                extra["replay"] = record["replay"]
            if "verify" in record:  # the exploitation guard's input with rl.imagined.guard_on=verify
                extra["verify"] = record["verify"]
        point["real_episodes_used"] = refresher.used
        log(f"eval step {index}: success {point['mean']:.3f}, real episodes used {refresher.used}/{rl.refresh.budget}")
        return point, extra

    def progress(point, eta):
        paid = "real success of the imagined actions" if executed else "imagined success"
        return (f"grpo step {point['step']}/{rl.grpo.steps} {paid} {point['success_rate']:.3f} "
                f"loss {point['loss']:.4f} clip {point['clip_fraction']:.3f} kept {point['kept_fraction']:.2f}"
                f"{sampled_mixed(point, rl)} "
                f"real episodes used {point['real_episodes_used']:.0f}{' (paused: simulator untrusted)' if point.get('paused') else ''} "
                f"eta {eta:.0f}s")

    # group_size, verify_starts and the closed loop enter only when set, so runs from before they were settings
    # still resume
    keys = (REFRESH_RUN_KEYS + (("group_size",) if rl.refresh.group_size != 1 else ())
            + (("verify_starts",) if rl.refresh.verify_starts else ())
            + (("closed_loop_starts", "closed_loop_share") if rl.refresh.closed_loop_starts else ()))
    run_id = grpo_run_id(rl, seed=cfg.seed, simulator="world_model_refreshed", **(facts or {}),
                         **{f"rl.refresh.{k}": getattr(rl.refresh, k) for k in keys})
    result, curve = train_grpo(step, state, lambda index: index, key=stream_key(jax.random.key(cfg.seed), "grpo/update"),
                               rl=rl, workdir=workdir, evaluate=evaluate, run_id=run_id, progress=progress,
                               curve_label="GRPO in the refreshed learned simulator", log=log,
                               frames_per_chunk=setup.sim.frames_per_step)
    refreshes = list(refresher.records)
    with open(os.path.join(workdir, "refreshes.json"), "w") as f:
        json.dump(refreshes, f, indent=1)
    return {"curve": curve, "workdir": workdir, "history": result.history, "refreshes": refreshes,
            "real_episodes_used": refresher.used, "params": result.state.params}


def make_verify(graphdef: Any, rl: Any, env: JaxEnv, collect_starts: Callable[[int, int], tuple],
                encode: Callable[..., Any], *, seed: int, num_context: int, frames_per_latent: int, mesh: Any,
                encode_prefix: Callable[..., Any] | None = None) -> Callable[..., dict]:
    """``verify(params, simulator, reward_model, step, decisions) -> report`` for ``rl.refresh.verify_starts``
    (:mod:`sword_jax.rl.imagined_check`): ``collect_starts(step, verify_starts)`` start states put in ``env``
    (their settled first frames, held still, start the simulator), each rolled out ``rl.grpo.group_size`` times
    by the policy in the simulator for ``decisions`` decisions as GRPO samples (a key from (seed, step)), each
    imagined trajectory's actions executed in ``env`` from the same start; the report of
    :func:`~sword_jax.rl.imagined_check.report` with ``starts``, ``group_size`` and ``actions`` (the horizon).
    With ``rl.imagined.start_encoding=prefix`` the starts are encoded by ``encode_prefix`` from their episode's
    frame 0, the settled frame itself (:func:`verify_prefix`)."""
    from sword_jax.rl import imagined_check, sim_agreement
    from sword_jax.rl.rollout import imagined_rollout

    g, per = rl.grpo.group_size, rl.imagined_actions_per_decision
    reset = jax.jit(env.reset)
    root = stream_key(jax.random.key(seed), "refresh/verify")
    encode_prefix = rl_data.prefix_encoder(rl.imagined.start_encoding, encode_prefix, "rl.refresh.verify_starts")
    compiled: dict[int, Callable] = {}

    def checked_fn(decisions: int) -> Callable:
        if decisions not in compiled:  # one compile per horizon (the run's is chosen at its first refresh)
            run_rl = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, max_chunks=decisions))

            def go(params, sim, rm, start, env_starts, key):
                rollout = imagined_rollout(graphdef, params, sim, rm, start, run_rl, key=key, group_size=g)
                return imagined_check.check(rollout, env, env_starts, rl.action_bins)

            compiled[decisions] = jax.jit(go)
        return compiled[decisions]

    def verify(params, sim, rm, step: int, decisions: int) -> dict:
        starts, instructions, _ = collect_starts(step, rl.refresh.verify_starts)
        starts = np.asarray(starts)
        _, obs = reset(jnp.asarray(starts))
        window = imagined_check.still_window(np.asarray(obs["frames"]), np.asarray(obs["proprio"]), list(instructions),
                                             num_context=num_context, frames_per_latent=frames_per_latent,
                                             action_dim=rl.action_dim)
        if encode_prefix is not None:
            window = verify_prefix(window, num_context=num_context, frames_per_latent=frames_per_latent)
        start = start_state(window, encode, rl, encode_prefix=encode_prefix)
        sim, rm = jax.device_put((sim, rm), shd.shardings_on((sim, rm), mesh))
        env_starts = jnp.asarray(np.repeat(starts, g, axis=0))
        checked = jax.device_get(checked_fn(decisions)(params, sim, rm, start, env_starts,
                                                       jax.random.fold_in(root, step)))
        actions = decisions * per
        horizons = tuple(h for h in sim_agreement.HORIZON_SWEEP if h < actions)
        return dict(imagined_check.report(checked, g, horizons=horizons), starts=len(starts), group_size=g,
                    actions=actions)

    return verify


def verify_prefix(window: dict[str, Any], *, num_context: int, frames_per_latent: int) -> dict[str, Any]:
    """A start at rest (:func:`~sword_jax.rl.imagined_check.still_window`) with the ``prefix`` and ``latent_index``
    of :func:`~sword_jax.rl.data.keyframe_window` at frame 0: the settled frame is its episode's first, so its prefix
    is that frame held to the end of the first context latent."""
    frames = np.asarray(window["first_frame"])[:, None]  # (n, 1, H, W, 3): the episode so far
    n = frames.shape[0]
    at_rest = rl_data.keyframe_window(frames, np.zeros((n, 1, 1), np.float32), np.zeros((n, 1, 1), np.float32),
                                      np.arange(n), np.zeros(n, np.int64), num_context=num_context,
                                      frames_per_latent=frames_per_latent, prefix_latents=num_context)
    return dict(window, prefix=at_rest["prefix"], latent_index=at_rest["latent_index"])


# the closed loop's keyframes are drawn as GRPO's step ``CLOSED_LOOP_STEPS + refresh step x draws + r``: steps a run
# never reaches, so they are not the starts GRPO's own steps are measured on
CLOSED_LOOP_STEPS = 1 << 30


def make_closed_loop(graphdef: Any, rl: Any, env: JaxEnv, setup: Any, encode_frames: Callable[[np.ndarray], np.ndarray],
                     *, seed: int, frames_per_latent: int, num_future: int, mesh: Any
                     ) -> Callable[..., tuple[Any, dict]]:
    """``closed_loop(params, simulator, reward_model, step, decisions) -> (segments, report)`` for
    ``rl.refresh.closed_loop_starts`` (:mod:`sword_jax.rl.closed_loop`): keyframe starts of ``setup`` (drawn as
    GRPO's are, for steps it never reaches: :data:`CLOSED_LOOP_STEPS`), each rolled out ``rl.grpo.group_size``
    times by the policy in the simulator (GRPO's imagined rollout with its detector, none stopped at a success)
    over ``decisions`` decisions (a key from (seed, step)), each trajectory's actions executed in ``env`` from its
    keyframe's recorded state, every frame kept and encoded by ``encode_frames`` after the keyframe's real history
    (:func:`~sword_jax.rl.closed_loop.real_latents`; with ``rl.imagined.start_encoding=prefix`` the starts and the
    real latents both after its episode from frame 0, ``setup.encode_prefix``). The report holds the executions
    (``episodes``), how often they really succeeded, and the closed loop's drift in latent space by decision
    (:func:`~sword_jax.rl.closed_loop.drift_by_decision`)."""
    from sword_jax.rl import closed_loop as cl
    from sword_jax.rl import imagined_check

    g, per = rl.grpo.group_size, rl.imagined_actions_per_decision
    draws = rl.refresh.closed_loop_starts // rl.imagined_starts_per_step
    execute_latents = per // frames_per_latent
    root = stream_key(jax.random.key(seed), "refresh/closed_loop")
    encode_prefix = rl_data.prefix_encoder(rl.imagined.start_encoding, setup.encode_prefix,
                                           "rl.refresh.closed_loop_starts")
    compiled: dict[int, Callable] = {}

    def traced(decisions: int) -> Callable:
        if decisions not in compiled:  # one compile per horizon
            def go(params, sim, rm, start, env_starts, key):
                trace = cl.trace_closed_loop(graphdef, params, sim, rm, start, rl, key=key, group_size=g,
                                             decisions=decisions)
                n, t = trace.actions.shape[:2]
                first, frames = imagined_check.execute_observed(env, env_starts, trace.actions,
                                                                jnp.full((n,), t, jnp.int32), every=1, rows=n)
                return trace, first, frames.astype(jnp.uint8)

            compiled[decisions] = jax.jit(go)
        return compiled[decisions]

    def closed_loop(params, sim, rm, step: int, decisions: int):
        sim, rm = jax.device_put((sim, rm), shd.shardings_on((sim, rm), mesh))
        parts, solved, drifts = [], [], []
        for r in range(draws):
            index = CLOSED_LOOP_STEPS + step * draws + r
            window = setup.windows(index)  # the keyframes GRPO's step `index` would draw, with their real history
            if encode_prefix is not None and "prefix" not in window:
                raise ValueError("rl.imagined.start_encoding=prefix: rl.refresh.closed_loop_starts' keyframes carry no "
                                 "episode from frame 0 (the setup's windows are cut without prefix_latents)")
            start = start_state(window, setup.encode, rl, encode_prefix=encode_prefix)
            env_starts = np.repeat(np.asarray(setup.env_starts(index)), g, axis=0)
            trace, first, frames = jax.device_get(traced(decisions)(params, sim, rm, start, jnp.asarray(env_starts),
                                                                    jax.random.fold_in(root, index)))
            # the executed frames after the keyframe's history, or with the prefix after the episode from frame 0
            # to the keyframe, as the start latents were encoded
            history, index = ((window["history"], None) if encode_prefix is None
                              else (window["prefix"][:, 1:], np.repeat(window["latent_index"], g)))
            real = cl.real_latents(encode_frames, np.repeat(window["first_frame"], g, axis=0),
                                   np.repeat(history, g, axis=0), np.asarray(frames),
                                   frames_per_latent=frames_per_latent, latent_index=index)
            latents, start_actions = (np.repeat(np.asarray(x), g, axis=0) for x in start.latents)
            contexts = np.asarray(trace.contexts, np.float32)
            parts.append(cl.closed_loop_segments(latents, start_actions, contexts, real, np.asarray(trace.actions),
                                                 num_future=num_future, execute_latents=execute_latents,
                                                 frames_per_latent=frames_per_latent))
            drifts.append(cl.drift_by_decision(contexts, real, execute_latents=execute_latents))
            solved.append(np.asarray(first) >= 0)
        segments = cl.ClosedLoopSegments.concatenate(parts)
        episodes = int(sum(len(x) for x in solved))
        return segments, {"episodes": episodes, "starts": draws * rl.imagined_starts_per_step, "group_size": g,
                          "actions": decisions * per, "real_success": float(np.concatenate(solved).mean()),
                          "latent_drift_by_decision": [float(np.mean(x)) for x in zip(*drifts)]}

    return closed_loop


def stratified_collect_starts(pool_starts: Callable[[int, np.random.Generator], tuple], seed: int
                              ) -> Callable[[int, int], tuple]:
    """``collect_starts(step, n)`` from ``pool_starts(n, rng) -> (starts, instructions, tasks)``, its rng a
    function of (seed, step)."""
    return lambda step, n: pool_starts(n, stream_rng(seed, "refresh/starts", step))
