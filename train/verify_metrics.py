"""Checks the metric networks against the reference PyTorch outputs: LPIPS, InceptionV3, I3D, FloLPIPS, Frechet.

    python -m train.verify_metrics DIR

``DIR/manifest.json`` lists the networks, weight files and cases (see :mod:`sword_jax.metrics.verify`).
Prints one line per compared output and a closing line; exits 0 when every output is within the
manifest's tolerance (default 1e-4 relative), 1 when one is not, and 2 when a file is missing or
corrupt, the manifest names an unknown network or lists no cases.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import jax

from sword_jax import cli
from sword_jax.metrics import verify


def main(argv: Sequence[str] | None = None) -> int:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("directory", help="a reference directory holding manifest.json")
    args = parser.parse_args(None if argv is None else list(argv))
    jax.config.update("jax_default_matmul_precision", "highest")  # parity is measured at float32
    try:
        results, tolerance = verify.run(args.directory)
    except (OSError, ValueError, KeyError) as exc:  # missing/corrupt files, unknown manifest entries
        print(f"verify: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    if not results:
        print("verify: the manifest lists no cases", file=sys.stderr)
        return 2
    line, failed = verify.summary(results, tolerance)
    print(line)
    return 1 if failed else 0


if __name__ == "__main__":
    cli.run(main)
