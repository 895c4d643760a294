"""VAE training from scratch: the loss falls on synthetic moving squares; sharded step keeps shardings."""

import json
import jax
import numpy as np
import pytest

from sword_jax import sharding
from sword_jax.vae import tiny_config, train


def test_moving_squares_in_range_and_moving():
    video = train.moving_squares(key=jax.random.key(0), batch=2, frames=5, size=32)
    assert video.shape == (2, 5, 32, 32, 3)
    assert float(video.min()) >= -1.0 and float(video.max()) <= 1.0
    assert float(np.abs(np.asarray(video[:, 0]) - np.asarray(video[:, 4])).max()) > 0.1


# A learning property (19 s on 2 cores); the default run trains the VAE in
# test_lpips_perceptual_loss_uses_published_weights_and_trains_the_reconstruction.
@pytest.mark.slow
def test_training_loss_falls():
    cfg = tiny_config(z_dim=8, learning_rate=3e-3, kl_weight=1e-4)
    graphdef, state = train.init_train_state(cfg, key=jax.random.key(0))
    step = train.make_vae_step(graphdef, cfg)
    root = jax.random.key(1)
    video = train.moving_squares(key=root, batch=2, frames=5, size=32)
    losses = []
    for _ in range(12):  # the loss is about a quarter of its first by then
        state, metrics = step(state, {"video": video}, root)
        losses.append(metrics["loss"])
    losses = [float(x) for x in losses]
    assert int(state.step) == 12
    assert all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.5 * losses[0], losses
    assert float(metrics["kl"]) > 0 and float(metrics["grad_norm"]) > 0


@pytest.mark.slow
def test_sharded_step_keeps_shardings():
    cfg = tiny_config(z_dim=8, dim=16, dec_dim=16)
    mesh = sharding.make_mesh(sharding.MeshConfig(data=2, fsdp=4))
    graphdef, state = train.init_train_state(cfg, key=jax.random.key(0), mesh=mesh)
    kernel = state.params["decoder"]["conv1"]["kernel"]
    assert kernel.value.sharding.spec[-1] == "fsdp"
    step = train.make_vae_step(graphdef, cfg, state=state, mesh=mesh)
    video = train.moving_squares(key=jax.random.key(1), batch=8, frames=5, size=32)
    for _ in range(2):
        state, metrics = step(state, {"video": video}, jax.random.key(2))
    assert np.isfinite(float(metrics["loss"]))
    assert state.params["decoder"]["conv1"]["kernel"].value.sharding.spec[-1] == "fsdp"


# ---------------------------------------------------------------------------------------------
# Raw plus training-style clips; held-out styles and held-out episodes never reach the VAE.


def _sim_episodes(num=3, t=9, size=32, init_split="train"):
    from sim.dataset import Episode
    from sword_jax.augment.synthetic import synthetic_episodes

    data = synthetic_episodes(num, num_frames=t, size=size)
    return [Episode(actions=data["actions"][i], states=np.zeros((t, 3), np.float32), rewards=np.zeros(t, np.float32),
                    dones=np.zeros(t, np.uint8), agentview_rgb=np.rint(data["frames"][i] * 255).astype(np.uint8),
                    ee_states=np.zeros((t, 6), np.float32), gripper_states=np.zeros((t, 2), np.float32),
                    joint_states=np.zeros((t, 7), np.float32), agentview_depth=data["depth"][i],
                    agentview_seg=data["seg"][i], task_id=0, init_split=init_split) for i in range(num)]


def test_vae_clips_are_raw_plus_training_styles(monkeypatch):
    from sword_jax.augment import style as style_lib
    from sword_jax.vae import data as vae_data

    clips = vae_data.clips_from_sim(_sim_episodes())
    seen = []
    real = vae_data.training_styles
    monkeypatch.setattr(vae_data, "training_styles", lambda key, num: seen.append(real(key, num)) or seen[-1])
    sampler = vae_data.ClipSampler(clips, batch=4, frames=5, seed=0, styled_fraction=0.5)
    raw_only = vae_data.ClipSampler(clips, batch=4, frames=5, seed=0, styled_fraction=0.0)
    styled_any = False
    for step in range(1, 4):
        video, raw = sampler.batch(step), raw_only.batch(step)
        assert video.shape == (4, 5, 32, 32, 3) and video.min() >= -1.0 and video.max() <= 1.0
        changed = np.abs(video - raw).max(axis=(1, 2, 3, 4)) > 0.05
        unchanged = np.abs(video - raw).max(axis=(1, 2, 3, 4)) == 0
        assert (changed | unchanged).all()  # a clip is either raw bit-exactly or restyled
        styled_any |= bool(changed.any())
        np.testing.assert_array_equal(video, sampler.batch(step))  # a pure function of the step
    assert styled_any and raw_only.styled_clips == 0 and sampler.styled_clips > 0
    # The first batch's time is split into clip sampling and restyling (its compile), and kept after it.
    assert set(sampler.first_batch_seconds) == {"sample", "restyle"} and sampler.first_batch_seconds["restyle"] > 0
    assert seen and all(style_lib.style_split(jax.tree.map(lambda x, i=i: x[i], s)) == "train"
                        for s in seen for i in range(4))

    # Whatever the sampler draws, a held-out style is refused before any pixel is restyled.
    monkeypatch.setattr(vae_data, "training_styles", real)
    monkeypatch.setattr(vae_data, "sample_styles", lambda key, num, split: style_lib.sample_styles(key, num, "heldout"))
    with pytest.raises(style_lib.HeldOutStyleError):
        for step in range(1, 6):
            sampler.batch(step)


def test_vae_refuses_held_out_episodes_and_missing_geometry():
    from sword_jax.vae import data as vae_data

    with pytest.raises(ValueError, match="held-out"):
        vae_data.clips_from_sim(_sim_episodes(init_split="heldout"))
    flat = [e.__class__(**{**e.__dict__, "agentview_depth": None}) for e in _sim_episodes()]
    clips = vae_data.clips_from_sim(flat)
    assert not clips.can_style
    with pytest.raises(ValueError, match="depth"):
        vae_data.ClipSampler(clips, batch=2, frames=5, seed=0, styled_fraction=0.5)
    vae_data.ClipSampler(clips, batch=2, frames=5, seed=0, styled_fraction=0.0).batch(1)  # raw only still works


def test_vae_loader_makes_only_its_devices_rows_of_the_single_process_batch(monkeypatch):
    """A process cuts and restyles only the rows of a batch its devices hold, each row the one a single process
    makes (here a "process" is a subset of the fake devices; two launched processes: tests/test_launch.py)."""
    from sword_jax.vae import data as vae_data

    clips = vae_data.clips_from_sim(_sim_episodes())
    mesh = sharding.make_mesh(sharding.MeshConfig(data=4, tensor=2))
    samplers = [vae_data.ClipSampler(clips, batch=8, frames=5, seed=0, styled_fraction=0.5) for _ in range(2)]
    raw = vae_data.ClipSampler(clips, batch=8, frames=5, seed=0)
    whole = vae_data.VideoLoader(samplers[0].batch, 8, mesh)
    third = vae_data.VideoLoader(samplers[1].batch, 8, mesh, devices=list(mesh.devices[2].flat))
    assert whole.rows.tolist() == list(range(8)) and third.rows.tolist() == [4, 5]
    cut, real_cut = [], vae_data._cut
    monkeypatch.setattr(vae_data, "_cut", lambda video, start, frames: cut.append(start) or real_cut(video, start, frames))
    restyled = False
    for step in range(1, 4):
        cut.clear()
        part = third.host_batch_at(step)
        assert part.shape == (2, 5, 32, 32, 3) and len(cut) == 3 * 2  # frames, depth and seg of its 2 clips only
        full = whole.host_batch_at(step)
        np.testing.assert_array_equal(part, full[4:6])
        restyled |= bool(np.abs(part - raw.batch(step, third.rows)).max() > 0.05)
        placed = whole.place(full)["video"]
        assert placed.sharding == sharding.batch_sharding(mesh, 5)  # the VAE step's input sharding
        np.testing.assert_array_equal(np.asarray(placed), full)
    assert restyled and samplers[1].styled_clips == samplers[0].styled_clips > 0  # the whole batch's count

    squares = jax.random.key(3)
    np.testing.assert_array_equal(train.moving_squares(key=squares, batch=8, frames=5, size=16, rows=np.array([4, 5])),
                                  train.moving_squares(key=squares, batch=8, frames=5, size=16)[4:6])


def test_a_vae_batch_that_does_not_split_over_the_devices_is_refused_naming_the_numbers(tmp_path):
    from sword_jax.vae import data as vae_data
    from train import train_vae

    mesh = sharding.make_mesh(sharding.MeshConfig(data=4, tensor=2))
    with pytest.raises(ValueError, match=r"vae.batch_size=6 does not split over the 4 devices .* "
                                         r"8 devices in 1 process\): use a multiple of 4"):
        vae_data.VideoLoader(lambda step, rows: None, 6, mesh)
    with pytest.raises(ValueError, match=r"vae.batch_size=3 does not split over the 2 devices"):
        train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "vae"), "--synthetic",
                        "--vae.batch_size=3", "--mesh.data=2", "--mesh.tensor=4"])
    assert not (tmp_path / "vae" / "checkpoints").exists()


@pytest.mark.slow
def test_train_vae_entry_trains_on_styled_clips(tmp_path):
    from sim.dataset import DatasetInfo, write_dataset
    from train import train_vae

    path = str(tmp_path / "train.hdf5")
    write_dataset(path, _sim_episodes(), DatasetInfo(env_name="test"))
    summary = train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "vae"), "--episodes", path,
                              "--vae.train_steps=2", "--clip-latents=1", "--mesh.data=2", "--mesh.tensor=4"])
    assert summary["styled_fraction"] == 0.5 and summary["styled_clips"] > 0
    assert np.isfinite(summary["final_loss"])
    held_out = str(tmp_path / "heldout.hdf5")
    write_dataset(held_out, _sim_episodes(init_split="heldout"), DatasetInfo(env_name="test"))
    with pytest.raises(ValueError, match="held-out"):
        train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "vae2"), "--episodes", held_out])


def test_lpips_perceptual_loss_uses_published_weights_and_trains_the_reconstruction():
    import jax
    import jax.numpy as jnp

    from sword_jax.metrics.config import EvalConfig
    from sword_jax.vae.perceptual import lpips_loss

    loss_fn, source = lpips_loss(EvalConfig())
    assert "random" not in source and "alexnet" in source
    video = jax.random.uniform(jax.random.key(0), (1, 2, 32, 32, 3), minval=-1.0, maxval=1.0)
    loss = jax.jit(loss_fn)  # eager op-by-op dispatch of the network takes several times longer
    assert float(loss(video, video)) == 0.0
    recon = jnp.zeros_like(video)
    assert float(loss(video, recon)) > 0.1
    grad_video, grad_recon = jax.jit(jax.grad(loss_fn, argnums=(0, 1)))(video, recon)
    assert float(jnp.abs(grad_recon).sum()) > 0 and float(jnp.abs(grad_video).sum()) == 0
    with pytest.raises(ValueError, match="must match"):
        loss_fn(video, recon[:, :1])


@pytest.mark.slow
def test_train_vae_perceptual_weight_reaches_the_loss(tmp_path):
    from train import train_vae

    summary = train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "vae"), "--synthetic",
                              "--vae.train_steps=2", "--clip-latents=1", "--vae.perceptual_weight=0.5",
                              "--mesh.data=2", "--mesh.tensor=4"])
    rows = [json.loads(line) for line in open(tmp_path / "vae" / "metrics.jsonl")]
    assert rows[-1]["perceptual"] > 0 and np.isfinite(summary["final_loss"])


def test_a_trained_vae_folder_is_reused_in_place_of_training(tiny_run, tmp_path):
    """--vae.checkpoint naming a trained VAE's folder (its work dir or ``vae``): the run trains nothing and keeps
    the same weights bit for bit where its own VAE goes (``<workdir>/vae``), which every loader reads; a different
    VAE already in the work dir is refused and kept; another architecture is named."""
    import dataclasses
    import os

    from flax import nnx

    import configs
    from sword_jax import load
    from sword_jax.checkpoint import CheckpointError, Checkpointer
    from tests.support.checkpoints import trees_equal
    from train import train_vae

    source = os.path.join(tiny_run, "vae_run")
    summary = train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "a"), f"--vae.checkpoint={source}"])
    assert summary == {"source": source, "steps": 0}
    vae_cfg = configs.get("sword:tiny").vae
    _, want = load.load_vae_params(vae_cfg, os.path.join(source, "vae"))
    want = nnx.to_pure_dict(want)
    for cfg, path in ((vae_cfg, str(tmp_path / "a" / "vae")), (dataclasses.replace(vae_cfg, checkpoint=source), "")):
        _, got = load.load_vae_params(cfg, path)
        assert trees_equal(want, nnx.to_pure_dict(got))
    # another VAE where this run's own goes: refused, left as it was
    other = tmp_path / "b" / "vae"
    with Checkpointer(str(other), max_to_keep=1) as writer:
        writer.save(0, jax.tree.map(lambda x: np.asarray(x) + 1.0, want), {"kind": "vae"})
    before = sorted(os.listdir(other))
    with pytest.raises(SystemExit, match="holds another VAE"):
        train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "b"), f"--vae.checkpoint={source}"])
    assert sorted(os.listdir(other)) == before and not os.path.exists(f"{other}.copying")
    with pytest.raises(CheckpointError, match="cannot restore"):
        train_vae.main(["--config", "sword:tiny", "--workdir", str(tmp_path / "c"), f"--vae.checkpoint={source}",
                        "--vae.dim=16"])
    assert not os.path.exists(tmp_path / "c" / "vae")
