"""GRPO in the learned simulator refreshed on the policy's real episodes, with MJX as the ground truth
(``train.grpo --simulator world_model --rl.refresh.every=K --rl.env.backend=mjx``).

The real episodes of each refresh start from training-split initial states stratified over the tasks
(never an evaluation state); the evaluations are the ground-truth GRPO's (:class:`~sword_jax.rl.jax_env_grpo.EnvGRPO`:
the greedy, ensembled policy and the sampled one on the tasks' fixed evaluation states, on MJX), so the
curve compares with ground-truth GRPO's point for point; with ``rl.imagined.eval_masked_proprio`` also the
sampled policy reading its "missing proprio" input, the mode GRPO trains inside the world model. The loop is
:func:`sword_jax.pipeline.grpo_refresh.run_refreshed`.
"""

from __future__ import annotations

import os

import jax
import numpy as np

from sim import tasks as sim_tasks
from sim.mjx_batch import MjxEpisodes, episode_starts, stratified_train_starts
from sword_jax.pipeline.grpo import log
from sword_jax.pipeline.grpo_refresh import run_refreshed, stratified_collect_starts
from sword_jax.rl.jax_env_grpo import EnvGRPO
from sword_jax.rl.policy import tokenize_instructions
from sword_jax.rl.reward_model import build_detector
from sword_jax.rl.sim_builder import stored_for_simulator
from sword_jax.rng import stream_key


def imagined_execution(rl) -> dict:
    """:class:`~sword_jax.rl.jax_env_grpo.EnvGRPO`'s training-execution arguments of GRPO in the learned simulator,
    which its evaluations read to also run the sampled policy as that GRPO executes it (``sampled_as_trained``):
    ``rl.imagined_actions_per_decision`` actions per decision, the policy reading its "missing proprio" input. Empty
    with ``rl.imagined.proprio=reckoned``, whose dead-reckoned proprio the MJX evaluation does not compute."""
    if rl.imagined.proprio != "missing":
        return {}
    return {"train_execute_steps": rl.imagined_actions_per_decision, "train_proprio": False}


def mjx_evaluation(cfg, rl, graphdef, params, workdir: str, *, episodes_per_task: int):
    """``(env, evaluate(step, params) -> (point, extra))``: the batched MJX episodes of ``cfg.sim`` and the
    ground-truth GRPO's evaluation on them (:class:`~sword_jax.rl.jax_env_grpo.EnvGRPO`: the greedy, ensembled
    policy and the sampled one on the tasks' fixed evaluation states; with ``rl.imagined.eval_masked_proprio``
    also the sampled policy reading its "missing proprio" input, the mode GRPO trains inside the world model; and
    the sampled policy executed as that GRPO executes it, :func:`imagined_execution`), what a run in the learned
    simulator is judged by on MJX. ``params``: the starting policy, whose greedy episodes fix the probe states
    (``<workdir>/probe``)."""
    tasks = list(cfg.sim.tasks)
    env = MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution)
    eval_episodes = sim_tasks.evaluation_episodes(tasks, episodes_per_task)
    eval_qpos, eval_text = episode_starts(eval_episodes)

    def no_training_starts(step, round_):
        raise RuntimeError("GRPO trains in the learned simulator here; EnvGRPO only evaluates")

    runner = EnvGRPO(graphdef, rl, env, max_steps=cfg.sim.max_steps, starts_at=no_training_starts,
                     eval_starts=eval_qpos, eval_tokens=tokenize_instructions(eval_text, rl.policy.max_instruction_bytes),
                     eval_tasks=[t for t, _ in eval_episodes],
                     key=stream_key(jax.random.key(cfg.seed), "grpo/mjx_eval"), log=log, **imagined_execution(rl))
    os.makedirs(workdir, exist_ok=True)
    runner.start_probe(params, os.path.join(workdir, "probe"))

    def evaluate_real(step, params):
        point, extra = runner.evaluate(params, step=step, sampled=True, masked=rl.imagined.eval_masked_proprio,
                                       as_trained=True)
        masked, executed = extra.get("sampled_proprio_masked"), extra.get("sampled_as_trained")
        log(f"eval step {step}: MJX success {point['mean']:.3f} [{point['ci95'][0]:.3f}, {point['ci95'][1]:.3f}]"
            f"; sampled T={rl.grpo.temperature:g} {extra['sampled']['mean']:.3f}"
            + (f", proprio masked {masked['mean']:.3f}" if masked else "")
            + (f", as trained ({executed['execute_steps']} actions per decision) {executed['mean']:.3f}"
               if executed else "") + f" ({point['episodes']} episodes)")
        return point, extra

    return env, evaluate_real


def run_refreshed_in_mjx(cfg, rl, graphdef, params, workdir: str, setup, *, vae, world_model, latents: str,
                         episodes_per_task: int, max_traces: int) -> dict:
    """GRPO in ``setup``'s learned simulator (:func:`sword_jax.pipeline.grpo.world_model_setup`), refreshed every
    ``rl.refresh.every`` steps on MJX episodes of the current policy; ``vae`` / ``world_model``: the run's
    ``(graphdef, state)`` as trained (the world model's float32 weights are what a refresh fine-tunes; the
    simulator stores them as its builder does, ``rl.imagined.sim_precision``); ``latents``: the world model's
    training latents (``.npz``). Returns as :func:`run_refreshed`."""
    from sword_jax.vae import api as vae_api
    from sword_jax.world_model.data import load_latent_dataset

    if rl.env.backend != "mjx":
        raise ValueError(f"rl.refresh collects real episodes on MJX; got rl.env.backend={rl.env.backend}")
    if cfg.sim.resolution != cfg.data.image_size:
        raise ValueError(f"rl.refresh trains the world model on real frames: sim.resolution={cfg.sim.resolution} must "
                         f"equal data.image_size={cfg.data.image_size}")
    tasks = list(cfg.sim.tasks)
    pool = {t: sim_tasks.split_init_states(t, "train", sim_tasks.TRAIN_RESERVE, seed=cfg.sim.init_seed) for t in tasks}
    env, evaluate_real = mjx_evaluation(cfg, rl, graphdef, params, workdir, episodes_per_task=episodes_per_task)

    def pool_starts(n, rng):
        picked = stratified_train_starts(tasks, n, rng, pool=pool)
        qpos, text = episode_starts(picked)
        return qpos, text, np.asarray([t for t, _ in picked])

    vae_graphdef, vae_state = vae
    encoder = vae_api.encoder(vae_graphdef, vae_state)
    batch = max(cfg.vae.batch_size, 1)

    def encode_frames(frames):  # [n, F, H, W, 3] in [0, 1] -> the world model's training latents
        return np.concatenate([np.asarray(encoder(frames[i:i + batch] * np.float32(2.0) - np.float32(1.0)))
                               for i in range(0, len(frames), batch)])

    wm_graphdef, wm_state = world_model
    _, vae_params = setup.sim.params

    def make_simulator(state):  # the fine-tuned float32 weights, stored as the simulator's builder stores them
        return setup.sim.replace(params=(stored_for_simulator(wm_graphdef, state, rl.imagined.sim_precision),
                                         vae_params))

    det_graphdef, _ = build_detector(rl, seed=cfg.seed)
    return run_refreshed(cfg, rl, graphdef, params, workdir, setup=setup, wm_state=wm_state,
                         make_simulator=make_simulator,
                         encode_frames=encode_frames, detector=(det_graphdef, setup.reward_model.params),
                         base=load_latent_dataset(latents), env=env,
                         collect_starts=stratified_collect_starts(pool_starts, cfg.seed), evaluate_real=evaluate_real,
                         max_traces=max_traces, facts={"sim.tasks": tasks, "sim.init_seed": cfg.sim.init_seed,
                                                       "sim.max_steps": cfg.sim.max_steps,
                                                       "sim.resolution": cfg.sim.resolution})
