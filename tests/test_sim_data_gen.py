"""``python -m train.gen_data`` smoke test: one tiny expert episode at 32x32 on the C engine."""

import numpy as np
import pytest

from sim.dataset import read_dataset
from sword_jax.cli import UsageError
from train import gen_data


def test_gen_data_writes_a_readable_libero_file(tmp_path):
    out = str(tmp_path / "demo.hdf5")
    gen_data.main(["--task", "2", "--episodes", "1", "--out", out, "--resolution", "32", "--max-steps", "6",
                   "--renderer", "jax"])
    info, episodes = read_dataset(out)
    assert info.num_demos == 1 and info.total == 6 and info.env_args["env_kwargs"]["tasks"] == [2]
    assert info.env_args["env_kwargs"]["renderer"] == "jax"
    assert "from table center" in info.problem_info["language_instruction"]
    ep = episodes[0]
    assert ep.actions.shape == (6, 7) and np.all(np.abs(ep.actions) <= 1.0) and ep.task_id == 2
    assert ep.agentview_rgb.shape == (6, 32, 32, 3) and ep.eye_in_hand_rgb.shape == (6, 32, 32, 3)
    assert ep.dones[-1] == 1 and ep.ee_states.shape == (6, 6) and ep.gripper_states.shape == (6, 2)
    # Depth is metric: the agentview camera sits ~0.7-1.5 m from the table.
    assert 0.3 < np.median(ep.agentview_depth[0]) < 2.5
    classes = info.seg_class_names
    seen = {classes[c] for c in np.unique(ep.agentview_seg[0])}
    assert {"table", "robot", "plate_1"} <= seen, seen
    # The recorded state is the sim state: qpos[:7] inside it equals the joint states.
    np.testing.assert_allclose(ep.states[:, 1:8], ep.joint_states)
    np.testing.assert_allclose(ep.init_state, ep.states[0])
    # The arm moves under the expert's actions, so frames differ over time.
    assert not np.array_equal(ep.agentview_rgb[0], ep.agentview_rgb[-1])
    with pytest.raises(FileExistsError, match="overwrite"):
        gen_data.main(["--task", "2", "--episodes", "1", "--out", out, "--resolution", "32", "--max-steps", "6"])


def test_gen_data_config_errors(tmp_path):
    with pytest.raises(ValueError, match="tasks"):
        gen_data.GenDataConfig(out=str(tmp_path / "a.hdf5"), tasks=(12,)).validate()
    with pytest.raises(ValueError, match="renderer=gl needs backend=cpu"):
        gen_data.GenDataConfig(out=str(tmp_path / "a.hdf5"), backend="mjx", renderer="gl").validate()
    with pytest.raises(ValueError, match="hdf5"):
        gen_data.GenDataConfig(out=str(tmp_path / "a.txt")).validate()
    with pytest.raises(UsageError, match="--task"):
        gen_data.main(["--task", "seven", "--out", str(tmp_path / "a.hdf5")])


def test_config_from_sim_section(tmp_path):
    from sim.config import SimConfig

    cfg = gen_data.config_from_sim(SimConfig(tasks=(1, 4), episodes_per_task=3, resolution=64, expert_noise=0.1),
                                   str(tmp_path / "d.hdf5"), seed=5)
    cfg.validate()
    assert cfg.tasks == (1, 4) and cfg.episodes == 3 and cfg.resolution == 64 and cfg.noise == 0.1 and cfg.seed == 5


def test_gen_data_gl_renderer_matches_jax_labels(tmp_path):
    """The fast CPU path (MuJoCo's OpenGL renderer) writes the same classes and depths."""
    from sim.render_gl import gl_available

    ok, reason = gl_available()
    if not ok:
        pytest.skip(reason)
    paths = {}
    for renderer in ("gl", "jax"):
        paths[renderer] = str(tmp_path / f"{renderer}.hdf5")
        gen_data.generate(gen_data.GenDataConfig(out=paths[renderer], tasks=(0,), resolution=32, max_steps=2,
                                                 renderer=renderer), progress=False)
    (_, [gl]), (_, [jx]) = read_dataset(paths["gl"]), read_dataset(paths["jax"])
    np.testing.assert_array_equal(gl.actions, jx.actions)
    assert np.mean(gl.agentview_seg == jx.agentview_seg) > 0.95
    assert np.median(np.abs(gl.agentview_depth - jx.agentview_depth)) < 1e-3
