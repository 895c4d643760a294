"""LIBERO-layout HDF5 IO: round trip, real-LIBERO-style files, corrupt-file errors, gen_data smoke."""

import json
import os

import h5py
import numpy as np
import pytest

from sim.dataset import DatasetError, DatasetInfo, DatasetWriter, Episode, read_dataset, read_info, write_dataset


def _episode(steps=5, size=8, seed=0, depth=True):
    rng = np.random.default_rng(seed)
    return Episode(
        actions=rng.uniform(-1, 1, (steps, 7)),
        states=rng.normal(size=(steps, 20)),
        rewards=np.r_[np.zeros(steps - 1), 1.0],
        dones=np.r_[np.zeros(steps - 1), 1.0],
        agentview_rgb=rng.integers(0, 256, (steps, size, size, 3), dtype=np.uint8),
        eye_in_hand_rgb=rng.integers(0, 256, (steps, size, size, 3), dtype=np.uint8),
        ee_states=rng.normal(size=(steps, 6)),
        gripper_states=rng.normal(size=(steps, 2)),
        joint_states=rng.normal(size=(steps, 7)),
        agentview_depth=rng.uniform(0.5, 2.0, (steps, size, size)).astype(np.float32) if depth else None,
        agentview_seg=rng.integers(0, 10, (steps, size, size)) if depth else None,
        model_file="<mujoco/>",
        task_id=3,
        language_instruction="pick up the black bowl on the cookie box and place it on the plate",
    )


INFO = DatasetInfo(env_name="sword/LiberoSpatial-v0", env_args={"type": 1, "env_kwargs": {"a": 1}},
                   problem_info={"language_instruction": "x"}, bddl_file_name="x.bddl",
                   seg_class_names=("background", "table"))


def test_round_trip_preserves_everything(tmp_path):
    path = tmp_path / "demo.hdf5"
    episodes = [_episode(5, seed=0), _episode(3, seed=1, depth=False)]
    write_dataset(path, episodes, INFO)
    info, back = read_dataset(path)
    assert info.num_demos == 2 and info.total == 8 and info.env_args == INFO.env_args
    assert info.seg_class_names == ("background", "table") and info.image_convention == "cv"
    for original, loaded in zip(episodes, back):
        for name in ("actions", "states", "rewards", "dones", "agentview_rgb", "eye_in_hand_rgb",
                     "ee_states", "gripper_states", "joint_states"):
            np.testing.assert_array_equal(getattr(loaded, name), getattr(original, name), err_msg=name)
        assert loaded.task_id == 3 and loaded.model_file == "<mujoco/>"
        np.testing.assert_array_equal(loaded.init_state, original.states[0])
    np.testing.assert_array_equal(back[0].agentview_depth, episodes[0].agentview_depth)
    np.testing.assert_array_equal(back[0].agentview_seg, episodes[0].agentview_seg)
    assert back[1].agentview_depth is None and back[1].agentview_seg is None
    with h5py.File(path) as f:  # LIBERO's own layout and attributes
        demo = f["data/demo_0"]
        assert demo.attrs["num_samples"] == 5 and "ee_pos" in demo["obs"] and "robot_states" in demo
        assert json.loads(f["data"].attrs["env_args"])["type"] == 1 and f["data"].attrs["total"] == 8


def test_reads_libero_file_and_flips_opengl_images(tmp_path):
    """A file shaped like LIBERO's own (opengl images, no depth/seg, demos out of order)."""
    path = tmp_path / "libero.hdf5"
    rgb = np.zeros((4, 6, 6, 3), np.uint8)
    rgb[:, 0] = 255  # top row as stored = bottom row of the scene (opengl convention)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["macros_image_convention"] = "opengl"
        data.attrs["problem_info"] = json.dumps({"language_instruction": "pick up"})
        data.attrs["env_args"] = json.dumps({"type": 1})
        data.attrs["total"] = 8
        for name in ("demo_10", "demo_2"):
            demo = data.create_group(name)
            for key, shape in (("actions", (4, 7)), ("states", (4, 9)), ("rewards", (4,)), ("dones", (4,)),
                               ("obs/ee_states", (4, 6)), ("obs/gripper_states", (4, 2)),
                               ("obs/joint_states", (4, 7))):
                demo.create_dataset(key, data=np.zeros(shape))
            demo.create_dataset("obs/agentview_rgb", data=rgb)
            demo.create_dataset("obs/eye_in_hand_rgb", data=rgb)
            demo.attrs["num_samples"] = 4
    info, episodes = read_dataset(path)
    assert info.problem_info["language_instruction"] == "pick up" and len(episodes) == 2
    assert episodes[0].agentview_depth is None
    assert np.all(episodes[0].agentview_rgb[:, -1] == 255) and np.all(episodes[0].agentview_rgb[:, 0] == 0)
    _, raw = read_dataset(path, flip_opengl=False, demos=["demo_2"])
    assert np.all(raw[0].agentview_rgb[:, 0] == 255)


def test_never_overwrites_and_leaves_no_partial_file(tmp_path):
    path = tmp_path / "demo.hdf5"
    write_dataset(path, [_episode()], INFO)
    with pytest.raises(FileExistsError, match="overwrite"):
        write_dataset(path, [_episode()], INFO)
    write_dataset(path, [_episode(2)], INFO, overwrite=True)
    assert read_info(path).total == 2
    bad = _episode()
    bad.actions = bad.actions[:-1]
    with pytest.raises(DatasetError, match="length mismatch"):
        write_dataset(tmp_path / "new.hdf5", [_episode(), bad], INFO)
    assert not os.path.exists(tmp_path / "new.hdf5") and not os.path.exists(tmp_path / "new.hdf5.partial")


@pytest.mark.parametrize(
    "corrupt, message",
    [
        ("not_hdf5", "not an HDF5 file"),
        ("truncated", "not an HDF5 file|truncated|cannot be opened"),
        ("no_data", "no 'data' group"),
        ("missing_key", "missing dataset 'obs/joint_states'"),
        ("length", "length mismatch: rewards"),
        ("image_shape", "agentview_rgb must be"),
        ("num_samples", "num_samples attribute"),
        ("depth_shape", "agentview_depth must be"),
    ],
)
def test_corrupt_files_raise_clear_errors(tmp_path, corrupt, message):
    path = tmp_path / "bad.hdf5"
    if corrupt == "not_hdf5":
        path.write_text("definitely not hdf5")
    else:
        write_dataset(path, [_episode()], INFO)
        if corrupt == "truncated":
            raw = path.read_bytes()
            path.write_bytes(raw[: len(raw) // 3])
        else:
            with h5py.File(path, "a") as f:
                demo = f["data/demo_0"]
                if corrupt == "no_data":
                    del f["data"]
                elif corrupt == "missing_key":
                    del demo["obs/joint_states"]
                elif corrupt == "length":
                    del demo["rewards"]
                    demo.create_dataset("rewards", data=np.zeros(4))
                elif corrupt == "image_shape":
                    del demo["obs/agentview_rgb"]
                    demo.create_dataset("obs/agentview_rgb", data=np.zeros((5, 8, 8), np.uint8))
                elif corrupt == "num_samples":
                    demo.attrs["num_samples"] = 7
                elif corrupt == "depth_shape":
                    del demo["obs/agentview_depth"]
                    demo.create_dataset("obs/agentview_depth", data=np.zeros((5, 4, 4), np.float32))
    with pytest.raises(DatasetError, match=message):
        read_dataset(path)


def test_missing_file_and_bad_episode_inputs(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_dataset(tmp_path / "nope.hdf5")
    bad = _episode()
    bad.actions[0, 0] = np.nan
    with pytest.raises(DatasetError, match="non-finite"):
        bad.validate()
    with DatasetWriter(tmp_path / "x.hdf5", INFO) as writer:
        seg_bad = _episode()
        seg_bad.agentview_seg = seg_bad.agentview_seg + 300
        with pytest.raises(DatasetError, match="0..255"):
            writer.add(seg_bad)
    with h5py.File(tmp_path / "x.hdf5") as f:
        assert "demo_0" not in f["data"]  # a rejected episode leaves nothing behind


def test_add_file_equals_adding_each_episode(tmp_path):
    """Merging files by HDF5 object copy (parallel data generation) gives the file that adding each
    episode gives: same episodes, numbering, attributes and totals."""
    first, second = [_episode(5, seed=0), _episode(3, seed=1, depth=False)], [_episode(4, seed=2)]
    write_dataset(tmp_path / "a.hdf5", first, INFO)
    write_dataset(tmp_path / "b.hdf5", second, INFO)
    with DatasetWriter(tmp_path / "merged.hdf5", INFO) as writer:
        assert writer.add_file(tmp_path / "a.hdf5") == 2
        assert writer.add_file(tmp_path / "b.hdf5") == 1
    write_dataset(tmp_path / "direct.hdf5", first + second, INFO)
    (merged_info, merged), (direct_info, direct) = read_dataset(tmp_path / "merged.hdf5"), read_dataset(tmp_path / "direct.hdf5")
    assert (merged_info.num_demos, merged_info.total) == (direct_info.num_demos, direct_info.total) == (3, 12)
    for a, b in zip(merged, direct, strict=True):
        for name in ("actions", "states", "rewards", "agentview_rgb", "agentview_depth", "agentview_seg", "ee_states"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert (a.task_id, a.model_file, a.language_instruction) == (b.task_id, b.model_file, b.language_instruction)
    with h5py.File(tmp_path / "merged.hdf5") as m, h5py.File(tmp_path / "direct.hdf5") as d:
        assert sorted(m["data"]) == sorted(d["data"]) == ["demo_0", "demo_1", "demo_2"]
        assert dict(m["data/demo_2"].attrs).keys() == dict(d["data/demo_2"].attrs).keys()
    with h5py.File(tmp_path / "junk.hdf5", "w") as f:
        f.create_group("other")
    with DatasetWriter(tmp_path / "never.hdf5", INFO) as writer, pytest.raises(DatasetError, match="no 'data' group"):
        writer.add_file(tmp_path / "junk.hdf5")
