"""The public API: a trained Sword world model for your own JAX code.

    import jax, sword_jax
    model = sword_jax.load_world_model("runs/sword-tiny")      # pipeline run, world-model work dir or checkpoint
    latents = sword_jax.encode(model, frames)                  # [B, 1+4k, H, W, 3] -> [B, 1+k, H/16, W/16, z]
    video = sword_jax.rollout(model, given, actions, key=jax.random.key(0))
    env = sword_jax.make_env(model, sword_jax.start_states(model, keyframes, instructions), reward_model=score)
    vec = sword_jax.make_vector_env(model, pool, num_envs=8, reward_model=score)   # gymnasium VectorEnv
    fast = sword_jax.load_world_model("runs/sword-tiny", light_decoder=True)   # + the run's light decoder
    env = sword_jax.make_env(fast, pool, reward_model=score, decoder="light")  # frames at its (the policy's) size

This module and the names ``sword_jax`` re-exports are the stable surface; everything else may change.

Conventions:
  * frames are channels-last ``[..., H, W, 3]``, float in [0, 1] (uint8 in [0, 255] is accepted);
    everything returned is float32. ``H = W = model.spec.image_size`` for the world model.
  * time: the VAE maps ``1 + 4k`` frames to ``1 + k`` latents (the first frame alone, then 4 frames
    per latent). A rollout is given the first frame and ``4 * spec.num_context`` context frames
    (``spec.given_frames`` in all) and predicts ``4 * spec.num_future`` frames per chunk.
  * actions: one per video frame, ``[B, T, spec.action_dim]`` in [-1, 1]; a rollout of ``n``
    chunks takes ``T = spec.given_frames + 4 * spec.num_future * n`` (frame ``t`` carries the action
    taken after it is seen, as in training).
  * randomness: every sampling function takes ``key`` (keyword-only); same key, same output.
  * :class:`LoadedWorldModel` is a pytree whose array leaves are the weights: pass it as an
    argument to your ``jax.jit`` (weights stay out of the compiled program's constants) and
    ``jax.vmap`` over your data, not over it.

The math lives in :mod:`sword_jax.world_model.rollout` (``rollout``, ``rollout_video``),
:mod:`sword_jax.vae.api` and :mod:`sword_jax.rl` (simulator, envs, GRPO); this module wires them to
a loaded checkpoint. Importing it runs nothing.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jaxtyping import Array, Float, Int

from sword_jax import load
from sword_jax.dit.config import DiTConfig
from sword_jax.load import CheckpointError
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.vae.config import VAEConfig
from sword_jax.world_model.config import DataConfig, FlowConfig

FRAME_RANGE_TOL = 1e-3

__all__ = [
    "CheckpointError", "LoadedWorldModel", "WorldModelSpec", "decode", "encode", "load_reward_model",
    "load_world_model", "learned_simulator", "make_env", "make_vector_env", "rollout", "rollout_latents",
    "start_states",
]


@dataclasses.dataclass(frozen=True)
class WorldModelSpec:
    """What a loaded world model was trained as (frozen, hashable: a static part of the pytree).

    Attributes:
      model / flow / vae: the DiT, flow-matching (sampler) and VAE config sections.
      image_size: frame height and width ``H = W``.
      num_context: context latents per chunk ``k`` (``4k`` context frames).
      num_future: latents predicted per chunk ``p`` (``4p`` frames per chunk).
      seed: the run's seed.
      name: the run's config name (e.g. ``sword-tiny``).
    """

    model: DiTConfig
    flow: FlowConfig
    vae: VAEConfig
    image_size: int
    num_context: int
    num_future: int
    seed: int = 0
    name: str = ""

    @property
    def action_dim(self) -> int:
        return self.model.action_dim

    @property
    def latent_size(self) -> int:
        """Latent height and width ``h = w = H / 16``."""
        return self.image_size // self.vae.spatial_factor

    @property
    def latent_dim(self) -> int:
        """Latent channels ``z``."""
        return self.vae.z_dim

    @property
    def given_frames(self) -> int:
        """Frames a pixel rollout is given: the first frame and ``4k`` context frames."""
        return 1 + self.vae.temporal_factor * self.num_context

    @property
    def frames_per_chunk(self) -> int:
        """Frames (and actions) each rollout chunk predicts, ``4p``."""
        return self.vae.temporal_factor * self.num_future

    def num_actions(self, num_chunks: int) -> int:
        """Per-frame actions a rollout of ``num_chunks`` chunks takes."""
        return self.given_frames + self.frames_per_chunk * num_chunks


@dataclasses.dataclass(frozen=True)
class LoadedFrom:
    """Where the pieces were read from ("" where absent)."""

    world_model: str
    step: int
    vae: str = ""
    reward_model: str = ""
    light_decoder: str = ""


@struct.dataclass
class LoadedWorldModel:
    """A trained world model (+ VAE, + reward model where the run has one, + light decoder if asked) as one pytree.

    Attributes:
      world_model_params: ``(params, buffers)`` pure dicts of the DiT world model (float32).
      vae_params: the VAE's ``nnx.State`` (None when loaded without a VAE: latent space only).
      reward_model: the run's success detector as a :class:`RewardModel` (frames -> [0, 1]), or None.
      world_model_graphdef / vae_graphdef: static graphs for ``nnx.merge``.
      spec: :class:`WorldModelSpec`. loaded_from: :class:`LoadedFrom`.
      light_decoder_params / light_decoder_graphdef: the light rollout decoder
        (:mod:`sword_jax.vae.light_decoder`) that the envs decode with under ``decoder="light"``, or None.

    The methods are the module's functions with the model bound (``model.rollout(...)`` is
    ``rollout(model, ...)``).
    """

    world_model_params: Any
    vae_params: Any
    reward_model: RewardModel | None
    world_model_graphdef: Any = struct.field(pytree_node=False)
    vae_graphdef: Any = struct.field(pytree_node=False)
    spec: WorldModelSpec = struct.field(pytree_node=False)
    loaded_from: LoadedFrom = struct.field(pytree_node=False)
    light_decoder_params: Any = None
    light_decoder_graphdef: Any = struct.field(pytree_node=False, default=None)

    def encode(self, frames):
        return encode(self, frames)

    def decode(self, latents):
        return decode(self, latents)

    def rollout(self, given_frames, actions, *, key, num_steps=None):
        return rollout(self, given_frames, actions, key=key, num_steps=num_steps)

    def rollout_latents(self, first_latent, context_latents, actions, *, key, num_steps=None):
        return rollout_latents(self, first_latent, context_latents, actions, key=key, num_steps=num_steps)


# ----------------------------------------------------------------------------------------- loading


def load_world_model(
    path: str,
    *,
    vae: str | None = None,
    reward_model: str | None = None,
    step: int | None = None,
    use_ema: bool = True,
    mesh: jax.sharding.Mesh | None = None,
    light_decoder: str | bool | None = None,
) -> LoadedWorldModel:
    """Loads a trained world model (and its VAE and reward model) for inference.

    Args:
      path: a pipeline work dir (``train.pipeline --workdir``: ``<dir>/world_model``,
        ``<dir>/vae_run/vae``, ``<dir>/rl/reward_model``), a world-model work dir
        (``train.train_world_model --workdir``), its ``checkpoints`` directory, or one step of it.
      vae: the VAE (``train.train_vae``'s work dir or its ``vae`` subdirectory, or an official Wan
        2.2 VAE ``.safetensors`` file). Default: the run's own, else the official weights the
        config names (``vae.checkpoint``), else none (latent space only: :func:`encode`,
        :func:`decode`, :func:`rollout` then raise).
      reward_model: a reward-model checkpoint (``train.train_reward``); default the run's own.
      step: the checkpoint step (default the newest).
      use_ema: the EMA weights where the run kept them.
      mesh: where the weights go (default unsharded on the first device; over a mesh you give, the
        world model is sharded by its logical axes and the VAE replicated).
      light_decoder: the light rollout decoder for the envs' frames (:func:`learned_simulator`'s
        ``decoder="light"``): ``train.train_light_decoder``'s work dir (or its ``checkpoints``), or True
        for the pipeline run's own ``<run>/light_decoder`` (trained when ``rl.imagined.decoder=light``).
        Default none. It must decode this world model's latents (channels, size, frames per latent).

    Raises:
      CheckpointError: a missing path, no checkpoint, a damaged one, or pieces that do not fit
        together (the message names the path).
    """
    workdir, run, step = load.find_run(path, step)
    checkpoints = os.path.join(workdir, "checkpoints")
    step = load.checkpoint_step(checkpoints, step)
    saved = load.read_run_config(workdir, step)
    missing = [name for name in ("model", "flow", "vae", "data") if not isinstance(saved.get(name), dict)]
    if missing:
        raise CheckpointError(f"{workdir}: the saved config lacks the sections {missing}")
    data = load.section_from_dict(DataConfig, saved["data"])
    vae_cfg = load.section_from_dict(VAEConfig, saved["vae"])
    spec = WorldModelSpec(
        model=load.section_from_dict(DiTConfig, saved["model"]), flow=load.section_from_dict(FlowConfig, saved["flow"]),
        vae=vae_cfg, image_size=data.image_size, num_context=data.context_frames // vae_cfg.temporal_factor,
        num_future=data.predict_frames // vae_cfg.temporal_factor,
        seed=int(saved.get("seed", 0)), name=str(saved.get("name", "")))
    graphdef, params, step = load.load_world_model_params(spec.model, checkpoints, seed=spec.seed, step=step,
                                                          use_ema=use_ema, mesh=mesh)
    vae_path = load.vae_dir(vae) if vae else (os.path.join(run, "vae_run", "vae") if run else "")
    if vae and not os.path.exists(vae_path):
        raise CheckpointError(f"VAE {vae} does not exist")
    vae_graphdef = vae_params = None
    if vae and os.path.isfile(vae_path):  # official Wan 2.2 weights (.safetensors)
        vae_graphdef, vae_params = load.load_vae_params(dataclasses.replace(spec.vae, checkpoint=vae_path), mesh=mesh)
    elif vae_path and os.path.isdir(vae_path):
        vae_graphdef, vae_params = load.load_vae_params(dataclasses.replace(spec.vae, checkpoint=""), vae_path,
                                                        mesh=mesh)
    elif spec.vae.checkpoint:
        vae_path = spec.vae.checkpoint
        vae_graphdef, vae_params = load.load_vae_params(spec.vae, mesh=mesh)
    else:
        vae_path = ""
    if reward_model is None and run and os.path.isdir(os.path.join(run, "rl", "reward_model")):
        reward_model = os.path.join(run, "rl", "reward_model")
    detector = load_reward_model(reward_model) if reward_model else None
    light_path = _light_decoder_dir(light_decoder, path, run)
    light_graphdef = light_params = None
    if light_path:
        light_graphdef, light_params, _ = load.load_light_decoder(
            light_path, z_dim=spec.latent_dim, latent_size=spec.latent_size,
            temporal_factor=spec.vae.temporal_factor, mesh=mesh)
    return LoadedWorldModel(params, vae_params, detector, graphdef, vae_graphdef, spec,
                            LoadedFrom(workdir, step, vae_path, reward_model or "", light_path), light_params,
                            light_graphdef)


def _light_decoder_dir(light_decoder: str | bool | None, path: str, run: str | None) -> str:
    """The light decoder's directory ("" for none); True: the pipeline run's own."""
    if light_decoder is None or light_decoder is False:
        return ""
    if light_decoder is not True:
        return str(light_decoder)
    if run is None:
        raise CheckpointError(f"light_decoder=True looks for the pipeline run's own <run>/light_decoder, and {path} "
                              "is not in a pipeline work dir: pass light_decoder=<train.train_light_decoder work dir>")
    if not os.path.isdir(os.path.join(run, "light_decoder", "checkpoints")):
        raise CheckpointError(f"{run} has no light decoder ({os.path.join(run, 'light_decoder')}: the pipeline trains "
                              "one with --rl.imagined.decoder=light; train.train_light_decoder makes one)")
    return os.path.join(run, "light_decoder")


def load_reward_model(path: str) -> RewardModel:
    """A success detector saved by ``train.train_reward`` (``<workdir>/rl/reward_model``), rebuilt
    from the RL config stored with it: ``score(frames [n, H, W, 3] in [0, 1]) -> [n]`` in [0, 1]."""
    from sword_jax.rl.reward_model import as_reward_model, build_detector

    graphdef, params, _ = load.load_rl_params(path, kind="reward_model", build=build_detector)
    return as_reward_model(graphdef, params)


# ---------------------------------------------------------------------------------- pure functions


def _frames_to_signed(frames: Array, name: str) -> Float[Array, "..."]:
    """[0, 1] float (or uint8) frames -> the VAE's [-1, 1] float32."""
    if frames.ndim < 3 or frames.shape[-1] != 3:
        raise ValueError(f"{name} must be channels-last [..., H, W, 3], got shape {frames.shape}")
    if frames.dtype == jnp.uint8:
        return frames.astype(jnp.float32) / jnp.float32(127.5) - jnp.float32(1.0)
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        raise ValueError(f"{name} must be float in [0, 1] or uint8, got dtype {frames.dtype}")
    return frames.astype(jnp.float32) * jnp.float32(2.0) - jnp.float32(1.0)


def check_frames(frames: Any, name: str = "frames") -> None:
    """Host check of concrete frames: finite, and in [0, 1] (floats). Raises ValueError.

    The public functions call it on concrete inputs; under your own jit (tracers) call it first.
    """
    if isinstance(frames, jax.core.Tracer):
        return
    values = np.asarray(jax.device_get(frames))
    if values.dtype == np.uint8:
        return
    values = values.astype(np.float32)
    if not np.isfinite(values).all():
        raise ValueError(f"{name} contain {int((~np.isfinite(values)).sum())} NaN/Inf values")
    if values.size and (values.min() < -FRAME_RANGE_TOL or values.max() > 1 + FRAME_RANGE_TOL):
        raise ValueError(f"{name} must lie in [0, 1] (got min {values.min():.4g}, max {values.max():.4g}); "
                         "pass uint8 pixels as they are, or divide them by 255")


def _check_latents(latents: Any, name: str = "latents") -> None:
    if not isinstance(latents, jax.core.Tracer):
        from sword_jax.vae.api import check_latent_values

        check_latent_values(latents, name=name)


def _require_vae(model: LoadedWorldModel, what: str) -> None:
    if model.vae_graphdef is None:
        raise ValueError(f"{what} needs the VAE, and this world model was loaded without one "
                         "(pass vae=<train.train_vae work dir> to load_world_model)")


def _check_actions(model: LoadedWorldModel, actions: Array, batch: int) -> None:
    if actions.ndim != 3 or actions.shape[0] != batch or actions.shape[2] != model.spec.action_dim:
        raise ValueError(f"actions must be [B={batch}, T, {model.spec.action_dim}], got shape {actions.shape}")


@jax.jit
def _encode(model: LoadedWorldModel, frames: Array) -> Array:
    from sword_jax.vae import api as vae_api

    video = _frames_to_signed(frames, "frames")
    return vae_api.encode(model.vae_graphdef, model.vae_params, video, check_values=False)


def encode(model: LoadedWorldModel, frames: Float[Array, "b t hh ww 3"]) -> Float[Array, "b l h w z"]:
    """Encodes video to the world model's latents (the VAE's normalised posterior means).

    Args:
      model: a loaded world model with a VAE.
      frames: ``[B, 1 + 4k, H, W, 3]`` float in [0, 1] (or uint8), ``H, W`` multiples of 16.

    Returns:
      ``[B, 1 + k, H/16, W/16, z]`` float32.
    """
    _require_vae(model, "encode")
    check_frames(frames)
    return _encode(model, frames)


@jax.jit
def _decode(model: LoadedWorldModel, latents: Array) -> Array:
    from sword_jax.vae import api as vae_api

    video = vae_api.decode(model.vae_graphdef, model.vae_params, latents.astype(jnp.float32), clamp=True,
                           check_values=False)
    return (video + jnp.float32(1.0)) * jnp.float32(0.5)


def decode(model: LoadedWorldModel, latents: Float[Array, "b l h w z"]) -> Float[Array, "b t hh ww 3"]:
    """Decodes latents ``[B, 1 + k, h, w, z]`` to video ``[B, 1 + 4k, 16h, 16w, 3]`` float32 in [0, 1]."""
    _require_vae(model, "decode")
    _check_latents(latents)
    return _decode(model, latents)


@functools.partial(jax.jit, static_argnames=("num_steps",))
def _rollout_latents(model, first_latent, context_latents, actions, key, num_steps):
    from sword_jax.world_model import rollout as wm_rollout

    spec = model.spec
    round_trip = None
    if spec.flow.pixel_round_trip:  # WoVR runs re-encode each decoded chunk as the next context
        round_trip = wm_rollout.make_pixel_round_trip(model.vae_graphdef, model.vae_params, spec.num_context)
    return wm_rollout.rollout(model.world_model_graphdef, model.world_model_params, first_latent, context_latents,
                              actions.astype(jnp.float32), key=key, cfg=spec.flow, num_future=spec.num_future,
                              num_steps=num_steps, round_trip=round_trip)


def rollout_latents(
    model: LoadedWorldModel,
    first_latent: Float[Array, "b 1 h w z"],
    context_latents: Float[Array, "b k h w z"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    num_steps: int | None = None,
) -> Float[Array, "b n h w z"]:
    """Imagines in latent space: the world model's autoregressive rollout (one ``lax.scan``).

    Args:
      model: a loaded world model.
      first_latent: the episode's first-frame latent ``[B, 1, h, w, z]`` (or ``[B, h, w, z]``).
      context_latents: the ``k = spec.num_context`` latents after it ``[B, k, h, w, z]``.
      actions: per-frame actions ``[B, 1 + 4k + 4pn, a]`` in [-1, 1] (``spec.num_actions(n)``).
      key: sampling key.
      num_steps: Euler steps per chunk (default ``spec.flow.sample_steps``).

    Returns:
      The ``p n`` predicted latents ``[B, p n, h, w, z]`` float32 (``p = spec.num_future``).
    """
    if model.spec.flow.pixel_round_trip:
        _require_vae(model, "a WoVR (flow.pixel_round_trip) rollout")
    _check_actions(model, actions, first_latent.shape[0])
    _check_latents(first_latent, "first_latent")
    _check_latents(context_latents, "context_latents")
    return _rollout_latents(model, first_latent, context_latents, actions, key, num_steps)


@functools.partial(jax.jit, static_argnames=("num_steps",))
def _rollout(model, given_frames, actions, key, num_steps):
    from sword_jax.world_model import rollout as wm_rollout

    spec = model.spec
    video, _, _ = wm_rollout.rollout_video(
        model.world_model_graphdef, model.world_model_params, model.vae_graphdef, model.vae_params,
        _frames_to_signed(given_frames, "given_frames"), actions.astype(jnp.float32), key=key, cfg=spec.flow,
        num_future=spec.num_future, num_steps=num_steps)
    return (video + jnp.float32(1.0)) * jnp.float32(0.5)


def rollout(
    model: LoadedWorldModel,
    given_frames: Float[Array, "b g hh ww 3"],
    actions: Float[Array, "b t a"],
    *,
    key: jax.Array,
    num_steps: int | None = None,
) -> Float[Array, "b t hh ww 3"]:
    """Imagines video: encode the given frames, roll the world model out, decode (one jit).

    Args:
      model: a loaded world model with a VAE.
      given_frames: the first frame and the context frames, ``[B, spec.given_frames, H, W, 3]``
        float in [0, 1] (or uint8).
      actions: per-frame actions ``[B, T, a]`` in [-1, 1], ``T = spec.num_actions(n)`` for ``n``
        chunks (the given frames' actions first).
      key: sampling key.
      num_steps: Euler steps per chunk (default ``spec.flow.sample_steps``).

    Returns:
      ``[B, T, H, W, 3]`` float32 in [0, 1]: the given frames as the VAE reconstructs them, then
      the ``T - spec.given_frames`` predicted frames.
    """
    _require_vae(model, "rollout")
    spec = model.spec
    if given_frames.ndim != 5 or given_frames.shape[1] != spec.given_frames:
        raise ValueError(f"given_frames must be [B, {spec.given_frames}, H, W, 3] (the first frame and "
                         f"{spec.given_frames - 1} context frames), got shape {given_frames.shape}")
    _check_actions(model, actions, given_frames.shape[0])
    check_frames(given_frames, "given_frames")
    return _rollout(model, given_frames, actions, key, num_steps)


# ------------------------------------------------------------------------------------- environments


def start_states(
    model: LoadedWorldModel,
    keyframes: Float[Array, "n hh ww 3"],
    instructions: Sequence[str] | Int[Array, "n l"],
    *,
    proprio: Float[Array, "n p"] | None = None,
    first_frames: Float[Array, "n hh ww 3"] | None = None,
    history: Float[Array, "n f hh ww 3"] | None = None,
    history_actions: Float[Array, "n s a"] | None = None,
    max_instruction_bytes: int = 96,
    proprio_dim: int = 8,
) -> StartState:
    """Start states for the learned simulator (host-side helper; encodes with the VAE).

    Args:
      model: a loaded world model with a VAE.
      keyframes: the frames episodes start from, ``[N, H, W, 3]`` in [0, 1] (or uint8).
      instructions: N instruction strings, or their byte tokens ``[N, L]`` int32
        (:func:`sword_jax.rl.policy.tokenize_instructions`).
      proprio: the proprioceptive state at each keyframe ``[N, P]`` (default zeros; the world
        model cannot report proprio, its observations mark it invalid).
      first_frames / history: the episode's first frame ``[N, H, W, 3]`` and the ``4 (k + 1)``
        frames up to and including the keyframe ``[N, 4(k+1), H, W, 3]``: the context then holds
        the real motion that led to the keyframe. Without them the keyframe is held still.
      history_actions: with ``history``, the actions of the first frame and the ``4k`` context
        frames ``[N, 1 + 4k, a]`` (default zeros).
      max_instruction_bytes: token length when ``instructions`` are strings.
      proprio_dim: size of the default proprio.

    Returns:
      A :class:`StartState` with leading axis N: ``frame`` float32 [0, 1], ``latents``
      ``[N, 1 + k, h, w, z]`` (or ``(latents, actions)`` with ``history_actions``).
    """
    from sword_jax.rl.policy import tokenize_instructions
    from sword_jax.rl.world_model_sim import encode_history, encode_keyframes

    _require_vae(model, "start_states")
    check_frames(keyframes, "keyframes")
    unit = lambda x: (_frames_to_signed(jnp.asarray(x), "frames") + 1.0) * 0.5  # noqa: E731 - uint8 or [0, 1]
    frames = unit(keyframes)
    if frames.ndim != 4:
        raise ValueError(f"keyframes must be [N, H, W, 3], got shape {frames.shape}")
    n, k = frames.shape[0], model.spec.num_context
    if isinstance(instructions, str) or not hasattr(instructions, "shape"):
        if isinstance(instructions, str) or len(instructions) != n:
            raise ValueError(f"give one instruction per keyframe ({n}), got {instructions!r}")
        tokens = jnp.asarray(tokenize_instructions(list(instructions), max_instruction_bytes))
    else:
        tokens = jnp.asarray(instructions, jnp.int32)
        if tokens.ndim != 2 or tokens.shape[0] != n:
            raise ValueError(f"instruction tokens must be [N={n}, L], got shape {tokens.shape}")
    proprio = jnp.zeros((n, proprio_dim), jnp.float32) if proprio is None else jnp.asarray(proprio, jnp.float32)
    if proprio.ndim != 2 or proprio.shape[0] != n:
        raise ValueError(f"proprio must be [N={n}, P], got shape {proprio.shape}")
    if history is None:
        latents: Any = encode_keyframes(model.vae_graphdef, model.vae_params, frames, num_context=k)
    else:
        if first_frames is None:
            raise ValueError("history needs first_frames (each episode's first frame)")
        check_frames(history, "history")
        latents = encode_history(model.vae_graphdef, model.vae_params, unit(first_frames), unit(history),
                                 num_context=k)
        if history_actions is not None:
            latents = (latents, jnp.asarray(history_actions, jnp.float32))
    return StartState(frames, proprio, tokens, latents)


def learned_simulator(
    model: LoadedWorldModel,
    *,
    sample_steps: int | None = None,
    execute_latents: int | None = None,
    proprio_dim: int = 8,
    proprio_reckoning: Any = None,
    precision: str = "fast",
    decoder: str = "full",
) -> LearnedSimulator:
    """The world model + VAE as a :class:`~sword_jax.rl.learned_simulator.LearnedSimulator` (one trajectory).

    ``sim.init(start) -> state``; ``sim.step(state, chunk [4p, a], key=key) -> (state, frames
    [E, S, S, 3])`` with ``E = 4 * execute_latents`` (default the whole chunk) and ``S = sim.frame_size``
    (``H``, or the light decoder's size); ``sim.observe(state) -> (proprio, valid)``. The GRPO step
    (:func:`sword_jax.rl.grpo.make_grpo_step`) and the envs below take it; its weights are pytree leaves,
    so pass it to jit as an argument.

    Args:
      sample_steps: Euler steps per chunk (default ``spec.flow.sample_steps``).
      execute_latents: predicted latents executed per step before the policy re-plans.
      proprio_dim: size of the proprio observation.
      proprio_reckoning: a :class:`sword_jax.rl.proprio_reckoning.ReckoningConfig` (the
        environment's action convention) to dead-reckon proprio from the executed actions, reported
        valid; None (default) reports it invalid.
      precision: ``fast`` (default: bfloat16 decode, weights in the compute dtype) or ``float32`` (the
        exact decode), as GRPO's ``rl.imagined.sim_precision`` (:mod:`sword_jax.rl.sim_builder`, the one
        builder GRPO and the benchmark use too).
      decoder: what turns the predicted latents into frames, as GRPO's ``rl.imagined.decoder``: ``full``
        (default: the VAE's decoder, ``H x H`` frames) or ``light`` (the light decoder loaded with
        ``load_world_model(..., light_decoder=...)``, frames at its own size, a small fraction of the work).

    Raises:
      ValueError: an unknown ``decoder``, or ``light`` for a model loaded without a light decoder.
    """
    from sword_jax.rl.config import DECODERS
    from sword_jax.rl.sim_builder import build_simulator

    _require_vae(model, "the learned simulator")
    if decoder not in DECODERS:
        raise ValueError(f"decoder must be one of {DECODERS}, got {decoder!r}")
    light_decoder = None
    if decoder == "light":
        if model.light_decoder_graphdef is None:
            raise ValueError("decoder='light' needs the light decoder, and this world model was loaded without one "
                             "(pass light_decoder=<train.train_light_decoder work dir>, or True for the pipeline "
                             "run's own, to load_world_model)")
        light_decoder = (model.light_decoder_graphdef, model.light_decoder_params)
    spec = model.spec
    return build_simulator(
        model.world_model_graphdef, model.world_model_params, model.vae_graphdef, model.vae_params,
        precision=precision, light_decoder=light_decoder, flow_cfg=spec.flow, frame_size=spec.image_size,
        num_context=spec.num_context, num_future=spec.num_future, sample_steps=sample_steps,
        action_dim=spec.action_dim, latent_size=spec.latent_size, proprio_dim=proprio_dim,
        execute_latents=execute_latents, proprio_reckoning=proprio_reckoning)


def _reward_model(model: LoadedWorldModel, reward_model: RewardModel | Callable | None) -> RewardModel:
    if isinstance(reward_model, RewardModel):
        return reward_model
    if callable(reward_model):  # a plain function frames [n, H, W, 3] -> scores [n] in [0, 1]
        return RewardModel(params=None, score_fn=lambda _, frames: reward_model(frames))
    if reward_model is None and model.reward_model is not None:
        return model.reward_model
    raise ValueError("no reward model: pass reward_model= (a RewardModel, or a function frames [n, H, W, 3] -> "
                     "success scores [n] in [0, 1]), or load a run that has rl/reward_model")


def make_env(
    model: LoadedWorldModel,
    start_pool: StartState,
    *,
    reward_model: RewardModel | Callable | None = None,
    success_threshold: float = 0.9,
    max_chunks: int = 8,
    success_frames: int = 1,
    **simulator_options: Any,
):
    """The learned simulator as a brax ``Env`` (:class:`sword_jax.rl.env.ImaginedPoolEnv`).

    Pure and jittable, one environment: ``state = env.reset(rng)`` starts from a start state drawn
    from ``start_pool`` (:func:`start_states`), ``state = env.step(state, chunk)`` advances one
    action chunk, ``[4p, a]`` or flat ``[4p * a]`` (``env.action_size``, as brax's trainers give it).
    ``state`` is a brax ``envs.State`` (``obs`` = ``{"pixels/frame": [S, S, 3], "proprio",
    "proprio_valid", "instruction_tokens"}``, the ``pixels/`` key being the one brax's vision PPO runs
    its CNN on; ``reward`` = the change of the success score, ``done``, ``info['frames']`` = the
    predicted frames). ``S`` is the world model's ``H``, or with ``decoder="light"`` the light decoder's
    frame size (the start frame is resized to it; ``env.observation_size`` tells). Batch with
    ``jax.vmap(env.reset)(keys)`` / ``jax.vmap(env.step)(states, chunks)``, or hand it to brax
    (``brax.envs.wrappers.training.wrap``, ``brax.training.agents.ppo.train``).

    Args:
      reward_model: a :class:`RewardModel`, or a function ``frames [n, H, W, 3] -> [n]`` in [0, 1]
        (default the run's own). An episode succeeds when ``success_frames`` consecutive frames
        (default 1: any frame) score >= ``success_threshold``.
      max_chunks: chunks per episode (then ``info['truncation']``).
      simulator_options: for :func:`learned_simulator` (``precision``, ``decoder``, ``sample_steps`` ...).
    """
    from sword_jax.rl.env import ImaginedEnv, ImaginedPoolEnv

    env = ImaginedEnv(learned_simulator(model, **simulator_options), _reward_model(model, reward_model),
                      success_threshold=success_threshold, max_chunks=max_chunks, success_frames=success_frames)
    return ImaginedPoolEnv(env, start_pool)


def make_vector_env(
    model: LoadedWorldModel,
    start_pool: StartState,
    num_envs: int,
    *,
    reward_model: RewardModel | Callable | None = None,
    success_threshold: float = 0.9,
    max_chunks: int = 8,
    success_frames: int = 1,
    **simulator_options: Any,
):
    """The learned simulator as a ``gymnasium.vector.VectorEnv`` (:class:`sword_jax.rl.env.ImaginedVectorEnv`).

    ``num_envs`` imagined episodes stepped by one jitted, vmapped call; numpy in and out; next-step
    auto-reset (gymnasium's ``AutoresetMode.NEXT_STEP``). Actions ``[num_envs, 4p, a]`` float32
    in [-1, 1]; observations as :func:`make_env`'s, batched (frames ``[num_envs, S, S, 3]``, ``S`` the light
    decoder's size with ``decoder="light"``); ``info['frames']`` holds the predicted frames.
    ``reset(seed=...)`` draws starts from ``start_pool`` with the env's ``np_random`` (or
    ``options={'start_index': [num_envs]}``). Arguments as :func:`make_env`.
    """
    from sword_jax.rl.env import ImaginedEnv, ImaginedVectorEnv

    env = ImaginedEnv(learned_simulator(model, **simulator_options), _reward_model(model, reward_model),
                      success_threshold=success_threshold, max_chunks=max_chunks, success_frames=success_frames)
    return ImaginedVectorEnv(env, start_pool, num_envs)
