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


def assert_same_final_checkpoint(reference: str, other: str, steps: int) -> tuple[dict[str, np.ndarray], dict, dict]:
    """Both runs' newest checkpoints hold bit-identical arrays, ``steps`` steps and the same data position;
    returns ``(reference arrays, reference meta, other meta)`` for further checks."""
    want, want_meta = final_arrays(reference)
    got, got_meta = final_arrays(other)
    assert want.keys() == got.keys() and len(want) > 10
    for name in want:
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert got_meta["step"] == want_meta["step"] == steps
    assert got_meta["data_position"] == want_meta["data_position"]
    return want, want_meta, got_meta
