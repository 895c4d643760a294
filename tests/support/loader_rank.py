"""One rank of a ``train.launch`` job (tests): checks that its world-model loader reads only the rows its
devices hold and that the global batch equals the one a single process builds; then rank 1 dies by
SIGKILL while rank 0 waits in a collective it will never complete.

Prints ``rank R rows [...] read N of B`` per checked step, and ``rank 1 dies at T`` (``time.time()``).
"""

from __future__ import annotations

import os
import signal
import sys
import time

import jax
import numpy as np
from jax.experimental import multihost_utils

from sword_jax import sharding as shd
from sword_jax.world_model import data
from train import distributed

BATCH = 8


def main() -> None:
    distributed.initialize(shd.MeshConfig(distributed=True))
    rank = jax.process_index()
    mesh = shd.make_mesh(shd.MeshConfig(data=-1))
    dataset = data.synthetic_latent_dataset(6, 6, 2, 2, 4, seed=0)
    sampler = data.SegmentSampler(6, 6, 1, 2, BATCH, seed=0)
    loader = data.SegmentLoader(dataset, sampler, 1, 2, mesh)
    gather = jax.jit(lambda batch: batch, out_shardings=shd.replicated(mesh))
    for step in range(3):
        held = loader.host_batch_at(step)
        got = jax.tree.map(np.asarray, gather(loader.place(held)))
        want = dataset.segment(*sampler.indices_at(step), 1, 2)
        for name in want:
            np.testing.assert_array_equal(got[name], want[name], err_msg=f"rank {rank} step {step} {name}")
        print(f"rank {rank} rows {loader.rows.tolist()} read {len(held['episode'])} of {BATCH}", flush=True)
    multihost_utils.sync_global_devices("checked")
    if rank == 1:
        print(f"rank 1 dies at {time.time()}", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(1.0)  # rank 1 is gone: the collective below cannot complete
    multihost_utils.sync_global_devices("never")
    print("rank 0 passed a collective without rank 1", flush=True)
    sys.exit(5)


if __name__ == "__main__":
    main()
