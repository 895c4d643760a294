"""Decoder-aware SFT: episodes round-tripped through the video VAE, batches mixing them in per sample
(``rl.sft.decoded_fraction``), fine-tuning from a given policy, and the entry points' ``--vae``."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax.rl import data as rl_data
from sword_jax.rl.config import SFTConfig
from sword_jax.rl.decoded_frames import padded_length, require_vae, round_trip_episodes, round_trip_videos
from sword_jax.rl.sft import decoded_samples, sft_batch_at, train_sft
from sword_jax.rng import stream_rng
from tests.support.rl import POLICY_CFG, TINY_RL, brightening_episodes, write_demos

CFG = dataclasses.replace(POLICY_CFG, sft=dataclasses.replace(POLICY_CFG.sft, batch_size=8, warmup_steps=0))
# the world-model replays below replay write_demos' 12 windows in one call of 16 (the default 64 would replay
# and encode 52 padding windows on the CPU)
REPLAY_BATCH = 16


@pytest.fixture(scope="module")
def tiny_vae():
    from sword_jax.vae import api as vae_api

    return nnx.split(vae_api.create_vae(configs.get("sword:tiny").vae, key=jax.random.key(1)))


def test_padded_lengths_are_latent_buckets():
    assert [padded_length(n, 4, 8) for n in (1, 2, 33, 34, 220)] == [1, 33, 33, 65, 225]
    assert [padded_length(n, 4, 1) for n in (3, 5, 6, 9)] == [5, 5, 9, 9]
    with pytest.raises(ValueError, match="must be >= 1"):
        padded_length(0, 4)


def test_episodes_round_trip_as_whole_padded_videos(tiny_vae):
    """Each episode is its frames up to its length, padded with the last frame to 1 + 4k, encoded and decoded
    whole, cropped back; frames after the length repeat the decoded last one; one compile per bucket."""
    from sword_jax.vae import api as vae_api

    graphdef, state = tiny_vae
    frames = np.random.default_rng(0).integers(0, 256, (3, 9, 32, 48, 3), dtype=np.uint8)
    lengths = np.array([9, 6, 3])
    compiled = round_trip_videos._cache_size()
    out = round_trip_episodes(graphdef, state, frames, lengths, episodes_per_call=2, bucket_latents=1)
    assert round_trip_videos._cache_size() - compiled == 2  # buckets of 9 (episodes 0, 1) and 5 frames (episode 2)
    assert out.shape == frames.shape and out.dtype == np.uint8
    for episode, (n, padded) in enumerate(zip(lengths, (9, 9, 5))):
        video = frames[episode, np.minimum(np.arange(padded), n - 1)][None].astype(np.float32) / 255.0 * 2.0 - 1.0
        decoded = vae_api.decode(graphdef, state, vae_api.encode(graphdef, state, jnp.asarray(video)), clamp=True)
        expected = np.clip(np.round((np.asarray(decoded[0]) + 1.0) * 127.5), 0, 255)
        np.testing.assert_allclose(out[episode, :n], expected[:n], atol=1)
        np.testing.assert_array_equal(out[episode, n:], np.broadcast_to(out[episode, n - 1], out[episode, n:].shape))
    assert np.abs(out.astype(float) - frames).mean() > 1.0  # a random VAE does change the frames
    with pytest.raises(ValueError, match="uint8"):
        round_trip_episodes(graphdef, state, frames.astype(np.float32))
    with pytest.raises(ValueError, match="lengths must be 3 values in"):
        round_trip_episodes(graphdef, state, frames, np.array([9, 10, 1]))


def test_decoded_fraction_must_be_a_share_and_needs_a_vae():
    for bad in (-0.1, 1.5, math.nan, True, "0.5"):
        with pytest.raises(ValueError, match=r"rl\.sft\.decoded_fraction must be a number in \[0, 1\]"):
            SFTConfig(decoded_fraction=bad).validate()
    for good in (0, 0.0, 0.5, 1.0):
        SFTConfig(decoded_fraction=good).validate()
    with pytest.raises(ValueError, match=r"decoded_fraction must be a number in \[0, 1\]"):
        configs.from_argv(["--config", "sword:tiny", "--rl.sft.decoded_fraction=1.5"])
    assert configs.get("sword:small").rl.sft.decoded_fraction == 0.0
    with pytest.raises(ValueError, match="give its checkpoint directory with --vae"):
        require_vae(0.5, "")
    with pytest.raises(ValueError, match="--vae v is read only by decoder-aware SFT"):
        require_vae(0.0, "v")
    require_vae(0.0, "")
    require_vae(0.5, "v")
    episodes = brightening_episodes()
    half = dataclasses.replace(CFG, sft=dataclasses.replace(CFG.sft, decoded_fraction=0.5))
    graphdef_params = (None, None)
    with pytest.raises(ValueError, match="needs decoded_frames"):
        train_sft(*graphdef_params, half, episodes)
    with pytest.raises(ValueError, match="decoded_fraction is 0"):
        train_sft(*graphdef_params, CFG, episodes, decoded_frames=episodes.frames)
    with pytest.raises(ValueError, match="shaped like the training frames"):
        train_sft(*graphdef_params, half, episodes, decoded_frames=episodes.frames[:, :3])


def test_each_batch_takes_its_share_of_decoded_frames_per_sample_as_a_function_of_seed_and_step():
    episodes = brightening_episodes()
    decoded = 255 - episodes.frames  # a stand-in VAE whose round trip inverts the frames
    chosen = decoded_samples(0, 5, 32, 0.5)
    assert chosen.sum() == 16 and np.array_equal(chosen, decoded_samples(0, 5, 32, 0.5))  # what a resume draws
    assert not np.array_equal(chosen, decoded_samples(0, 6, 32, 0.5))
    assert not np.array_equal(chosen, decoded_samples(1, 5, 32, 0.5))
    assert not decoded_samples(0, 5, 32, 0.0).any() and decoded_samples(0, 5, 32, 1.0).all()
    for step in (0, 3):
        real = rl_data.sample_bc_batch(episodes, 8, CFG.chunk_len, CFG.policy.max_instruction_bytes,
                                       stream_rng(0, "sft/batches", step))
        for fraction in (0.0, 0.5, 1.0):
            cfg = dataclasses.replace(CFG, sft=dataclasses.replace(CFG.sft, decoded_fraction=fraction))
            batch = sft_batch_at(episodes, cfg, 0, step, decoded if fraction else None)
            for name in ("instruction_tokens", "proprio", "actions"):
                np.testing.assert_array_equal(batch[name], real[name])
            use = decoded_samples(0, step, 8, fraction)
            np.testing.assert_array_equal(batch["frames"][use], 255 - real["frames"][use])
            np.testing.assert_array_equal(batch["frames"][~use], real["frames"][~use])
            assert use.sum() == round(fraction * 8)


def test_decoded_fraction_zero_trains_as_before_and_one_trains_on_the_decoded_frames_only():
    from sword_jax.rl.policy import build_policy, compute_proprio_stats, set_proprio_stats
    from sword_jax.rl.sft import make_sft_step

    episodes = brightening_episodes()
    graphdef, params = build_policy(CFG, seed=0)

    def fresh():
        return jax.tree.map(jnp.copy, params)

    trained, history = train_sft(graphdef, fresh(), CFG, episodes, seed=3, steps=1, log=lambda m: None)
    # the step as it ran before decoded frames existed: stats, then one step on sample_bc_batch's batch
    valid = np.concatenate([episodes.proprio[e, : episodes.lengths[e]] for e in range(episodes.num_episodes)])
    init, step = make_sft_step(graphdef, CFG, total_steps=1)
    batch = rl_data.sample_bc_batch(episodes, 8, CFG.chunk_len, CFG.policy.max_instruction_bytes,
                                    stream_rng(3, "sft/batches", 0))
    state, metrics = step(init(set_proprio_stats(fresh(), compute_proprio_stats(valid, CFG))), batch, jax.random.key(3))
    jax.tree.map(np.testing.assert_array_equal, nnx.to_pure_dict(trained), nnx.to_pure_dict(state.params))
    assert history[-1]["loss"] == float(metrics["loss"])

    # fraction 1 on inverted frames is training on episodes whose frames are inverted
    inverted = 255 - episodes.frames
    cfg_all = dataclasses.replace(CFG, sft=dataclasses.replace(CFG.sft, decoded_fraction=1.0))
    on_decoded, _ = train_sft(graphdef, fresh(), cfg_all, episodes, seed=3, steps=2, log=lambda m: None,
                              decoded_frames=inverted)
    on_inverted, _ = train_sft(graphdef, fresh(), CFG, dataclasses.replace(episodes, frames=inverted), seed=3,
                               steps=2, log=lambda m: None)
    jax.tree.map(np.testing.assert_array_equal, nnx.to_pure_dict(on_decoded), nnx.to_pure_dict(on_inverted))
    on_real, _ = train_sft(graphdef, fresh(), CFG, episodes, seed=3, steps=2, log=lambda m: None)
    assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(nnx.to_pure_dict(on_decoded)),
                                                         jax.tree.leaves(nnx.to_pure_dict(on_real))))


@pytest.mark.slow  # the decoded-fraction and world-model tests train on decoded frames in the default run
def test_train_policy_fine_tunes_the_given_policy_on_decoded_frames(tmp_path, monkeypatch, tiny_vae):
    """--rl.sft.init starts from that policy (its proprio normalisation kept, a fresh optimizer);
    --rl.sft.decoded_fraction with --vae round-trips the training episodes once; the flags refuse each other's
    absence."""
    import sword_jax.load
    from sim.policy_training import initial_policy
    from sword_jax.rl.params_io import load_params, save_params_npz
    from sword_jax.rl.policy import build_policy
    from train import train_policy

    data = write_demos(str(tmp_path / "demos.hdf5"))
    common = ["--config", "sword:tiny", f"--workdir={tmp_path}", "--demos", data, *TINY_RL,
              "--rl.sft.steps=1", "--rl.sft.batch_size=4"]
    with pytest.raises(ValueError, match="give its checkpoint directory with --vae"):
        train_policy.main(common + ["--rl.sft.decoded_fraction=0.5"])
    with pytest.raises(ValueError, match="read only by decoder-aware SFT"):
        train_policy.main(common + ["--vae", str(tmp_path)])

    cfg, _ = configs.from_argv(common)
    _, given = build_policy(cfg.rl, seed=7)
    given["proprio_mean"] = given["proprio_mean"].replace(jnp.full_like(given["proprio_mean"][...], 0.25))
    save_params_npz(str(tmp_path / "given.npz"), given)
    fine_cfg, _ = configs.from_argv(common + [f"--rl.sft.init={tmp_path / 'given.npz'}"])
    start = nnx.to_pure_dict(initial_policy(fine_cfg)[1])
    jax.tree.map(np.testing.assert_array_equal, start, nnx.to_pure_dict(given))

    round_trips = []

    def stand_in_vae(cfg, path, **_):
        round_trips.append(path)
        return tiny_vae

    monkeypatch.setattr(sword_jax.load, "experiment_vae", stand_in_vae)
    result = train_policy.main(common + [f"--rl.sft.init={tmp_path / 'given.npz'}", "--rl.sft.decoded_fraction=1",
                                         "--vae", str(tmp_path / "vae")])
    assert round_trips == [str(tmp_path / "vae")] and result["decoded"]["fraction"] == 1
    assert result["init"] == str(tmp_path / "given.npz")
    tuned = nnx.to_pure_dict(load_params(result["path"], build_policy(cfg.rl, seed=0)[1], kind="policy")[0])
    fresh = nnx.to_pure_dict(build_policy(cfg.rl, seed=cfg.seed)[1])
    np.testing.assert_array_equal(tuned["proprio_mean"], start["proprio_mean"])
    moved = [np.abs(a - b).max() for a, b in zip(jax.tree.leaves(tuned), jax.tree.leaves(start))]
    away = [np.abs(a - b).max() for a, b in zip(jax.tree.leaves(tuned), jax.tree.leaves(fresh))]
    assert max(moved) < 0.02 < max(away)  # one small step from the given policy, not from a fresh one


def test_bench_policy_refuses_decoded_fraction_without_vae_before_making_demonstrations(tmp_path):
    from benchmarks import bench_policy

    with pytest.raises(ValueError, match="give its checkpoint directory with --vae"):
        bench_policy.main(["sft", "--config", "sword:tiny", "--out", str(tmp_path / "o"),
                           "--rl.sft.decoded_fraction=0.5"])
    with pytest.raises(ValueError, match="read only by decoder-aware SFT"):
        bench_policy.main(["sft", "--config", "sword:tiny", "--out", str(tmp_path / "o"), "--vae", "v"])
    with pytest.raises(ValueError, match="read by the sft stage only"):
        bench_policy.main(["seeds", "--config", "sword:tiny", "--out", str(tmp_path / "o"), "--vae", "v"])
    assert not (tmp_path / "o").exists()


def test_decoded_source_world_model_needs_the_world_model_and_nothing_else_reads_it():
    with pytest.raises(ValueError, match="decoded_source must be vae or world_model"):
        SFTConfig(decoded_source="both").validate()
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="decoded_window must be an integer >= 0"):
            SFTConfig(decoded_window=bad).validate()
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--rl.sft.decoded_window=0"])
    assert cfg.rl.sft_decoded_window == cfg.rl.imagined.max_chunks * cfg.rl.imagined_actions_per_decision
    assert configs.from_argv(["--config", "sword:tiny", "--rl.sft.decoded_window=12"])[0].rl.sft_decoded_window == 12
    with pytest.raises(ValueError, match="give its checkpoint directory with --world-model"):
        require_vae(0.5, "v", "", "world_model")
    with pytest.raises(ValueError, match="--world-model w is read only with rl.sft.decoded_source=world_model"):
        require_vae(0.5, "v", "w", "vae")
    with pytest.raises(ValueError, match="--world-model w is read only"):
        require_vae(0.0, "", "w", "world_model")
    require_vae(0.5, "v", "w", "world_model")


def test_train_policy_fine_tunes_on_frames_the_world_model_imagines(tmp_path, monkeypatch, tiny_vae):
    """rl.sft.decoded_source=world_model: the training episodes replayed window by window in the world model
    GRPO would build (here a random tiny one, decoded by a random tiny VAE), their real frames kept at each
    window's start and imagined elsewhere, and the policy trained on them."""
    import sword_jax.load
    import sword_jax.rl.imagined_frames as imagined
    from train import train_policy

    data = write_demos(str(tmp_path / "demos.hdf5"), size=32)  # the tiny world model's data.image_size
    common = ["--config", "sword:tiny", f"--workdir={tmp_path}", "--demos", data, *TINY_RL,
              "--rl.sft.steps=1", "--rl.sft.batch_size=4", "--holdout=0"]
    with pytest.raises(ValueError, match="with --world-model"):
        train_policy.main(common + ["--rl.sft.decoded_fraction=1", "--rl.sft.decoded_source=world_model",
                                    "--vae", "v"])
    with pytest.raises(ValueError, match="read only with rl.sft.decoded_source=world_model"):
        train_policy.main(common + ["--rl.sft.decoded_fraction=1", "--vae", "v", "--world-model", "w"])
    loaded, made = [], []
    real_world_model = sword_jax.load.experiment_world_model
    monkeypatch.setattr(sword_jax.load, "experiment_vae", lambda cfg, path, **_: tiny_vae)
    monkeypatch.setattr(sword_jax.load, "experiment_world_model",
                        lambda cfg, path: loaded.append(path) or real_world_model(cfg, None))
    replay = imagined.imagined_episode_frames

    def kept(simulator, encode, episodes, **kwargs):
        out = replay(simulator, encode, episodes, **kwargs, batch=REPLAY_BATCH)
        made.append((episodes, kwargs["window"], out))
        return out

    monkeypatch.setattr(imagined, "imagined_episode_frames", kept)
    result = train_policy.main(common + ["--rl.sft.decoded_fraction=1", "--rl.sft.decoded_source=world_model",
                                         "--rl.sft.decoded_window=4", "--vae", str(tmp_path / "vae"),
                                         "--world-model", str(tmp_path / "wm")])
    assert loaded == [str(tmp_path / "wm")]
    assert result["decoded"] == {"vae": str(tmp_path / "vae"), "fraction": 1, "source": "world_model",
                                 "world_model": str(tmp_path / "wm"), "window": 4}
    [(episodes, window, out)] = made
    assert window == 4 and out.shape == episodes.frames.shape
    for e, length in enumerate(episodes.lengths):
        starts = np.arange(0, length, 5)  # each window: its real start and the 4 frames its replay shows
        np.testing.assert_array_equal(out[e, starts], episodes.frames[e, starts])
        shown = np.setdiff1d(np.arange(length), starts)
        assert all(not np.array_equal(out[e, t], episodes.frames[e, t]) for t in shown)  # a random world model's
    assert np.isfinite(result["final_loss"])


def test_a_trained_world_model_replays_the_episodes_over_several_devices(tiny_run, tmp_path, monkeypatch):
    """rl.sft.decoded_source=world_model with a trained world model, placed on the mesh (here 8 CPU devices): the
    VAE is placed beside it, so the replay's jitted steps read both (on the first device alone they refused)."""
    import functools
    import os

    import sword_jax.rl.imagined_frames as imagined
    from sim.policy_training import decoded_training_frames

    monkeypatch.setattr(imagined, "imagined_episode_frames",
                        functools.partial(imagined.imagined_episode_frames, batch=REPLAY_BATCH))

    assert jax.device_count() > 1
    from configs.cli import apply_overrides

    cfg = apply_overrides(configs.get("sword:tiny"), ["--model.num_layers=1"])
    cfg = dataclasses.replace(cfg, rl=dataclasses.replace(cfg.rl, sft=dataclasses.replace(
        cfg.rl.sft, decoded_fraction=1.0, decoded_source="world_model", decoded_window=4)))
    from sim.dataset import read_dataset

    episodes = rl_data.load_episodes([write_demos(str(tmp_path / "demos.hdf5"), size=32)], read=read_dataset)
    out = decoded_training_frames(cfg, os.path.join(tiny_run, "vae_run", "vae"), episodes,
                                  world_model=os.path.join(tiny_run, "world_model"))
    assert out.shape == episodes.frames.shape
    np.testing.assert_array_equal(out[:, 0], episodes.frames[:, 0])  # each window's real start is kept
