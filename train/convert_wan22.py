"""Checks the Wan 2.2 converters (VAE, DiT) against the official PyTorch code's reference outputs.

    python -m train.convert_wan22 verify DIR [--tol 1e-4]

``verify`` runs every reference case found in DIR (VAE when DIR has ``vae*`` files: ``vae*.npz`` with
``vae_weights.safetensors``; DiT when it has ``dit*`` files) through the JAX port in float32, prints the
largest absolute and relative error per output and exits

* 0 when every output is within tolerance (an output fails when both its max abs error and its
  max error relative to the reference's largest magnitude exceed ``--tol``),
* 1 when an output is out of tolerance or a runner raised (corrupt file, config mismatch ...),
* 2 when DIR is missing or holds no reference cases.

The check is :func:`sword_jax.convert.wan22.verify`.
"""

from __future__ import annotations

from collections.abc import Sequence

from sword_jax import cli
from sword_jax.convert import wan22


def main(argv: Sequence[str] | None = None) -> int:
    parser = cli.ArgumentParser(prog="python -m train.convert_wan22", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    verify_parser = sub.add_parser("verify", help="run the reference cases of a directory through the JAX port")
    verify_parser.add_argument("dir", help="directory with *.safetensors weights and *.npz cases")
    verify_parser.add_argument("--tol", type=float, default=1e-4, help="max abs (and rel) error allowed")
    args = parser.parse_args(None if argv is None else list(argv))
    if args.command == "verify":
        return wan22.verify(args.dir, args.tol)
    return 2


if __name__ == "__main__":
    cli.run(main)
