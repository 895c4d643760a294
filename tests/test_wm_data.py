"""Latent dataset: segment layout, deterministic resumable sampler, file loading, bad input."""

import h5py
import jax
import numpy as np
import pytest

from sword_jax import sharding as shd
from sword_jax.world_model import data
from tests.support.world_model import full_mesh, tiny_dataset


def test_segment_layout_matches_slots():
    ds = tiny_dataset(num_episodes=3, num_latents=6)
    batch = ds.segment(np.array([2, 0]), np.array([3, 1]), 1, 2)
    np.testing.assert_array_equal(batch["latents"][0], ds.latents[2, [0, 3, 4, 5]])
    np.testing.assert_array_equal(batch["latents"][1], ds.latents[0, [0, 1, 2, 3]])
    # actions: frame 0, then video frames 4*3-3 = 9 .. 4*5 = 20
    np.testing.assert_array_equal(batch["actions"][0], ds.actions[2, [0] + list(range(9, 21))])
    np.testing.assert_array_equal(batch["actions"][1], ds.actions[0, list(range(0, 13))])
    assert batch["actions"].shape == (2, 13, 7)
    with pytest.raises(ValueError, match="out of range"):
        ds.segment(np.array([0]), np.array([4]), 1, 2)


def test_sampler_visits_every_segment_once_per_epoch_and_resumes_exactly():
    sampler = data.SegmentSampler(5, 6, 1, 2, 4, seed=3)  # 5 episodes x 3 starts = 15 segments
    first_epoch = [sampler.next_indices() for _ in range(3)]  # 12 of 15
    saved = sampler.position
    rest = [sampler.next_indices() for _ in range(4)]  # crosses into epoch 1
    seen = np.concatenate([np.stack(b, 1) for b in first_epoch] + [np.stack(rest[0], 1)[:3]])
    assert len({tuple(s) for s in seen}) == 15
    resumed = data.SegmentSampler(5, 6, 1, 2, 4, seed=3)
    resumed.restore(saved)
    for expected in rest:
        got = resumed.next_indices()
        np.testing.assert_array_equal(got[0], expected[0])
        np.testing.assert_array_equal(got[1], expected[1])
    other_seed = data.SegmentSampler(5, 6, 1, 2, 4, seed=4).next_indices()
    assert not np.array_equal(np.stack(other_seed), np.stack(first_epoch[0]))
    with pytest.raises(ValueError, match="position"):
        resumed.restore({"epoch": 0, "index": 99})


@pytest.mark.parametrize("batch_size", [4, 5, 35])  # 15 segments: crossing, meeting, spanning epoch ends
def test_sampler_batch_of_a_step_equals_the_sequential_batch(batch_size):
    sequential = data.SegmentSampler(5, 6, 1, 2, batch_size, seed=3)
    pure = data.SegmentSampler(5, 6, 1, 2, batch_size, seed=3)
    for step in range(8):
        assert pure.position_at(step) == sequential.position
        np.testing.assert_array_equal(np.stack(pure.indices_at(step)), np.stack(sequential.next_indices()))
    np.testing.assert_array_equal(np.stack(pure.indices_at(5)), np.stack(data.SegmentSampler(
        5, 6, 1, 2, batch_size, seed=3).indices_at(5)))  # out of order, from a fresh sampler: the same batch
    assert pure.position_at(8) == sequential.position


def test_loader_batches_are_global_and_sharded():
    mesh = full_mesh()
    ds = tiny_dataset()
    loader = data.SegmentLoader(ds, data.SegmentSampler(8, 6, 1, 2, 8, seed=0), 1, 2, mesh)
    batch = loader.next()
    assert batch["latents"].shape == (8, 4, 2, 2, 8)
    assert len(batch["latents"].sharding.device_set) == 8 and batch["latents"].sharding.spec[0] is not None
    assert all(batch[name].sharding == loader.shardings[name] for name in batch)
    expected = ds.segment(np.asarray(batch["episode"]), np.asarray(batch["start"]), 1, 2)
    for name, value in expected.items():  # every entry, placed as sharding.put places it
        np.testing.assert_array_equal(np.asarray(batch[name]), value)


def test_rows_held_are_the_rows_of_a_process_devices():
    """A process reads only the rows its devices hold (here a "process" is a subset of the fake devices; the
    two-process run is ``tests/test_launch.py``'s); on one process the loader reads the whole batch."""
    mesh = shd.make_mesh(shd.MeshConfig(data=2, tensor=4))
    sharding = data.batch_shardings(mesh, {"episode": np.zeros(8)})["episode"]
    first_data_slot = list(mesh.devices[0].flat)  # 4 devices, one row block, replicated over tensor
    assert shd.rows_held(sharding, 8, first_data_slot).tolist() == [0, 1, 2, 3]
    assert shd.rows_held(sharding, 8, list(mesh.devices[1].flat)[:1]).tolist() == [4, 5, 6, 7]
    odd = data.batch_shardings(mesh, {"episode": np.zeros(5)})["episode"]  # 5 rows: replicated
    assert shd.rows_held(odd, 5, first_data_slot[:1]).tolist() == [0, 1, 2, 3, 4]
    loader = data.SegmentLoader(tiny_dataset(), data.SegmentSampler(8, 6, 1, 2, 8, seed=0), 1, 2, full_mesh())
    assert loader.rows.tolist() == list(range(8)) and len(loader.host_batch_at(0)["episode"]) == 8


def test_a_batch_that_does_not_split_over_the_devices_is_refused_naming_the_numbers():
    """Not replicated: every device would compute the whole batch and every process read all of it."""
    mesh = shd.make_mesh(shd.MeshConfig(data=4, tensor=2))
    with pytest.raises(ValueError, match=r"data.batch_size=6 does not split over the 4 devices .*'data': 4.* "
                                         r"8 devices in 1 process\): use a multiple of 4"):
        data.SegmentLoader(tiny_dataset(), data.SegmentSampler(8, 6, 1, 2, 6, seed=0), 1, 2, mesh)
    loader = data.SegmentLoader(tiny_dataset(), data.SegmentSampler(8, 6, 1, 2, 4, seed=0), 1, 2, mesh)
    assert loader.shardings["latents"].spec[0] == "data"  # 4 rows: one per data slot


def test_load_npz_and_h5_and_reject_bad_files(tmp_path):
    ds = tiny_dataset(num_episodes=2, num_latents=3)
    np.savez(tmp_path / "d.npz", latents=ds.latents, actions=ds.actions)
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f["latents"], f["actions"] = ds.latents, ds.actions
    for name in ("d.npz", "d.h5"):
        loaded = data.load_latent_dataset(str(tmp_path / name))
        np.testing.assert_array_equal(loaded.latents, ds.latents)
    np.savez(tmp_path / "bad.npz", latents=ds.latents)
    with pytest.raises(ValueError, match="actions"):
        data.load_latent_dataset(str(tmp_path / "bad.npz"))
    (tmp_path / "corrupt.h5").write_bytes(b"not hdf5")
    with pytest.raises(ValueError, match="cannot read"):
        data.load_latent_dataset(str(tmp_path / "corrupt.h5"))
    with pytest.raises(ValueError, match="actions shape"):
        data.LatentDataset(ds.latents, ds.actions[:, :-1])
    nan = ds.latents.copy()
    nan[0, 0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        data.LatentDataset(nan, ds.actions)


def test_synthetic_latents_depend_on_actions():
    a = data.synthetic_latent_dataset(2, 4, 2, 2, 8, seed=0)
    assert a.latents.shape == (2, 4, 2, 2, 8) and a.actions.shape == (2, 13, 7)
    np.testing.assert_array_equal(a.latents, data.synthetic_latent_dataset(2, 4, 2, 2, 8, seed=0).latents)
    assert jax.numpy.isfinite(a.latents).all()
