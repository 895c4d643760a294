"""Reading a finished run's checkpoint back as flat numpy arrays, on whatever devices this process has."""

from __future__ import annotations

import os

import jax
import numpy as np
import orbax.checkpoint as ocp


def final_arrays(workdir: str) -> tuple[dict[str, np.ndarray], dict]:
    """``({"/path/to/leaf": array}, meta)`` of the newest checkpoint in ``<workdir>/checkpoints``."""
    directory = os.path.join(workdir, "checkpoints")
    manager = ocp.CheckpointManager(directory, item_handlers={"state": ocp.StandardCheckpointHandler(),
                                                              "meta": ocp.JsonCheckpointHandler()})
    step = manager.latest_step()
    # Restore onto this process's first device, whatever topology wrote the checkpoint.
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    target = jax.tree.map(lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device),
                          manager.item_metadata(step)["state"])
    restored = manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target),
                                                             meta=ocp.args.JsonRestore()))
    manager.close()
    flat = {}

    def visit(prefix, tree):
        if isinstance(tree, dict):
            for k, v in tree.items():
                visit(f"{prefix}/{k}", v)
        elif isinstance(tree, (list, tuple)):
            for i, v in enumerate(tree):
                visit(f"{prefix}/{i}", v)
        elif tree is not None:
            flat[prefix] = np.asarray(tree)

    visit("", restored["state"])
    return flat, restored["meta"]
