"""Behaviour cloning (SFT) of the VLA policy on expert demonstrations: the GRPO starting point.

:func:`run_sft_policy` is what ``python -m train.train_policy`` and the pipeline's supervised-policy
stage run (:func:`given_policy` instead, with ``rl.sft.init``). Writes ``<workdir>/rl/policy_sft`` (orbax)
and, with ``eval_episodes``, the ground-truth success in the MuJoCo sim. The train state is checkpointed to ``<workdir>/rl/sft_checkpoints`` and a
rerun resumes from there. With ``rl.sft.init`` it fine-tunes that policy; with ``rl.sft.decoded_fraction`` it trains
on a share of frames round-tripped through a trained VAE (decoder-aware SFT, :mod:`sword_jax.rl.decoded_frames`).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Sequence

import jax
import numpy as np

from sim.dataset import read_dataset
from sword_jax import sharding as shd
from sword_jax.rl import data as rl_data
from sword_jax.rl.params_io import load_params, save_params
from sword_jax.rl.policy import build_policy
from sword_jax.rl.policy_success import evaluate_in_sim
from sword_jax.rl.sft import train_sft


def given_policy(cfg, source: str) -> dict:
    """The ``sft_policy`` stage with ``rl.sft.init``: copies the trained policy ``source`` (a
    ``train.train_policy`` checkpoint directory or ``.npz``) into ``<cfg.workdir>/rl`` and checks that it loads
    into ``cfg.rl``'s policy. Returns the stage's summary, ``path`` the copy (later stages read it, so the run
    does not depend on ``source`` staying where it is).

    Raises:
      FileNotFoundError: ``source`` does not exist.
      ValueError: it holds another kind of checkpoint or another architecture than ``cfg.rl`` builds.
    """
    if cfg.rl.sft.decoded_fraction > 0:
        raise ValueError(f"rl.sft.decoded_fraction={cfg.rl.sft.decoded_fraction}: the sft_policy stage with rl.sft.init "
                         "copies the given policy without training it; fine-tune it on decoded frames with "
                         "train.train_policy --vae DIR (or benchmarks.bench_policy sft --vae DIR) and pass the result")
    _require_policy(source)
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    is_npz = source.endswith(".npz")
    path = os.path.abspath(os.path.join(workdir, "policy_given.npz" if is_npz else "policy_given"))
    tmp = path[: -len(".npz")] + ".tmp.npz" if is_npz else path + ".tmp"  # load_params tells formats by suffix
    shutil.rmtree(tmp, ignore_errors=True)
    if os.path.isfile(tmp):
        os.remove(tmp)
    (shutil.copyfile if is_npz else shutil.copytree)(source, tmp)
    try:
        _load_policy(cfg, source, tmp)
    except ValueError:
        (os.remove if is_npz else shutil.rmtree)(tmp)
        raise
    if os.path.isdir(path):
        shutil.rmtree(path)
    os.replace(tmp, path)
    result = {"given": os.path.abspath(source), "path": path, "steps": 0, "demos": 0}
    with open(os.path.join(workdir, "sft_result.json"), "w") as f:
        json.dump(result, f, indent=1)
    print(f"sft_policy: starting from the given policy {source}", flush=True)
    return result


def run_sft_policy(cfg, demos: Sequence[str], *, eval_episodes: int = 0, eval_workers: int = 0,
                   renderer: str = "jax", holdout: float = 0.1, vae: str = "", world_model: str = "") -> dict:
    """Behaviour-clones (or resumes) the policy on ``demos`` in ``<cfg.workdir>/rl``; with ``eval_episodes``
    per task, measures its success in the simulator. Returns the summary (also in ``sft_result.json``).

    ``rl.sft.init``: start from that trained policy (:func:`initial_policy`). ``vae``: the VAE checkpoint
    directory whose round trip ``rl.sft.decoded_fraction`` of each batch's frames go through (required exactly
    when that fraction is above 0); the training episodes are round-tripped once, before the first step.
    ``world_model``: with ``rl.sft.decoded_source=world_model``, the world model whose replays of the episodes'
    actions the decoded frames are (:func:`decoded_training_frames`).

    Raises:
      ValueError: ``vae`` missing or superfluous (:func:`sword_jax.rl.decoded_frames.require_vae`).
    """
    from sword_jax.rl.decoded_frames import require_vae

    demos, rl = list(demos), cfg.rl
    require_vae(rl.sft.decoded_fraction, vae, world_model, rl.sft.decoded_source)
    workdir = os.path.join(cfg.workdir, "rl")
    os.makedirs(workdir, exist_ok=True)
    rng = np.random.default_rng(cfg.seed)
    episodes = rl_data.successful(rl_data.load_episodes(demos, read=read_dataset))
    episodes = rl_data.EpisodeSet(episodes.frames, episodes.actions, episodes.proprio[..., : rl.proprio_dim],
                                  episodes.lengths, episodes.success, episodes.instructions)
    train_eps, held_out = rl_data.split_holdout(episodes, holdout, rng)
    train_eps = rl_data.per_task_subset(train_eps, rl.sft.episodes_per_task, rng)
    print(f"train_policy: {train_eps.num_episodes} demonstrations ({0 if held_out is None else held_out.num_episodes}"
          f" held out), {len(set(train_eps.instructions))} instructions")
    graphdef, params = initial_policy(cfg)
    start = time.time()
    decoded = decoded_training_frames(cfg, vae, train_eps, world_model=world_model) if vae else None
    params, history = train_sft(graphdef, params, rl, train_eps, held_out, seed=cfg.seed,
                                log=lambda m: print(m, flush=True),
                                checkpoint_dir=os.path.join(workdir, "sft_checkpoints"), mesh=shd.make_mesh(cfg.mesh),
                                rules=cfg.mesh.rules, decoded_frames=decoded, fit_proprio_stats=not rl.sft.init)
    path = os.path.join(workdir, "policy_sft")
    save_params(path, params, rl, kind="policy", step=rl.sft.steps)
    result = {"steps": rl.sft.steps, "demos": train_eps.num_episodes, "path": path,
              "final_loss": history[-1]["loss"], "seconds": round(time.time() - start, 1),
              "heldout_loss": history[-1].get("heldout_loss"), "heldout_token_accuracy":
              history[-1].get("heldout_token_accuracy")}
    if rl.sft.init:
        result["init"] = os.path.abspath(rl.sft.init)
    if vae:
        result["decoded"] = {"vae": os.path.abspath(vae), "fraction": rl.sft.decoded_fraction,
                             "source": rl.sft.decoded_source,
                             **({"world_model": os.path.abspath(world_model), "window": rl.sft_decoded_window}
                                if world_model else {})}
    if eval_episodes:
        from sim.lockstep import lockstep_evaluation

        result["eval"] = evaluate_in_sim(graphdef, params, rl, **lockstep_evaluation(
            cfg.sim.tasks, eval_episodes, resolution=cfg.sim.resolution, max_steps=cfg.sim.max_steps,
            renderer=renderer, workers=eval_workers))
        print("ground-truth success:", json.dumps(result["eval"]))
    with open(os.path.join(workdir, "sft_result.json"), "w") as f:
        json.dump(dict(result, history=history), f, indent=1)
    return result


def initial_policy(cfg):
    """``(graphdef, params)`` SFT starts from: the trained policy ``rl.sft.init`` (a ``train.train_policy``
    checkpoint directory or ``.npz``) when set, else a fresh one (seed ``cfg.seed``).

    Raises:
      FileNotFoundError: ``rl.sft.init`` does not exist.
      ValueError: it holds another architecture than ``cfg.rl`` builds.
    """
    source = cfg.rl.sft.init
    if not source:
        return build_policy(cfg.rl, seed=cfg.seed)
    _require_policy(source)
    graphdef, params = _load_policy(cfg, source)
    print(f"sft: fine-tuning the given policy {source}", flush=True)
    return graphdef, params


def _require_policy(source: str) -> None:
    if not os.path.exists(source):
        raise FileNotFoundError(f"rl.sft.init: no such policy {source!r} (a train_policy checkpoint directory or .npz)")


def _load_policy(cfg, source: str, path: str = ""):
    """``(graphdef, params)``: the policy ``source`` (read from ``path``, a copy of it, when given) loaded into
    ``cfg.rl``'s policy; a ValueError naming ``source`` when it holds another kind or architecture."""
    graphdef, params = build_policy(cfg.rl, seed=cfg.seed)
    try:
        params, _ = load_params(path or source, params, kind="policy")
    except ValueError as err:  # CheckpointError (another config) included
        raise ValueError(f"rl.sft.init: {source} does not load into this config's policy: {err}") from err
    return graphdef, params


def decoded_training_frames(cfg, vae: str, episodes: rl_data.EpisodeSet, *, world_model: str = "") -> np.ndarray:
    """``episodes.frames`` round-tripped through the VAE checkpoint ``vae`` (:func:`sword_jax.load.experiment_vae`
    with ``cfg.vae``), episode by episode (:func:`sword_jax.rl.decoded_frames.round_trip_episodes`); with
    ``world_model`` (``rl.sft.decoded_source=world_model``) the frames that world model, decoded by that VAE, shows
    when each episode's actions are replayed in windows of ``rl.sft_decoded_window`` actions from its real frames
    (:func:`sword_jax.rl.imagined_frames.imagined_episode_frames`, the simulator GRPO builds)."""
    from sword_jax.load import experiment_vae
    from sword_jax.rl.decoded_frames import round_trip_episodes

    start = time.time()
    # beside the world model, on its mesh, where the replay's steps read both
    vae_graphdef, vae_state = experiment_vae(cfg, vae, mesh=shd.make_mesh(cfg.mesh) if world_model else None)
    if world_model:
        return imagined_training_frames(cfg, (vae_graphdef, vae_state), world_model, episodes)
    decoded = round_trip_episodes(vae_graphdef, vae_state, episodes.frames, episodes.lengths,
                                  log=lambda m: print(m, flush=True))
    print(f"decoder-aware SFT: {episodes.num_episodes} episodes round-tripped through {vae} in "
          f"{time.time() - start:.0f}s; {cfg.rl.sft.decoded_fraction:.0%} of each batch reads them", flush=True)
    return decoded


def imagined_training_frames(cfg, vae: tuple, world_model: str, episodes: rl_data.EpisodeSet) -> np.ndarray:
    """:func:`decoded_training_frames` from the world model ``world_model``: its simulator as GRPO builds it
    (:func:`sword_jax.pipeline.grpo.setup_from_weights`: ``rl.imagined``'s precision, decoder and actions per
    decision; proprio as the episodes carry it), each episode replayed window by window from its real frames."""
    from sword_jax.load import experiment_world_model
    from sword_jax.pipeline.grpo import setup_from_weights
    from sword_jax.rl.imagined_frames import imagined_episode_frames

    rl, start = cfg.rl, time.time()
    if episodes.frames.shape[2] != cfg.data.image_size:
        raise ValueError(f"rl.sft.decoded_source=world_model: the demonstrations are {episodes.frames.shape[2]} px "
                         f"but the world model's frames are data.image_size={cfg.data.image_size}; render them at "
                         "that size (sim.resolution)")
    setup = setup_from_weights(cfg, rl, None, world_model=experiment_world_model(cfg, world_model), vae=vae,
                               detector=(None, None))
    window = rl.sft_decoded_window
    frames = imagined_episode_frames(setup.sim, setup.encode, episodes, window=window,
                                     key=jax.random.key(cfg.seed), num_context=cfg.data.context_frames //
                                     cfg.vae.temporal_factor, frames_per_latent=cfg.vae.temporal_factor,
                                     max_instruction_bytes=rl.policy.max_instruction_bytes,
                                     log=lambda m: print(m, flush=True), encode_prefix=setup.encode_prefix)
    print(f"decoder-aware SFT: {episodes.num_episodes} episodes replayed in {world_model} in windows of {window} "
          f"actions in {time.time() - start:.0f}s; {rl.sft.decoded_fraction:.0%} of each batch reads them", flush=True)
    return frames
