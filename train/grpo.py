"""GRPO post-training of the VLA policy inside the learned simulator, evaluated in MuJoCo.

    # the real thing: world model + VAE + SFT policy + reward model, keyframes from demos
    python -m train.grpo --config sword:small --simulator world_model --demos demos.hdf5 \
        --world-model runs/sword-small --vae runs/sword-small/vae --policy runs/sword-small/rl/policy_sft \
        --reward runs/sword-small/rl/reward_model [--rl.grpo.steps=200 --rl.grpo.eval_every=20]
    # the ground truth: GRPO in the MuJoCo environments themselves (reward = true success)
    python -m train.grpo --config sword:small --simulator env --policy runs/sword-small/rl/policy_sft \
        [--env-workers 14] [--rl.grpo.steps=100]
    # smoke run: the analytic toy simulator (no checkpoints needed)
    python -m train.grpo --config sword:tiny --simulator toy --rl.grpo.steps=4

Each step samples ``rl.grpo.rollout_batch`` keyframe start states, G = ``rl.grpo.group_size`` imagined
trajectories each, and applies the GRPO update (one jitted, donated step). With ``--simulator env``
the start states are training-split initial states (never the 50 evaluation states), the
trajectories run in MuJoCo's C engine (``sim.lockstep``), and the same ``grpo_update`` trains on
them: this validates the update independently of any world model. Every ``rl.grpo.eval_every``
steps (and at step 0) the policy is evaluated in the ground-truth MuJoCo envs (world_model mode)
or by greedy imagined rollouts (toy mode); the curve goes to ``<workdir>/success_curve.{json,png}``.
The GRPO state is checkpointed at each evaluation and the run resumes from it exactly (killed and
rerun = bit-identical, curve included; :mod:`sword_jax.rl.grpo_loop`); a work dir holding another run's
checkpoint is refused, naming the config keys that differ. A non-finite loss stops the run.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import sys
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

import configs
from train.distributed import ENTRY_MAX_TRACES
from sword_jax import sharding as shd
from sword_jax import tracing
from sword_jax.rl import data as rl_data
from sword_jax.rl import grpo, sim_agreement
from sword_jax.rl.env_rollout import make_act_fns
from sword_jax.rl.grpo_loop import grpo_run_id, train_grpo
from sword_jax.rl.learned_simulator import StartState, toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.params_io import load_params
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.policy_success import evaluate_in_sim
from sword_jax.rl.reward_model import as_reward_model, build_detector
from sword_jax.rl.rollout import expand_groups, imagined_rollout
from sword_jax.rng import stream_key, stream_rng

log = functools.partial(print, flush=True)
SIMULATORS = ("world_model", "env", "toy")


def _toy_setup(cfg, rl):
    size = rl.image_size
    sim, reward_model = toy_simulator(frame_size=size, chunk_len=rl.chunk_len, proprio_dim=rl.proprio_dim), toy_reward_model()
    texts = [f"reach the goal of task {t}" for t in range(max(len(cfg.sim.tasks), 2))]
    tokens = jnp.asarray(tokenize_instructions(texts, rl.policy.max_instruction_bytes))

    def starts(key, step):
        del step  # the key is already a function of the step
        pick = jax.random.randint(key, (rl.grpo.rollout_batch,), 0, tokens.shape[0])
        return toy_start_states(tokens[pick], key=key, frame_size=size, proprio_dim=rl.proprio_dim)

    eval_key = stream_key(jax.random.key(cfg.seed), "grpo/toy_eval_starts")
    eval_start = expand_groups(toy_start_states(jnp.tile(tokens, (4, 1)), key=eval_key, frame_size=size,
                                                proprio_dim=rl.proprio_dim), 2)
    return sim, reward_model, starts, eval_start, None


def sim_reckoning(episodes):
    """The simulator controller's action convention as a proprio ReckoningConfig, with the realised
    fraction of each commanded axis fitted to ``episodes`` (an ``rl.data.EpisodeSet``)."""
    from sim import controller, panda
    from sword_jax.rl.proprio_reckoning import ReckoningConfig, fit_gains

    ctl = controller.ControllerConfig()
    base = ReckoningConfig(pos_scale=ctl.pos_scale, rot_scale=ctl.rot_scale, finger_open=panda.FINGER_OPEN,
                           finger_closed_target=panda.FINGER_CLOSED_TARGET)
    cfg = fit_gains(episodes.proprio, episodes.actions, base, lengths=episodes.lengths)
    print(f"grpo: imagined proprio reckoned from actions, gains pos {[round(g, 3) for g in cfg.pos_gain]} "
          f"rot {[round(g, 3) for g in cfg.rot_gain]} (fitted to {len(episodes.lengths)} demonstrations)")
    return cfg


def _world_model_setup(cfg, rl, inputs: "GRPOInputs"):
    from sim.dataset import read_dataset
    from sword_jax.load import experiment_vae, experiment_world_model
    from sword_jax.rl.world_model_sim import encode_history, world_model_simulator

    episodes = rl_data.load_episodes(inputs.demos, read=read_dataset)
    if rl.imagined.proprio == "reckoned" and rl.proprio_dim != 8:
        raise ValueError(f"rl.imagined.proprio=reckoned integrates the simulator's 8-D proprio; got rl.proprio_dim="
                         f"{rl.proprio_dim} (use --rl.imagined.proprio=missing)")
    reckoning = sim_reckoning(episodes) if rl.imagined.proprio == "reckoned" else None
    wm_graphdef, wm_state = experiment_world_model(cfg, inputs.world_model)
    vae_graphdef, vae_state = experiment_vae(cfg, inputs.vae)
    # the world model's geometry is the config's (ExperimentConfig.validate checks rl against it)
    tf = cfg.vae.temporal_factor  # frames per latent
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, flow_cfg=cfg.flow,
                                frame_size=cfg.data.image_size, sample_steps=cfg.flow.sample_steps,
                                num_context=cfg.data.context_frames // tf, num_future=cfg.data.predict_frames // tf,
                                action_dim=cfg.model.action_dim, proprio_dim=rl.proprio_dim,
                                execute_latents=(rl.imagined.execute_steps or rl.chunk_len) // tf,
                                proprio_reckoning=reckoning)
    det_graphdef, det_params = build_detector(rl, seed=cfg.seed)
    det_params, _ = load_params(inputs.reward, det_params, kind="reward_model")
    reward_model = as_reward_model(det_graphdef, det_params)
    if rl.imagined.eval_replay_episodes and cfg.sim.resolution != cfg.data.image_size:
        raise ValueError(f"rl.imagined.eval_replay_episodes replays real episodes rendered at sim.resolution="
                         f"{cfg.sim.resolution} in a world model of data.image_size={cfg.data.image_size}; make them "
                         "equal or pass --rl.imagined.eval_replay_episodes=0")

    def encode(first_frames, history):  # the real history before a start frame -> the world model's latents
        return encode_history(vae_graphdef, vae_state, first_frames, history, num_context=cfg.data.context_frames // tf)

    def starts(key, step):
        del key  # keyframes: a host rng that is a function of (seed, step), so a resumed run draws the same
        pick = rl_data.keyframe_starts(episodes, rl.grpo.rollout_batch, stream_rng(cfg.seed, "grpo/keyframes", step),
                                       max_fraction=rl.imagined.keyframe_fraction)
        unit = lambda x: jnp.asarray(x, jnp.float32) / jnp.float32(255.0)  # noqa: E731
        latents = encode(unit(pick["first_frame"]), unit(pick["history"]))
        return StartState(unit(pick["frame"]), jnp.asarray(pick["proprio"][:, : rl.proprio_dim]),
                          jnp.asarray(tokenize_instructions(pick["instructions"], rl.policy.max_instruction_bytes)),
                          (latents, jnp.asarray(pick["actions"], jnp.float32)))

    return sim, reward_model, starts, None, encode


def _extra_point(step: int, what: str, result: dict, **tags) -> dict:
    """An evaluation stored beside the greedy true-proprio success: logged, and its rates kept with ``tags``."""
    print(f"eval step {step}, {what}: success {result['mean']:.3f} "
          f"[{result['ci95'][0]:.3f}, {result['ci95'][1]:.3f}]", flush=True)
    return dict(**tags, **{k: result[k] for k in ("mean", "ci95", "per_task", "episodes", "successes")})


def _mode_point(graphdef, params, rl, step: int, proprio: str, reckoning=None, **eval_kwargs) -> dict:
    """The real-environment evaluation with the policy reading proprio as ``proprio`` (an input mode of
    the learned simulator), as the extra point stored beside the true-proprio success."""
    other = evaluate_in_sim(graphdef, params, rl, proprio=proprio, reckoning=reckoning, **eval_kwargs)
    return _extra_point(step, f"proprio {proprio}", other, proprio=proprio)


def _sampled_point(graphdef, params, rl, step: int, root, **eval_kwargs) -> dict:
    """The real-environment evaluation of the sampled policy (``rl.grpo.eval_sampled``: at
    ``rl.grpo.temperature``, the policy GRPO trains), stored as ``sampled`` beside the greedy success;
    its sampling key is a function of (root, step)."""
    key = jax.random.fold_in(stream_key(root, "grpo/eval_sampled"), step)
    other = evaluate_in_sim(graphdef, params, rl, greedy=False, key=key, **eval_kwargs)
    return _extra_point(step, f"sampled at temperature {rl.grpo.temperature:g}", other,
                        temperature=rl.grpo.temperature)


def keyframe_horizon(rl) -> int:
    """Actions an imagined rollout executes at most: ``max_chunks`` decisions of the simulator's execution."""
    return rl.imagined.max_chunks * (rl.imagined.execute_steps or rl.chunk_len)


def check_keyframe_episodes(episodes) -> None:
    """Refuses demonstrations that ``rl.env.starts=keyframes`` cannot continue (no recorded states or task ids)."""
    if episodes.states is None or episodes.tasks is None:
        raise ValueError("rl.env.starts=keyframes continues demonstrations from their recorded states; these "
                         "episodes have no states or task ids (LIBERO-layout HDF5 from train.gen_data has both)")


def keyframe_env_starts(episodes, rl, *, seed: int, step: int, num_context: int = 1) -> list:
    """GRPO step ``step``'s ground-truth start states with ``rl.env.starts=keyframes``: ``(task, flat state)``
    of the demonstrations at the keyframes GRPO in the learned simulator draws (the same sampler; a
    function of (seed, step)), each repeated ``group_size`` times."""
    check_keyframe_episodes(episodes)
    pick = rl_data.keyframe_starts(episodes, rl.grpo.rollout_batch, stream_rng(seed, "grpo/env_keyframes", step),
                                   max_fraction=rl.imagined.keyframe_fraction, num_context=num_context)
    return [(int(episodes.tasks[e]), episodes.states[e, t]) for e, t in zip(pick["episode"], pick["t"])
            for _ in range(rl.grpo.group_size)]


def run_in_env(cfg, rl, graphdef, params, workdir: str, *, episodes_per_task: int, workers: int = 0,
               renderer: str = "jax", reckoning=None, keyframes=None) -> dict:
    """GRPO against the ground-truth environments (see the module docstring); resumes from ``workdir``.

    The policy reads proprio as ``rl.env.proprio`` says (``reckoning``: the action convention for
    ``reckoned``, e.g. :func:`sim_reckoning`); unless it is ``true``, each evaluation also measures
    that mode, stored as ``train_mode`` beside the true-proprio success. With ``rl.env.starts=keyframes``
    the rollouts start from ``keyframes`` (an ``rl.data.EpisodeSet`` with states: the demonstrations)
    as :func:`keyframe_env_starts` draws them, for :func:`keyframe_horizon` actions, executing
    ``rl.imagined.execute_steps or chunk_len`` actions per decision as the learned simulator does;
    evaluations still start at rest and execute ``rl.env.execute_steps``.

    Returns ``{"curve": evaluation points, "workdir", "history": per-step metrics of the whole run}``.
    """
    from sim import tasks as sim_tasks
    from sim.lockstep import LockstepEnvs, lockstep_evaluation
    from sim.mjx_batch import stratified_train_starts
    from sword_jax.rl.env_rollout import run_policy
    from sword_jax.rl.grpo import UPDATE_KEY_SALT

    if rl.grpo.max_sample_rounds > 1:
        raise ValueError("rl.grpo.max_sample_rounds > 1 (dynamic sampling) runs on rl.env.backend=mjx only")
    update = jax.jit(tracing.max_traces(lambda s, batch, key: grpo.grpo_update(graphdef, rl, s, batch, key),
                                        n=ENTRY_MAX_TRACES), donate_argnums=(0,))
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
            extra = {"train_mode": _mode_point(graphdef, params, rl, step, mode, reckoning, **eval_kwargs)}
        if rl.grpo.eval_sampled:
            extra["sampled"] = _sampled_point(graphdef, params, rl, step, jax.random.key(cfg.seed), **eval_kwargs)
        log(f"eval step {step}: success {result['mean']:.3f} [{result['ci95'][0]:.3f}, {result['ci95'][1]:.3f}] "
            f"({result['episodes']} episodes, {result['seconds']}s)")
        return result, extra

    horizon, rollout_rl = cfg.sim.max_steps, rl
    if rl.env.starts == "keyframes":  # the learned simulator's setting: its starts, horizon and execution
        if keyframes is None:
            raise ValueError("rl.env.starts=keyframes needs the demonstrations (train.grpo: --demos)")
        horizon = keyframe_horizon(rl)
        rollout_rl = dataclasses.replace(rl, env=dataclasses.replace(
            rl.env, execute_steps=rl.imagined.execute_steps or rl.chunk_len))
        check_keyframe_episodes(keyframes)  # now, not after the first evaluation

    def starts_at(step):  # a function of (seed, step), so a resumed run draws the same ones
        if rl.env.starts == "keyframes":
            return keyframe_env_starts(keyframes, rl, seed=cfg.seed, step=step)
        # stratified over the tasks, as the MJX backend draws them (sim.mjx_batch.stratified_train_starts)
        picked = stratified_train_starts(tasks, rl.grpo.rollout_batch, stream_rng(cfg.seed, "grpo/env_starts", step),
                                         pool=pool)
        return [start for start in picked for _ in range(rl.grpo.group_size)]

    envs = []  # worker processes live for the whole run; each step re-targets them

    def step_in_env(state, starts, rollout_key):
        # not one jitted function: the episodes run in the C engine, then the jitted update trains on them
        if not envs:
            envs.append(LockstepEnvs(starts, resolution=cfg.sim.resolution, max_steps=horizon,
                                     renderer=renderer, workers=workers))
        step_key = jax.random.fold_in(rollout_key, state.step)
        rollout = run_policy(act, state.params, envs[0], rollout_rl, key=step_key,
                             greedy=False, max_steps=horizon, episodes=starts, proprio=mode,
                             reckoning=reckoning)
        state, metrics = update(state, jax.tree.map(jnp.asarray, rollout), jax.random.fold_in(step_key, UPDATE_KEY_SALT))
        return state, dict(metrics, rollout_success=jnp.mean(jnp.asarray(rollout.success, jnp.float32)))

    def progress(point, eta):
        return (f"grpo step {point['step']}/{rl.grpo.steps} rollout success {point['rollout_success']:.3f} "
                f"loss {point['loss']:.4f} clip {point['clip_fraction']:.3f} kept {point['kept_fraction']:.2f} "
                f"nll {point['behaviour_nll']:.3f} eta {eta:.0f}s")

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
    save_history(workdir, result.history)
    return {"curve": curve, "workdir": workdir, "history": result.history}


def run_in_mjx(cfg, rl, graphdef, params, workdir: str, *, episodes_per_task: int) -> dict:
    """GRPO against the ground-truth environments on MJX (``rl.env.backend=mjx``), rollouts and
    evaluations on the accelerator (:mod:`sword_jax.rl.jax_env_grpo`); resumes from ``workdir``.

    Each sampling round's ``rl.grpo.rollout_batch`` start states are training-split initial states
    stratified over the tasks (:func:`sim.mjx_batch.stratified_train_starts`, a function of (seed, step,
    round)); evaluations run the tasks' fixed evaluation states, the greedy (deployed) and the sampled policy
    each time, with the probe's argmax flips and top-1 margin. Returns as :func:`run_in_env`.
    """
    from sim import tasks as sim_tasks
    from sim.mjx_batch import MjxEpisodes, episode_starts, stratified_train_starts
    from sword_jax.rl.jax_env_grpo import EnvGRPO

    if rl.env.starts != "initial" or rl.env.proprio != "true":
        raise ValueError(f"rl.env.backend=mjx runs GRPO from initial states with true proprio; got rl.env.starts="
                         f"{rl.env.starts}, rl.env.proprio={rl.env.proprio}")
    tasks = list(cfg.sim.tasks)
    pool = {t: sim_tasks.split_init_states(t, "train", sim_tasks.TRAIN_RESERVE, seed=cfg.sim.init_seed) for t in tasks}
    env = MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution)
    eval_episodes = sim_tasks.evaluation_episodes(tasks, episodes_per_task)
    eval_qpos, eval_text = episode_starts(eval_episodes)
    max_bytes = rl.policy.max_instruction_bytes

    def starts_at(step, round_):  # a function of (seed, step, round), so a resumed run draws the same ones
        picked = stratified_train_starts(tasks, rl.grpo.rollout_batch, stream_rng(cfg.seed, "grpo/mjx_starts", step,
                                                                                  round_), pool=pool)
        qpos, text = episode_starts(picked)
        return qpos, tokenize_instructions(text, max_bytes)

    root = jax.random.key(cfg.seed)
    runner = EnvGRPO(graphdef, rl, env, max_steps=cfg.sim.max_steps, starts_at=starts_at, eval_starts=eval_qpos,
                     eval_tokens=tokenize_instructions(eval_text, max_bytes),
                     eval_tasks=[t for t, _ in eval_episodes], key=stream_key(root, "grpo/mjx_eval"), log=log)
    os.makedirs(workdir, exist_ok=True)
    runner.start_probe(params, os.path.join(workdir, "probe"))

    def evaluate(step, params):
        point, extra = runner.evaluate(params, step=step, sampled=True)  # greedy and sampled, every time
        sampled = extra.get("sampled")
        log(f"eval step {step}: success {point['mean']:.3f} [{point['ci95'][0]:.3f}, {point['ci95'][1]:.3f}] "
            f"({point['episodes']} episodes on MJX, {point['seconds']}s)"
            + (f"; sampled T={rl.grpo.temperature:g} {sampled['mean']:.3f}" if sampled else "")
            + f"; probe flips vs start {extra['probe']['flip_rate_vs_start']:.3f}, top-1 margin "
              f"{extra['probe']['top1_margin']:.3f}")
        return point, extra

    def progress(point, eta):
        return (f"grpo step {point['step']}/{rl.grpo.steps} rollout success {point['rollout_success']:.3f} "
                f"mixed {point['mixed_fraction']:.2f} rounds {point['sample_rounds']:.0f} loss {point['loss']:.4f} "
                f"clip {point['clip_fraction']:.3f} ratio {point['ratio_mean']:.3f} kept {point['kept_fraction']:.2f} "
                f"nll {point['behaviour_nll']:.3f} {point['step_seconds']:.1f}s/step "
                f"(rollout {point['rollout_seconds']:.1f}s) eta {eta:.0f}s")

    run_id = grpo_run_id(rl, seed=cfg.seed, simulator="env", **{
        "sim.tasks": tasks, "sim.init_seed": cfg.sim.init_seed, "sim.max_steps": cfg.sim.max_steps,
        "sim.resolution": cfg.sim.resolution})
    result, curve = train_grpo(runner.step, grpo.init_state(params, rl), lambda step: step,
                               key=stream_key(root, "grpo/mjx_rollouts"), rl=rl, workdir=workdir, evaluate=evaluate,
                               run_id=run_id, progress=progress, curve_label="GRPO in the ground-truth MJX environments",
                               log=log)
    save_history(workdir, result.history)
    return {"curve": curve, "workdir": workdir, "history": result.history}


def save_history(workdir: str, history: Sequence[dict]) -> None:
    """``<workdir>/train_history.jsonl``: the whole run's per-step metrics, restored steps included."""
    with open(os.path.join(workdir, "train_history.jsonl"), "w") as f:
        for point in history:
            f.write(json.dumps(point) + "\n")


def training_success(history: Sequence[dict], window: int = 10) -> dict:
    """The success of GRPO's own training rollouts (imagined in a world model, real in the env) over its
    first and last ``window`` steps: ``{"metric", "first", "last", "steps"}``, ``{}`` without any."""
    metric = next((k for k in ("success_rate", "rollout_success") if history and k in history[0]), None)
    if metric is None:
        return {}
    values = [float(p[metric]) for p in history if metric in p]
    return {"metric": metric, "first": sum(values[:window]) / len(values[:window]),
            "last": sum(values[-window:]) / len(values[-window:]), "steps": len(values), "window": window}


class _Replayer:
    """Replays traced real evaluation episodes in the learned simulator (``rl.imagined.eval_replay_episodes``;
    :mod:`sword_jax.rl.sim_agreement`), with one compile for the run."""

    def __init__(self, cfg, rl, sim, reward_model, encode, root):
        self.cfg, self.rl, self.sim, self.reward_model, self.encode = cfg, rl, sim, reward_model, encode
        self.key = stream_key(root, "grpo/replay")
        self.tf = cfg.vae.temporal_factor
        self.k = cfg.data.context_frames // self.tf
        self.fn = jax.jit(lambda s, r, st, a, n, key: sim_agreement.replay_actions(
            s, r, st, a, n, success_threshold=rl.success_threshold, key=key,
            settle_steps=rl.imagined.eval_replay_settle_steps, success_frames=rl.imagined.success_frames))

    def trace(self) -> sim_agreement.EpisodeTrace:
        return sim_agreement.EpisodeTrace(self.tf * self.k)

    def report(self, step: int, trace: sim_agreement.EpisodeTrace) -> dict:
        rl, traced = self.rl, trace.result()
        picked = sim_agreement.spread(len(traced.lengths), rl.imagined.eval_replay_episodes)
        traced = sim_agreement.select(traced, picked)
        out = sim_agreement.replay_report(
            traced, self.sim, self.reward_model, self.encode, success_threshold=rl.success_threshold,
            key=jax.random.fold_in(self.key, step), batch=rl.grpo.rollout_batch * rl.grpo.group_size,
            num_context=self.k, frames_per_latent=self.tf, proprio_dim=rl.proprio_dim,
            max_instruction_bytes=rl.policy.max_instruction_bytes, max_steps=self.cfg.sim.max_steps,
            settle_steps=rl.imagined.eval_replay_settle_steps, replay_fn=self.fn)

        def rate(name):
            r = out[name]
            if r["rate"] is None:
                return "n/a"
            return f"{r['rate']:.3f} [{r['ci95'][0]:.3f}, {r['ci95'][1]:.3f}] of {r['of']}"

        if out["episodes"]:
            log(f"eval step {step}, {out['episodes']} real episodes replayed in the learned simulator: imagined "
                f"success {out['imagined_success']:.3f} vs real {out['real_success']:.3f}; false success "
                f"{rate('false_success')}; missed success {rate('missed_success')}; another noise draw ends "
                f"differently {rate('resample_disagreement')}")
            sweep = out["sustained_success_sweep"]

            def short(r):
                return "n/a" if r["rate"] is None else f"{r['rate']:.3f}"

            log(f"eval step {step}, replay false / missed success if success needed k consecutive frames: " + ", ".join(
                f"k={k}: {short(v['false_success'])} / {short(v['missed_success'])}" for k, v in sweep.items()))
            log(f"eval step {step}, replay imagined success by action h, real successes / real failures: " + ", ".join(
                f"h={h}: {short(v['real_success'])} / {short(v['real_failure'])}"
                for h, v in out["imagined_success_by_horizon"].items()))
        return out


@dataclasses.dataclass(frozen=True)
class GRPOInputs:
    """The checkpoints and demonstrations GRPO starts from (``--simulator world_model`` needs
    ``world_model``, ``reward`` and ``demos``; ``env`` reads ``demos`` only to fit the proprio reckoning
    or, with ``rl.env.starts=keyframes``, to start from their recorded states)."""

    demos: tuple[str, ...] = ()  # LIBERO-layout HDF5 whose frames are the start keyframes
    world_model: str = ""  # train_world_model work dir
    vae: str = ""  # VAE checkpoint directory (train_vae)
    policy: str = ""  # SFT policy checkpoint (train_policy); empty: from scratch
    reward: str = ""  # reward model checkpoint (train_reward)


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--simulator", choices=SIMULATORS, default="world_model")
    parser.add_argument("--env-workers", type=int, default=0, help="C-engine processes (--simulator env, evaluation)")
    parser.add_argument("--renderer", choices=("jax", "gl"), default="jax",
                        help="frames of the C-engine episodes: the renderer the demonstrations were made with")
    parser.add_argument("--demos", action="append", default=[], help="demos whose frames are the start keyframes")
    parser.add_argument("--world-model", default="", help="world-model workdir (train_world_model)")
    parser.add_argument("--vae", default="", help="VAE checkpoint directory (train_vae)")
    parser.add_argument("--policy", default="", help="SFT policy checkpoint (train_policy); empty = from scratch")
    parser.add_argument("--reward", default="", help="reward model checkpoint (train_reward)")
    parser.add_argument("--eval-episodes", type=int, default=0, help="override rl.grpo.eval_episodes_per_task")
    args = parser.parse_args(rest)
    inputs = GRPOInputs(demos=tuple(args.demos), world_model=args.world_model, vae=args.vae, policy=args.policy,
                        reward=args.reward)
    return run(cfg, inputs, simulator=args.simulator, env_workers=args.env_workers, renderer=args.renderer,
               eval_episodes=args.eval_episodes)


def run(cfg, inputs: GRPOInputs, *, simulator: str = "world_model", env_workers: int = 0, renderer: str = "jax",
        eval_episodes: int = 0) -> dict:
    """GRPO in ``simulator`` (``world_model``, ``env`` or ``toy``), resuming from ``<cfg.workdir>/rl/grpo``.

    ``eval_episodes`` (per task) overrides ``rl.grpo.eval_episodes_per_task``; ``env_workers`` are the C-engine
    processes of the evaluations (and of the episodes with ``simulator="env"``). Returns
    ``{"curve": evaluation points, "workdir", "history": per-step metrics of the whole run}`` (the history
    is also written to ``<workdir>/train_history.jsonl``).
    """
    if simulator not in SIMULATORS:
        raise ValueError(f"train.grpo: simulator {simulator!r} is none of {SIMULATORS}")
    rl = cfg.rl
    if simulator == "toy":
        rl = dataclasses.replace(rl, proprio_dim=max(rl.proprio_dim, 2))
    elif simulator == "env":
        if rl.env.starts == "keyframes" and not inputs.demos:
            raise SystemExit("train.grpo --simulator env --rl.env.starts=keyframes needs --demos (the rollouts start "
                             "from their recorded states)")
    elif not (inputs.world_model and inputs.reward and inputs.demos):
        raise SystemExit("train.grpo --simulator world_model needs --world-model, --reward and --demos (see --help)")
    workdir = os.path.join(cfg.workdir, "rl", "grpo")
    os.makedirs(workdir, exist_ok=True)

    graphdef, params = build_policy(rl, seed=cfg.seed)
    if inputs.policy:
        params, _ = load_params(inputs.policy, params, kind="policy")
    if simulator == "env":
        if rl.env.proprio == "reckoned" and not inputs.demos:
            raise SystemExit("train.grpo --simulator env --rl.env.proprio=reckoned needs --demos (the reckoning's "
                             "gains are fitted to them)")
        reckoning = keyframes = None
        if rl.env.proprio == "reckoned" or rl.env.starts == "keyframes":
            from sim.dataset import read_dataset

            demos = rl_data.load_episodes(inputs.demos, read=read_dataset)
            reckoning = sim_reckoning(demos) if rl.env.proprio == "reckoned" else None
            keyframes = demos if rl.env.starts == "keyframes" else None
        if rl.env.backend == "mjx":
            return run_in_mjx(cfg, rl, graphdef, params, workdir,
                              episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task)
        return run_in_env(cfg, rl, graphdef, params, workdir,
                          episodes_per_task=eval_episodes or rl.grpo.eval_episodes_per_task,
                          workers=env_workers, renderer=renderer, reckoning=reckoning, keyframes=keyframes)
    if simulator == "toy":
        sim, reward_model, starts, eval_start, encode = _toy_setup(cfg, rl)
    else:
        sim, reward_model, starts, eval_start, encode = _world_model_setup(cfg, rl, inputs)

    # The step runs on the config's mesh, where the world model already lives; the policy state and the
    # other weights are placed there once, so the step's inputs and outputs agree and nothing is copied per step.
    mesh = shd.make_mesh(cfg.mesh)
    sim, reward_model = shd.place((sim, reward_model), shd.shardings_on((sim, reward_model), mesh))
    state = jax.device_put(grpo.init_state(params, rl), shd.replicated(mesh))
    step_fn = grpo.make_train_step(graphdef, rl, max_traces=ENTRY_MAX_TRACES, mesh=mesh, rules=cfg.mesh.rules)
    root = jax.random.key(cfg.seed)
    episodes = eval_episodes or rl.grpo.eval_episodes_per_task

    if eval_start is not None:
        greedy = jax.jit(lambda p: imagined_rollout(graphdef, p, sim, reward_model, eval_start, rl,
                                                    key=stream_key(root, "grpo/toy_eval"), greedy=True).success)

    act = make_act_fns(graphdef, rl)  # one compile for every evaluation of the run
    replay = _Replayer(cfg, rl, sim, reward_model, encode, root) if encode and rl.imagined.eval_replay_episodes else None

    def evaluate(step, params):
        extra = {}
        if simulator == "toy":
            success = np.asarray(greedy(params))
            result = {"per_task": {"toy": float(success.mean())}, "mean": float(success.mean()),
                      "episodes": int(success.size), "where": "imagined (toy)"}
        else:
            from sim.lockstep import lockstep_evaluation

            kwargs = dict(lockstep_evaluation(cfg.sim.tasks, episodes, resolution=cfg.sim.resolution,
                                              max_steps=cfg.sim.max_steps, renderer=renderer,
                                              workers=env_workers), act=act)
            trace = replay.trace() if replay else None
            result = evaluate_in_sim(graphdef, params, rl, trace=trace, **kwargs)
            result["where"] = "mujoco"
            if rl.imagined.eval_masked_proprio:
                extra = {"proprio_masked": _mode_point(graphdef, params, rl, step, "missing", **kwargs)}
            if rl.grpo.eval_sampled:
                extra["sampled"] = _sampled_point(graphdef, params, rl, step, root, **kwargs)
            if replay:
                extra["replay"] = replay.report(step, trace)
        log(f"eval step {step}: success {result['mean']:.3f} {json.dumps(result['per_task'])}")
        return result, extra

    # named streams of the root; the start states' is folded with the step (the update folds in state.step itself)
    starts_key = stream_key(root, "grpo/starts")

    def batch_at(step):
        return sim, reward_model, starts(jax.random.fold_in(starts_key, step), step)

    def progress(point, eta):
        return (f"grpo step {point['step']}/{rl.grpo.steps} imagined success {point['success_rate']:.3f} "
                f"return {point['mean_return']:.3f} loss {point['loss']:.4f} clip {point['clip_fraction']:.3f} "
                f"kept {point['kept_fraction']:.2f} nll {point['behaviour_nll']:.3f} eta {eta:.0f}s")

    run_id = grpo_run_id(rl, seed=cfg.seed, simulator=simulator, **{"sim.tasks": cfg.sim.tasks})
    result, curve = train_grpo(step_fn, state, batch_at, key=stream_key(root, "grpo/update"), rl=rl,
                               workdir=workdir, evaluate=evaluate, run_id=run_id, progress=progress, log=log)
    save_history(workdir, result.history)
    return {"curve": curve, "workdir": workdir, "history": result.history}


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
