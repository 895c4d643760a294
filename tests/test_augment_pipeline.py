"""Augmentation in the training pipeline, the evaluation splits and the ingest of externally styled episodes."""

import json
import os

import cv2
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.augment import style as st
from sword_jax.augment.config import AugmentConfig
from sword_jax.augment.episodes import as_episodes
from sword_jax.augment.eval_splits import build_eval_splits
from sword_jax.augment.ingest import StyledEpisodeError, load_styled_episodes
from sword_jax.augment.pipeline import encode_styled_copies, make_step_augmenter, make_styled_copies
from sword_jax.augment.synthetic import synthetic_episodes

SIZE, FRAMES = 32, 2


@pytest.fixture(scope="module")
def episodes():
    eps = synthetic_episodes(4, FRAMES, SIZE)
    eps["episode_ids"] = np.array([40, 11, 7, 23])
    return eps


def test_step_augmenter_training_styles_and_raw_share(episodes):
    fn = jax.jit(make_step_augmenter(AugmentConfig(), raw_fraction=0.5))
    frames, depth, seg = (jnp.asarray(episodes[k]) for k in ("frames", "depth", "seg"))
    out, styles, styled = fn(frames, depth, seg, key=jax.random.key(0))
    out2, _, _ = fn(frames, depth, seg, key=jax.random.key(0))
    np.testing.assert_array_equal(out, out2)
    st.assert_training_style(styles)
    styled = np.asarray(styled)
    diff = np.abs(np.asarray(out) - episodes["frames"]).reshape(4, -1).max(-1)
    assert (diff[~styled] == 0).all() and (diff[styled] > 0.05).all(), (styled, diff)
    shares = [np.asarray(fn(frames, depth, seg, key=jax.random.key(i))[2]).mean() for i in range(1, 9)]
    assert 0.2 < np.mean(shares) < 0.8


def test_styled_copies_deterministic_per_episode_and_training_only(episodes):
    copies = make_styled_copies(episodes, 2, jax.random.key(5))
    assert copies.frames.shape == (4, 2, FRAMES, SIZE, SIZE, 3)
    assert jax.tree.leaves(copies.styles)[0].shape[:2] == (4, 2)
    st.assert_training_style(copies.styles)
    assert np.abs(copies.frames[:, 0] - copies.frames[:, 1]).mean() > 0.02  # two different styles
    # Same key, episodes in another order and fewer of them: each episode's copies are unchanged.
    subset = {k: v[[2, 0]] for k, v in episodes.items()}
    again = make_styled_copies(subset, 2, jax.random.key(5))
    np.testing.assert_allclose(again.frames, copies.frames[[2, 0]], atol=1e-6)
    flat_frames, flat_actions, flat_ids = copies.flatten()
    assert flat_frames.shape[0] == 8 and list(flat_ids[:2]) == [40, 40]
    np.testing.assert_array_equal(flat_actions[1], episodes["actions"][0])
    with pytest.raises(ValueError, match="n_copies"):
        make_styled_copies(episodes, 0, jax.random.key(5))


def test_encode_styled_copies_keeps_latents_only(episodes):
    seen = []

    def fake_encode(video):
        seen.append((float(video.min()), float(video.max())))
        return video[:, :, ::16, ::16, :2]  # [C, T, 2, 2, 2]

    out = encode_styled_copies(episodes, 2, jax.random.key(5), fake_encode)
    assert out.frames.shape == (4, 2, FRAMES, 2, 2, 2)
    assert min(lo for lo, _ in seen) < -0.5  # the encoder got [-1, 1] video
    ref = make_styled_copies(episodes, 2, jax.random.key(5))
    np.testing.assert_allclose(out.frames, ref.frames[:, :, :, ::16, ::16, :2] * 2 - 1, atol=1e-5)


def test_eval_splits_deterministic_half_heldout(episodes, tmp_path):
    splits = build_eval_splits(episodes, seed=3)
    assert list(splits.original.episode_ids) == [7, 11, 23, 40]
    np.testing.assert_array_equal(splits.original.frames[0], episodes["frames"][2])
    mixed = splits.mixed
    assert mixed.styled.sum() == 2
    for i in range(4):
        changed = np.abs(mixed.frames[i] - splits.original.frames[i]).max()
        assert (changed > 0.05) == bool(mixed.styled[i])
        if mixed.styled[i]:
            assert st.style_split(jax.tree.map(lambda x, i=i: x[i], mixed.styles)) == "heldout"
    # Deterministic for the seed, independent of input order; another seed picks other styles.
    shuffled = {k: v[[3, 1, 0, 2]] for k, v in episodes.items()}
    again = build_eval_splits(shuffled, seed=3)
    np.testing.assert_array_equal(again.mixed.frames, mixed.frames)
    other = build_eval_splits(episodes, seed=4)
    assert np.abs(other.mixed.frames - mixed.frames).max() > 0.05
    manifest = json.load(open(splits.write_manifest(str(tmp_path / "eval" / "splits.json"))))
    assert manifest["seed"] == 3 and len(manifest["libero_mixed"]) == 4
    styled_entry = next(e for e in manifest["libero_mixed"] if e["styled"])
    assert st.style_split(st.style_from_record(styled_entry["style"])) == "heldout"
    with pytest.raises(ValueError, match="training episodes"):
        build_eval_splits(episodes, seed=3, training_ids=np.array([11, 99]))


def _styled_frames(episodes):
    return np.clip(1.0 - episodes["frames"], 0, 1)  # a stand-in "style transfer"


def test_ingest_npz_hdf5_png(episodes, tmp_path):
    styled = _styled_frames(episodes)
    ids = episodes["episode_ids"]
    np.savez(tmp_path / "stacked.npz", episode_ids=ids, frames=(styled * 255).round().astype(np.uint8),
             actions=episodes["actions"])
    np.savez(tmp_path / "per_episode.npz", **{f"episode_{i}": styled[k] * 2 - 1 for k, i in enumerate(ids)})
    with h5py.File(tmp_path / "styled.h5", "w") as f:
        for k, i in enumerate(ids[:2]):
            f.create_dataset(f"episodes/{i}/frames", data=styled[k])
            f.create_dataset(f"episodes/{i}/actions", data=episodes["actions"][k])
    for k, i in enumerate(ids):
        os.makedirs(tmp_path / "pngs" / str(i))
        for t in range(FRAMES):
            cv2.imwrite(str(tmp_path / "pngs" / str(i) / f"{t:04d}.png"), (styled[k, t, ..., ::-1] * 255).round().astype(np.uint8))
    order = np.argsort(ids)
    for name, tol in (("stacked.npz", 1 / 255), ("per_episode.npz", 1e-6), ("pngs", 1 / 255)):
        loaded = load_styled_episodes(str(tmp_path / name), episodes, require_all=True)
        np.testing.assert_array_equal(loaded.episode_ids, ids[order])
        np.testing.assert_allclose(loaded.frames, styled[order], atol=tol)
        np.testing.assert_array_equal(loaded.depth, episodes["depth"][order])
        np.testing.assert_array_equal(loaded.actions, episodes["actions"][order])
    partial = load_styled_episodes(str(tmp_path / "styled.h5"), episodes)
    assert sorted(partial.episode_ids) == sorted(ids[:2])
    with pytest.raises(StyledEpisodeError, match="no styled version"):
        load_styled_episodes(str(tmp_path / "styled.h5"), episodes, require_all=True)


def test_ingest_mismatches_are_named(episodes, tmp_path):
    styled = _styled_frames(episodes)
    ids = episodes["episode_ids"]
    cases = {
        "unknown.npz": (dict(episode_ids=ids + 1000, frames=styled), "no original"),
        "short.npz": (dict(episode_ids=ids, frames=styled[:, :1]), "1 frames, the original has 2"),
        "size.npz": (dict(episode_ids=ids, frames=styled[:, :, :16]), "original's are"),
        "actions.npz": (dict(episode_ids=ids, frames=styled, actions=episodes["actions"] + 1), "actions differ"),
        "nan.npz": (dict(episode_ids=ids, frames=styled * np.nan), "NaN"),
    }
    for name, (arrays, match) in cases.items():
        np.savez(tmp_path / name, **arrays)
        with pytest.raises(StyledEpisodeError, match=match):
            load_styled_episodes(str(tmp_path / name), episodes)
    (tmp_path / "corrupt.npz").write_bytes(b"not a zip file")
    with pytest.raises(StyledEpisodeError, match="cannot read"):
        load_styled_episodes(str(tmp_path / "corrupt.npz"), episodes)
    os.makedirs(tmp_path / "gap" / "7")
    for t in (0, 2):
        cv2.imwrite(str(tmp_path / "gap" / "7" / f"{t}.png"), np.zeros((SIZE, SIZE, 3), np.uint8))
    with pytest.raises(StyledEpisodeError, match="missing"):
        load_styled_episodes(str(tmp_path / "gap"), episodes)
    with pytest.raises(FileNotFoundError):
        load_styled_episodes(str(tmp_path / "nope.npz"), episodes)


def test_episode_validation(episodes):
    with pytest.raises(ValueError, match="duplicate"):
        as_episodes({**episodes, "episode_ids": np.array([1, 1, 2, 3])})
    with pytest.raises(ValueError, match="signed"):
        as_episodes({**episodes, "frames": episodes["frames"] * 2 - 1})
    ok = as_episodes({**episodes, "frames": episodes["frames"] * 2 - 1}, frames_range="signed")
    np.testing.assert_allclose(ok.frames, episodes["frames"], atol=1e-6)
    with pytest.raises(KeyError, match="depth"):
        as_episodes({k: v for k, v in episodes.items() if k != "depth"})


def test_config_validation():
    AugmentConfig().validate()
    for bad, match in ((dict(intensity=1.5), "intensity"), (dict(fov_deg=2.0), "fov_deg"),
                       (dict(seg_classes=(("arm", (2,)),)), "seg_classes")):
        with pytest.raises(ValueError, match=match):
            AugmentConfig(**bad).validate()
    with pytest.raises(ValueError, match="raw_fraction"):
        make_step_augmenter(AugmentConfig(), raw_fraction=-0.1)
    for removed in ("mode", "raw_fraction"):  # settings no pipeline read: gone, not silently ignored
        with pytest.raises(TypeError):
            AugmentConfig(**{removed: 0.5})


def test_gallery_writes_labelled_png(tmp_path):
    from train import gallery

    out = tmp_path / "gallery.png"
    assert gallery.main(["--out", str(out), "--source", "synthetic", "--size", "32", "--styles", "2"]) == 0
    image = cv2.imread(str(out))
    assert image is not None and image.shape[1] == 3 * 256 and image.shape[0] > 2 * 256
    assert image.std() > 20  # not blank


def test_gallery_of_a_sim_frame(tmp_path, capsys):
    from train import gallery as sim_gallery

    argv = ["--out", str(tmp_path / "sim.png"), "--source", "sim", "--size", "32", "--styles", "1"]
    assert sim_gallery.main(argv) == 0
    assert "source=sim" in capsys.readouterr().out
    rgb, depth, seg, classes, fov = sim_gallery.sim_frame(32, 0)
    assert rgb.shape == (1, 32, 32, 3) and depth.shape == seg.shape == (1, 32, 32) and fov > 0
    assert len(np.unique(seg)) > 3 and rgb.std() > 0.05  # table, robot and objects in view
    assert classes.fixtures  # the scene's cabinet / stove count as fixtures


def test_gallery_falls_back_to_the_synthetic_scene(tmp_path, capsys, monkeypatch):
    from sword_jax import cli
    from train import gallery

    def no_renderer(size, seed):
        raise RuntimeError("no GL")

    monkeypatch.setattr(gallery, "sim_frame", no_renderer)
    out = tmp_path / "auto.png"
    assert gallery.main(["--out", str(out), "--size", "32", "--styles", "1"]) == 0  # --source auto
    captured = capsys.readouterr()
    assert "sim render unavailable (RuntimeError: no GL)" in captured.err and "source=synthetic" in captured.out
    assert cv2.imread(str(out)) is not None
    with pytest.raises(RuntimeError, match="no GL"):  # asked for the sim: no silent substitute
        gallery.main(["--out", str(out), "--source", "sim", "--size", "32"])
    with pytest.raises(SystemExit) as exit_info:
        cli.run(gallery.main, ["--out", str(out), "--intensity", "5"])
    assert exit_info.value.code == 2 and "--intensity must be in [0, 1]" in capsys.readouterr().err


def test_episodes_from_sim_dataset_records(episodes):
    from types import SimpleNamespace

    from sword_jax.augment.episodes import episodes_from_sim

    sims = [SimpleNamespace(agentview_rgb=(episodes["frames"][k] * 255).round().astype(np.uint8),
                            agentview_depth=episodes["depth"][k], agentview_seg=episodes["seg"][k].astype(np.uint8),
                            actions=episodes["actions"][k]) for k in range(2)]
    eps = episodes_from_sim(sims, episode_ids=[5, 6])
    np.testing.assert_allclose(eps.frames, episodes["frames"][:2], atol=1 / 255)
    assert eps.seg.dtype == np.int32 and list(eps.episode_ids) == [5, 6]
    sims[1].agentview_depth = None
    with pytest.raises(ValueError, match="depth"):
        episodes_from_sim(sims)
