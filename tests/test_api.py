"""The public API (sword_jax.api) on a tiny trained run: loading, shapes and dtypes, envs, errors."""

import dataclasses
import os
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sword_jax
from sword_jax import tracing
from sword_jax.api import CheckpointError
from tests.conftest import REPO, example_env


@pytest.fixture(scope="module")
def model(tiny_run):
    return sword_jax.load_world_model(tiny_run)


def _given(model, batch=2, seed=0):
    spec = model.spec
    return jax.random.uniform(jax.random.key(seed), (batch, spec.given_frames, spec.image_size, spec.image_size, 3))


def test_import_is_light():
    code = "import sys, sword_jax; print('jax' in sys.modules, callable(sword_jax.load_world_model), 'jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=example_env(), capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "True", "True"]  # jax only once an API name is used


def test_every_path_form_loads_the_same_weights(tiny_run, model):
    spec = model.spec
    assert (spec.image_size, spec.num_context, spec.num_future, spec.action_dim, spec.latent_dim) == (32, 1, 2, 7, 48)
    assert (spec.given_frames, spec.frames_per_chunk, spec.num_actions(2)) == (5, 8, 21)
    assert spec.model.num_layers == 1  # the run's own config, not the default tiny one
    workdir = os.path.join(tiny_run, "world_model")
    assert model.loaded_from.world_model == workdir and model.loaded_from.step == 2
    assert model.loaded_from.vae == os.path.join(tiny_run, "vae_run", "vae") and model.reward_model is None
    for path in (workdir, os.path.join(workdir, "checkpoints"), os.path.join(workdir, "checkpoints", "2")):
        other = sword_jax.load_world_model(path)
        assert other.loaded_from.vae == model.loaded_from.vae  # the VAE is found beside the world model
        for a, b in zip(jax.tree.leaves(other), jax.tree.leaves(model)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    leaves = jax.tree.leaves(model.world_model_params)
    assert leaves and all(x.dtype == jnp.float32 and x.devices() == {jax.devices()[0]} for x in leaves)
    from sword_jax import sharding as shd

    mesh = shd.make_mesh(shd.MeshConfig())  # the tests' 8 fake devices
    sharded = sword_jax.load_world_model(tiny_run, mesh=mesh)
    for leaf in jax.tree.leaves((sharded.world_model_params, sharded.vae_params)):
        assert leaf.sharding.mesh == mesh


def test_encode_decode_rollout_shapes_dtypes_and_determinism(model):
    given = _given(model)
    latents = sword_jax.encode(model, given)
    assert latents.shape == (2, 2, 2, 2, 48) and latents.dtype == jnp.float32
    decoded = sword_jax.decode(model, latents)
    assert decoded.shape == given.shape and decoded.dtype == jnp.float32
    assert 0.0 <= float(decoded.min()) and float(decoded.max()) <= 1.0
    np.testing.assert_allclose(np.asarray(sword_jax.encode(model, np.rint(np.asarray(given) * 255).astype(np.uint8))),
                               np.asarray(sword_jax.encode(model, np.rint(given * 255) / 255)), atol=1e-5)
    actions = jax.random.uniform(jax.random.key(1), (2, model.spec.num_actions(2), 7), minval=-1.0, maxval=1.0)
    video = model.rollout(given, actions, key=jax.random.key(2))
    assert video.shape == (2, 21, 32, 32, 3) and video.dtype == jnp.float32
    assert 0.0 <= float(video.min()) and float(video.max()) <= 1.0
    # the given frames come back as the VAE reconstructs them (streaming decode == whole decode)
    np.testing.assert_allclose(np.asarray(video[:, :5]), np.asarray(decoded), atol=1e-4)
    again = model.rollout(given, actions, key=jax.random.key(2))
    other = model.rollout(given, actions, key=jax.random.key(3))
    np.testing.assert_array_equal(np.asarray(again), np.asarray(video))
    assert float(jnp.abs(other[:, 5:] - video[:, 5:]).max()) > 0  # the key drives the sampler
    with pytest.raises(ValueError, match="given_frames must be"):
        model.rollout(given[:, :4], actions, key=jax.random.key(2))
    with pytest.raises(ValueError, match="1 \\+ 4\\*1 \\+ 4\\*2\\*n"):
        model.rollout(given, actions[:, :20], key=jax.random.key(2))
    with pytest.raises(ValueError, match="\\[0, 1\\]"):
        sword_jax.encode(model, given * 255)


def test_latent_rollout_without_a_vae(tiny_run, tmp_path):
    alone = tmp_path / "wm"
    shutil.copytree(os.path.join(tiny_run, "world_model"), alone)
    latent_only = sword_jax.load_world_model(str(alone))
    assert latent_only.vae_params is None and latent_only.loaded_from.vae == ""
    first = jax.random.normal(jax.random.key(0), (2, 1, 2, 2, 48))
    context = jax.random.normal(jax.random.key(1), (2, 1, 2, 2, 48))
    predicted = sword_jax.rollout_latents(latent_only, first, context, jnp.zeros((2, 29, 7)), key=jax.random.key(2))
    assert predicted.shape == (2, 6, 2, 2, 48) and predicted.dtype == jnp.float32  # 3 chunks x 2 latents
    with pytest.raises(ValueError, match="without one"):
        sword_jax.encode(latent_only, jnp.zeros((1, 5, 32, 32, 3)))
    with pytest.raises(ValueError, match="actions must be"):
        sword_jax.rollout_latents(latent_only, first, context, jnp.zeros((2, 29, 6)), key=jax.random.key(2))


def _brightness(frames):
    return jnp.mean(frames, axis=(1, 2, 3))


def test_learned_simulator_brax_env_is_jittable_and_vmappable(model):
    pool = sword_jax.start_states(model, _given(model, 3)[:, 0], ["pick up the bowl", "open the drawer", "wait"])
    assert pool.latents.shape == (3, 2, 2, 2, 48) and pool.instruction_tokens.dtype == jnp.int32
    # the exact float32 simulator: a batched env equals one stepped alone to float32 rounding (bf16's differs by more)
    env = sword_jax.make_env(model, pool, reward_model=_brightness, max_chunks=2, precision="float32")
    assert env.action_size == 8 * 7 and env.action_shape == (8, 7) and env.observation_size["pixels/frame"] == (32, 32, 3)
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(tracing.max_traces(jax.vmap(env.step), n=1))  # one compile for every step
    state = reset(jax.random.split(jax.random.key(0), 4))
    assert state.obs["pixels/frame"].shape == (4, 32, 32, 3) and state.obs["proprio_valid"].shape == (4, 1)
    actions = jax.random.uniform(jax.random.key(1), (4, 8, 7), minval=-1.0, maxval=1.0)
    first = step(state, actions)
    second = step(first, actions)
    assert first.info["frames"].shape == (4, 8, 32, 32, 3) and first.reward.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(first.reward), np.asarray(_brightness(first.info["frames"][:, -1])
                                                                    - _brightness(state.obs["pixels/frame"])), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(second.done), 1.0)  # the 2-chunk limit
    # an env of the batch equals that env stepped alone
    single = jax.jit(env.step)(jax.tree.map(lambda x: x[1], state), actions[1].reshape(-1))  # flat, as brax's
    np.testing.assert_allclose(np.asarray(single.obs["pixels/frame"]), np.asarray(first.obs["pixels/frame"][1]),
                               atol=1e-4)
    with pytest.raises(ValueError, match="no reward model"):
        sword_jax.make_env(model, pool)


def test_vector_env_passes_gymnasium_checks(model):
    import gymnasium as gym
    from gymnasium.utils.env_checker import check_env, data_equivalence

    from sword_jax.rl.env import ImaginedGymEnv

    pool = sword_jax.start_states(model, _given(model, 3)[:, 0], ["a", "b", "c"])
    # one env: the same compiled functions as the single-env view that check_env drives below
    vec = sword_jax.make_vector_env(model, pool, 1, reward_model=_brightness, max_chunks=2)
    assert isinstance(vec, gym.vector.VectorEnv) and vec.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    assert vec.action_space == gym.vector.utils.batch_space(vec.single_action_space, 1)
    assert vec.observation_space == gym.vector.utils.batch_space(vec.single_observation_space, 1)
    assert vec.single_action_space.shape == (8, 7) and vec.single_observation_space["frame"].shape == (32, 32, 3)
    vec.action_space.seed(0)
    action = vec.action_space.sample()
    runs = []
    for _ in range(2):  # the same seed and actions give the same episode
        obs, info = vec.reset(seed=5)
        runs.append((obs, info, vec.step(action), vec.step(action), vec.step(action)))
    assert data_equivalence(runs[0], runs[1])
    obs, _, first, second, after = runs[0]
    for observation, reward, terminated, truncated, info in (first, second, after):
        assert vec.observation_space.contains(observation)
        assert reward.dtype == np.float32 and reward.shape == (1,)
        assert terminated.dtype == np.bool_ and truncated.dtype == np.bool_ and info["frames"].shape == (1, 8, 32, 32, 3)
    assert second[2][0] or second[3][0]  # the 2-chunk limit ends the episode ...
    assert after[1][0] == 0.0 and not (after[2][0] or after[3][0])  # ... and the next step resets it
    with pytest.raises(ValueError, match="shape"):
        vec.step(np.zeros((1, 8, 6), np.float32))
    check_env(ImaginedGymEnv(vec.env, pool), skip_render_check=True)  # gymnasium's checker, single-env view


def test_reward_model_loads_from_its_checkpoint(tiny_run, model, tmp_path):
    from sword_jax.rl.config import RewardModelConfig, RLConfig
    from sword_jax.rl.params_io import save_params
    from sword_jax.rl.reward_model import build_detector

    rl = RLConfig(image_size=32, reward_model=RewardModelConfig(width=8))
    graphdef, params = build_detector(rl, seed=3)
    path = str(tmp_path / "reward_model")
    save_params(path, params, rl, kind="reward_model", step=7)
    loaded = sword_jax.load_reward_model(path)
    for a, b in zip(jax.tree.leaves(loaded.params), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    scores = loaded.score(_given(model, 1)[0])
    assert scores.shape == (5,) and bool(jnp.all((scores >= 0) & (scores <= 1)))
    with_reward = sword_jax.load_world_model(tiny_run, reward_model=path)
    assert with_reward.reward_model is not None and with_reward.loaded_from.reward_model == path
    with pytest.raises(CheckpointError, match="expected 'reward_model'"):
        save_params(str(tmp_path / "policy"), params, rl, kind="policy")
        sword_jax.load_reward_model(str(tmp_path / "policy"))


def test_a_reward_model_saved_with_the_flat_rl_config_of_earlier_versions_loads(tmp_path):
    from flax import nnx

    from sword_jax import checkpoint
    from sword_jax.rl.config import RewardModelConfig, RLConfig
    from sword_jax.rl.reward_model import build_detector

    rl = RLConfig(image_size=32, reward_model=RewardModelConfig(width=8))
    _, params = build_detector(rl, seed=3)
    path = str(tmp_path / "reward_model")
    ckpt = checkpoint.Checkpointer(path, max_to_keep=1)  # as save_params wrote it before rl had sections
    ckpt.save(0, nnx.to_pure_dict(params), {"kind": "reward_model", "rl": {"image_size": 32, "reward_width": 8}})
    ckpt.close()
    loaded = sword_jax.load_reward_model(path)  # the width moved to rl.reward_model.width: the same network
    for a, b in zip(jax.tree.leaves(loaded.params), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_missing_and_corrupt_checkpoints_are_named(tiny_run, tmp_path):
    with pytest.raises(CheckpointError, match="no-such-run does not exist"):
        sword_jax.load_world_model(str(tmp_path / "no-such-run"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="is not a world-model run"):
        sword_jax.load_world_model(str(tmp_path / "empty"))
    (tmp_path / "nothing_saved" / "checkpoints").mkdir(parents=True)
    with pytest.raises(CheckpointError, match="no complete checkpoint in .*nothing_saved"):
        sword_jax.load_world_model(str(tmp_path / "nothing_saved"))
    with pytest.raises(CheckpointError, match="no checkpoint for step 5"):
        sword_jax.load_world_model(tiny_run, step=5)
    with pytest.raises(CheckpointError, match="VAE .*nowhere does not exist"):
        sword_jax.load_world_model(tiny_run, vae=str(tmp_path / "nowhere"))
    broken = tmp_path / "broken"
    shutil.copytree(os.path.join(tiny_run, "world_model"), broken)
    for root, _, files in os.walk(broken / "checkpoints" / "2" / "state"):
        for name in files:  # every array file of the saved state: garbage of the same size
            path = os.path.join(root, name)
            size = os.path.getsize(path)
            with open(path, "wb") as f:
                f.write(b"\x00garbage" * (size // 8 + 1))
    with pytest.raises(CheckpointError, match="broken"):
        sword_jax.load_world_model(str(broken))


# float32's exactness is tested by default in test_rl_world_model_sim (the builder's float32 path equals the former one)
@pytest.mark.parametrize("precision", ["fast", pytest.param("float32", marks=pytest.mark.slow)])
def test_grpo_the_api_and_the_benchmark_build_the_same_simulator(tiny_run, model, tmp_path, precision):
    """The three callers of the learned simulator (GRPO's world_model_setup, sword_jax.learned_simulator,
    bench_imagined_rollout) go through one builder: same settings, same weights in the same dtypes, the same
    frames from the same start, actions and key."""
    import configs
    from benchmarks import bench_imagined_rollout
    from sword_jax.pipeline.grpo import GRPOInputs, world_model_setup
    from sword_jax.rl.learned_simulator import StartState
    from sword_jax.rl.params_io import save_params
    from sword_jax.rl.reward_model import build_detector

    cfg = configs.get("sword:tiny")
    cfg = dataclasses.replace(cfg, model=model.spec.model)  # as the tiny run was trained (one layer)
    rl = dataclasses.replace(cfg.rl, imagined=dataclasses.replace(cfg.rl.imagined, sim_precision=precision))
    reward = str(tmp_path / "detector")
    save_params(reward, build_detector(rl, seed=0)[1], rl, kind="reward_model", step=0)
    inputs = GRPOInputs(world_model=os.path.join(tiny_run, "world_model"), vae=os.path.join(tiny_run, "vae_run", "vae"),
                        reward=reward)
    grpo_sim = world_model_setup(cfg, rl, inputs, None).sim
    api_sim = sword_jax.learned_simulator(model, precision=precision)
    bench_sim = bench_imagined_rollout.simulator(model.world_model_graphdef, model.world_model_params,
                                                 model.vae_graphdef, model.vae_params, frame_size=model.spec.image_size,
                                                 sample_steps=cfg.flow.sample_steps, rl=rl, precision=precision)
    sims = {"grpo": grpo_sim, "api": api_sim, "bench": bench_sim}
    static = {name: (s.chunk_len, s.frame_size, s.execute_len, s.action_dim, s.max_slice) for name, s in sims.items()}
    assert len(set(static.values())) == 1, static
    dtypes = {name: tuple(str(x.dtype) for x in jax.tree.leaves(s.params)) for name, s in sims.items()}
    assert len(set(dtypes.values())) == 1
    assert ("bfloat16" in dtypes["api"]) == (precision == "fast")

    frames = jax.random.uniform(jax.random.key(2), (2, 32, 32, 3))
    latents = sword_jax.start_states(model, frames, ["a", "b"]).latents
    start = StartState(frames, jnp.zeros((2, 8)), jnp.zeros((2, 8), jnp.int32), latents)
    chunk = jax.random.uniform(jax.random.key(7), (2, api_sim.chunk_len, api_sim.action_dim), minval=-1.0, maxval=1.0)

    @jax.jit
    def run(sim, key):
        state = jax.vmap(sim.init)(start)
        return jax.vmap(lambda s, c, k: sim.step(s, c, key=k)[1])(state, chunk, jax.random.split(key, 2))

    one_device = jax.sharding.SingleDeviceSharding(jax.devices()[0])  # GRPO's world model is on the config's mesh
    out = {name: np.asarray(run(jax.device_put(s, one_device), jax.random.key(3))) for name, s in sims.items()}
    np.testing.assert_array_equal(out["grpo"], out["api"])
    np.testing.assert_array_equal(out["bench"], out["api"])
