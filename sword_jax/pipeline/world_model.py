"""Training of the action-conditioned world model: teacher forcing, or DLB when ``cache.enabled``.

:func:`run_world_model` is what ``python -m train.train_world_model`` and the pipeline's world-model
stage run. The latent dataset comes from ``cfg.data.path`` (``.npz``/``.h5`` with ``latents [E, L, h, w, c]``
and ``actions [E, 1 + 4(L-1), a]``) or, with ``synthetic``, from action-dependent synthetic latents.
The loop is :func:`sword_jax.train_loop.run_steps`; the batch of a step is a pure function of it. The
run auto-resumes from ``<workdir>/checkpoints`` (train state with the DLB cache, data position,
RNG root, config). Metrics are read one log step late and appended to ``<workdir>/metrics.jsonl`` and
TensorBoard event files in ``<workdir>/tensorboard``.
A non-finite loss stops the run (``trainer.on_nonfinite=stop``) naming the step; the last good
checkpoint stays, and the faulty step's update was never applied (``skip`` goes on without it).
Every ``trainer.eval_every`` steps the run also logs the flow loss and the sampler's error on fixed segments of
training and of held-out episodes (``--data.heldout_path``; synthetic ones of another seed with ``--synthetic``),
:mod:`sword_jax.world_model.heldout`.
"""

from __future__ import annotations

import json
import os

import jax
import numpy as np
from flax import nnx

from configs.base import ExperimentConfig
from configs.cli import to_dict
from sword_jax import checkpoint
from sword_jax import sharding as shd
from sword_jax import tracing
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dlb import cache as dlb_cache
from sword_jax.atomic_write import write_json_atomic
from sword_jax.train_loop import differing_keys, run_steps
from sword_jax.world_model import data, heldout, train_state, train_step
from sword_jax.metrics.config import EvalConfig
from sword_jax.world_model.config import DataConfig


def latent_grid(cfg: ExperimentConfig) -> tuple[int, int, int, int]:
    """``(L, h, w, c)`` of a latent episode for the config's frames and VAE."""
    side = cfg.data.image_size // cfg.vae.spatial_factor
    return 1 + (cfg.data.episode_frames - 1) // cfg.vae.temporal_factor, side, side, cfg.vae.z_dim


def build_dataset(cfg: ExperimentConfig, synthetic: bool) -> data.LatentDataset:
    num_latents, height, width, channels = latent_grid(cfg)
    if synthetic or not cfg.data.path:
        if not synthetic:
            raise SystemExit("train_world_model: set --data.path=latents.npz or pass --synthetic")
        return data.synthetic_latent_dataset(cfg.data.num_episodes, num_latents, height, width, channels,
                                             seed=cfg.seed, action_dim=cfg.model.action_dim)
    dataset = data.load_latent_dataset(cfg.data.path)
    if dataset.shape[2:] != (height, width, channels) or dataset.actions.shape[2] != cfg.model.action_dim:
        raise SystemExit(f"train_world_model: {cfg.data.path} holds latents {dataset.shape} / actions "
                         f"{dataset.actions.shape}, but the config expects [E, L, {height}, {width}, {channels}] "
                         f"and {cfg.model.action_dim}-D actions")
    return dataset


# trainer.eval_segments' record: every fixed segment's sample error at the run's end (HeldOutEvaluator.per_segment)
SEGMENTS_FILE = "heldout_segments.json"

# Trainer keys that may change between a run and its resumption (e.g. extending the run).
# The held-out evaluation's settings are among them: it reads the weights and changes nothing.
RESUMABLE_KEYS = ("steps", "log_every", "checkpoint_every", "keep_checkpoints", "on_nonfinite", "eval_every",
                  "eval_batches", "eval_sample_steps", "eval_segments")


def _comparable(cfg_dict: dict) -> dict:
    trainer = {k: v for k, v in cfg_dict.get("trainer", {}).items() if k not in RESUMABLE_KEYS}
    # what the held-out evaluation reads changes nothing the model trains on, nor how many processes record the
    # policy's rollouts (the same file for any number)
    data_cfg = {k: v for k, v in cfg_dict.get("data", {}).items()
                if k not in ("heldout_path", "heldout_policy_rollouts_per_task", *DataConfig.result_free_fields)}
    # how the pipeline's evaluation stage scores is not read here (EvalConfig.scoring_fields)
    eval_cfg = {k: v for k, v in cfg_dict.get("eval", {}).items() if k not in EvalConfig.scoring_fields}
    # The mesh may change between runs: checkpoints restore onto any device count.
    return {**cfg_dict, "trainer": trainer, "data": data_cfg, "eval": eval_cfg, "workdir": None, "mesh": None}


def build_heldout(cfg: ExperimentConfig, synthetic: bool,
                  dataset: data.LatentDataset) -> dict[str, data.LatentDataset]:
    """The held-out splits of ``trainer.eval_every``'s evaluation: ``data.heldout_path``'s (``heldout``, and
    ``policy`` where the file holds the supervised policy's held-out rollouts:
    :func:`~sword_jax.world_model.data.load_heldout_splits`), or, with ``synthetic`` and no path, synthetic
    episodes of another seed; none without either (the training segments alone are then measured)."""
    if cfg.data.heldout_path:
        splits = data.load_heldout_splits(cfg.data.heldout_path)
        for split, held in splits.items():
            if held.shape[1:] != dataset.shape[1:] or held.actions.shape[1:] != dataset.actions.shape[1:]:
                raise SystemExit(f"train_world_model: data.heldout_path {cfg.data.heldout_path} holds {split} "
                                 f"latents {held.shape} / actions {held.actions.shape}, but the training data's "
                                 f"are {dataset.shape} / {dataset.actions.shape}")
        return splits
    if synthetic:
        num_latents, height, width, channels = dataset.shape[1:]
        return {"heldout": data.synthetic_latent_dataset(max(dataset.shape[0] // 4, 1), num_latents, height, width,
                                                         channels, seed=cfg.seed + 1, action_dim=cfg.model.action_dim)}
    return {}


def _check_config_matches(workdir: str, cfg_dict: dict) -> None:
    path = os.path.join(workdir, "config.json")
    if os.path.exists(path):
        with open(path) as f:
            saved = _comparable(json.load(f))
        current = _comparable(cfg_dict)
        if saved != current:
            raise SystemExit(f"train_world_model: {workdir} was made with another config (sections differ: "
                             f"{differing_keys(saved, current)}); use a new --workdir")
    elif jax.process_index() == 0:
        os.makedirs(workdir, exist_ok=True)
        with open(path, "w") as f:
            json.dump(cfg_dict, f, indent=1, sort_keys=True)


def run_world_model(cfg: ExperimentConfig, *, synthetic: bool = False) -> dict:
    """Trains (or resumes) the world model in ``cfg.workdir`` on ``cfg.data.path`` (or synthetic latents).

    Returns ``{"step", "metrics" (the last logged), "workdir"}``.
    """
    workdir = cfg.workdir
    cfg_dict = to_dict(cfg)
    cfg_dict["synthetic"] = synthetic
    _check_config_matches(workdir, cfg_dict)
    mesh = shd.make_mesh(cfg.mesh)
    rules = cfg.mesh.rules
    num_context, num_future = (cfg.data.context_frames // cfg.vae.temporal_factor,
                               cfg.data.predict_frames // cfg.vae.temporal_factor)
    dataset = build_dataset(cfg, synthetic)
    held_splits = build_heldout(cfg, synthetic, dataset) if cfg.trainer.eval_every else {}
    held, policy_held = held_splits.get("heldout"), held_splits.get("policy")
    # the training episodes that are the supervised policy's rollouts (the latents file's sources), measured apart
    sources = (None if synthetic or not cfg.trainer.eval_every or not cfg.data.path
               else data.load_sources(cfg.data.path, dataset.shape[0]))
    train_policy = None if sources is None else np.flatnonzero(sources == 1)
    is_main = jax.process_index() == 0
    if is_main:
        print(f"[train_world_model] {cfg.name}: mesh {dict(mesh.shape)}, dataset latents {dataset.shape}, "
              f"DLB {'on (' + cfg.cache.schedule + ', ' + cfg.cache.replacement + ', ' + cfg.cache.scope + ')' if cfg.cache.enabled else 'off'}")
        if cfg.cache.enabled:
            per_device = dlb_cache.cache_bytes_per_device(cfg.cache, dataset.shape, mesh, rules)
            print(f"[train_world_model] latent cache: {per_device / 2**20:.2f} MiB per device "
                  f"({cfg.cache.dtype}, {dlb_cache.episode_shards(mesh, rules)} episode shards)")

    graphdef, state, shardings = train_state.create_train_state(
        lambda: WorldModel(cfg.model, rngs=nnx.Rngs(cfg.seed)), cfg.trainer, cfg.cache, dataset.shape, mesh, rules)
    sampler = data.SegmentSampler(dataset.shape[0], dataset.shape[1], num_context, num_future,
                                  cfg.data.batch_size, seed=cfg.seed)
    loader = data.SegmentLoader(dataset, sampler, num_context, num_future, mesh, rules)
    step_fn = train_step.make_train_step(graphdef, flow_cfg=cfg.flow, trainer_cfg=cfg.trainer, cache_cfg=cfg.cache,
                                         num_context=num_context, num_episodes=dataset.shape[0])
    # A retrace (a batch or state whose shape, dtype or structure changed) is a bug; the guard names the step.
    step = train_step.compile_train_step(tracing.max_traces(step_fn, n=tracing.ENTRY_MAX_TRACES), shardings,
                                         loader.shardings, mesh, rules)
    if is_main and cfg.trainer.eval_every:
        print(f"[train_world_model] evaluation every {cfg.trainer.eval_every} steps: "
              f"{cfg.trainer.eval_batches} x {cfg.data.batch_size} fixed training segments"
              + (f" and as many of {held.shape[0]} held-out episodes" if held is not None else
                 "; no held-out episodes (data.heldout_path is not set)")
              + (f" and of {policy_held.shape[0]} held-out rollouts of the supervised policy"
                 if policy_held is not None else "")
              + (f"; and training segments of the {len(train_policy)} training episodes that are the policy's "
                 "rollouts" if train_policy is not None and len(train_policy) else ""))
    evaluator = None if not cfg.trainer.eval_every else heldout.HeldOutEvaluator(
        graphdef, cfg.flow, cfg.trainer, train=dataset, heldout=held, loader=loader, num_context=num_context,
        num_future=num_future, mesh=mesh, rules=rules, seed=cfg.seed, policy=policy_held, train_policy=train_policy)
    root_key = jax.random.key(cfg.seed)  # the config check above pins the seed of a resumed run
    rng_root = np.asarray(jax.random.key_data(root_key)).tolist()
    logger = checkpoint.MetricLogger(cfg.trainer.steps, cfg.trainer.log_every,
                                     jsonl_path=os.path.join(workdir, "metrics.jsonl"),
                                     tensorboard_dir=os.path.join(workdir, "tensorboard"))

    try:
        result = run_steps(
            step, state, loader.host_batch_at, key=shd.put(root_key, shd.replicated(mesh)), steps=cfg.trainer.steps,
            log_every=cfg.trainer.log_every, name="train_world_model",
            report=lambda done, metrics, observed, eta: logger.write(
                done, {**metrics, **heldout.measured(observed)}, eta_s=eta), observe=evaluator, place=loader.place,
            checkpoint_dir=os.path.join(workdir, "checkpoints"), checkpoint_every=cfg.trainer.checkpoint_every,
            keep_checkpoints=cfg.trainer.keep_checkpoints,
            checkpoint_meta=lambda done: {"data_position": sampler.position_at(done), "rng_root": rng_root,
                                          "config": cfg_dict},
            metrics_finite=train_step.step_was_finite, on_nonfinite=cfg.trainer.on_nonfinite,
            settle=True, log=print if is_main else lambda _line: None)
    finally:
        logger.close()
    if evaluator is not None and cfg.trainer.eval_segments:
        per_segment = evaluator.per_segment(result.state)  # every process: the segments are gathered
        if is_main:
            write_json_atomic(os.path.join(workdir, SEGMENTS_FILE),
                              {"step": int(result.state.step), "splits": per_segment})
    last = result.history[-1] if result.history else {}
    return {"step": max(result.first_step, cfg.trainer.steps), "metrics": last, "workdir": workdir}
