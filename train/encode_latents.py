r"""Encodes episode files with a given VAE into the world model's training latents, as the pipeline's latents stage.

    python -m train.encode_latents --config sword:small [--vae.dim_mult=1,4,4 ...] --vae DIR --out latents.npz \
        FILE [FILE ...]

A world model that travelled as a bundle (``train.bundle``: world model, VAE, success detector, no latents) is
refreshed in GRPO (``train.grpo --rl.refresh.every=K ... --latents latents.npz``) on the latents this writes: the
refresh mixes them into its fine-tune. Give the config (and overrides) the world model was trained with, its VAE
(a bundle's ``vae_run/vae``) and the same episode files: the expert's first, then the supervised policy's rollouts
(``sources`` 0 and 1). Every episode is encoded raw and in ``augment.styled_copies`` training styles, so the file
holds the same arrays the pipeline wrote (``latents`` [E, L, h, w, c], ``actions``, ``sources``).

A ``--out`` that exists is refused (nothing saved is replaced), as are a missing episode file, a folder that holds
no VAE and a VAE of another architecture than the config's; the file is written whole or not at all.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

import numpy as np

import configs
from sim.data_stages import encode_episode_latents, latents_summary


def main(argv: Sequence[str] | None = None) -> dict:
    cfg, rest = configs.from_argv(sys.argv[1:] if argv is None else list(argv))
    parser = configs.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vae", default="", metavar="DIR",
                        help="VAE folder (train_vae's <workdir>/vae, a bundle's vae_run/vae)")
    parser.add_argument("--out", required=True, metavar="FILE", help="the new latents file (.npz)")
    parser.add_argument("files", nargs="+", help="LIBERO-layout episode files: the expert's, then policy rollouts")
    args = parser.parse_args(rest)
    return run(cfg, args.vae, args.files, args.out)


def run(cfg, vae: str, files: Sequence[str], out: str) -> dict:
    """:func:`write_episode_latents`, reported in one line; episodes it cannot cut to the config's
    length (and other bad input it meets while reading them) refused in one line too."""
    try:
        summary = write_episode_latents(cfg, vae, files, out)
    except ValueError as err:
        raise SystemExit(f"train.encode_latents: {err}") from None
    print(f"[encode_latents] {out}: {summary['episodes']} episodes ({summary['raw_episodes']} raw, "
          f"{summary['styled_copies']} styled copies each, {summary['policy_episodes']} of the policy), latents "
          f"{'x'.join(map(str, summary['latent_shape']))}, {summary['seconds']:.1f} s", flush=True)
    return summary


def _refuse(problem: str):
    raise SystemExit(f"train.encode_latents: {problem}")


def _vae_of_config(cfg, vae: str):
    """``(graphdef, state)`` of the VAE saved at ``vae`` (a VAE work dir or its ``vae`` folder; or the one named by
    ``vae.checkpoint``); refuses a folder that holds no VAE and a VAE of another architecture than ``cfg.vae``."""
    from flax import nnx

    from sword_jax.checkpoint import CheckpointError, Checkpointer
    from sword_jax.load import checkpoint_step, load_vae_params, read_meta, vae_dir
    from sword_jax.vae import api as vae_api

    if not vae and not cfg.vae.checkpoint:
        _refuse("pass --vae DIR (train.train_vae's <workdir>/vae, a bundle's vae_run/vae) or --vae.checkpoint")
    if not cfg.vae.checkpoint:
        vae = vae_dir(vae)
        try:
            kind = read_meta(vae, checkpoint_step(vae)).get("kind", "vae")
        except CheckpointError:
            kind = None
        if kind != "vae":
            _refuse(f"{vae} is not a VAE folder (train.train_vae's <workdir>/vae, a bundle's vae_run/vae)")
        with Checkpointer(vae, read_only=True) as reader:  # shapes from metadata: no array is read
            saved = _shapes(reader.state_metadata(checkpoint_step(vae)))
        wanted = _shapes(nnx.to_pure_dict(nnx.split(vae_api.abstract_vae(cfg.vae))[1]))
        if saved != wanted:
            name = next(k for k in sorted(set(saved) | set(wanted)) if saved.get(k) != wanted.get(k))
            _refuse(f"{vae} holds a VAE of another architecture than the config's (vae.z_dim={cfg.vae.z_dim}, "
                    f"vae.dim={cfg.vae.dim}, vae.dim_mult={','.join(map(str, cfg.vae.dim_mult))}; {name}: saved "
                    f"{saved.get(name)}, the config's {wanted.get(name)}): pass the --vae.* overrides it was "
                    "trained with")
    return load_vae_params(cfg.vae, vae)


def _shapes(tree, prefix: str = "") -> dict[str, tuple]:
    """``{path: shape}`` of the leaves of a nested dict (or list) of arrays or array metadata."""
    if isinstance(tree, (dict, list, tuple)):
        items = tree.items() if isinstance(tree, dict) else enumerate(tree)
        return {path: shape for key, value in items for path, shape in _shapes(value, f"{prefix}{key}/").items()}
    return {prefix.rstrip("/"): tuple(tree.shape)}


def write_episode_latents(cfg, vae: str, files: Sequence[str], out: str) -> dict:
    """Writes :func:`sim.data_stages.encode_episode_latents` of ``files`` with the VAE saved at ``vae`` to the new ``.npz`` file
    ``out`` (written whole or not at all): the training latents that a world model which travelled without them
    (a bundle) needs for GRPO's refresh (``train.grpo --rl.refresh.every=K --latents OUT``).

    Returns:
      ``path``, ``episodes`` (E), ``raw_episodes``, ``policy_episodes``, ``styled_copies``, ``latent_shape``
      ([L, h, w, c]), ``files`` and ``seconds``.

    Raises:
      SystemExit: ``out`` exists or does not end in ``.npz``, an input file is missing, ``vae`` is no VAE folder or
        holds a VAE of another architecture than ``cfg.vae``, or the latents are not of the shape the config
        gives (frames of another size than ``data.image_size``).
    """
    from sword_jax.vae import api as vae_api

    start = time.monotonic()
    if os.path.exists(out):
        _refuse(f"{out} exists; name a new file (nothing is replaced)")
    if not out.endswith(".npz"):
        _refuse(f"--out {out} must end in .npz (the latents file train.grpo --latents reads)")
    if not files:
        _refuse("name at least one episode file")
    missing = [f for f in files if not os.path.isfile(f)]
    if missing:
        _refuse(f"no episode file at {', '.join(missing)}")
    graphdef, state = _vae_of_config(cfg, vae)
    temporal, spatial = vae_api.factors(graphdef, state)
    size = cfg.data.image_size // spatial
    expected = (1 + (cfg.data.episode_frames - 1) // temporal, size, size, cfg.vae.z_dim)
    arrays = encode_episode_latents(cfg, graphdef, state, files)
    latents = arrays["latents"]
    if latents.shape[1:] != expected:
        _refuse(f"the latents of {', '.join(files)} are {list(latents.shape[1:])}, the config's world model reads "
                f"{list(expected)}: frames of data.image_size={cfg.data.image_size} and data.episode_frames="
                f"{cfg.data.episode_frames} are needed")
    if os.path.dirname(out):
        os.makedirs(os.path.dirname(out), exist_ok=True)
    partial = f"{out}.partial"
    try:
        with open(partial, "wb") as f:
            np.savez(f, **arrays)
        if os.path.exists(out):
            _refuse(f"{out} appeared while encoding; name a new file (nothing is replaced)")
        os.replace(partial, out)
    finally:
        if os.path.exists(partial):
            os.remove(partial)
    return {"path": out, **latents_summary(cfg, arrays), "files": list(files), "seconds": time.monotonic() - start}


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
