"""Process setup for multi-host runs (entry points only; the library never calls this).

``initialize(cfg.mesh)`` calls ``jax.distributed.initialize`` when ``mesh.distributed`` is set.
Cluster launchers (SLURM, Open MPI, Cloud TPU, Kubernetes) are auto-detected by JAX; a plain launch
reads ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``. On CPU the
collectives go through gloo, so the same path runs on one machine's loopback.
"""

from __future__ import annotations

from sword_jax.pipeline import launch
from sword_jax.sharding import MeshConfig
from sword_jax.tracing import ENTRY_MAX_TRACES  # noqa: F401  (the entry points' retrace margin)


def initialize(mesh_cfg: MeshConfig) -> None:
    """Joins the multi-process job if the config asks for it; a no-op otherwise."""
    if not mesh_cfg.distributed:
        return
    try:
        launch.join()
    except (ValueError, RuntimeError) as err:
        raise SystemExit(
            f"mesh.distributed=true but the multi-process job could not start ({err}). Launch under SLURM / "
            "Open MPI / a TPU pod, or set JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID."
        ) from None
