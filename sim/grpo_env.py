"""GRPO against the ground-truth environments: in MuJoCo's C engine (:class:`sim.lockstep.LockstepEnvs`)
or on MJX (:class:`sim.mjx_batch.MjxEpisodes`), from the training split's initial states or the
demonstrations' keyframes, and the simulator's action convention for reckoned proprio.

The same ``grpo_update`` trains on these rollouts as on imagined ones, so this validates the update
independently of any world model (``python -m train.grpo --simulator env`` is the command line).
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from sim import controller, panda
from sim import tasks as sim_tasks
from sim.lockstep import LockstepEnvs, lockstep_evaluation
from sim.mjx_batch import MjxEpisodes, episode_starts, stratified_train_starts
from sword_jax import tracing
from sword_jax.pipeline.grpo import log, mode_point, sampled_point, skipped_note
from sword_jax.rl import data as rl_data
from sword_jax.rl import grpo
from sword_jax.rl.env_rollout import make_act_fns, run_policy
from sword_jax.rl.grpo import UPDATE_KEY_SALT
from sword_jax.rl.grpo_loop import grpo_run_id, train_grpo
from sword_jax.rl.imagined_check import outcomes_by_start
from sword_jax.rl.jax_env_grpo import EnvGRPO, branch_starts, start_value
from sword_jax.rl.policy import tokenize_instructions
from sword_jax.rl.policy_success import evaluate_in_sim
from sword_jax.rl.proprio_reckoning import ReckoningConfig, fit_gains
from sword_jax.rl.value import as_value, build_value
from sword_jax.rng import stream_key, stream_rng


def sim_reckoning(episodes):
    """The simulator controller's action convention as a proprio ReckoningConfig, with the realised
    fraction of each commanded axis fitted to ``episodes`` (an ``rl.data.EpisodeSet``)."""
    ctl = controller.ControllerConfig()
    base = ReckoningConfig(pos_scale=ctl.pos_scale, rot_scale=ctl.rot_scale, finger_open=panda.FINGER_OPEN,
                           finger_closed_target=panda.FINGER_CLOSED_TARGET)
    cfg = fit_gains(episodes.proprio, episodes.actions, base, lengths=episodes.lengths)
    print(f"grpo: imagined proprio reckoned from actions, gains pos {[round(g, 3) for g in cfg.pos_gain]} "
          f"rot {[round(g, 3) for g in cfg.rot_gain]} (fitted to {len(episodes.lengths)} demonstrations)")
    return cfg


def keyframe_horizon(rl) -> int:
    """Actions an imagined rollout executes at most: ``max_chunks`` decisions of the simulator's execution."""
    return rl.imagined.max_chunks * rl.imagined_actions_per_decision


def cut_at_horizon(rl) -> bool:
    """Whether ground-truth GRPO's training rollouts run in the learned simulator's setting: ``rl.env.starts``
    ``keyframes``, ``branch`` or ``rest`` run :func:`keyframe_horizon` actions at most (never past the episode
    limit), executing ``rl.imagined_actions_per_decision`` a decision; ``initial`` runs whole episodes with
    ``rl.env.execute_steps``."""
    return rl.env.starts in ("keyframes", "branch", "rest")


def training_horizon(rl, episode_limit: int) -> int:
    """Actions a ground-truth GRPO training rollout runs at most: :func:`keyframe_horizon`, never past
    ``episode_limit``, where :func:`cut_at_horizon`; else the whole episode."""
    return min(keyframe_horizon(rl), episode_limit) if cut_at_horizon(rl) else episode_limit


def check_keyframe_episodes(episodes) -> None:
    """Refuses demonstrations that ``rl.env.starts=keyframes`` cannot continue: none given, or without recorded
    states or task ids."""
    if episodes is None:
        raise ValueError("rl.env.starts=keyframes needs the demonstrations (train.grpo: --demos)")
    if episodes.states is None or episodes.tasks is None:
        raise ValueError("rl.env.starts=keyframes continues demonstrations from their recorded states; these "
                         "episodes have no states or task ids (LIBERO-layout HDF5 from train.gen_data has both)")


def keyframe_picks(episodes, rl, *, seed: int, step: int, round_: int = 0, num_context: int = 1) -> list:
    """The ``rl.grpo.rollout_batch`` ground-truth start states of GRPO step ``step`` (sampling round
    ``round_``) with ``rl.env.starts=keyframes``: ``(task, flat state)`` of the demonstrations at the
    keyframes GRPO in the learned simulator draws (the same sampler; a function of (seed, step, round))."""
    check_keyframe_episodes(episodes)
    ep, t = _keyframe_draw(episodes, rl, seed=seed, step=step, round_=round_, num_context=num_context)
    return [(int(episodes.tasks[e]), episodes.states[e, s]) for e, s in zip(ep, t)]


def _keyframe_draw(episodes, rl, *, seed: int, step: int, round_: int, num_context: int) -> tuple:
    """``(episode [B], frame t [B])`` of GRPO step ``step``'s keyframes (sampling round ``round_``): a function of
    (seed, step, round)."""
    rng = (stream_rng(seed, "grpo/env_keyframes", step) if round_ == 0
           else stream_rng(seed, "grpo/env_keyframes", step, round_))
    return rl_data.keyframe_indices(episodes, rl.grpo.rollout_batch, rng, max_fraction=rl.imagined.keyframe_fraction,
                                    min_fraction=rl.imagined.keyframe_from, num_context=num_context)


def keyframe_steps(episodes, rl, *, seed: int, step: int, round_: int = 0, num_context: int = 1) -> np.ndarray:
    """Each of :func:`keyframe_picks`' start states' step in its demonstration (``[B]`` int32, the same draw)."""
    return np.asarray(_keyframe_draw(episodes, rl, seed=seed, step=step, round_=round_, num_context=num_context)[1],
                      np.int32)


def keyframe_env_starts(episodes, rl, *, seed: int, step: int, num_context: int = 1) -> list:
    """:func:`keyframe_picks` of step ``step``, each repeated ``group_size`` times (the C engine's rollouts)."""
    return keyframe_env_draw(episodes, rl, seed=seed, step=step, num_context=num_context)[0]


def keyframe_env_draw(episodes, rl, *, seed: int, step: int, num_context: int = 1) -> tuple[list, np.ndarray]:
    """:func:`keyframe_env_starts` of step ``step`` and each one's step in its demonstration (``[B x group_size]``
    int32, :func:`keyframe_steps` repeated as the starts are), from one draw."""
    check_keyframe_episodes(episodes)
    ep, t = _keyframe_draw(episodes, rl, seed=seed, step=step, round_=0, num_context=num_context)
    g = rl.grpo.group_size
    starts = [(int(episodes.tasks[e]), episodes.states[e, s]) for e, s in zip(ep, t) for _ in range(g)]
    return starts, np.repeat(np.asarray(t, np.int32), g)


def run_in_env(cfg, rl, graphdef, params, workdir: str, *, episodes_per_task: int, workers: int = 0,
               renderer: str = "jax", reckoning=None, keyframes=None,
               max_traces: int = tracing.ENTRY_MAX_TRACES) -> dict:
    """GRPO against the ground-truth environments (see the module docstring); resumes from ``workdir``.

    The policy reads proprio as ``rl.env.proprio`` says (``reckoning``: the action convention for
    ``reckoned``, e.g. :func:`sim_reckoning`); unless it is ``true``, each evaluation also measures
    that mode, stored as ``train_mode`` beside the true-proprio success. With ``rl.env.starts=keyframes``
    the rollouts start from ``keyframes`` (an ``rl.data.EpisodeSet`` with states: the demonstrations)
    as :func:`keyframe_env_starts` draws them, for :func:`keyframe_horizon` actions, executing
    ``rl.imagined_actions_per_decision`` actions per decision as the learned simulator does, and each step
    counts its trajectories and their successes by their keyframe's step
    (:func:`~sword_jax.rl.imagined_check.outcomes_by_start`, as :func:`run_in_mjx` does);
    evaluations still start at rest and execute ``rl.env.execute_steps``. ``rl.env.starts=rest`` starts them at
    training-split states at rest, as ``initial`` does, in that same setting (:func:`cut_at_horizon`).
    ``max_traces``: traces of the jitted update before the retrace guard fails.

    Returns ``{"curve": evaluation points, "workdir", "history": per-step metrics of the whole run}``.
    """
    if rl.grpo.max_sample_rounds > 1:
        raise ValueError("rl.grpo.max_sample_rounds > 1 (dynamic sampling) runs on rl.env.backend=mjx only")
    update = jax.jit(tracing.max_traces(lambda s, batch, key: grpo.grpo_update(graphdef, rl, s, batch, key),
                                        n=max_traces), donate_argnums=(0,))
    act = make_act_fns(graphdef, rl)
    os.makedirs(workdir, exist_ok=True)
    tasks = list(cfg.sim.tasks)
    pool = {t: sim_tasks.split_init_states(t, "train", sim_tasks.TRAIN_RESERVE, seed=cfg.sim.init_seed) for t in tasks}
    eval_kwargs = dict(lockstep_evaluation(tasks, episodes_per_task, resolution=cfg.sim.resolution,
                                           max_steps=cfg.sim.max_steps, renderer=renderer, workers=workers), act=act)
    mode = rl.env.proprio
    if mode == "reckoned" and reckoning is None:
        raise ValueError("rl.env.proprio=reckoned needs the action convention (train.grpo: --demos to fit it)")

    def evaluate(step, params):
        result = dict(evaluate_in_sim(graphdef, params, rl, **eval_kwargs), where="mujoco")
        extra = {}
        if mode != "true":
            extra = {"train_mode": mode_point(graphdef, params, rl, step, mode, reckoning, **eval_kwargs)}
        if rl.grpo.eval_sampled:
            extra["sampled"] = sampled_point(graphdef, params, rl, step, jax.random.key(cfg.seed), **eval_kwargs)
        log(f"eval step {step}: success {result['mean']:.3f} [{result['ci95'][0]:.3f}, {result['ci95'][1]:.3f}] "
            f"({result['episodes']} episodes, {result['seconds']}s)")
        return result, extra

    horizon, rollout_rl = training_horizon(rl, cfg.sim.max_steps), rl
    if rl.env.starts == "keyframes":
        check_keyframe_episodes(keyframes)  # now, not after the first evaluation
    if cut_at_horizon(rl):  # the learned simulator's setting: its horizon and execution
        rollout_rl = dataclasses.replace(rl, env=dataclasses.replace(
            rl.env, execute_steps=rl.imagined_actions_per_decision))

    def starts_at(step):  # a function of (seed, step), so a resumed run draws the same ones
        # (the start states, one per trajectory; from keyframes also each one's step in its demonstration)
        if rl.env.starts == "keyframes":
            return keyframe_env_draw(keyframes, rl, seed=cfg.seed, step=step)
        # stratified over the tasks, as the MJX backend draws them (sim.mjx_batch.stratified_train_starts)
        picked = stratified_train_starts(tasks, rl.grpo.rollout_batch, stream_rng(cfg.seed, "grpo/env_starts", step),
                                         pool=pool)
        return [start for start in picked for _ in range(rl.grpo.group_size)], None

    envs = []  # worker processes live for the whole run; each step re-targets them

    def step_in_env(state, batch, rollout_key):
        # not one jitted function: the episodes run in the C engine, then the jitted update trains on them
        starts, start_steps = batch
        if not envs:
            envs.append(LockstepEnvs(starts, resolution=cfg.sim.resolution, max_steps=horizon,
                                     renderer=renderer, workers=workers))
        step_key = jax.random.fold_in(rollout_key, state.step)
        rollout = run_policy(act, state.params, envs[0], rollout_rl, key=step_key,
                             greedy=False, max_steps=horizon, episodes=starts, proprio=mode,
                             reckoning=reckoning)
        state, metrics = update(state, jax.tree.map(jnp.asarray, rollout), jax.random.fold_in(step_key, UPDATE_KEY_SALT))
        # from keyframes, the trajectories and their successes by where their starts stood, as on MJX
        counted = ({} if start_steps is None else
                   outcomes_by_start(jnp.asarray(start_steps), None, jnp.asarray(rollout.success, bool)))
        return state, dict(metrics, rollout_success=jnp.mean(jnp.asarray(rollout.success, jnp.float32)), **counted)

    def progress(point, eta):
        return (f"grpo step {point['step']}/{rl.grpo.steps} rollout success {point['rollout_success']:.3f} "
                f"loss {point['loss']:.4f} clip {point['clip_fraction']:.3f} kept {point['kept_fraction']:.2f} "
                f"nll {point['behaviour_nll']:.3f} {skipped_note(point)}eta {eta:.0f}s")

    run_id = grpo_run_id(rl, seed=cfg.seed, simulator="env", **{
        "sim.tasks": tasks, "sim.init_seed": cfg.sim.init_seed, "sim.max_steps": cfg.sim.max_steps,
        "sim.resolution": cfg.sim.resolution, "keyframe_episodes": 0 if keyframes is None else keyframes.num_episodes})
    try:
        result, curve = train_grpo(step_in_env, grpo.init_state(params, rl), starts_at,
                                   key=stream_key(jax.random.key(cfg.seed), "grpo/env_rollouts"), rl=rl,
                                   workdir=workdir, evaluate=evaluate, run_id=run_id, progress=progress,
                                   curve_label="GRPO in the ground-truth MuJoCo environments", log=log)
    finally:
        for env in envs:
            env.close()
    return {"curve": curve, "workdir": workdir, "history": result.history}


def run_in_mjx(cfg, rl, graphdef, params, workdir: str, *, episodes_per_task: int, keyframes=None) -> dict:
    """GRPO against the ground-truth environments on MJX (``rl.env.backend=mjx``), rollouts and
    evaluations on the accelerator (:mod:`sword_jax.rl.jax_env_grpo`); resumes from ``workdir``.

    Each sampling round's ``rl.grpo.rollout_batch`` start states are training-split initial states
    stratified over the tasks (:func:`sim.mjx_batch.stratified_train_starts`, a function of (seed, step,
    round)); evaluations run the tasks' fixed evaluation states, the greedy (deployed) and the sampled policy
    each time, with the probe's argmax flips and top-1 margin. Returns as :func:`run_in_env`.

    The learned simulator's setting, one part at a time: ``rl.env.starts=keyframes`` starts the rollouts
    at ``keyframes``' recorded states (the demonstrations, :func:`keyframe_picks`) for
    :func:`keyframe_horizon` actions, executing ``rl.imagined_actions_per_decision`` per decision, and each step
    counts its trajectories and their successes by their keyframe's step (:func:`keyframe_steps`);
    ``rl.env.proprio=missing`` has the policy read its "missing proprio" input in the rollouts, and each
    evaluation then also runs the sampled policy that way (``sampled_proprio_masked``). Evaluations
    always start at rest with ``rl.env.execute_steps``; where the training rollouts execute another number of
    actions per decision, each evaluation also runs the sampled policy executed and reading proprio as they do
    (``sampled_as_trained``, :meth:`~sword_jax.rl.jax_env_grpo.EnvGRPO.evaluate`).

    With ``rl.value.episodes > 0`` a value fitted to that many real episodes of the starting policy
    (:func:`~sword_jax.rl.jax_env_grpo.start_value`, saved under ``workdir/value``; the episodes start at rest
    from training-split states, whatever ``rl.env.starts`` says) pays the training rollouts that reach their
    horizon without an outcome (unless ``rl.value.bootstrap=false``); the result then has its record as ``value``.
    ``rl.env.starts=branch`` starts the training rollouts at those episodes' decisions (every phase);
    ``rest`` at training-split states at rest as ``initial`` does, cut at the horizon (:func:`cut_at_horizon`).
    """
    if rl.env.proprio not in ("true", "missing"):
        raise ValueError(f"rl.env.backend=mjx reads proprio true or missing; got rl.env.proprio={rl.env.proprio} "
                         "(the C engine's rl.env.backend=cpu reckons it)")
    if rl.env.starts == "keyframes":
        check_keyframe_episodes(keyframes)
    tasks = list(cfg.sim.tasks)
    pool = {t: sim_tasks.split_init_states(t, "train", sim_tasks.TRAIN_RESERVE, seed=cfg.sim.init_seed) for t in tasks}
    env = MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution)
    eval_episodes = sim_tasks.evaluation_episodes(tasks, episodes_per_task)
    eval_qpos, eval_text = episode_starts(eval_episodes)
    max_bytes = rl.policy.max_instruction_bytes

    def value_starts(round_):  # the value's episodes: training-split states at rest, a function of (seed, round)
        picked = stratified_train_starts(tasks, rl.grpo.rollout_batch,
                                         stream_rng(cfg.seed, "grpo/value_starts", round_), pool=pool)
        qpos, text = episode_starts(picked)
        return qpos, tokenize_instructions(text, max_bytes)

    def listed_starts(step, round_):  # a function of (seed, step, round), so a resumed run draws the same ones
        if rl.env.starts == "keyframes":
            picked = [(t, np.asarray(flat, np.float32)) for t, flat in
                      keyframe_picks(keyframes, rl, seed=cfg.seed, step=step, round_=round_)]
        else:
            picked = stratified_train_starts(tasks, rl.grpo.rollout_batch,
                                             stream_rng(cfg.seed, "grpo/mjx_starts", step, round_), pool=pool)
        qpos, text = episode_starts(picked)
        return qpos, tokenize_instructions(text, max_bytes)

    decisions = []  # with rl.env.starts=branch: the value episodes' decisions, once start_value has them

    def starts_at(step, round_):
        if rl.env.starts == "branch":
            return branch_starts(decisions[0], rl.grpo.rollout_batch,
                                 stream_rng(cfg.seed, "grpo/mjx_branch", step, round_), rl.value.branch_starts)
        return listed_starts(step, round_)

    setting = {}
    if cut_at_horizon(rl):
        setting = dict(train_max_steps=training_horizon(rl, cfg.sim.max_steps),
                       train_execute_steps=rl.imagined_actions_per_decision)
    masked = rl.env.proprio == "missing"
    root = jax.random.key(cfg.seed)
    value_net = build_value(rl, seed=cfg.seed) if rl.value.episodes else None
    pays_value = value_net is not None and rl.value.bootstrap
    runner = EnvGRPO(graphdef, rl, env, max_steps=cfg.sim.max_steps, starts_at=starts_at, eval_starts=eval_qpos,
                     eval_tokens=tokenize_instructions(eval_text, max_bytes),
                     eval_tasks=[t for t, _ in eval_episodes], key=stream_key(root, "grpo/mjx_eval"), log=log,
                     train_proprio=not masked, value=as_value(*value_net) if pays_value else None,
                     start_steps_at=((lambda step, round_: keyframe_steps(keyframes, rl, seed=cfg.seed, step=step,
                                                                         round_=round_))
                                     if rl.env.starts == "keyframes" else None), **setting)
    os.makedirs(workdir, exist_ok=True)
    value_record = None
    if value_net is not None:  # fitted once, before the first step; a resumed run loads the fit
        value_record, recorded = start_value(runner, params, os.path.join(workdir, "value"), seed=cfg.seed,
                                             max_steps=cfg.sim.max_steps, starts_at=value_starts, log=log)
        decisions.append(recorded)
    runner.start_probe(params, os.path.join(workdir, "probe"))

    def evaluate(step, params):
        point, extra = runner.evaluate(params, step=step, sampled=True, masked=masked, as_trained=True)
        sampled = extra.get("sampled")
        trained = extra.get("sampled_proprio_masked")
        executed = extra.get("sampled_as_trained")
        log(f"eval step {step}: success {point['mean']:.3f} [{point['ci95'][0]:.3f}, {point['ci95'][1]:.3f}] "
            f"({point['episodes']} episodes on MJX, {point['seconds']}s)"
            + (f"; sampled T={rl.grpo.temperature:g} {sampled['mean']:.3f}" if sampled else "")
            + (f"; sampled, proprio masked {trained['mean']:.3f}" if trained else "")
            + (f"; sampled as trained ({executed['execute_steps']} actions per decision) {executed['mean']:.3f}"
               if executed else "")
            + f"; probe flips vs start {extra['probe']['flip_rate_vs_start']:.3f}, top-1 margin "
              f"{extra['probe']['top1_margin']:.3f}")
        return point, extra

    def progress(point, eta):
        paid = (f"value paid {point['terminal_value']:.3f} to {point['truncated_fraction']:.2f} "
                if "terminal_value" in point else "")
        return (f"grpo step {point['step']}/{rl.grpo.steps} rollout success {point['rollout_success']:.3f} {paid}"
                f"mixed {point['mixed_fraction']:.2f} rounds {point['sample_rounds']:.0f} loss {point['loss']:.4f} "
                f"clip {point['clip_fraction']:.3f} ratio {point['ratio_mean']:.3f} kept {point['kept_fraction']:.2f} "
                f"nll {point['behaviour_nll']:.3f} {point['step_seconds']:.1f}s/step "
                f"(rollout {point['rollout_seconds']:.1f}s) {skipped_note(point)}eta {eta:.0f}s")

    run_id = grpo_run_id(rl, seed=cfg.seed, simulator="env", **{
        "sim.tasks": tasks, "sim.init_seed": cfg.sim.init_seed, "sim.max_steps": cfg.sim.max_steps,
        "sim.resolution": cfg.sim.resolution},
        **({"keyframe_episodes": keyframes.num_episodes} if rl.env.starts == "keyframes" else {}))
    result, curve = train_grpo(runner.step, grpo.init_state(params, rl), lambda step: step,
                               key=stream_key(root, "grpo/mjx_rollouts"), rl=rl, workdir=workdir, evaluate=evaluate,
                               run_id=run_id, progress=progress, curve_label="GRPO in the ground-truth MJX environments",
                               log=log)
    return {"curve": curve, "workdir": workdir, "history": result.history,
            **({"value": value_record} if value_record is not None else {})}
