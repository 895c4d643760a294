"""Training of the Wan 2.2-style video VAE from scratch on simulator videos (or loading official weights).

:func:`run_vae` is what ``python -m train.train_vae`` and the pipeline's VAE stage run. Clips of
``1 + 4k`` frames are cut at random from the episodes' agentview frames; with ``vae.train_styles`` a
``vae.styled_fraction`` share of them is restyled in *training* styles (:mod:`sword_jax.vae.data`;
held-out styles and held-out episodes never reach the VAE). The state is an orbax checkpoint under
``<workdir>/checkpoints`` that the run auto-resumes from; ``<workdir>/vae/`` holds the final pure-dict
VAE state.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from collections.abc import Sequence

import jax
import numpy as np
from flax import nnx

from configs.base import ExperimentConfig
from sim.dataset import read_dataset
from sword_jax import checkpoint
from sword_jax import sharding as shd
from sword_jax.load import load_vae_params, vae_dir
from sword_jax.tracing import ENTRY_MAX_TRACES
from sword_jax.train_loop import run_steps
from sword_jax.vae import data as vae_data
from sword_jax.vae import train as vae_train


def load_clips(paths: Sequence[str]) -> vae_data.VAEClips:
    """Training episodes (uint8 agentview frames, depth and segmentation) from LIBERO-layout HDF5 files.

    Episodes from held-out initial states are refused: evaluation data never trains the VAE.
    """
    episodes = []
    for path in paths:
        episodes += read_dataset(path)[1]
    return vae_data.clips_from_sim(episodes, name="train_vae")


def clip_sampler(cfg: ExperimentConfig, clips: vae_data.VAEClips, frames: int) -> vae_data.ClipSampler:
    """Raw clips plus, with ``vae.train_styles``, a ``vae.styled_fraction`` share in training styles."""
    from sword_jax.augment.pipeline import seg_classes_from_config

    return vae_data.ClipSampler(clips, batch=cfg.vae.batch_size, frames=frames, seed=cfg.seed,
                                styled_fraction=cfg.vae.styled_fraction if cfg.vae.train_styles else 0.0,
                                intensity=cfg.augment.intensity, classes=seg_classes_from_config(cfg.augment),
                                fov_deg=cfg.augment.fov_deg)


def save_vae(path: str, graphdef: nnx.GraphDef, params: nnx.State, constants: nnx.State) -> None:
    """Writes the whole VAE state (params + latent statistics) as one pure dict."""
    state = nnx.to_pure_dict(nnx.merge_state(params, constants))
    ckpt = checkpoint.Checkpointer(path, max_to_keep=1)
    ckpt.save(0, state, {"kind": "vae"})
    ckpt.close()


def vae_run_id(cfg: ExperimentConfig, *, clip_latents: int, synthetic: bool) -> dict:
    """What a resumed VAE run must share with its checkpoint (flat ``vae.<key>`` names): the VAE
    section but ``train_steps`` (a run may be extended), the seed, the frame size and the training clips."""
    vae = {f"vae.{k}": v for k, v in dataclasses.asdict(cfg.vae).items() if k != "train_steps"}
    return {"seed": cfg.seed, "data.image_size": cfg.data.image_size, "clip_latents": clip_latents,
            "synthetic": synthetic, **vae}


def _place_trained_vae(source: str, final_path: str) -> None:
    """A trained VAE reused (``vae.checkpoint`` naming its folder) is copied to where this run keeps its own
    (``<workdir>/vae``), so that readers of the run (GRPO's ``--vae``, bundles) find it there; a different VAE
    already there is refused, never replaced."""
    from sword_jax.pipeline.inputs import hash_checkpoint

    if os.path.exists(final_path):
        if hash_checkpoint(final_path) != hash_checkpoint(source):
            raise SystemExit(f"train_vae: {final_path} holds another VAE than --vae.checkpoint={source}; reuse a "
                             "trained VAE in a new work dir")
        return
    staged = f"{final_path}.copying"
    shutil.rmtree(staged, ignore_errors=True)
    shutil.copytree(source, staged)
    os.replace(staged, final_path)


def run_vae(cfg: ExperimentConfig, episodes: Sequence[str] = (), *, synthetic: bool = False,
            clip_latents: int = 2) -> dict:
    """Trains (or resumes) the VAE in ``cfg.workdir``, or validates ``vae.checkpoint``; returns the summary.

    Args:
      cfg: the experiment config; ``cfg.workdir`` is this run's work dir.
      episodes: LIBERO-layout HDF5 files of training episodes.
      synthetic: train on moving squares instead (when ``episodes`` is empty).
      clip_latents: ``k`` of the ``1 + 4k``-frame training clips.
    """
    is_main = jax.process_index() == 0
    final_path = os.path.join(cfg.workdir, "vae")
    if cfg.vae.checkpoint:
        load_vae_params(cfg.vae, final_path)  # validates the official file or the trained VAE's folder now
        if os.path.isdir(cfg.vae.checkpoint) and is_main:
            _place_trained_vae(vae_dir(cfg.vae.checkpoint), final_path)
        return {"source": cfg.vae.checkpoint, "steps": 0}
    if not episodes and not synthetic:
        raise SystemExit("train_vae: pass --episodes FILE.hdf5 (repeatable), --synthetic, or --vae.checkpoint=...")
    frames = 1 + cfg.vae.temporal_factor * clip_latents
    sampler: vae_data.ClipSampler | None = None  # loaded below, once the batch is known to split over the mesh

    def rows_at(step: int, rows: np.ndarray) -> np.ndarray:  # 0-based step; the clip draws count from 1
        if sampler is not None:
            return sampler.batch(step + 1, rows)
        return np.asarray(vae_train.moving_squares(key=jax.random.key(step + 1), batch=cfg.vae.batch_size,
                                                   frames=frames, size=cfg.data.image_size, rows=rows))

    mesh = shd.make_mesh(cfg.mesh)
    # each process makes only the rows of a batch its devices hold
    loader = vae_data.VideoLoader(rows_at, cfg.vae.batch_size, mesh, cfg.mesh.rules)
    loaded = time.perf_counter()
    sampler = clip_sampler(cfg, load_clips(episodes), frames) if episodes else None
    if sampler is not None and is_main:
        print(f"[train_vae] {len(sampler.clips.frames)} training episodes loaded in "
              f"{time.perf_counter() - loaded:.1f} s", flush=True)
    graphdef, state = vae_train.init_train_state(cfg.vae, key=jax.random.key(cfg.seed), mesh=mesh,
                                                 rules=cfg.mesh.rules)
    perceptual_fn = None
    if cfg.vae.perceptual_weight > 0:  # LPIPS with the evaluation's weights (published AlexNet by default)
        from sword_jax.vae.perceptual import lpips_loss

        perceptual_fn, source = lpips_loss(cfg.eval)
        if is_main:
            print(f"[train_vae] perceptual loss: LPIPS x {cfg.vae.perceptual_weight} ({source})")
    step_fn = vae_train.make_vae_step(graphdef, cfg.vae, state=state, mesh=mesh, rules=cfg.mesh.rules,
                                          perceptual_fn=perceptual_fn, max_traces=ENTRY_MAX_TRACES)
    root = shd.put(jax.random.key(cfg.seed), shd.replicated(mesh))
    logger = checkpoint.MetricLogger(cfg.vae.train_steps, max(cfg.trainer.log_every, 1),
                                     jsonl_path=os.path.join(cfg.workdir, "metrics.jsonl"),
                                     tensorboard_dir=os.path.join(cfg.workdir, "tensorboard"))

    first_batch_s: list[float] = []  # the first batch's time: the restyling's compile, inside the first step

    def batch_at(step: int) -> np.ndarray:
        start = time.perf_counter()
        out = loader.host_batch_at(step)
        if not first_batch_s:
            first_batch_s.append(time.perf_counter() - start)
        return out

    def first_step_done() -> None:  # compile (and autotuning) time, separate from the step rate
        if is_main:
            parts = getattr(sampler, "first_batch_seconds", {})
            split = (f" (clip sampling {parts['sample']:.1f} s, restyling with its compile on "
                     f"{jax.default_backend()} {parts['restyle']:.1f} s)" if parts else "")
            print(f"[train_vae] first step (compile included) done {time.perf_counter() - loaded:.1f} s after "
                  f"loading began; its batch took {first_batch_s[0] if first_batch_s else 0.0:.1f} s of it{split}",
                  flush=True)

    try:
        result = run_steps(
            step_fn, state, batch_at, key=root, steps=cfg.vae.train_steps, log_every=max(cfg.trainer.log_every, 1),
            name="train_vae", report=lambda done, metrics, _observed, eta: logger.write(done, metrics, eta_s=eta),
            place=loader.place,
            checkpoint_dir=os.path.join(cfg.workdir, "checkpoints"), checkpoint_every=cfg.trainer.checkpoint_every,
            keep_checkpoints=1, settle=True, on_first_step=first_step_done,
            run_id=vae_run_id(cfg, clip_latents=clip_latents, synthetic=sampler is None),
            log=print if is_main else lambda _line: None)
    finally:
        logger.close()
    state = result.state
    save_vae(final_path, graphdef, state.params, state.constants)
    last = result.history[-1] if result.history else {}
    first = result.history[0] if result.history else {}
    return {"steps": cfg.vae.train_steps, "first_loss": first.get("loss"), "final_loss": last.get("loss"),
            "path": final_path, "styled_fraction": sampler.styled_fraction if sampler is not None else 0.0,
            "styled_clips": sampler.styled_clips if sampler is not None else 0}
