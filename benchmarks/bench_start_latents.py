"""How far GRPO's start latents are from the latents the world model was trained on.

The latents stage encodes whole episodes with the causal VAE (:func:`sim.data_stages.encode_episode_latents`), so a
training segment's context latent carries everything the encoder's cache saw since the episode's first frame. GRPO in
the world model starts from keyframes, and encodes each one's context in one of three ways:

* ``window`` (``rl.imagined.start_encoding=window``, the default; :func:`~sword_jax.rl.world_model_sim.encode_history`):
  the first frame, then the ``4 (k + 1)`` frames up to the keyframe, the oldest four only warming the encoder's
  cache; before frame 0 the window repeats frame 0;
* ``still`` (:func:`~sword_jax.rl.world_model_sim.encode_keyframes`, the fallback without history): the keyframe held
  still;
* ``prefix`` (``rl.imagined.start_encoding=prefix``; :func:`~sword_jax.rl.world_model_sim.encode_prefix`): the episode
  from its first frame to the keyframe, which must equal the whole episode's latent (the check of this benchmark).

For keyframes at the given latents (``--latents 1,2,6,12``: frame ``4 s``) of every episode long enough, each
context latent is compared with the whole episode's latent there: the relative error (norm of the difference over
the norm), median and largest over the episodes, per keyframe and way. The world model's own one-call error on real
context is about 0.01 in relative squared error (0.1 in relative norm) on ``small``: a start context further off
than that starts the closed loop outside what the model was trained on. ::

    python -m benchmarks.bench_start_latents --config sword:small --vae runs/p/vae_run/vae \\
        --episodes runs/p/data/demos.hdf5 --vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true --out runs/sl

Writes ``start_latents.json`` to ``--out`` and prints one row per keyframe latent.
"""

from __future__ import annotations

import datetime
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic

WAYS = ("window", "still", "prefix")


def relative_error(latents: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per row (leading axis), the norm of ``latents - reference`` over the norm of ``reference``."""
    axes = tuple(range(1, reference.ndim))
    return np.sqrt(np.sum(np.square(latents - reference), axis=axes) / np.sum(np.square(reference), axis=axes))


def relative_errors(vae_graphdef: Any, vae_state: Any, frames: np.ndarray, lengths: np.ndarray, latents: Sequence[int],
                    *, num_context: int = 1, frames_per_latent: int = 4) -> dict[int, dict[str, np.ndarray]]:
    """Per keyframe latent ``s`` in ``latents`` and per way (:data:`WAYS`), the context latent's relative error
    against latent ``s`` of the whole episode encoded at once, for each episode of ``frames [E, T, H, W, 3]``
    (uint8) whose length reaches past frame ``4 s``."""
    import jax.numpy as jnp

    from sword_jax.rl import data as rl_data
    from sword_jax.rl.world_model_sim import encode_history, encode_keyframes, encode_prefix
    from sword_jax.vae import api as vae_api

    k, f = num_context, frames_per_latent
    unit = lambda x: jnp.asarray(x, jnp.float32) / jnp.float32(255.0)  # noqa: E731
    # each whole episode (cut to 1 + 4 m frames) encoded at once, as the latents stage encodes it
    whole_episode = {}
    for e in np.flatnonzero(lengths > f * min(latents)):
        video = unit(frames[e, :1 + f * ((int(lengths[e]) - 1) // f)])[None] * 2.0 - 1.0
        whole_episode[int(e)] = np.asarray(vae_api.encode(vae_graphdef, vae_state, video, check_values=False))[0]
    out: dict[int, dict[str, np.ndarray]] = {}
    for s in latents:
        if s < k:
            raise ValueError(f"keyframe latent {s} precedes the {k} context latents")
        ep = np.flatnonzero(lengths > f * s)
        if not ep.size:
            continue
        t = np.full(ep.size, f * s, np.int64)
        window = rl_data.keyframe_window(frames, np.zeros(frames.shape[:2] + (1,), np.float32),
                                         np.zeros(frames.shape[:2] + (1,), np.float32), ep, t, num_context=k,
                                         frames_per_latent=f, prefix_latents=s)
        whole = np.stack([whole_episode[e][s] for e in ep])
        ways = {
            "window": encode_history(vae_graphdef, vae_state, unit(window["first_frame"]), unit(window["history"]),
                                     num_context=k),
            "still": encode_keyframes(vae_graphdef, vae_state, unit(window["frame"]), num_context=k),
            "prefix": encode_prefix(vae_graphdef, vae_state, unit(window["prefix"]), window["latent_index"],
                                    num_context=k),
        }
        out[s] = {way: relative_error(np.asarray(z)[:, -1], whole) for way, z in ways.items()}
    return out


def summary(errors: dict[int, dict[str, np.ndarray]], frames_per_latent: int = 4) -> list[dict[str, Any]]:
    """One row per keyframe latent: its frame, the episodes measured, and per way the median and largest error."""
    rows = []
    for s, ways in sorted(errors.items()):
        row: dict[str, Any] = {"latent": s, "frame": frames_per_latent * s,
                               "episodes": int(next(iter(ways.values())).size)}
        for way, e in ways.items():
            row[way] = {"median": float(np.median(e)), "max": float(np.max(e))}
        rows.append(row)
    return rows


def line(row: dict[str, Any]) -> str:
    return (f"[start-latents] keyframe at frame {row['frame']} ({row['episodes']} episodes): "
            + ", ".join(f"{way} {row[way]['median']:.3f} (max {row[way]['max']:.3f})" for way in WAYS))


def main(argv: Sequence[str] | None = None) -> dict:
    import configs

    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, rest = configs.from_argv(argv, default="sword:small")
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae", required=True, help="VAE checkpoint directory (train_vae; a pipeline's vae_run/vae)")
    parser.add_argument("--episodes", action="append", default=[],
                        help="episodes (LIBERO-layout HDF5, e.g. a pipeline's data/demos.hdf5); repeat for more files")
    parser.add_argument("--latents", default="1,2,3,6,12", help="comma list of keyframe latents s (frame 4 s)")
    parser.add_argument("--max-episodes", type=int, default=32, help="episodes read (the first ones of the file)")
    parser.add_argument("--out", required=True, help="folder of start_latents.json")
    args = parser.parse_args(rest)
    try:
        latents = sorted({int(x) for x in args.latents.split(",") if x})
    except ValueError:
        raise cli.UsageError(f"bench_start_latents: --latents takes a comma list of integers, got {args.latents!r}")
    k = cfg.data.context_frames // cfg.vae.temporal_factor
    if not latents or latents[0] < k:
        raise cli.UsageError(f"bench_start_latents: --latents must be >= {k} (the context latents), got {args.latents!r}")
    if args.max_episodes < 1:
        raise cli.UsageError(f"bench_start_latents: --max-episodes must be >= 1, got {args.max_episodes}")
    if not args.episodes:
        raise cli.UsageError("bench_start_latents: give at least one --episodes file")
    for flag, path, is_dir in (("--vae", args.vae, True), *(("--episodes", p, False) for p in args.episodes)):
        if not (os.path.isdir(path) if is_dir else os.path.isfile(path)):
            raise cli.UsageError(f"bench_start_latents: {flag} {path}: no such {'folder' if is_dir else 'file'}")

    from benchmarks.common import device_name
    from sim.dataset import read_dataset
    from sword_jax.load import experiment_vae
    from sword_jax.rl import data as rl_data

    began = time.time()
    vae_graphdef, vae_state = experiment_vae(cfg, args.vae)
    episodes = rl_data.load_episodes(args.episodes, read=read_dataset, stop_at_success=False)
    n = min(args.max_episodes, episodes.num_episodes)
    errors = relative_errors(vae_graphdef, vae_state, episodes.frames[:n], episodes.lengths[:n], latents,
                             num_context=k, frames_per_latent=cfg.vae.temporal_factor)
    rows = summary(errors, cfg.vae.temporal_factor)
    for row in rows:
        print(line(row))
    out = {"rows": rows, "config": cfg.name, "vae": args.vae, "episodes": args.episodes, "device": device_name(),
           "command": " ".join(["python -m benchmarks.bench_start_latents", *argv]),
           "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
           "seconds": round(time.time() - began, 1)}
    os.makedirs(args.out, exist_ok=True)
    write_json_atomic(os.path.join(args.out, "start_latents.json"), out)
    return out


if __name__ == "__main__":
    cli.run(main)
