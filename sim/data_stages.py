"""Pipeline glue between the simulator's episodes, the VAE, style augmentation and evaluation.

Episodes are fixed length (the expert keeps moving after success) and cut to
``data.episode_frames`` frames; shorter ones are refused, never padded. Style augmentation is applied as pre-encoded styled copies: each
training episode is encoded raw plus ``augment.styled_copies`` times in training styles (see
:mod:`sword_jax.augment.pipeline` for why copies rather than per-step augmentation). Held-out
episodes make LIBERO-Original (raw) and LIBERO-Mixed (half in held-out styles).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence

import jax
import numpy as np

from sword_jax.rng import stream_key, stream_seed
from sword_jax.pipeline.stages import Context, cpu_workers


def episode_steps(cfg) -> int:
    """Steps of the pipeline's fixed-length expert episodes (never fewer than the world model's frames)."""
    return max(cfg.sim.episode_steps, cfg.data.episode_frames, cfg.eval.horizon_frames)


def generate_expert_data(ctx: Context) -> dict:
    """Fixed-length expert episodes for training (``train`` initial states) and evaluation (``heldout``).

    The expert keeps moving after success, so world-model segments and scored windows hold no
    padding; behaviour cloning reads the same file up to each demo's ``first_success``.

    The two files' initial states are checked disjoint (and both are disjoint from the policy's 50
    evaluation states per task by construction of ``sim.tasks.split_init_states``).
    """
    from sim import tasks
    from sim.datagen import GenDataConfig, generate
    from sim.dataset import read_dataset

    cfg = ctx.cfg
    results, init = {}, {}
    heldout_per_task = max(1, -(-cfg.eval.num_episodes // len(cfg.sim.tasks)))
    for split, per_task in (("train", cfg.sim.episodes_per_task), ("heldout", heldout_per_task)):
        seed = stream_seed(cfg.seed, f"data/{split}_episodes")  # expert-noise stream of each file
        path = ctx.path("data", f"{split}.hdf5")
        gen = GenDataConfig(out=path, tasks=tuple(cfg.sim.tasks), episodes=per_task, backend=cfg.sim.backend,
                            resolution=cfg.data.image_size, noise=cfg.sim.expert_noise,
                            noisy_share=cfg.sim.noisy_share, seed=seed, max_steps=episode_steps(cfg),
                            stop_at_success=False, wrist_camera=cfg.sim.wrist_camera, overwrite=True,
                            renderer="jax",  # one look on every backend (and no GL context per process)
                            init_split=split, init_seed=cfg.sim.init_seed)
        generate(gen, progress=ctx.is_main, workers=cpu_workers())
        _, episodes = read_dataset(path)
        init[split] = {task: start_qpos(episodes, task) for task in cfg.sim.tasks}
        success = sum(bool(e.rewards.max() > 0) for e in episodes) / max(len(episodes), 1)
        results[split] = {"path": path, "episodes": len(episodes), "success_rate": success}
    for task in cfg.sim.tasks:
        tasks.assert_disjoint(init["heldout"][task], init["train"][task], f"task {task}: held-out vs training episodes")
    results["demos"] = _policy_demos(ctx, cfg)
    if cfg.data.exploration_episodes_per_task:
        results["exploration"] = _exploration_episodes(ctx, cfg)
    return results


def _exploration_episodes(ctx: Context, cfg) -> dict:
    """``data.exploration_episodes_per_task`` fixed-length expert episodes per task with time-correlated noise on the
    motion (executed and recorded), from the train split after the world model's episodes and the demonstrations,
    for the world model's training data (``exploration.hdf5``)."""
    from sim.datagen import GenDataConfig, generate
    from sim.dataset import read_dataset

    path = ctx.path("data", "exploration.hdf5")
    after = cfg.sim.episodes_per_task + (cfg.rl.sft.episodes_per_task or cfg.sim.episodes_per_task)
    gen = GenDataConfig(out=path, tasks=tuple(cfg.sim.tasks), episodes=cfg.data.exploration_episodes_per_task,
                        backend=cfg.sim.backend, resolution=cfg.data.image_size, noise=cfg.data.exploration_noise,
                        noisy_share=1.0, noise_correlation=cfg.data.exploration_correlation,
                        seed=stream_seed(cfg.seed, "data/exploration_episodes"), max_steps=episode_steps(cfg),
                        stop_at_success=False, wrist_camera=cfg.sim.wrist_camera, overwrite=True, renderer="jax",
                        init_split="train", init_start=after, init_seed=cfg.sim.init_seed)
    generate(gen, progress=ctx.is_main, workers=cpu_workers())
    _, episodes = read_dataset(path)
    success = sum(bool(e.rewards.max() > 0) for e in episodes) / max(len(episodes), 1)
    return {"path": path, "episodes": len(episodes), "success_rate": success}


def _policy_demos(ctx: Context, cfg) -> dict:
    """Demonstrations for the policy and the success detector: episodes that end at their first
    success (within ``sim.max_steps``), from the train split after the world model's episodes."""
    from sim.datagen import GenDataConfig, generate
    from sim.dataset import read_dataset

    path = ctx.path("data", "demos.hdf5")
    per_task = cfg.rl.sft.episodes_per_task or cfg.sim.episodes_per_task
    gen = GenDataConfig(out=path, tasks=tuple(cfg.sim.tasks), episodes=per_task, backend=cfg.sim.backend,
                        resolution=cfg.data.image_size, noise=cfg.sim.expert_noise,
                        noisy_share=cfg.sim.noisy_share, seed=stream_seed(cfg.seed, "data/policy_demos"),
                        max_steps=cfg.sim.max_steps,
                        stop_at_success=True, wrist_camera=False, overwrite=True, renderer="jax",
                        init_split="train", init_start=cfg.sim.episodes_per_task, init_seed=cfg.sim.init_seed)
    generate(gen, progress=ctx.is_main, workers=cpu_workers())
    _, episodes = read_dataset(path)
    success = sum(bool(e.rewards.max() > 0) for e in episodes) / max(len(episodes), 1)
    return {"path": path, "episodes": len(episodes), "success_rate": success}


def start_qpos(episodes, task: int) -> np.ndarray:
    """(N, nq) qpos of the initial states (after settling) of ``task``'s episodes."""
    from sim import scene

    nq = scene.build_model().nq
    return np.asarray([e.init_state[1:1 + nq] for e in episodes if e.task_id == task], np.float64).reshape(-1, nq)


def fixed_length(episodes, num_frames: int) -> list:
    """The first ``num_frames`` steps of every episode, with the executed actions as ``actions``.

    World-model frames follow the actions that were executed (noisy ones for DART demos), so
    those condition the world model. An episode shorter than ``num_frames`` raises: holding its
    last frame would feed the world model padding (generate with ``sim.episode_steps``).
    """
    import dataclasses

    out = []
    for episode in episodes:
        if episode.num_samples < num_frames:
            raise ValueError(f"episode of task {episode.task_id} has {episode.num_samples} < {num_frames} steps: "
                             "generate fixed-length episodes (train.gen_data without --stop-at-success, "
                             "--max-steps >= data.episode_frames) instead of padding")
        if episode.executed_actions is not None:
            episode = dataclasses.replace(episode, actions=episode.executed_actions, executed_actions=None)
        cut = slice(0, num_frames)
        episode = dataclasses.replace(episode, **{
            f.name: getattr(episode, f.name)[cut] for f in dataclasses.fields(episode)
            if isinstance(getattr(episode, f.name), np.ndarray) and f.name != "init_state"})
        if episode.first_success is not None and episode.first_success >= num_frames:
            episode = dataclasses.replace(episode, first_success=-1)
        out.append(episode)
    return out


def load_episodes(path: str | list[str], num_frames: int):
    """``(sim episodes, augment.Episodes)`` of LIBERO-layout file(s), in order, fixed to ``num_frames``."""
    from sim.dataset import read_dataset
    from sword_jax.augment.episodes import episodes_from_sim

    episodes = [e for p in ([path] if isinstance(path, str) else path) for e in read_dataset(p)[1]]
    episodes = fixed_length(episodes, num_frames)
    return episodes, episodes_from_sim(episodes, num_frames=num_frames)


def _vae(ctx: Context):
    from sword_jax.load import load_vae_params

    return load_vae_params(ctx.cfg.vae, ctx.results["vae"]["path"])


def styled_copies(cfg) -> int:
    """Styled copies encoded per training episode beside the raw one (0 with ``augment.enabled`` off)."""
    return cfg.augment.styled_copies if cfg.augment.enabled and cfg.augment.styled_copies > 0 else 0


def _encode_frames(encode, frames: np.ndarray, batch_size: int) -> np.ndarray:
    """Latents of uint8-range ``frames`` [N, T, H, W, 3] in [0, 1], ``batch_size`` episodes per call."""
    return np.concatenate([np.asarray(encode(frames[start:start + batch_size] * np.float32(2.0) - np.float32(1.0)))
                           for start in range(0, len(frames), max(batch_size, 1))])


# what the latents' ``sources`` say of each training episode
SOURCES = {"expert": 0, "policy": 1, "exploration": 2}


def encode_episode_latents(cfg, vae_graphdef, vae_state, files: Sequence[str],
                           kinds: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """The world model's training latents of the episodes in ``files``, as the pipeline's latents stage writes them.

    Every episode is cut to ``data.episode_frames`` frames and encoded raw, then ``augment.styled_copies`` more
    times in training styles (stream ``augment/styled_copies`` of ``cfg.seed``) where ``augment.enabled``.

    Args:
      cfg: the experiment config (``data``, ``vae.batch_size``, ``augment``, ``seed``).
      vae_graphdef: the VAE's graph definition.
      vae_state: its weights (:func:`sword_jax.load.load_vae_params`).
      files: LIBERO-layout episode files; the first holds the expert's episodes, the others the supervised
        policy's rollouts unless ``kinds`` says otherwise.
      kinds: per file its episodes' source (:data:`SOURCES`); default the expert's for the first, the policy's
        for the others.

    Returns:
      ``latents`` [E, L, h, w, c] float32, ``actions`` [E, T, A] float32 and ``sources`` [E] uint8 (0 the expert's,
      1 the policy's, 2 the exploring expert's): the raw episodes in file order, then each one's styled copies after
      them (copy-major within an episode), so E = episodes x (1 + styled copies).
    """
    from sim.dataset import read_info
    from sword_jax.augment.pipeline import encode_styled_copies, seg_classes_from_config
    from sword_jax.vae import api as vae_api

    files = list(files)
    kinds = list(kinds) if kinds is not None else ["expert"] + ["policy"] * (len(files) - 1)
    if len(kinds) != len(files) or set(kinds) - set(SOURCES):
        raise ValueError(f"latents: kinds {kinds} must name one of {sorted(SOURCES)} for each of the {len(files)} files")
    _, episodes = load_episodes(files, cfg.data.episode_frames)
    encode = vae_api.encoder(vae_graphdef, vae_state)  # the weights are an argument of the jit, not baked-in constants
    latents, actions = [_encode_frames(encode, episodes.frames, cfg.vae.batch_size)], [episodes.actions]
    copies = styled_copies(cfg)
    if copies:
        styled = encode_styled_copies(episodes, copies, stream_key(jax.random.key(cfg.seed), "augment/styled_copies"),
                                      encode, intensity=cfg.augment.intensity,
                                      classes=seg_classes_from_config(cfg.augment), fov_deg=cfg.augment.fov_deg)
        styled_latents, styled_actions, _ = styled.flatten()
        latents.append(styled_latents)
        actions.append(styled_actions)
    # which episodes are the expert's (0), the policy's rollouts (1) and the exploring expert's (2): the raw ones in
    # file order, then each one's styled copies after it (the trainer measures the policy's training segments apart)
    raw = np.concatenate([np.full(read_info(f).num_demos, SOURCES[kind], np.uint8) for f, kind in zip(files, kinds)])
    if len(raw) != episodes.num:
        raise ValueError(f"latents: the files {files} list {len(raw)} episodes, {episodes.num} were read")
    return {"latents": np.concatenate(latents).astype(np.float32),
            "actions": np.concatenate(actions).astype(np.float32),
            "sources": np.concatenate([raw, np.repeat(raw, copies)])}


def latents_summary(cfg, arrays: dict[str, np.ndarray]) -> dict:
    """What :func:`encode_episode_latents`' ``arrays`` hold: ``episodes`` (E), ``raw_episodes``, ``policy_episodes``
    (and ``exploration_episodes`` where there are any; styled copies counted), ``styled_copies`` and
    ``latent_shape`` ([L, h, w, c])."""
    latents, copies, sources = arrays["latents"], styled_copies(cfg), arrays["sources"]
    exploring = int(np.sum(sources == SOURCES["exploration"]))
    return {"episodes": int(latents.shape[0]), "raw_episodes": len(latents) // (1 + copies),
            "policy_episodes": int(np.sum(sources == SOURCES["policy"])),
            **({"exploration_episodes": exploring} if exploring else {}), "styled_copies": copies,
            "latent_shape": list(latents.shape[1:])}


def encode_training_latents(ctx: Context) -> dict:
    """Encodes the training episodes (raw + styled copies) to ``latents.npz`` for the world model: the
    expert's, then the supervised policy's own rollouts where the pipeline made them (``policy_data``), then the
    exploring expert's (``data.exploration_episodes_per_task``); and the
    held-out expert episodes (raw) to ``heldout_latents.npz`` for its held-out evaluation."""
    from sword_jax.vae import api as vae_api

    cfg = ctx.cfg
    files, kinds = [ctx.results["data"]["train"]["path"]], ["expert"]
    if ctx.results.get("policy_data", {}).get("path"):
        files.append(ctx.results["policy_data"]["path"])
        kinds.append("policy")
    if ctx.results["data"].get("exploration", {}).get("path"):
        files.append(ctx.results["data"]["exploration"]["path"])
        kinds.append("exploration")
    graphdef, state = _vae(ctx)
    training = encode_episode_latents(cfg, graphdef, state, files, kinds)
    path = ctx.path("data", "latents.npz")
    np.savez(path, **training)
    encode = vae_api.encoder(graphdef, state)

    def encoded(frames: np.ndarray) -> np.ndarray:
        return _encode_frames(encode, frames, cfg.vae.batch_size).astype(np.float32)

    # the held-out expert episodes, unstyled, for the world model's held-out evaluation (trainer.eval_every)
    _, held = load_episodes(ctx.results["data"]["heldout"]["path"], cfg.data.episode_frames)
    heldout_path = ctx.path("data", "heldout_latents.npz")
    arrays = {"latents": encoded(held.frames), "actions": held.actions.astype(np.float32)}
    # and the supervised policy's held-out rollouts (policy_data), the evaluation's "policy" segments
    policy_held = ctx.results.get("policy_data", {}).get("heldout", {}).get("path")
    if policy_held:
        _, rolled = load_episodes(policy_held, cfg.data.episode_frames)
        arrays.update(policy_latents=encoded(rolled.frames), policy_actions=rolled.actions.astype(np.float32))
    np.savez(heldout_path, **arrays)
    return {"path": path, **latents_summary(cfg, training), "files": files, "heldout_path": heldout_path,
            "heldout_episodes": int(held.num),
            **({"heldout_policy_episodes": int(rolled.num)} if policy_held else {})}


def write_eval_splits(ctx: Context) -> dict[str, str]:
    """LIBERO-Original / LIBERO-Mixed from the held-out episodes, as ``.npz`` files for ``train.evaluate_world_model``
    (with each episode's true state ``targets`` and ``rewards`` for the action-following metrics)."""
    from sword_jax.augment.eval_splits import build_eval_splits
    from sword_jax.augment.pipeline import seg_classes_from_config
    from sim.probe_targets import episode_targets

    cfg = ctx.cfg
    sim_episodes, episodes = load_episodes(ctx.results["data"]["heldout"]["path"], cfg.data.episode_frames)
    episodes = episodes.take(np.arange(min(episodes.num, cfg.eval.num_episodes)))
    splits = build_eval_splits(episodes, seed=stream_seed(cfg.seed, "augment/eval_splits"),
                               mixed_fraction=cfg.augment.mixed_fraction, intensity=cfg.augment.intensity,
                               classes=seg_classes_from_config(cfg.augment), fov_deg=cfg.augment.fov_deg)
    splits.write_manifest(ctx.path("eval_splits", "manifest.json"))
    paths = {}
    for name, split in (("original", splits.original), ("mixed", splits.mixed)):
        if name not in cfg.eval.splits:
            continue
        paths[name] = ctx.path("eval_splits", f"{name}.npz")
        np.savez(paths[name], frames=split.frames.astype(np.float32), actions=split.actions.astype(np.float32),
                 episode_ids=split.episode_ids, styled=split.styled,
                 targets=np.stack([episode_targets(sim_episodes[i]) for i in split.episode_ids]),
                 rewards=np.stack([sim_episodes[i].rewards for i in split.episode_ids]).astype(np.float32))
    return paths


def read_eval_results(out_dir: str) -> dict:
    """The overall metrics per split and model from ``train.evaluate_world_model``'s ``results.json``."""
    path = os.path.join(out_dir, "results.json")
    if not os.path.exists(path):
        return {}
    with open(path) as f:
        results = json.load(f)
    return {split: {model: r["overall"] for model, r in per.items()} for split, per in results.get("models", {}).items()}


def generate_policy_rollouts(ctx: Context) -> dict:
    """Pipeline stage: ``data.policy_rollouts_per_task`` episodes per task of the supervised policy, as
    long as the world model's expert episodes, from the same training initial states; and
    ``data.heldout_policy_rollouts_per_task`` more from the held-out initial states (those of the held-out
    expert episodes, first), for the world model's held-out evaluation only (``heldout_path``).
    ``data.policy_rollout_workers`` processes record them (the same files for any number)."""
    import functools

    from sim.datagen import GenDataConfig
    from sim.policy_rollouts import write_policy_episodes
    from sword_jax.rl.env_rollout import make_act_fns
    from sword_jax.rl.params_io import load_params
    from sword_jax.rl.policy import build_policy

    cfg = ctx.cfg
    per_task, held_per_task = cfg.data.policy_rollouts_per_task, cfg.data.heldout_policy_rollouts_per_task
    summary: dict = {"path": "", "episodes": 0, "success_rate": 0.0}
    if per_task == 0 and held_per_task == 0:
        return summary
    graphdef, params = build_policy(cfg.rl, seed=cfg.seed)
    params, _ = load_params(ctx.results["sft_policy"]["path"], params, kind="policy")
    make_act = functools.partial(make_act_fns, graphdef, cfg.rl)  # built where the episodes are recorded

    def rollouts(name: str, episodes: int, split: str, stream: str) -> dict:
        gen = GenDataConfig(out=ctx.path("data", name), tasks=tuple(cfg.sim.tasks), episodes=episodes, backend="cpu",
                            resolution=cfg.data.image_size, max_steps=episode_steps(cfg), stop_at_success=False,
                            wrist_camera=False, overwrite=True, renderer="jax", init_split=split, init_start=0,
                            init_seed=cfg.sim.init_seed)
        made = write_policy_episodes(gen.out, make_act, params, cfg.rl, gen,
                                     key=stream_key(jax.random.key(cfg.seed), stream),
                                     workers=cfg.data.policy_rollout_workers)
        if ctx.is_main:
            print(f"[policy_data] {made['episodes']} policy episodes from {split} initial states "
                  f"({made['success_rate']:.0%} successful) -> {gen.out}", flush=True)
        return made

    if per_task:
        summary = rollouts("policy_rollouts.hdf5", per_task, "train", "data/policy_rollouts")
    if held_per_task:
        held = rollouts("policy_heldout.hdf5", held_per_task, "heldout", "data/policy_heldout")
        summary = {**summary, "heldout": {k: held[k] for k in ("path", "episodes", "success_rate")}}
    return summary
