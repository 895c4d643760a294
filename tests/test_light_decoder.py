"""The light rollout decoder (sword_jax.vae.light_decoder): causal frames at the chosen size, streaming equal to
the whole-sequence decode; its distillation from the VAE (sword_jax.vae.light_train, the pipeline's light_decoder
stage) lowers the loss and resumes exactly, each process cutting only its rows of a batch; the simulator builder
decodes GRPO's frames with it."""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax import sharding as shd
from sword_jax.vae import api as vae_api
from sword_jax.vae import light_decoder as light
from sword_jax.vae import light_train
from sword_jax.vae.config import LightDecoderConfig
from tests.support.light_decoder import numpy_weights

Z = 48


def _decoder(scale=16, width=16, blocks=1, seed=0):
    """A split light decoder with random weights everywhere (its zero-started residual convs too)."""
    return numpy_weights(lambda: light.LightDecoder(LightDecoderConfig(width=width, blocks=blocks), z_dim=Z,
                                                    scale=scale, temporal_factor=4, rngs=nnx.Rngs(seed)), seed=seed)


def test_frames_are_causal_at_the_chosen_size_and_stream_as_the_whole():
    graphdef, state = _decoder()
    latents = jax.random.normal(jax.random.key(2), (2, 4, 2, 2, Z))
    video = light.decode(graphdef, state, latents)
    assert video.shape == (2, 1 + 4 * 3, 32, 32, 3) and np.all(np.isfinite(np.asarray(video)))
    # a later latent changes only its own frames: frame 0 from latent 0, frames 4k-3 .. 4k from latent k
    changed = light.decode(graphdef, state, latents.at[:, 2].add(1.0))
    diff = np.abs(np.asarray(changed - video)).max(axis=(0, 2, 3, 4))
    assert np.all(diff[:5] == 0) and np.all(diff[5:] > 0), diff
    # chunk by chunk (first 1 + 1 latents, then 1, then 1) equals the whole decode
    cache = light.init_stream_cache(graphdef, state, 2, 2, 2)
    parts = []
    for chunk in (latents[:, :2], latents[:, 2:3], latents[:, 3:]):
        frames, cache = light.decode_chunk(graphdef, state, chunk, cache)
        parts.append(frames)
    assert [p.shape[1] for p in parts] == [5, 4, 4]
    np.testing.assert_allclose(np.asarray(jnp.concatenate(parts, axis=1)), np.asarray(video), atol=1e-6)
    # bfloat16 convolutions (the simulator's fast path) stay near float32
    fast = light.decode(graphdef, state, latents, compute_dtype="bfloat16")
    assert float(jnp.mean(jnp.abs(fast - video))) < 0.02 * float(jnp.mean(jnp.abs(video)))
    with pytest.raises(ValueError, match=r"\[B, T, h, w, 48\]"):
        light.decode(graphdef, state, latents[..., :8])


def test_its_work_per_frame_is_a_small_fraction_of_the_vae_decoders():
    """Counted on the jaxprs (benchmarks.common.jaxpr_flops): at the paper's 256 px VAE (16x16 latents), the
    default light decoder at the policy's 64 px and even at 256 px does well under a tenth of the Wan 2.2
    decoder's streamed work per frame (abstract shapes: nothing is allocated)."""
    from benchmarks.common import jaxpr_flops
    from sword_jax.vae.config import VAEConfig

    frames = 4 * 4  # a stream chunk of 4 latents
    chunk = jax.ShapeDtypeStruct((1, 4, 16, 16, Z), jnp.float32)
    vae_graphdef, vae_state = nnx.split(vae_api.abstract_vae(VAEConfig()))
    cache = jax.eval_shape(lambda s: vae_api.init_decode_cache(vae_graphdef, s, 1, 16, 16), vae_state)
    cache = vae_api.StreamCache(cache.features, started=True)
    full = jaxpr_flops(lambda s, z, c: vae_api.decode_chunk(vae_graphdef, s, z, c, check_values=False)[0],
                       vae_state, chunk, cache) / frames
    per_frame = {}
    for size in (64, 256):
        graphdef, state = nnx.split(light.abstract_light_decoder(LightDecoderConfig(), z_dim=Z, scale=size // 16,
                                                                 temporal_factor=4))
        memory = jax.eval_shape(lambda s: light.init_stream_cache(graphdef, s, 1, 16, 16), state)
        memory = vae_api.StreamCache(memory.features, started=True)
        per_frame[size] = jaxpr_flops(lambda s, z, c: light.decode_chunk(graphdef, s, z, c)[0], state, chunk,
                                      memory) / frames
    assert full > 500e9  # the Wan 2.2 decoder: over 0.5 TFLOP per 256 px frame
    assert per_frame[64] < 1e9 and per_frame[256] < 5e9 and per_frame[256] < full / 100, (per_frame, full)


@pytest.mark.parametrize("flags, match", [
    (["--rl.imagined.decoder=tiny"], "rl.imagined.decoder must be full|light"),
    (["--rl.imagined.decoder=light", "--light_decoder.frame_size=24"], "power of two"),
    (["--rl.imagined.decoder=light", "--light_decoder.frame_size=64"], "exceeds data.image_size=32"),
    (["--rl.imagined.decoder=light", "--flow.pixel_round_trip=true"], "pixel_round_trip"),
    (["--light_decoder.teacher_precision=bf16"], "light_decoder.teacher_precision"),
    (["--light_decoder.width=0"], "light_decoder.width"),
    (["--light_decoder.l1_weight=0", "--light_decoder.l2_weight=0"], "nothing to learn"),
])
def test_bad_light_decoder_settings_are_refused_naming_the_key(flags, match):
    with pytest.raises(configs.ConfigError, match=match):
        configs.from_argv(["--config", "sword:tiny", *flags])


def _teacher_and_latents(episodes=4, latents=5):
    """The tiny config's VAE with random weights as the teacher, and latent episodes ``[E, L, 2, 2, 48]``."""
    cfg = configs.get("sword:tiny")
    graphdef, state = numpy_weights(lambda: vae_api.create_vae(cfg.vae, key=jax.random.key(1)), seed=1)
    return cfg, graphdef, state, np.asarray(jax.random.normal(jax.random.key(0), (episodes, latents, 2, 2, Z)))


def test_distillation_lowers_the_loss_and_a_resumed_run_equals_an_uninterrupted_one(tmp_path):
    """Through the shared loop (sword_jax.train_loop.run_steps) with orbax checkpoints: 8 steps lower the
    held clips' L1 to the teacher, and 4 steps then a resumed 4 end bit-identical (state and metrics)."""
    from sword_jax.train_loop import run_steps

    cfg, vae_graphdef, vae_state, latents = _teacher_and_latents()
    ld = dataclasses.replace(cfg.light_decoder, clip_latents=2, learning_rate=5e-3)
    mesh = shd.make_mesh(shd.MeshConfig(data=1), jax.devices()[:1])
    graphdef, state0 = light_train.init_train_state(ld, z_dim=Z, scale=16, temporal_factor=4, key=jax.random.key(0),
                                                    mesh=mesh)
    sampler = light_train.ClipSampler(latents, batch=2, clip_latents=ld.clip_latents, seed=0)
    held = light_train.ClipSampler(latents, batch=2, clip_latents=ld.clip_latents, seed=0, name="held").batch_at(0)
    assert held.shape == (2, 1 + ld.clip_latents, 2, 2, Z)
    k = ld.clip_latents
    for clip in sampler.batch_at(1):  # an episode's first latent, then k consecutive latents of it from >= 1
        e = next(i for i in range(len(latents)) if np.array_equal(clip[0], latents[i, 0]))
        assert any(np.array_equal(clip[1:], latents[e, s:s + k]) for s in range(1, latents.shape[1] - k + 1))
    np.testing.assert_array_equal(sampler.batch_at(3), sampler.batch_at(3))  # a pure function of the step
    teacher = jax.device_put(vae_state, shd.replicated(mesh))
    step = light_train.bind_teacher(light_train.make_distill_step(graphdef, vae_graphdef, ld, frame_size=32), teacher,
                                    state0, {"latents": sampler.batch_at(0)}, mesh=mesh)
    fresh = lambda: jax.tree.map(jnp.copy, state0)  # noqa: E731 - every run starts from the same init (donated)

    def run(steps, directory):
        return run_steps(step, fresh(), sampler.batch_at, key=jax.random.key(5), steps=steps, log_every=1,
                         name="light", report=lambda done, m, _o, _e: {"step": done, **m}, checkpoint_dir=directory,
                         place=lambda clips: {"latents": clips}, checkpoint_every=4, settle=True,
                         log=lambda _line: None)

    straight = run(8, str(tmp_path / "straight"))
    run(4, str(tmp_path / "split"))
    resumed = run(8, str(tmp_path / "split"))
    assert resumed.first_step == 4
    for a, b in zip(jax.tree.leaves(straight.state), jax.tree.leaves(resumed.state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert resumed.history == straight.history

    @jax.jit
    def held_l1(params):
        target = light_train.teacher_frames(vae_graphdef, vae_state, held, frame_size=32)
        return jnp.mean(jnp.abs(light.decode(graphdef, params, held) - target))

    before, after = float(held_l1(state0.params)), float(held_l1(straight.state.params))
    assert after < 0.95 * before, (before, after)
    losses = [p["loss"] for p in straight.history]
    assert np.mean(losses[-2:]) < losses[0]


def test_clip_loader_cuts_only_its_devices_rows_of_the_single_process_batch(monkeypatch):
    """A process cuts only the clips of a batch its devices hold, each the one a single process cuts (here a
    "process" is a subset of the fake devices; two launched processes: tests/test_launch.py)."""
    latents = np.asarray(jax.random.normal(jax.random.key(0), (5, 6, 2, 2, Z)))
    mesh = shd.make_mesh(shd.MeshConfig(data=4, tensor=2))
    sampler = light_train.ClipSampler(latents, batch=8, clip_latents=2, seed=0)
    whole = light_train.clip_loader(sampler, mesh)
    third = light_train.clip_loader(sampler, mesh, devices=list(mesh.devices[2].flat))
    assert whole.rows.tolist() == list(range(8)) and third.rows.tolist() == [4, 5]
    cut, real_cut = [], light_train.cut_clip
    monkeypatch.setattr(light_train, "cut_clip", lambda *args: cut.append(args[1:3]) or real_cut(*args))
    for step in range(3):
        cut.clear()
        part = third.host_batch_at(step)
        assert part.shape == (2, 3, 2, 2, Z) and len(cut) == 2  # its 2 clips only
        full = whole.host_batch_at(step)
        np.testing.assert_array_equal(part, full[4:6])
        placed = whole.place(full)["latents"]
        assert placed.sharding == shd.batch_sharding(mesh, 5)  # the distillation step's input sharding
        np.testing.assert_array_equal(np.asarray(placed), full)
    assert not np.array_equal(whole.host_batch_at(0), whole.host_batch_at(1))


def test_a_light_decoder_batch_that_does_not_split_over_the_devices_is_refused_naming_the_numbers(tmp_path):
    """Refused by the loader, and by the entry point before the teacher is loaded (no VAE is given here)."""
    from train import train_light_decoder

    sampler = light_train.ClipSampler(np.zeros((2, 4, 2, 2, Z), np.float32), batch=6, clip_latents=2, seed=0)
    with pytest.raises(ValueError, match=r"light_decoder.batch_size=6 does not split over the 4 devices .* "
                                         r"8 devices in 1 process\): use a multiple of 4"):
        light_train.clip_loader(sampler, shd.make_mesh(shd.MeshConfig(data=4, tensor=2)))
    np.savez(tmp_path / "latents.npz", latents=np.zeros((3, 5, 2, 2, Z), np.float32),
             actions=np.zeros((3, 17, 7), np.float32))
    with pytest.raises(SystemExit, match=r"light_decoder.batch_size=3 does not split over the 2 devices"):
        train_light_decoder.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "run"), "--vae",
                                  str(tmp_path / "no_vae"), "--latents", str(tmp_path / "latents.npz"),
                                  "--light_decoder.batch_size=3", "--light_decoder.clip_latents=2", "--mesh.data=2",
                                  "--mesh.tensor=4"])
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_teacher_frames_are_the_vae_frames_clipped_and_resized_as_the_policy_sees_them():
    from sword_jax.rl.policy import resize_frames

    cfg, vae_graphdef, vae_state, latents = _teacher_and_latents(episodes=1, latents=2)
    target = light_train.teacher_frames(vae_graphdef, vae_state, jnp.asarray(latents), frame_size=8)
    video = vae_api.decode(vae_graphdef, vae_state, jnp.asarray(latents))
    policy_view = resize_frames(jnp.clip((video + 1.0) * 0.5, 0.0, 1.0), 8)
    assert target.shape == (1, 5, 8, 8, 3)
    np.testing.assert_allclose(np.asarray((target + 1.0) * 0.5), np.asarray(policy_view), atol=1e-5)
