"""The public API's envs with the light rollout decoder (``load_world_model(light_decoder=...)``,
``make_env(..., decoder="light")``) on the tiny run: frames at the light decoder's size, equal to the light decoder
applied to the simulator's latents, through brax's training wrappers and the gymnasium vector env; bad decoders are
refused by name.

brax's wrappers mix int and float arrays, so they run under standard dtype promotion (as in test_brax_envs)."""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training

import configs
import sword_jax
from sword_jax.api import CheckpointError
from sword_jax.rl.policy import resize_frames
from sword_jax.vae import light_decoder as light
from tests.support.light_decoder import save_random_light_decoder

LIGHT_SIZE = 16  # the tiny run's 2x2 latents decoded at 16 px (its VAE's frames are 32 px)


def _light_cfg(**sections):
    """The tiny experiment with a 16 px light decoder (``sections``: replaced config sections, for wrong layouts)."""
    cfg = configs.from_argv(["--config", "sword:tiny", f"--rl.image_size={LIGHT_SIZE}"])[0]
    return dataclasses.replace(cfg, **sections)


@pytest.fixture(scope="module")
def light_run(tiny_run, tmp_path_factory):
    """The tiny run (links to its world model and VAE) with a light decoder where the pipeline puts it."""
    run = tmp_path_factory.mktemp("light_run")
    for part in ("world_model", "vae_run"):
        os.symlink(os.path.join(tiny_run, part), run / part)
    save_random_light_decoder(run / "light_decoder" / "checkpoints", _light_cfg())
    return str(run)


@pytest.fixture(scope="module")
def model(light_run):
    return sword_jax.load_world_model(light_run, light_decoder=True)


def _brightness(frames):
    return jnp.mean(frames, axis=(1, 2, 3))


def _pool(model, n=3):
    frames = jax.random.uniform(jax.random.key(0), (n, model.spec.image_size, model.spec.image_size, 3))
    return sword_jax.start_states(model, frames, ["pick up the bowl", "open the drawer", "wait"][:n])


def _fake_world_model(monkeypatch):
    """Predictions that are a fixed function of the chunk's actions and the context (the DiT is not what is
    tested), so the latents behind each frame are known here."""
    from sword_jax.rl import world_model_sim

    base = jax.random.normal(jax.random.key(9), (1, 2, 2, 2, 48))

    def predict(model_fn, first, context, actions, *, key, num_future, cfg, num_steps):
        return base[:, :num_future] + jnp.mean(actions[:, -num_future:, :1]) + 0.1 * context[:, -1:]

    monkeypatch.setattr(world_model_sim, "predict_chunk", predict)
    return lambda context, chunk: predict(None, None, context, chunk[None], key=None, num_future=2, cfg=None,
                                          num_steps=None)


def test_make_env_with_the_light_decoder_steps_under_brax_wrappers_and_shows_the_light_decoders_frames(
        light_run, model, monkeypatch):
    predict = _fake_world_model(monkeypatch)
    assert model.loaded_from.light_decoder == os.path.join(light_run, "light_decoder")
    pool = _pool(model)
    env = sword_jax.make_env(model, pool, reward_model=_brightness, max_chunks=4, precision="float32",
                             decoder="light")
    assert env.observation_size["pixels/frame"] == (LIGHT_SIZE, LIGHT_SIZE, 3)
    assert sword_jax.make_env(model, pool, reward_model=_brightness).observation_size["pixels/frame"] == (32, 32, 3)
    wrapped = training.wrap(env, episode_length=3)
    assert wrapped.observation_size == env.observation_size
    actions = jnp.stack([jnp.full((8 * 7,), value, jnp.float32) for value in (0.5, -0.25, 0.0)])  # flat, as PPO's
    with jax.numpy_dtype_promotion("standard"):
        reset, step = jax.jit(wrapped.reset), jax.jit(wrapped.step)
        first = reset(jax.random.split(jax.random.PRNGKey(0), 3))  # brax's wrappers take raw keys
        states = [first]
        for _ in range(2):
            states.append(step(states[-1], actions))
    one, two = states[1:]
    # which start each env drew: its first latent
    drawn = [int(np.argmin(np.abs(np.asarray(pool.latents[:, 0]) - np.asarray(latent)).sum(axis=(1, 2, 3))))
             for latent in first.pipeline_state.simulator.first_latent[:, 0, 0]]
    np.testing.assert_allclose(np.asarray(first.obs["pixels/frame"]),
                               np.asarray(resize_frames(pool.frame[np.asarray(drawn)], LIGHT_SIZE)), atol=1e-6)
    assert one.info["frames"].shape == (3, 8, LIGHT_SIZE, LIGHT_SIZE, 3)
    # the light decoder applied to the whole stream [start latents, chunk 1, chunk 2] of each env
    for env_index, start_index in enumerate(drawn):
        start = pool.latents[start_index]
        chunk = actions[env_index].reshape(8, 7)
        future_one = predict(start[None, 1:], chunk)
        future_two = predict(future_one[:, -1:], chunk)
        stream = jnp.concatenate([start[None], future_one, future_two], axis=1)  # (1, 6, 2, 2, 48)
        video = light.decode(model.light_decoder_graphdef, model.light_decoder_params, stream, compute_dtype="float32")
        expected = np.clip((np.asarray(video[0]) + 1.0) * 0.5, 0.0, 1.0)  # frames 0 .. 20
        np.testing.assert_allclose(np.asarray(one.info["frames"][env_index]), expected[5:13], atol=1e-5)
        np.testing.assert_allclose(np.asarray(two.info["frames"][env_index]), expected[13:21], atol=1e-5)
    np.testing.assert_array_equal(np.asarray(two.obs["pixels/frame"]), np.asarray(two.info["frames"][:, -1]))
    np.testing.assert_allclose(np.asarray(two.reward), np.asarray(_brightness(two.info["frames"][:, -1])
                                                                  - _brightness(one.info["frames"][:, -1])), atol=1e-5)


def test_vector_env_with_the_light_decoder_observes_frames_at_its_size(model):
    vec = sword_jax.make_vector_env(model, _pool(model, 2), 2, reward_model=_brightness, max_chunks=2,
                                    decoder="light")
    assert vec.single_observation_space["frame"].shape == (LIGHT_SIZE, LIGHT_SIZE, 3)
    obs, _ = vec.reset(seed=0)
    assert vec.observation_space.contains(obs)
    obs, reward, _, _, info = vec.step(np.full(vec.action_space.shape, 0.5, np.float32))  # the real world model
    assert vec.observation_space.contains(obs) and np.isfinite(reward).all()
    assert info["frames"].shape == (2, 8, LIGHT_SIZE, LIGHT_SIZE, 3)
    np.testing.assert_array_equal(obs["frame"], info["frames"][:, -1])


def test_a_light_decoder_given_by_path_is_the_runs_and_bad_ones_are_refused_by_name(tiny_run, light_run, model,
                                                                                    tmp_path):
    given = sword_jax.load_world_model(tiny_run, light_decoder=os.path.join(light_run, "light_decoder", "checkpoints"))
    for a, b in zip(jax.tree.leaves(given.light_decoder_params), jax.tree.leaves(model.light_decoder_params),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    plain = sword_jax.load_world_model(light_run)  # not asked for: not loaded
    assert plain.light_decoder_params is None and plain.loaded_from.light_decoder == ""
    pool = _pool(plain, 1)
    with pytest.raises(ValueError, match="loaded without one .*light_decoder="):
        sword_jax.make_env(plain, pool, reward_model=_brightness, decoder="light")
    with pytest.raises(ValueError, match="decoder must be one of"):
        sword_jax.make_env(model, pool, reward_model=_brightness, decoder="vae")
    with pytest.raises(CheckpointError, match="has no light decoder"):
        sword_jax.load_world_model(tiny_run, light_decoder=True)
    (tmp_path / "alone").mkdir()  # a world-model work dir outside a pipeline run
    os.symlink(os.path.join(tiny_run, "world_model"), tmp_path / "alone" / "world_model")
    with pytest.raises(CheckpointError, match="not in a pipeline work dir"):
        sword_jax.load_world_model(str(tmp_path / "alone" / "world_model"), light_decoder=True)
    with pytest.raises(CheckpointError, match="light decoder .*nowhere does not exist"):
        sword_jax.load_world_model(tiny_run, light_decoder=str(tmp_path / "nowhere"))
    with pytest.raises(CheckpointError, match="expected 'light_decoder'"):
        sword_jax.load_world_model(tiny_run, light_decoder=os.path.join(tiny_run, "world_model"))
    cfg = _light_cfg()
    wrong = {"channels": (_light_cfg(vae=dataclasses.replace(cfg.vae, z_dim=16)), "16-channel 2x2"),
             "size": (_light_cfg(data=dataclasses.replace(cfg.data, image_size=64)), "48-channel 4x4")}
    for name, (other, match) in wrong.items():
        save_random_light_decoder(tmp_path / name, other)
        with pytest.raises(CheckpointError, match=f"{name}: a light decoder of {match} .* the world model's are "
                                                  "48-channel 2x2 latents of 4 frames each"):
            sword_jax.load_world_model(tiny_run, light_decoder=str(tmp_path / name))
