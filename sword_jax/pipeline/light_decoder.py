"""Distilling the light rollout decoder from the run's VAE on the run's own latents.

:func:`run_light_decoder` is what ``python -m train.train_light_decoder`` and the pipeline's
``light_decoder`` stage run (the stage runs when ``rl.imagined.decoder=light``). The teacher is the
VAE's decoder (``light_decoder.teacher_precision``), the data the world model's training latents
(``latents.npz``: raw and styled episodes), the student :mod:`sword_jax.vae.light_decoder` at
``light_decoder.frame_size`` (default the policy's ``rl.image_size``). The loop is
:func:`sword_jax.train_loop.run_steps`: checkpoints under ``<workdir>/checkpoints``, an exact resume
from them, metrics in ``<workdir>/metrics.jsonl``. Each checkpoint carries the decoder's geometry, so the
newest is the trained decoder (:func:`sword_jax.load.load_light_decoder` reads its weights alone), and
``<workdir>/strip.png`` shows a held clip decoded by both decoders, before and after.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from sword_jax import checkpoint
from sword_jax import sharding as shd
from sword_jax.tracing import ENTRY_MAX_TRACES
from sword_jax.train_loop import run_steps
from sword_jax.vae import light_decoder as light
from sword_jax.vae import light_train

KIND = "light_decoder"


def light_geometry(cfg: Any) -> tuple[int, int]:
    """``(latent size, frame size)`` of the experiment's light decoder (``LightDecoderConfig.geometry``)."""
    return cfg.light_decoder.geometry(image_size=cfg.data.image_size, spatial_factor=cfg.vae.spatial_factor,
                                      policy_size=cfg.rl.image_size)


def light_meta(cfg: Any) -> dict:
    """What rebuilds the light decoder, saved with every checkpoint: its config section, the latent channels, the
    scale and the temporal factor (:func:`sword_jax.load.load_light_decoder` reads it)."""
    latent, frame = light_geometry(cfg)
    return {"kind": KIND, "light_decoder": dataclasses.asdict(cfg.light_decoder), "z_dim": cfg.vae.z_dim,
            "scale": frame // latent, "temporal_factor": cfg.vae.temporal_factor, "latent_size": latent,
            "frame_size": frame}


def save_light_decoder(directory: str, params: Any, cfg: Any, *, step: int = 0) -> None:
    """Writes light-decoder weights as the training's checkpoints hold them (``params`` and :func:`light_meta`),
    e.g. weights made elsewhere."""
    with checkpoint.Checkpointer(directory, max_to_keep=1) as ckpt:
        ckpt.save(step, {"params": nnx.to_pure_dict(params)}, light_meta(cfg))


def run_id(cfg: Any, *, latent_shape: tuple[int, ...]) -> dict:
    """What a resumed run must share with its checkpoint: the light-decoder section but ``train_steps`` (a run
    may be extended), the seed, the geometry, the official teacher's file if any and the data's shape."""
    section = {f"light_decoder.{k}": v for k, v in dataclasses.asdict(cfg.light_decoder).items() if k != "train_steps"}
    return {"seed": cfg.seed, "geometry": list(light_geometry(cfg)), "vae.checkpoint": cfg.vae.checkpoint,
            "latent_shape": list(latent_shape), **section}


def _write_strip(path: str, before: np.ndarray, after: np.ndarray, target: np.ndarray) -> None:
    from sword_jax.evaluation.report import write_strip

    unit = lambda v: np.clip((np.asarray(v, np.float32) + 1.0) * 0.5, 0.0, 1.0)  # noqa: E731
    write_strip(path, {"VAE decoder": unit(target), "light, init": unit(before), "light, trained": unit(after)})


def run_light_decoder(cfg: Any, *, vae: str, latents: str) -> dict:
    """Trains (or resumes) the light decoder in ``cfg.workdir``; returns the summary.

    Args:
      cfg: the experiment config (``light_decoder``, ``vae``, ``data.image_size``, ``rl.image_size``, ``seed``,
        ``mesh``, ``trainer.log_every`` / ``checkpoint_every``).
      vae: the VAE's saved state (``<vae_workdir>/vae``; ignored with ``vae.checkpoint``).
      latents: the world model's training latents (``.npz``/``.h5`` with ``latents [E, L, h, w, z]``).

    Returns:
      ``{"path", "steps", "frame_size", "latent_size", "params", "first_loss", "final_loss", "eval": {"init_l1",
      "final_l1", "init_psnr", "final_psnr"}, "strip"}``: ``path`` is the checkpoints directory
      (:func:`sword_jax.load.load_light_decoder`'s input, ``train.grpo --light-decoder``); ``eval`` the numbers
      on a fixed batch of clips before and after (float32, student vs teacher at the student's resolution,
      PSNR on frames clipped to [0, 1]).
    """
    from sword_jax.load import load_vae_params
    from sword_jax.rl.sim_builder import inference_vae
    from sword_jax.world_model.data import load_latent_dataset

    ld = cfg.light_decoder
    ld.validate()
    is_main = jax.process_index() == 0
    log = print if is_main else (lambda *_a, **_k: None)
    latent_size, frame_size = light_geometry(cfg)
    if not vae and not cfg.vae.checkpoint:
        raise SystemExit("train_light_decoder: the teacher is the run's VAE: give its saved state (--vae, train_vae's "
                         "<workdir>/vae) or --vae.checkpoint")
    try:
        dataset = load_latent_dataset(latents).latents
    except (FileNotFoundError, ValueError) as err:
        raise SystemExit(f"train_light_decoder: {err}") from None
    want = (latent_size, latent_size, cfg.vae.z_dim)
    if tuple(dataset.shape[2:]) != want:
        raise SystemExit(f"train_light_decoder: {latents} holds latents {dataset.shape}, the config's VAE makes [E, L, "
                         f"{want[0]}, {want[1]}, {want[2]}] (data.image_size / vae.spatial_factor, vae.z_dim)")
    mesh = shd.make_mesh(cfg.mesh)
    try:  # each process cuts only the rows of a batch its devices hold
        loader = light_train.clip_loader(light_train.ClipSampler(
            dataset, batch=ld.batch_size, clip_latents=ld.clip_latents, seed=cfg.seed), mesh, cfg.mesh.rules)
    except ValueError as err:
        raise SystemExit(f"train_light_decoder: {err}") from None
    held_loader = light_train.clip_loader(light_train.ClipSampler(
        dataset, batch=ld.batch_size, clip_latents=ld.clip_latents, seed=cfg.seed, name="light_decoder/eval"),
        mesh, cfg.mesh.rules)
    held_clips = held_loader.place(held_loader.host_batch_at(0))["latents"]
    teacher_graphdef, teacher_state = inference_vae(*load_vae_params(cfg.vae, vae, mesh=mesh), ld.teacher_precision)
    scale = frame_size // latent_size
    graphdef, state = light_train.init_train_state(ld, z_dim=cfg.vae.z_dim, scale=scale,
                                                   temporal_factor=cfg.vae.temporal_factor,
                                                   key=jax.random.key(cfg.seed), mesh=mesh, rules=cfg.mesh.rules)
    params_count = light.param_count(state.params)
    perceptual_fn = None
    if ld.perceptual_weight > 0:
        from sword_jax.vae.perceptual import lpips_loss

        perceptual_fn, source = lpips_loss(cfg.eval)
        log(f"[light_decoder] perceptual loss: LPIPS x {ld.perceptual_weight} ({source})")
    step = light_train.make_distill_step(graphdef, teacher_graphdef, ld, frame_size=frame_size,
                                         perceptual_fn=perceptual_fn)
    step_fn = light_train.bind_teacher(step, teacher_state, state, {"latents": held_clips}, mesh=mesh,
                                       rules=cfg.mesh.rules, max_traces=ENTRY_MAX_TRACES)

    @functools.partial(jax.jit, out_shardings=shd.replicated(mesh))  # every process reads them
    def evaluate(teacher_state, params, clips):
        target = light_train.teacher_frames(teacher_graphdef, teacher_state, clips, frame_size=frame_size)
        video = light.decode(graphdef, params, clips, compute_dtype="float32")
        return jnp.mean(jnp.abs(video - target)), light_train.frame_psnr(video, target), video[0], target[0]

    init_l1, init_psnr, init_video, _ = evaluate(teacher_state, state.params, held_clips)
    log(f"[light_decoder] {params_count / 1e6:.2f}M parameters, {latent_size}x{latent_size} latents -> "
        f"{frame_size}x{frame_size} frames; {dataset.shape[0]} episodes of {dataset.shape[1]} latents; teacher "
        f"{ld.teacher_precision}; init l1 {float(init_l1):.4f}, psnr {float(init_psnr):.2f} dB")
    root = shd.put(jax.random.key(cfg.seed), shd.replicated(mesh))
    log_every = max(cfg.trainer.log_every, 1)
    logger = checkpoint.MetricLogger(ld.train_steps, log_every, jsonl_path=os.path.join(cfg.workdir, "metrics.jsonl"),
                                     tensorboard_dir=os.path.join(cfg.workdir, "tensorboard"))
    started = time.perf_counter()
    try:
        result = run_steps(
            step_fn, state, loader.host_batch_at, key=root, steps=ld.train_steps, log_every=log_every,
            name="train_light_decoder", report=lambda done, metrics, _obs, eta: logger.write(done, metrics, eta_s=eta),
            place=loader.place,
            checkpoint_dir=os.path.join(cfg.workdir, "checkpoints"), checkpoint_every=cfg.trainer.checkpoint_every,
            keep_checkpoints=1, settle=True, checkpoint_meta=lambda _done: light_meta(cfg),
            run_id=run_id(cfg, latent_shape=dataset.shape), log=log)
    finally:
        logger.close()
    params = result.state.params
    final_l1, final_psnr, final_video, target = evaluate(teacher_state, params, held_clips)
    path = os.path.join(cfg.workdir, "checkpoints")
    strip = os.path.join(cfg.workdir, "strip.png")
    if is_main:
        _write_strip(strip, jax.device_get(init_video), jax.device_get(final_video), jax.device_get(target))
    log(f"[light_decoder] {ld.train_steps} steps in {time.perf_counter() - started:.1f} s; held clips: l1 "
        f"{float(init_l1):.4f} -> {float(final_l1):.4f}, psnr {float(init_psnr):.2f} -> {float(final_psnr):.2f} dB")
    first = result.history[0] if result.history else {}
    last = result.history[-1] if result.history else {}
    return {"path": path, "steps": ld.train_steps, "frame_size": frame_size, "latent_size": latent_size,
            "params": params_count, "first_loss": first.get("loss"), "final_loss": last.get("loss"),
            "eval": {"init_l1": float(init_l1), "final_l1": float(final_l1), "init_psnr": float(init_psnr),
                     "final_psnr": float(final_psnr)}, "strip": strip}
