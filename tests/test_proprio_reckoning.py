"""Proprio dead-reckoned from actions for imagined rollouts (sword_jax.rl.proprio_reckoning)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl.policy import axis_angle_to_matrix
from sword_jax.rl.proprio_reckoning import ReckoningConfig, fit_gains, matrix_to_axis_angle, reckon, reckon_step


def _angle_between(a, b):
    r = np.asarray(axis_angle_to_matrix(jnp.asarray(a))).T @ np.asarray(axis_angle_to_matrix(jnp.asarray(b)))
    return np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))


def test_matrix_to_axis_angle_inverts_rodrigues_up_to_180_degrees():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(64, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angles = np.concatenate([rng.uniform(0, np.pi - 1e-3, 60), [0.0, 1e-6, np.pi - 1e-4, np.pi - 1e-2]])
    aa = axes * angles[:, None]
    back = np.asarray(matrix_to_axis_angle(axis_angle_to_matrix(jnp.asarray(aa, jnp.float32))))
    for a, b in zip(aa, back):
        assert _angle_between(a, b) < 0.05  # the same rotation (axis-angle is not unique at 180 degrees)
    np.testing.assert_allclose(back[:60], aa[:60], atol=2e-3)


def test_reckon_step_follows_the_action_convention():
    cfg = ReckoningConfig()
    p = jnp.asarray([0.1, -0.2, 1.0, 0.0, 0.0, 0.3, 0.04, -0.04], jnp.float32)
    still = reckon_step(p, jnp.asarray([0, 0, 0, 0, 0, 0, -1.0]), cfg)
    np.testing.assert_allclose(np.asarray(still), np.asarray(p), atol=1e-6)  # open gripper stays open
    moved = reckon_step(p, jnp.asarray([1.0, -0.5, 0.2, 0, 0, 0.4, 1.0]), cfg)
    np.testing.assert_allclose(np.asarray(moved[:3]), [0.15, -0.225, 1.01], atol=1e-6)
    np.testing.assert_allclose(np.asarray(moved[3:6]), [0, 0, 0.5], atol=1e-5)  # z rotations add
    assert 0 <= float(moved[6]) < 0.04 and float(moved[7]) == -float(moved[6])  # closing, mirrored
    many = reckon(p, jnp.tile(jnp.asarray([0.0, 0, 0, 0, 0, 0, 1.0]), (40, 1)), cfg)
    assert many.shape == (40, 8) and float(many[-1, 6]) < 1e-4  # fingers close fully without an object


def test_reckoning_tracks_the_c_engine_better_than_holding_the_start_proprio():
    """Against the simulator's own proprio over 8-step windows of noisy-expert episodes."""
    from sim import config as sim_config, controller, expert, panda, tasks
    from sim import env as sim_env

    ctl = controller.ControllerConfig()
    cfg = ReckoningConfig(pos_scale=ctl.pos_scale, rot_scale=ctl.rot_scale, finger_open=panda.FINGER_OPEN,
                          finger_closed_target=panda.FINGER_CLOSED_TARGET)
    starts, actions, targets, episodes = [], [], [], []
    for task in (0, 5):
        env = sim_env.make_env(sim_config.SimConfig(backend="cpu"), task)
        qpos = tasks.split_init_states(task, "train", 1)[0]
        out = expert.rollout_cpu(env, qpos, cfg=expert.ExpertConfig(noise=0.1), rng=np.random.default_rng(task),
                                 record=True, stop_at_success=False, max_steps=64)
        prop = np.stack([np.asarray(s.obs["proprio"], np.float32) for s in out["states"]])
        episodes.append((prop[:-1], out["executed"]))
        for s in range(0, 64 - 8 + 1, 4):
            starts.append(prop[s]), actions.append(out["executed"][s:s + 8]), targets.append(prop[s + 8])
    cfg = fit_gains(np.stack([p for p, _ in episodes]), np.stack([a for _, a in episodes]), cfg)
    assert 0.2 < cfg.rot_gain[2] < 0.7 and all(0.5 < g < 1.5 for g in cfg.pos_gain), cfg  # yaw under-realised
    pred = np.asarray(jax.jit(lambda p, a: reckon(p, a, cfg))(jnp.asarray(np.stack(starts)),
                                                                jnp.asarray(np.stack(actions), jnp.float32)))[:, -1]
    targets, starts = np.stack(targets), np.stack(starts)
    err = np.linalg.norm(pred[:, :3] - targets[:, :3], axis=-1).mean()
    hold = np.linalg.norm(starts[:, :3] - targets[:, :3], axis=-1).mean()
    assert err < 0.04 and err < 0.5 * hold, (err, hold)  # measured: ~1.9 cm vs the arm's motion
    rot_err = np.mean([_angle_between(a[3:6], b[3:6]) for a, b in zip(pred, targets)])
    rot_hold = np.mean([_angle_between(a[3:6], b[3:6]) for a, b in zip(starts, targets)])
    assert rot_err < 8.0 and rot_err < rot_hold, (rot_err, rot_hold)


def test_config_names_the_bad_imagined_proprio_setting():
    import pytest

    from sword_jax.rl.config import ImaginedConfig, RLConfig

    with pytest.raises(ValueError, match=r"rl\.imagined\.proprio"):
        RLConfig(imagined=ImaginedConfig(proprio="guess")).validate()
    RLConfig(imagined=ImaginedConfig(proprio="missing")).validate()
    with pytest.raises(ValueError, match="pos_gain"):
        ReckoningConfig(pos_gain=(1.0, 1.0)).validate()


def test_masked_proprio_act_runs_the_missing_proprio_mode():
    """``act(..., proprio_valid=0)`` (rl.imagined.eval_masked_proprio, rl.env.proprio=missing) is the policy with proprio
    marked missing -- the mode GRPO trains in a simulator that reports none -- and differs from the default."""
    from flax import nnx

    from sword_jax.rl.config import PolicyConfig, RLConfig
    from sword_jax.rl.env_rollout import make_act_fns
    from sword_jax.rl.policy import build_policy, resize_frames, tokenize_instructions

    rl = RLConfig(image_size=8, action_bins=8,
                  policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32))
    graphdef, params = build_policy(rl, seed=0)
    frames = jax.random.randint(jax.random.key(1), (3, 16, 16, 3), 0, 256).astype(jnp.uint8)
    tokens = jnp.asarray(tokenize_instructions(["a", "b", "c"], 32))
    proprio = jax.random.normal(jax.random.key(2), (3, 8))
    key = jax.random.key(3)
    act = make_act_fns(graphdef, rl)
    _, _, lp_valid, _ = act(params, frames, tokens, proprio, key, greedy=True)
    _, chunk, lp_masked, _ = act(params, frames, tokens, proprio, key, greedy=True, proprio_valid=jnp.zeros((3,)))
    # jitted: eager op-by-op dispatch of the forward pass takes several times longer
    logits = jax.jit(lambda p: nnx.merge(graphdef, p)(resize_frames(frames, 8), tokens, 0.0 * proprio,
                                                     jnp.zeros((3,))))(params)
    want = jnp.take_along_axis(jax.nn.log_softmax(logits, -1), chunk[..., None], -1)[..., 0]
    np.testing.assert_allclose(np.asarray(lp_masked), np.asarray(want), atol=1e-5)  # proprio values ignored
    assert not np.allclose(np.asarray(lp_valid), np.asarray(lp_masked))


class _StillArmEnvs:
    """A lockstep env whose proprio never moves (so reckoned and true proprio differ once it acts)."""

    def __init__(self, n: int, max_steps: int):
        self.n, self.language, self.max_steps = n, ["pick up the bowl"] * n, max_steps
        self.start = np.tile(np.asarray([[0.1, -0.2, 1.0, 0.0, 0.0, 0.3, 0.04, -0.04]], np.float32), (n, 1))
        self.executed: list[np.ndarray] = []

    def _obs(self):
        return {"frames": np.full((self.n, 16, 16, 3), 90, np.uint8), "proprio": self.start.copy()}

    def reset(self, episodes=None):
        self.executed = []
        return self._obs()

    def step(self, actions):
        self.executed.append(np.asarray(actions, np.float32))
        done = np.full(self.n, sum(a.shape[1] for a in self.executed) >= self.max_steps)
        return dict(self._obs(), success=np.zeros(self.n, bool), executed=np.full(self.n, actions.shape[1]),
                    done=done)

    def close(self):
        pass


@pytest.mark.parametrize("mode", ["true", "reckoned", "missing"])
def test_env_rollouts_feed_the_policy_the_configured_proprio_mode(mode):
    """rl.env.proprio: ground-truth rollouts read true, dead-reckoned or missing proprio, and record what
    was read, so GRPO's update recomputes the same log-probs (the learned simulator's input modes,
    isolated from world-model error)."""
    from flax import nnx

    from sword_jax.rl.config import EnvConfig, PolicyConfig, RLConfig
    from sword_jax.rl.env_rollout import make_act_fns, run_policy
    from sword_jax.rl.policy import build_policy, resize_frames

    rl = RLConfig(image_size=8, action_bins=8,
                  policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32),
                  env=EnvConfig(execute_steps=4, action_ensemble=False, proprio=mode))
    graphdef, params = build_policy(rl, seed=0)
    envs = _StillArmEnvs(n=3, max_steps=12)
    reckoning = ReckoningConfig(pos_gain=(0.9, 0.9, 0.8), rot_gain=(0.9, 0.8, 0.4))
    rollout = run_policy(make_act_fns(graphdef, rl), params, envs, rl, key=jax.random.key(4), greedy=False,
                         max_steps=12, proprio=mode, reckoning=reckoning)
    assert rollout.proprio.shape == (3, 3, 8)
    np.testing.assert_allclose(rollout.proprio[:, 0], envs.start)  # every mode starts from the episode's proprio
    if mode == "reckoned":
        executed = np.concatenate(envs.executed, axis=1)  # [n, 12, 7]
        want = np.asarray(reckon(jnp.asarray(envs.start), jnp.asarray(executed), reckoning))
        np.testing.assert_allclose(rollout.proprio[:, 1], want[:, 3], atol=1e-5)
        np.testing.assert_allclose(rollout.proprio[:, 2], want[:, 7], atol=1e-5)
        assert np.abs(rollout.proprio[:, 2] - envs.start).max() > 1e-3
    else:
        np.testing.assert_allclose(rollout.proprio, np.broadcast_to(envs.start[:, None], (3, 3, 8)))
    np.testing.assert_array_equal(rollout.proprio_valid, 0.0 if mode == "missing" else 1.0)
    # the recorded inputs reproduce the sampled tokens' log-probs (what grpo_update relies on)
    logits = nnx.merge(graphdef, params)(resize_frames(jnp.asarray(rollout.obs_frames[:, 1]), 8),
                                         jnp.asarray(rollout.instruction_tokens), jnp.asarray(rollout.proprio[:, 1]),
                                         jnp.asarray(rollout.proprio_valid[:, 1]))
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits, -1)[:, :4], jnp.asarray(rollout.tokens[:, 1])[..., None],
                               -1)[..., 0]
    np.testing.assert_allclose(np.asarray(logp), rollout.log_probs[:, 1], atol=1e-4)


def test_env_proprio_mode_errors_name_the_setting():
    from sword_jax.rl.config import EnvConfig, RLConfig
    from sword_jax.rl.env_rollout import run_policy

    with pytest.raises(ValueError, match=r"rl\.env\.proprio"):
        RLConfig(env=EnvConfig(proprio="guess")).validate()
    with pytest.raises(ValueError, match="ReckoningConfig"):
        run_policy(None, None, _StillArmEnvs(1, 4), RLConfig(), key=jax.random.key(0), greedy=True, max_steps=4,
                   proprio="reckoned")


def test_reckoning_file_round_trips_and_names_bad_fields(tmp_path):
    import json

    from sword_jax.rl.proprio_reckoning import load_reckoning, save_reckoning

    cfg = ReckoningConfig(pos_gain=(0.87, 0.88, 0.82), rot_gain=(0.92, 0.76, 0.39))
    save_reckoning(str(tmp_path / "r.json"), cfg)
    assert load_reckoning(str(tmp_path / "r.json")) == cfg
    (tmp_path / "bad.json").write_text(json.dumps({"pos_gain": [1, 1, 1], "yaw_fudge": 2}))
    with pytest.raises(ValueError, match="yaw_fudge"):
        load_reckoning(str(tmp_path / "bad.json"))
    with pytest.raises(FileNotFoundError, match="missing.json"):
        load_reckoning(str(tmp_path / "missing.json"))
