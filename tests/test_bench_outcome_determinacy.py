"""benchmarks.bench_outcome_determinacy: a pixel's width at a depth, an object moved by a set offset, a replay that
repeats itself, the flip counts of designed outcomes, the refused command lines, and a tiny run end to end."""

import json
import re

import mujoco
import numpy as np
import pytest

from benchmarks import bench_outcome_determinacy as od
from sword_jax.cli import UsageError

_CAMERA = """<mujoco><worldbody>
  <camera name="agentview" pos="0 0 0" xyaxes="1 0 0 0 1 0" fovy="90"/>
  <body name="ball" pos="0 0 -2"><freejoint/><geom size="0.1"/></body>
</worldbody></mujoco>"""


def test_a_pixel_is_as_wide_as_the_view_at_that_depth_over_the_resolution():
    model = mujoco.MjModel.from_xml_string(_CAMERA)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    # fovy 90: the view is 2 x depth high; the camera looks along its -z
    assert od.metres_per_pixel(model, data, np.array([0.3, -0.2, -2.0]), 100) == pytest.approx(4.0 / 100)
    assert od.metres_per_pixel(model, data, np.array([0.0, 0.0, -0.5]), 128) == pytest.approx(1.0 / 128)
    with pytest.raises(ValueError, match="behind camera 'agentview'"):
        od.metres_per_pixel(model, data, np.array([0.0, 0.0, 1.0]), 128)
    assert od.free_joint_qpos(model, model.body("ball").id) == 0
    with pytest.raises(ValueError, match="body 'world' has no free joint"):
        od.free_joint_qpos(model, 0)


def test_the_bowl_moves_by_the_offset_and_a_replay_repeats_itself():
    from sim import expert
    from sim.config import SimConfig
    from sim.env import CpuEnv

    env = CpuEnv(SimConfig(resolution=16), 2)
    out = expert.rollout_cpu(env, env.init_states[0], record=True)
    assert out["success"]
    actions = np.asarray(out["actions"], np.float64)
    start = env.reset_to(env.init_states[0]).data  # the settled start the expert acted from
    flat = np.concatenate([[start.time], start.qpos, start.qvel])
    kept = flat.copy()
    adr = od.free_joint_qpos(env.mj_model, env.bowl_body)
    before = env.restore(flat).data.xpos[env.bowl_body].copy()
    moved = od.displaced(flat, adr, np.array([0.004, -0.003]))
    np.testing.assert_allclose(env.restore(moved).data.xpos[env.bowl_body] - before, [0.004, -0.003, 0.0], atol=1e-9)
    assert np.array_equal(flat, kept)  # the given state is left as it was
    # the expert's actions from its own start succeed, twice alike; cut before the place they do not
    assert od.replay(env, flat, actions) and od.replay(env, flat, actions)
    assert not od.replay(env, flat, actions[: len(actions) // 3])
    # the bowl carried 30 cm away: the same actions close on nothing
    assert not od.replay(env, od.displaced(flat, adr, np.array([0.3, 0.0])), actions)


def test_flips_kept_and_false_successes_are_counted_per_group_and_perturbation():
    reference = np.array([True, False, True])
    nan = np.nan
    succeeded = {"bowl, 1 px": np.array([[0.0, 1.0], [0.0, 0.0], [nan, nan]]),  # start 2 (held) not replayed
                 "plate, 1 px": np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 0.0]])}
    out = od.summarise({"all": np.ones(3, bool), "first": np.array([True, False, False])}, reference, succeeded)
    every = out["all"]
    assert every["starts"] == 3 and every["reference_success"] == pytest.approx(2 / 3)
    assert every["measured_starts"] == {"bowl, 1 px": 2, "plate, 1 px": 3}
    assert every["flipped"] == {"bowl, 1 px": 0.25, "plate, 1 px": 0.5}  # 1 of 4 replays; 3 of 6
    assert every["starts_with_a_flip"] == {"bowl, 1 px": 0.5, "plate, 1 px": pytest.approx(2 / 3)}
    assert every["kept"] == {"bowl, 1 px": 0.5, "plate, 1 px": 0.75}  # the successes' replays still succeeding
    assert every["false_success"] == {"bowl, 1 px": 0.0, "plate, 1 px": 1.0}  # the failure's replays succeeding
    assert out["first"]["flipped"] == {"bowl, 1 px": 0.5, "plate, 1 px": 0.0}
    assert out["first"]["false_success"] == {"bowl, 1 px": None, "plate, 1 px": None}  # no failure among its starts
    empty = od.summarise({"none": np.zeros(3, bool)}, reference, succeeded)["none"]
    assert empty["starts"] == 0 and empty["reference_success"] is None and empty["flipped"]["bowl, 1 px"] is None


def test_directions_are_unit_vectors():
    d = od.directions(np.random.default_rng(0), 50)
    assert d.shape == (50, 2)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)


@pytest.mark.parametrize("flags, message", [
    (["--scales-px", "0.5,x"], "--scales-px must be a comma list of numbers, got '0.5,x'"),
    (["--scales-px", "0,1"], "--scales-px positive"),
    (["--draws", "0"], "--draws and --workers must be >= 1"),
    (["--workers", "0"], "--draws and --workers must be >= 1"),
    (["--tiny-m", "-1"], "--tiny-m and --starts-before >= 0"),
    (["--starts-before", "-2"], "--tiny-m and --starts-before >= 0"),
    (["--over-m", "0"], "--temperature and --over-m must be > 0"),
    ([], "no such file"),
])
def test_bad_command_lines_are_refused(flags, message, tmp_path):
    with pytest.raises(UsageError, match=re.escape(message)):
        od.parse(["--policy", str(tmp_path / "missing.npz"), "--out", "o", *flags])


@pytest.mark.slow  # the policy's episodes rendered on the C engine, then the replays in 2 processes
def test_a_tiny_run_on_the_c_engine(tmp_path):
    """A random tiny policy: 2 episodes (none succeeds), 6 starts, 2 draws of two scales per object: every replay is
    counted once, a held bowl is never moved, and nothing flips where nothing succeeds."""
    import configs
    from sword_jax.rl.params_io import save_params_npz
    from sword_jax.rl.policy import build_policy

    _, params = build_policy(configs.get("sword:tiny").rl, seed=0)
    save_params_npz(str(tmp_path / "p.npz"), params)
    out = od.main(["--policy", str(tmp_path / "p.npz"), "--out", str(tmp_path), "--config", "sword:tiny",
                   "--episodes", "2", "--starts", "6", "--draws", "2", "--scales-px", "0.5,2", "--horizon", "2",
                   "--starts-before", "5"])
    assert out["episodes"] == 2 and out["episode_success"] == 0 and out["starts"] == 6
    assert out["resolution"] == 32 and out["metres_per_pixel"]["bowl"]["median"] > 0.005  # 32 px across the scene
    every = out["groups"]["all"]
    assert every["starts"] == 6 and every["reference_success"] == 0
    assert set(every["flipped"]) == {f"{o}, {s}" for o in od.OBJECTS for s in ("0.5 px", "2 px", "1e-06 m")}
    assert all(v == 0 for v in every["flipped"].values())  # a random policy solves nothing, moved or not
    assert every["measured_starts"]["plate, 2 px"] == 6
    assert out["replay_repeats_recorded"] == 1.0
    assert sum(out["groups"][f"stage: {s}"]["starts"] for s in
               ("before the grasp", "grasped", "over the plate", "after a release")) == 6
    saved = json.loads((tmp_path / "outcome_determinacy.json").read_text())
    assert saved["starts"] == 6 and saved["starts_before_decision"] == 5
    assert max(saved["per_start"]["step"]) < 5 * 4  # within the first 5 decisions of 4 actions
    assert saved["per_start"]["succeeded"]["plate, 2 px"] == [0] * 6 and saved["per_start"]["reference"] == [False] * 6
