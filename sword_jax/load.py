"""Reading trained checkpoints outside the training loops: world model, VAE, reward model.

Layouts read (what the entry points write):

* world-model work dir (``train.train_world_model``): ``<dir>/config.json`` and
  ``<dir>/checkpoints/<step>/{state,meta}``; ``state`` is the train state as a pure-dict pytree
  (``params``, ``buffers``, ``ema_params`` or None, ``opt_state``, ``cache`` ...), ``meta`` is JSON
  with the config the run was trained with (``meta["config"]``).
* VAE (``train.train_vae``): ``<vae_workdir>/vae/0/{state,meta}``, the whole VAE state (params and
  latent statistics) as one pure dict; or official Wan 2.2 weights (``vae.checkpoint``).
* light rollout decoder (:mod:`sword_jax.pipeline.light_decoder`): ``<workdir>/checkpoints/<step>/{state,meta}``,
  the train state (``params``, ``opt_state``, ``step``), the decoder's geometry and config section in ``meta``.
* reward model / policy (:mod:`sword_jax.rl.params_io`): ``<dir>/<step>/{state,meta}`` with the
  RL config in ``meta["rl"]``.
* pipeline work dir (``train.pipeline``): ``<run>/world_model``, ``<run>/vae_run/vae``,
  ``<run>/rl/reward_model`` (:func:`find_run`).

Only the arrays needed for inference are read (orbax partial restore): a world model is loaded
without its optimizer state or latent cache. Every failure to find or read a checkpoint raises
:class:`CheckpointError` naming the path. Nothing here runs at import.
"""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from typing import Any

import jax
from flax import nnx

from sword_jax import sharding as shd
from sword_jax.checkpoint import CheckpointError, Checkpointer


def checkpoint_step(directory: str, step: int | None = None) -> int:
    """The newest complete checkpoint step in ``directory`` (or checks that ``step`` is there).

    Raises:
      CheckpointError: the directory does not exist or holds no complete checkpoint.
    """
    if not os.path.isdir(directory):
        raise CheckpointError(f"checkpoint directory {directory} does not exist")
    with Checkpointer(directory, read_only=True) as reader:
        steps = reader.all_steps()
    if not steps:
        raise CheckpointError(f"no complete checkpoint in {directory} (expected <step>/state and <step>/meta "
                              "written by a sword-jax trainer)")
    if step is None:
        return max(steps)
    if step not in steps:
        raise CheckpointError(f"no checkpoint for step {step} in {directory}; saved steps: {sorted(steps)}")
    return step


def read_meta(directory: str, step: int) -> dict[str, Any]:
    """The JSON metadata saved with checkpoint ``step`` (config, data position, kind ...)."""
    with Checkpointer(directory, read_only=True) as reader:
        return reader.read_meta(step)


def saved_keys(directory: str, step: int) -> dict[str, bool]:
    """Top-level entries of the saved state and whether each holds arrays (None entries: False)."""
    with Checkpointer(directory, read_only=True) as reader:
        node = reader.state_metadata(step)
    if not isinstance(node, dict):
        raise CheckpointError(f"checkpoint step {step} in {directory} does not hold a dict state")
    return {key: value is not None for key, value in node.items()}


def restore_subtree(directory: str, step: int, abstract: dict[str, Any]) -> dict[str, Any]:
    """Restores the entries of ``abstract`` (``ShapeDtypeStruct`` leaves with shardings) from ``step``.

    Entries of the saved state that ``abstract`` does not name are not read.
    """
    with Checkpointer(directory, read_only=True) as reader:
        return reader.restore_subtree(step, abstract)


def _section_value(value: Any, annotation: Any) -> Any:
    if isinstance(value, list):  # JSON lists are the configs' tuples (also nested, e.g. mesh rules)
        args = typing.get_args(annotation)
        inner = args[0] if len(args) == 2 and args[1] is Ellipsis else None
        return tuple(_section_value(v, inner) for v in value)
    return value


def _nest_renamed(cls: type, values: dict[str, Any]) -> dict[str, Any]:
    # keys an earlier version kept flat (``cls.renamed_fields``: old -> "section.key") moved into their sections
    renamed = getattr(cls, "renamed_fields", {})
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in values.items() if k not in renamed}
    for key in renamed.keys() & values.keys():
        *path, leaf = renamed[key].split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node.setdefault(leaf, values[key])  # a key saved under its new path wins over its old flat one
    return out


def section_from_dict(cls: type, values: dict[str, Any]) -> Any:
    """A frozen config section ``cls`` from its saved JSON dict, nested sections included; unknown
    keys are ignored, missing ones keep their defaults and keys an earlier version kept flat move to
    their sections (``cls.renamed_fields``), so a checkpoint from an older version still loads."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in _nest_renamed(cls, values).items():
        if key not in fields:
            continue
        section = hints.get(key)
        if dataclasses.is_dataclass(section) and isinstance(value, dict):
            kwargs[key] = section_from_dict(section, value)
        else:
            kwargs[key] = _section_value(value, section)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"saved {cls.__name__} settings are not valid: {err}") from err


def read_run_config(world_model_dir: str, step: int) -> dict[str, Any]:
    """The config a world-model run was trained with: the checkpoint's own ``meta["config"]``,
    else ``<dir>/config.json``."""
    meta = read_meta(os.path.join(world_model_dir, "checkpoints"), step)
    if isinstance(meta.get("config"), dict):
        return meta["config"]
    path = os.path.join(world_model_dir, "config.json")
    if not os.path.exists(path):
        raise CheckpointError(f"{world_model_dir}: neither the checkpoint metadata nor config.json holds the "
                              "config the world model was trained with")
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise CheckpointError(f"{path}: not a readable JSON config: {err}") from err


def _first_device() -> jax.sharding.Sharding:
    # A plain device placement (no mesh in the arrays' types): results of jitted functions that
    # mix these weights with the caller's unsharded arrays keep the callers' types, so a user's
    # step function that carries its own state compiles once.
    return jax.sharding.SingleDeviceSharding(jax.devices()[0])


def find_run(path: str, step: int | None) -> tuple[str, str | None, int | None]:
    """``(world-model work dir, pipeline run dir or None, step)`` for any of the paths
    :func:`sword_jax.api.load_world_model` takes (a pipeline work dir, a world-model work dir, its
    ``checkpoints`` directory or one step of it)."""
    full = os.path.abspath(os.path.expanduser(str(path)))
    if not os.path.exists(full):
        raise CheckpointError(f"{path} does not exist")
    name, parent = os.path.basename(full), os.path.dirname(full)
    if os.path.isdir(os.path.join(full, "world_model", "checkpoints")):
        return os.path.join(full, "world_model"), full, step
    if os.path.isdir(os.path.join(full, "checkpoints")):
        workdir = full
    elif name == "checkpoints":
        workdir = parent
    elif name.isdigit() and os.path.basename(parent) == "checkpoints":
        if step is not None and step != int(name):
            raise CheckpointError(f"{path} is step {name}, but step={step} was asked for")
        workdir, step = os.path.dirname(parent), int(name)
    else:
        raise CheckpointError(
            f"{path} is not a world-model run: expected a pipeline work dir (<dir>/world_model/checkpoints), "
            "a world-model work dir (<dir>/checkpoints, from train.train_world_model), its checkpoints "
            "directory or one step of it")
    run = os.path.dirname(workdir)
    return workdir, (run if os.path.isdir(os.path.join(run, "vae_run")) else None), step


def vae_dir(path: str) -> str:
    """A VAE work dir (``train.train_vae --workdir``) or its ``vae`` subdirectory -> the latter."""
    return os.path.join(path, "vae") if os.path.isdir(os.path.join(path, "vae")) else path


def load_world_model_params(
    model_cfg: Any,
    checkpoint_dir: str,
    *,
    seed: int = 0,
    step: int | None = None,
    use_ema: bool = True,
    mesh: jax.sharding.Mesh | None = None,
    rules=shd.DEFAULT_RULES,
) -> tuple[nnx.GraphDef, tuple[dict, dict], int]:
    """The world model saved under ``checkpoint_dir`` (``<workdir>/checkpoints``), for inference.

    Args:
      model_cfg: the :class:`~sword_jax.dit.config.DiTConfig` it was trained with.
      checkpoint_dir: the trainer's orbax directory.
      seed: only shapes the abstract module (no random values are kept).
      step: which checkpoint (default the newest).
      use_ema: the EMA parameters where the run kept them (``trainer.ema_decay > 0``).
      mesh: where the weights go, sharded by their logical axes (default: unsharded on the first device).

    Returns:
      ``(graphdef, (params, buffers), step)``; ``(params, buffers)`` are pure dicts of float32
      arrays, the state :func:`sword_jax.world_model.sampler.model_fn_from_state` takes.
    """
    from sword_jax.dit.action_dit import WorldModel

    step = checkpoint_step(checkpoint_dir, step)
    graphdef, abstract_params, abstract_rest = nnx.split(
        shd.abstract_module(lambda: WorldModel(model_cfg, rngs=nnx.Rngs(seed))), nnx.Param, ...)

    def placed(abstract):
        shardings = (jax.tree.map(lambda _: _first_device(), nnx.to_pure_dict(abstract)) if mesh is None
                     else nnx.to_pure_dict(shd.state_shardings(abstract, mesh, rules)))
        return jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                            nnx.to_pure_dict(abstract), shardings)

    params_abstract, buffers_abstract = placed(abstract_params), placed(abstract_rest)
    present = saved_keys(checkpoint_dir, step)
    if not present.get("params"):
        raise CheckpointError(f"{checkpoint_dir} step {step} holds no world-model params (saved: {sorted(present)})")
    source = "ema_params" if use_ema and present.get("ema_params") else "params"
    wanted = {source: params_abstract}
    if jax.tree.leaves(buffers_abstract):
        wanted["buffers"] = buffers_abstract
    restored = restore_subtree(checkpoint_dir, step, wanted)
    return graphdef, (restored[source], restored.get("buffers", {})), step


def load_vae_params(vae_cfg: Any, path: str = "", *, mesh: jax.sharding.Mesh | None = None
                    ) -> tuple[nnx.GraphDef, nnx.State]:
    """The VAE of ``vae_cfg``, replicated over ``mesh`` (default: unsharded on the first device): where
    ``vae_cfg.checkpoint`` names a file, the official Wan 2.2 weights in it; where it names a folder, the state a
    sword-jax VAE run saved there (``train.train_vae``'s ``<workdir>/vae`` or its work dir, a bundle's
    ``vae_run/vae``); else the state saved at ``path``.

    Raises:
      CheckpointError: no such checkpoint, or one of another architecture.
    """
    from sword_jax.vae import api as vae_api

    if vae_cfg.checkpoint and os.path.isdir(vae_cfg.checkpoint):
        path = vae_dir(vae_cfg.checkpoint)
    elif vae_cfg.checkpoint:
        from sword_jax.convert import wan22_vae

        graphdef, state, official = wan22_vae.load_vae(vae_cfg.checkpoint, compute_dtype=vae_cfg.compute_dtype)
        if (official.z_dim, official.dim, official.dec_dim) != (vae_cfg.z_dim, vae_cfg.dim, vae_cfg.dec_dim):
            raise CheckpointError(f"{vae_cfg.checkpoint} holds a VAE with z_dim/dim/dec_dim {official.z_dim}/"
                                  f"{official.dim}/{official.dec_dim}, the config asks for "
                                  f"{vae_cfg.z_dim}/{vae_cfg.dim}/{vae_cfg.dec_dim}")
        return graphdef, state
    step = checkpoint_step(path)
    graphdef, state = nnx.split(vae_api.abstract_vae(vae_cfg))
    replicated = _first_device() if mesh is None else shd.replicated(mesh)
    abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated),
                            nnx.to_pure_dict(state))
    nnx.replace_by_pure_dict(state, restore_subtree(path, step, abstract))
    return graphdef, state


def _latent_layout(geometry: dict[str, Any]) -> str:
    size = geometry.get("latent_size")
    return f"{geometry.get('z_dim')}-channel {size}x{size} latents of {geometry.get('temporal_factor')} frames each"


def load_light_decoder(
    path: str,
    *,
    z_dim: int | None = None,
    latent_size: int | None = None,
    temporal_factor: int | None = None,
    mesh: jax.sharding.Mesh | None = None,
) -> tuple[nnx.GraphDef, Any, dict[str, Any]]:
    """The light rollout decoder of a ``light_decoder`` run (its work dir or ``checkpoints`` directory; the newest
    checkpoint), rebuilt from the checkpoint's own metadata; only its weights are read (not the optimizer state),
    replicated over ``mesh`` (default: unsharded on the first device).

    Args:
      path: the run's work dir (``train.train_light_decoder --workdir``, a pipeline's ``<run>/light_decoder``) or
        its ``checkpoints`` directory.
      z_dim / latent_size / temporal_factor: the latents the decoder must take (the world model's channels, latent
        height and width, frames per latent); each one given is checked against the decoder's metadata before
        any weight is read.
      mesh: where the weights go.

    Returns:
      ``(graphdef, state, meta)``; ``meta`` holds ``scale``, ``temporal_factor``, ``z_dim``, ``latent_size``,
      ``frame_size`` and its config section.

    Raises:
      CheckpointError: no such directory or checkpoint, one of another kind, or a decoder of other latents (the
        message names the path and both layouts).
    """
    from sword_jax.vae import light_decoder as light
    from sword_jax.vae.config import LightDecoderConfig

    if not os.path.isdir(path):
        raise CheckpointError(f"light decoder {path} does not exist")
    if os.path.isdir(os.path.join(path, "checkpoints")):
        path = os.path.join(path, "checkpoints")
    step = checkpoint_step(path)
    meta = read_meta(path, step)
    if meta.get("kind") != "light_decoder":
        raise CheckpointError(f"{path} holds a {meta.get('kind')!r} checkpoint, expected 'light_decoder' (a "
                              "train_light_decoder run)")
    expected = {"z_dim": z_dim, "latent_size": latent_size, "temporal_factor": temporal_factor}
    wanted = {name: meta.get(name) if value is None else value for name, value in expected.items()}
    if wanted != {name: meta.get(name) for name in expected}:
        raise CheckpointError(f"{path}: a light decoder of {_latent_layout(meta)}, the world model's are "
                              f"{_latent_layout(wanted)} (train one on its latents: train.train_light_decoder)")
    cfg = section_from_dict(LightDecoderConfig, meta.get("light_decoder", {}))
    graphdef, state = nnx.split(light.abstract_light_decoder(cfg, z_dim=meta["z_dim"], scale=meta["scale"],
                                                             temporal_factor=meta["temporal_factor"]))
    replicated = _first_device() if mesh is None else shd.replicated(mesh)
    abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=replicated),
                            nnx.to_pure_dict(state))
    nnx.replace_by_pure_dict(state, restore_subtree(path, step, {"params": abstract})["params"])
    return graphdef, state, meta


def load_rl_params(path: str, *, kind: str, build) -> tuple[nnx.GraphDef, nnx.State, Any]:
    """A policy / reward-model checkpoint (:mod:`sword_jax.rl.params_io`) rebuilt from its own RL config.

    Args:
      path: the orbax directory ``save_params`` wrote.
      kind: the expected ``meta["kind"]`` (``"policy"`` or ``"reward_model"``).
      build: ``build(rl_cfg) -> (graphdef, params)``, e.g. :func:`sword_jax.rl.reward_model.build_detector`.

    Returns:
      ``(graphdef, params, rl_cfg)``.
    """
    from sword_jax.rl.config import RLConfig

    step = checkpoint_step(path)
    meta = read_meta(path, step)
    if meta.get("kind") != kind:
        raise CheckpointError(f"{path} holds a {meta.get('kind')!r} checkpoint, expected {kind!r}")
    rl_cfg = section_from_dict(RLConfig, meta.get("rl", {}))
    graphdef, params = build(rl_cfg)
    abstract = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=a.sharding),
                            nnx.to_pure_dict(params))
    nnx.replace_by_pure_dict(params, restore_subtree(path, step, abstract))
    return graphdef, params, rl_cfg


def experiment_world_model(cfg: Any, workdir: str | None) -> tuple[nnx.GraphDef, Any]:
    """``(graphdef, state)`` of an experiment's world model: the one trained in ``workdir`` (EMA weights
    where kept; :func:`load_world_model_params`), placed by ``cfg.mesh``, or a random initialisation of
    ``cfg.model`` (seed ``cfg.seed``) when ``workdir`` is None. ``workdir`` is any path :func:`find_run` takes:
    its newest checkpoint, or the step it names (``<workdir>/checkpoints/<step>``)."""
    if workdir is not None:
        run_dir, _, step = find_run(workdir, None)
        graphdef, state, _ = load_world_model_params(cfg.model, os.path.join(run_dir, "checkpoints"), seed=cfg.seed,
                                                     step=step, mesh=shd.make_mesh(cfg.mesh), rules=cfg.mesh.rules)
        return graphdef, state
    from sword_jax.dit.action_dit import WorldModel

    graphdef, params, rest = nnx.split(WorldModel(cfg.model, rngs=nnx.Rngs(cfg.seed)), nnx.Param, ...)
    return graphdef, (params, rest)


def experiment_vae(cfg: Any, path: str = "", *, mesh: jax.sharding.Mesh | None = None
                   ) -> tuple[nnx.GraphDef, nnx.State]:
    """``(graphdef, state)`` of an experiment's VAE: official weights if ``cfg.vae.checkpoint`` is set,
    else the state ``train.train_vae`` saved at ``path`` (:func:`load_vae_params`; replicated over ``mesh``
    if given, else on the first device), else (neither) a random initialisation (seed ``cfg.seed``)."""
    if path or cfg.vae.checkpoint:
        return load_vae_params(cfg.vae, path, mesh=mesh)
    from sword_jax.vae import api as vae_api

    return nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(cfg.seed)))
