"""One rank of a ``train.launch`` job (tests): checks that its world-model, VAE and light-decoder loaders read
only the rows its devices hold and that each global batch equals the one a single process builds; then rank 1
dies by SIGKILL while rank 0 waits in a collective it will never complete.

Prints ``rank R rows [...] read N of B`` per checked world-model step, ``rank R vae rows [...] cut N of B``
per checked VAE step (clips cut from the episodes, some restyled), ``rank R squares rows [...] drew N of B``
(the synthetic videos), ``rank R light rows [...] cut N of B`` per checked light-decoder step (latent clips)
and ``rank 1 dies at T`` (``time.time()``).
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
from sword_jax.augment.synthetic import synthetic_episodes
from sword_jax.vae import data as vae_data
from sword_jax.vae import light_train
from sword_jax.vae.train import moving_squares
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
    check_vae_loader(rank, mesh, gather)
    check_light_loader(rank, mesh, gather)
    multihost_utils.sync_global_devices("checked")
    if rank == 1:
        print(f"rank 1 dies at {time.time()}", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(1.0)  # rank 1 is gone: the collective below cannot complete
    multihost_utils.sync_global_devices("never")
    print("rank 0 passed a collective without rank 1", flush=True)
    sys.exit(5)


def check_vae_loader(rank: int, mesh, gather) -> None:
    episodes = synthetic_episodes(3, num_frames=9, size=16)
    clips = vae_data.VAEClips([np.rint(f * 255).astype(np.uint8) for f in episodes["frames"]],
                              list(episodes["depth"]), list(episodes["seg"]))
    cut = []
    real_cut = vae_data._cut
    vae_data._cut = lambda video, start, frames: cut.append(start) or real_cut(video, start, frames)
    sampler = vae_data.ClipSampler(clips, batch=BATCH, frames=5, seed=0, styled_fraction=0.5)
    loader = vae_data.VideoLoader(sampler.batch, BATCH, mesh)
    for step in range(1, 4):
        want = vae_data.ClipSampler(clips, batch=BATCH, frames=5, seed=0, styled_fraction=0.5).batch(step)
        cut.clear()
        held = loader.host_batch_at(step)
        clips_cut = len(cut) // 3  # frames, depth and seg of each clip
        got = np.asarray(gather(loader.place(held))["video"])
        np.testing.assert_array_equal(got, want, err_msg=f"rank {rank} vae step {step}")
        print(f"rank {rank} vae rows {loader.rows.tolist()} cut {clips_cut} of {BATCH}", flush=True)
    vae_data._cut = real_cut

    drawn = []

    def squares(step, rows):
        drawn.append(len(rows))
        return np.asarray(moving_squares(key=jax.random.key(step), batch=BATCH, frames=5, size=16, rows=rows))

    loader = vae_data.VideoLoader(squares, BATCH, mesh)
    got = np.asarray(gather(loader.place(loader.host_batch_at(1)))["video"])
    np.testing.assert_array_equal(got, moving_squares(key=jax.random.key(1), batch=BATCH, frames=5, size=16))
    print(f"rank {rank} squares rows {loader.rows.tolist()} drew {drawn[0]} of {BATCH}", flush=True)



def check_light_loader(rank: int, mesh, gather) -> None:
    latents = np.asarray(jax.random.normal(jax.random.key(0), (5, 6, 2, 2, 4)))
    cut = []
    real_cut = light_train.cut_clip
    light_train.cut_clip = lambda *args: cut.append(args[1:3]) or real_cut(*args)
    loader = light_train.clip_loader(light_train.ClipSampler(latents, batch=BATCH, clip_latents=2, seed=0), mesh)
    single = light_train.ClipSampler(latents, batch=BATCH, clip_latents=2, seed=0)
    for step in range(3):
        want = single.batch_at(step)
        cut.clear()
        held = loader.host_batch_at(step)
        clips_cut = len(cut)
        got = np.asarray(gather(loader.place(held))["latents"])
        np.testing.assert_array_equal(got, want, err_msg=f"rank {rank} light step {step}")
        print(f"rank {rank} light rows {loader.rows.tolist()} cut {clips_cut} of {BATCH}", flush=True)
    light_train.cut_clip = real_cut


if __name__ == "__main__":
    main()
