"""Expert data: ``python -m train.gen_data`` and :mod:`sim.datagen` on tiny episodes."""

import os
import numpy as np
import pytest

from sim import datagen
from sim.dataset import Episode, read_dataset
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
        datagen.GenDataConfig(out=str(tmp_path / "a.hdf5"), tasks=(12,)).validate()
    with pytest.raises(ValueError, match="renderer=gl needs backend=cpu"):
        datagen.GenDataConfig(out=str(tmp_path / "a.hdf5"), backend="mjx", renderer="gl").validate()
    with pytest.raises(ValueError, match="hdf5"):
        datagen.GenDataConfig(out=str(tmp_path / "a.txt")).validate()
    with pytest.raises(UsageError, match="--task"):
        gen_data.main(["--task", "seven", "--out", str(tmp_path / "a.hdf5")])


def test_config_from_sim_section(tmp_path):
    from sim.config import SimConfig

    cfg = datagen.config_from_sim(SimConfig(tasks=(1, 4), episodes_per_task=3, resolution=64, expert_noise=0.1),
                                   str(tmp_path / "d.hdf5"), seed=5)
    cfg.validate()
    assert cfg.tasks == (1, 4) and cfg.episodes == 3 and cfg.resolution == 64 and cfg.noise == 0.1 and cfg.seed == 5
    assert cfg.stop_at_success and cfg.init_split == "train"
    fixed = datagen.config_from_sim(SimConfig(), str(tmp_path / "d.hdf5"), episode_steps=129, init_split="heldout")
    assert not fixed.stop_at_success and fixed.max_steps == 129 and fixed.init_split == "heldout"


def test_gen_data_gl_renderer_matches_jax_labels(tmp_path):
    """The fast CPU path (MuJoCo's OpenGL renderer) writes the same classes and depths."""
    from sim.render_gl import gl_available

    ok, reason = gl_available()
    if not ok:
        pytest.skip(reason)
    paths = {}
    for renderer in ("gl", "jax"):
        paths[renderer] = str(tmp_path / f"{renderer}.hdf5")
        datagen.generate(datagen.GenDataConfig(out=paths[renderer], tasks=(0,), resolution=32, max_steps=2,
                                                 renderer=renderer), progress=False)
    (_, [gl]), (_, [jx]) = read_dataset(paths["gl"]), read_dataset(paths["jax"])
    np.testing.assert_array_equal(gl.actions, jx.actions)
    assert np.mean(gl.agentview_seg == jx.agentview_seg) > 0.95
    assert np.median(np.abs(gl.agentview_depth - jx.agentview_depth)) < 1e-3


def near_identical_share(frames: np.ndarray, threshold: float = 0.5) -> float:
    """Share of consecutive frame pairs whose mean absolute difference is below ``threshold`` (of 255)."""
    diff = np.abs(np.diff(frames.astype(np.float32), axis=0)).mean(axis=(1, 2, 3))
    return float(np.mean(diff < threshold))


def test_fixed_length_episodes_keep_moving_after_success(tmp_path):
    """World-model data: 129 steps, the expert carries on after success, few near-identical frames."""
    out = str(tmp_path / "wm.hdf5")
    gen_data.main(["--task", "0", "--episodes", "1", "--out", out, "--resolution", "32", "--max-steps", "129",
                   "--no-wrist"])
    info, (ep,) = read_dataset(out)
    assert ep.num_samples == 129 and not info.env_args["env_kwargs"]["stop_at_success"]
    solved = np.flatnonzero(ep.rewards > 0)
    assert solved.size and ep.first_success == solved[0] < 80
    assert np.any(ep.rewards[ep.first_success:] == 0), "the bowl is moved on after success"
    assert near_identical_share(ep.agentview_rgb) < 0.05
    # The padded data this replaces (hold the last frame to 129) was mostly static.
    padded = np.concatenate([ep.agentview_rgb[:ep.first_success + 1]] + [ep.agentview_rgb[ep.first_success:][:1]] *
                            (128 - ep.first_success))
    assert near_identical_share(padded) > 0.5


# A property of the expert's episodes over several tasks (12 s on 2 cores); the default run generates data in
# test_parallel_generation_writes_the_same_file and test_fixed_length_episodes_keep_moving_after_success.
@pytest.mark.slow
def test_world_model_data_has_few_near_identical_frames_on_several_tasks(tmp_path):
    """Issue 18: the expert keeps the picture moving while the gripper acts (pipeline renderer, 32 px).

    Before it did, these episodes had 2-37% near-identical pairs (14% on average: the hand held
    still while the fingers closed or opened, and in task 1 a bowl hanging on the opened fingers
    was chased out of view).
    """
    out = str(tmp_path / "wm.hdf5")
    datagen.generate(datagen.GenDataConfig(out=out, tasks=(1, 3, 4, 7, 9), resolution=32, max_steps=129,
                                             wrist_camera=False, renderer="jax"), progress=False)
    _, episodes = read_dataset(out)
    assert all(ep.num_samples == 129 and ep.first_success >= 0 for ep in episodes)
    shares = [near_identical_share(ep.agentview_rgb) for ep in episodes]
    assert np.mean(shares) < 0.05 and max(shares) < 0.08, shares


def test_stop_at_success_demos_are_the_default_expert(tmp_path):
    """Policy SFT demos (``--stop-at-success``) are untouched by the world-model data's expert options:
    clean and DART-noisy demos equal a default-expert rollout and fingerprints recorded before the
    options changed, while the cycling expert acts differently on the same episodes."""
    import sim
    from sim import expert

    cfg = datagen.GenDataConfig(out=str(tmp_path / "sft.hdf5"), tasks=(2,), episodes=2, resolution=16, noise=0.1,
                                 noisy_share=0.5, stop_at_success=True, wrist_camera=False, renderer="jax")
    datagen.generate(cfg, progress=False)
    _, episodes = read_dataset(cfg.out)
    env = sim.load("libero_spatial", task_id=2, backend="cpu", resolution=16, max_steps=cfg.max_steps)
    recorded = ((40, [4.25143, 2.074, -4.83815, 0.01782, -0.11857, -0.02963, 6.0]),
                (38, [4.13541, 1.81883, -4.18697, 0.073, -0.01762, -0.01508, 6.0]))
    for i, (ep, qpos, (steps, action_sums)) in enumerate(zip(episodes, datagen.init_states(cfg, 2), recorded, strict=True)):
        noise = cfg.noise if datagen.noisy(cfg, i) else 0.0
        runs = {cycle: expert.rollout_cpu(env, qpos, cfg=expert.ExpertConfig(noise=noise, cycle=cycle),
                                          rng=np.random.default_rng([cfg.seed, 2, i]), max_steps=steps, record=True,
                                          stop_at_success=not cycle) for cycle in (False, True)}
        np.testing.assert_array_equal(ep.actions, runs[False]["actions"])
        np.testing.assert_array_equal(ep.executed_actions, runs[False]["executed"])
        assert ep.num_samples == steps and ep.first_success == steps - 1
        np.testing.assert_allclose(ep.actions.sum(axis=0), action_sums, atol=1e-4)
        assert not np.allclose(runs[True]["actions"], ep.actions), "the world-model options must change the expert"


def test_stop_at_success_demos_end_at_the_first_success(tmp_path):
    out = str(tmp_path / "sft.hdf5")
    gen_data.main(["--task", "2", "--episodes", "1", "--out", out, "--resolution", "16", "--max-steps", "120",
                   "--stop-at-success", "--no-wrist", "--renderer", "jax"])
    _, (ep,) = read_dataset(out)
    assert ep.first_success == ep.num_samples - 1 and ep.rewards[-1] == 1 and ep.rewards[:-1].max() == 0


def test_world_model_episodes_are_never_padded_and_use_executed_actions():
    from sim.data_stages import fixed_length

    steps = 9
    ep = Episode(actions=np.zeros((steps, 7)), states=np.zeros((steps, 5)), rewards=np.r_[np.zeros(6), np.ones(3)],
                 dones=np.zeros(steps), agentview_rgb=np.zeros((steps, 4, 4, 3), np.uint8), ee_states=np.zeros((steps, 6)),
                 gripper_states=np.zeros((steps, 2)), joint_states=np.zeros((steps, 7)),
                 executed_actions=np.ones((steps, 7)), first_success=6)
    (cut,) = fixed_length([ep], 5)
    assert cut.num_samples == 5 and np.all(cut.actions == 1) and cut.first_success == -1
    with pytest.raises(ValueError, match="padding"):
        fixed_length([ep], 13)


def test_parallel_generation_writes_the_same_file(tmp_path):
    """One process per task (``workers``) gives the episodes, order and attributes of one process."""
    from sim.dataset import read_info

    paths = {}
    for workers in (0, 2):
        paths[workers] = str(tmp_path / f"w{workers}.hdf5")
        datagen.generate(datagen.GenDataConfig(out=paths[workers], tasks=(0, 3), episodes=2, resolution=16,
                                                 max_steps=6, renderer="jax", noise=0.1, noisy_share=0.5,
                                                 wrist_camera=False, seed=3),
                          progress=False, workers=workers)
    (serial_info, serial), (parallel_info, parallel) = read_dataset(paths[0]), read_dataset(paths[2])
    assert read_info(paths[2]).env_args == read_info(paths[0]).env_args
    assert parallel_info.seg_class_names == serial_info.seg_class_names
    assert [e.task_id for e in parallel] == [0, 0, 3, 3]
    for a, b in zip(serial, parallel, strict=True):
        for name in ("actions", "states", "rewards", "agentview_rgb", "agentview_seg", "init_state"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert (a.init_state_id, a.first_success) == (b.init_state_id, b.first_success)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".gen_data_")], "temporary files are removed"


@pytest.mark.slow
def test_mjx_generation_runs_the_shared_expert_and_agrees_with_the_c_engine(tmp_path):
    """``--backend mjx`` rolls out ``sim.expert.episode_mjx`` (the one JAX expert, not a copy): its file
    has the C engine's layout, and its first actions and states agree with the C engine's from the same
    initial state (float32 physics vs float64: the tolerances of ``test_sim_mjx``). Minutes on a CPU."""
    files = {}
    for backend in ("cpu", "mjx"):
        files[backend] = str(tmp_path / f"{backend}.hdf5")
        gen_data.main(["--task", "2", "--episodes", "1", "--out", files[backend], "--resolution", "32",
                       "--max-steps", "4", "--renderer", "jax", "--no-wrist", "--backend", backend])
    (_, (cpu,)), (_, (mjx,)) = read_dataset(files["cpu"]), read_dataset(files["mjx"])
    assert mjx.actions.shape == cpu.actions.shape == (4, 7) and mjx.agentview_rgb.shape == (4, 32, 32, 3)
    # The same settled initial state ([time, qpos, qvel]): positions within 0.1 mm. Velocities within 5e-3: in
    # float32 a box resting on four corner contacts rocks at noise level (here up to 1.3e-3 rad/s after the
    # settle steps, 8.6e-3 at its peak; 0 in float64 MJX and in the C engine).
    import sim

    nq = sim.load("libero_spatial").mj_model.nq
    np.testing.assert_allclose(mjx.states[0][:1 + nq], cpu.states[0][:1 + nq], atol=1e-4)
    np.testing.assert_allclose(mjx.states[0][1 + nq:], cpu.states[0][1 + nq:], atol=5e-3)
    np.testing.assert_allclose(mjx.actions, cpu.actions, atol=2e-2)
    np.testing.assert_allclose(mjx.states[:, 1:10], cpu.states[:, 1:10], atol=2e-2)  # arm and fingers


def test_the_data_stage_records_exploring_expert_episodes_from_fresh_training_states(tmp_path):
    """data.exploration_episodes_per_task: the data stage writes exploration.hdf5, the expert with time-correlated
    noise executed (recorded as executed_actions beside the clean labels) from the training states after the world
    model's episodes and the demonstrations; without the setting it writes none."""
    import configs
    from sim import data_stages
    from sword_jax.pipeline.stages import Context

    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--sim.tasks=0", "--sim.episode_steps=33",
                                "--data.exploration_episodes_per_task=2", "--data.exploration_noise=0.4"])
    results = data_stages.generate_expert_data(Context(cfg=cfg, workdir=str(tmp_path), results={}))
    made = results["exploration"]
    info, episodes = read_dataset(made["path"])
    assert made["episodes"] == len(episodes) == 2 and made["path"].endswith("exploration.hdf5")
    kwargs = info.env_args["env_kwargs"]
    assert kwargs["expert_noise"] == 0.4 and kwargs["expert_noise_correlation"] == 0.9 and kwargs["noisy_share"] == 1.0
    _, demos = read_dataset(results["demos"]["path"])
    _, train = read_dataset(results["train"]["path"])
    taken = {e.init_state_id for e in train} | {e.init_state_id for e in demos}
    assert [e.init_state_id for e in episodes] == [max(taken) + 1, max(taken) + 2]
    assert all(e.init_split == "train" and e.executed_actions is not None for e in episodes)
    assert all(not np.allclose(e.executed_actions, e.actions) for e in episodes)
    plain, _ = configs.from_argv(["--config", "sword:tiny", "--sim.tasks=0", "--sim.episode_steps=33"])
    assert "exploration" not in data_stages.generate_expert_data(Context(cfg=plain, workdir=str(tmp_path / "p"),
                                                                         results={}))
    with pytest.raises(ValueError, match="data.exploration_correlation"):
        configs.from_argv(["--config", "sword:tiny", "--data.exploration_correlation=1"])[0].validate()
    with pytest.raises(ValueError, match="noise_correlation"):
        datagen.GenDataConfig(out=str(tmp_path / "a.hdf5"), noise_correlation=-0.1).validate()
