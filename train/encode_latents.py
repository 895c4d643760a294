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
import sys
from collections.abc import Sequence

import configs
from sim.data_stages import write_episode_latents


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
    """:func:`sim.data_stages.write_episode_latents`, reported in one line; episodes it cannot cut to the config's
    length (and other bad input it meets while reading them) refused in one line too."""
    try:
        summary = write_episode_latents(cfg, vae, files, out)
    except ValueError as err:
        raise SystemExit(f"train.encode_latents: {err}") from None
    print(f"[encode_latents] {out}: {summary['episodes']} episodes ({summary['raw_episodes']} raw, "
          f"{summary['styled_copies']} styled copies each, {summary['policy_episodes']} of the policy), latents "
          f"{'x'.join(map(str, summary['latent_shape']))}, {summary['seconds']:.1f} s", flush=True)
    return summary


if __name__ == "__main__":
    from sword_jax import cli

    cli.run(main)
