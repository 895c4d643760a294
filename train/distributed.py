"""Process setup for multi-host runs (entry points only; the library never calls this).

``initialize(cfg.mesh)`` calls ``jax.distributed.initialize`` when ``mesh.distributed`` is set.
Cluster launchers (SLURM, Open MPI, Cloud TPU, Kubernetes) are auto-detected by JAX; a plain launch
reads ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``. On CPU the
collectives go through gloo, so the same path runs on one machine's loopback.
"""

from __future__ import annotations

import os

import jax

from sword_jax.sharding import MeshConfig

# Entry points let a jitted step trace twice before the retrace guard fires. On the GPU image
# (jax 0.11.2) the VAE step traced a second time because avals there record the mesh of a jit's
# output sharding, so a state made outside such a jit changed type after one step; entry points now
# pass their state through ``sharding.settle`` first, and the margin of one trace is kept for type
# changes of that kind that the CPU tests (jax 0.10.2) cannot show. A step that retraces on every
# call still fails at its third trace, naming the function.
ENTRY_MAX_TRACES = 2


def initialize(mesh_cfg: MeshConfig) -> None:
    """Joins the multi-process job if the config asks for it; a no-op otherwise."""
    if not mesh_cfg.distributed:
        return
    kwargs = {}
    if os.environ.get("JAX_NUM_PROCESSES"):
        kwargs["num_processes"] = int(os.environ["JAX_NUM_PROCESSES"])
    if os.environ.get("JAX_PROCESS_ID"):
        kwargs["process_id"] = int(os.environ["JAX_PROCESS_ID"])
    if os.environ.get("JAX_PLATFORMS", "").startswith("cpu"):
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    try:
        jax.distributed.initialize(**kwargs)
    except (ValueError, RuntimeError) as err:
        raise SystemExit(
            f"mesh.distributed=true but the multi-process job could not start ({err}). Launch under SLURM / "
            "Open MPI / a TPU pod, or set JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID."
        ) from None
