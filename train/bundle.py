"""Moves a trained pipeline's inference weights between machines in parts of a limited size.

    python -m train.bundle pack RUN OUT [--part-mib 16] [--step N]
    python -m train.bundle unpack DEST FOLDER [FOLDER ...]

``pack`` writes the world model's inference weights (its EMA where kept), the VAE and the success detector of
pipeline work dir RUN into the new folder OUT, as one tar stream cut into ``part-NNNN`` files of at most
``--part-mib`` MiB and a manifest ``bundle.json`` of their sizes and SHA-256. ``unpack`` checks every part
(they may lie in several folders, as they travelled) and restores the work dir into the new folder DEST, which
``train.grpo --world-model DEST/world_model --vae DEST/vae_run/vae --reward DEST/rl/reward_model`` and
``sword_jax.load_world_model(DEST)`` read as they read RUN. A missing or damaged part is named and nothing is
written (:mod:`sword_jax.bundle`).
"""

from __future__ import annotations

from collections.abc import Sequence

from sword_jax import bundle, cli


def _parts(manifest: dict) -> str:
    count = len(manifest["parts"])
    return f"{count} part" + ("" if count == 1 else "s")


def main(argv: Sequence[str] | None = None) -> dict:
    parser = cli.ArgumentParser(prog="python -m train.bundle", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    packing = sub.add_parser("pack", help="a pipeline run's inference weights -> parts and a manifest")
    packing.add_argument("run", help="pipeline work dir (train.pipeline --workdir)")
    packing.add_argument("out", help="a new (or empty) folder for the parts and bundle.json")
    packing.add_argument("--part-mib", type=float, default=16.0, help="largest part, MiB (default 16)")
    packing.add_argument("--step", type=int, default=None, help="the world model's checkpoint (default: newest)")
    unpacking = sub.add_parser("unpack", help="parts and a manifest -> the work dir, every part checked")
    unpacking.add_argument("dest", help="a new (or empty) folder for the work dir")
    unpacking.add_argument("folders", nargs="+", help="folders holding bundle.json and the parts")
    args = parser.parse_args(None if argv is None else list(argv))
    try:
        if args.command == "pack":
            manifest = bundle.pack(args.run, args.out, part_bytes=int(args.part_mib * 2**20), step=args.step)
            wm = manifest["world_model"]
            print(f"[bundle] {args.run} -> {args.out}: {', '.join(manifest['contents'])}; world model step "
                  f"{wm['step']} ({wm['weights']}, {wm['parameters']:,} parameters); {_parts(manifest)}, "
                  f"{manifest['bytes'] / 2**20:.1f} MiB", flush=True)
        else:
            manifest = bundle.unpack(args.folders, args.dest)
            print(f"[bundle] {_parts(manifest)} checked -> {args.dest}: "
                  f"{', '.join(manifest['contents'])}", flush=True)
    except bundle.BundleError as err:
        raise SystemExit(str(err)) from None
    return manifest


if __name__ == "__main__":
    cli.run(main)
