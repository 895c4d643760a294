"""train.encode_latents: episode files encoded with a given VAE into the world model's training latents, the
arrays the pipeline's latents stage writes for the same VAE and files."""

import os

import jax
import numpy as np
import pytest
from flax import nnx

import configs
from sim import data_stages
from sim.dataset import DatasetInfo, Episode, write_dataset
from sword_jax.pipeline.stages import Context
from sword_jax.world_model.data import load_latent_dataset, load_sources
from train import encode_latents

FRAMES = 13  # 4 latent frames: the shortest episodes the tiny world model's segments fit in
CONFIG = ["--config", "sword:tiny", f"--data.episode_frames={FRAMES}", f"--eval.horizon_frames={FRAMES}",
          f"--sim.episode_steps={FRAMES}"]


def _episode(steps: int, seed: int) -> Episode:
    rng = np.random.default_rng(seed)
    size = 32
    return Episode(actions=rng.uniform(-1, 1, (steps, 7)), states=rng.normal(size=(steps, 20)),
                   rewards=np.zeros(steps), dones=np.zeros(steps),
                   agentview_rgb=rng.integers(0, 256, (steps, size, size, 3), dtype=np.uint8),
                   eye_in_hand_rgb=rng.integers(0, 256, (steps, size, size, 3), dtype=np.uint8),
                   ee_states=rng.normal(size=(steps, 6)), gripper_states=rng.normal(size=(steps, 2)),
                   joint_states=rng.normal(size=(steps, 7)),
                   agentview_depth=rng.uniform(0.5, 2.0, (steps, size, size)).astype(np.float32),
                   agentview_seg=rng.integers(0, 10, (steps, size, size)), model_file="<mujoco/>", task_id=0,
                   language_instruction="pick up the black bowl")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """An expert file of 2 episodes (one longer than the world model's), a policy-rollout file of 1 and the tiny
    config's VAE (random weights) saved as train_vae saves it."""
    from sim.vae_training import save_vae
    from sword_jax.vae import api as vae_api

    root = tmp_path_factory.mktemp("encode_latents")
    info = DatasetInfo(env_name="sword/LiberoSpatial-v0", seg_class_names=("background", "table"))
    expert, policy = str(root / "expert.hdf5"), str(root / "policy.hdf5")
    write_dataset(expert, [_episode(FRAMES + 2, 0), _episode(FRAMES, 1)], info)
    write_dataset(policy, [_episode(FRAMES, 2)], info)
    cfg, _ = configs.from_argv(CONFIG)
    graphdef, state = nnx.split(vae_api.create_vae(cfg.vae, key=jax.random.key(3)))
    params, constants = state.split(nnx.Param, ...)
    save_vae(str(root / "vae"), graphdef, params, constants)
    return {"root": root, "cfg": cfg, "files": [expert, policy], "vae": str(root / "vae")}


def test_the_entry_writes_the_latents_the_pipeline_stage_writes(inputs, capsys):
    """E = 3 episodes x (1 raw + 2 styled copies) of [4, 2, 2, 48] latents that load_latent_dataset reads; the
    policy file's episode and its copies are marked 1; the raw latents are the VAE's encoding of the frames; and
    the arrays equal, bit for bit, those the pipeline's latents stage writes for the same VAE and files."""
    from sword_jax.load import load_vae_params
    from sword_jax.vae import api as vae_api

    root, cfg, files = inputs["root"], inputs["cfg"], inputs["files"]
    out = str(root / "entry" / "latents.npz")
    summary = encode_latents.main(CONFIG + ["--vae", inputs["vae"], "--out", out, *files])
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"[encode_latents] {out}: 9 episodes (3 raw, 2 styled copies each") and "4x2x2x48" in line
    assert len(line.splitlines()) == 1 and sorted(os.listdir(root / "entry")) == ["latents.npz"]
    data = load_latent_dataset(out)
    assert data.latents.shape == (9, 4, 2, 2, 48) and data.actions.shape == (9, FRAMES, 7)
    assert summary["latent_shape"] == [4, 2, 2, 48] and summary["styled_copies"] == 2
    sources = load_sources(out, 9)
    np.testing.assert_array_equal(sources, [0, 0, 1, 0, 0, 0, 0, 1, 1])  # raw in file order, then 2 copies each
    _, episodes = data_stages.load_episodes(files, FRAMES)
    np.testing.assert_array_equal(data.actions[:3], episodes.actions.astype(np.float32))
    np.testing.assert_array_equal(data.actions[3:], np.repeat(episodes.actions, 2, axis=0).astype(np.float32))
    graphdef, state = load_vae_params(cfg.vae, inputs["vae"])
    raw = np.asarray(vae_api.encode(graphdef, state, episodes.frames[2:3] * 2.0 - 1.0))
    np.testing.assert_allclose(data.latents[2], raw[0], rtol=1e-5, atol=1e-5)
    assert np.abs(data.latents[7] - data.latents[2]).mean() > 1e-3  # a styled copy is another look
    # the pipeline's stage on the same files (expert data, then the policy's rollouts) and VAE
    ctx = Context(cfg=cfg, workdir=str(root / "run"), results={
        "data": {"train": {"path": files[0]}, "heldout": {"path": files[1]}}, "policy_data": {"path": files[1]},
        "vae": {"path": inputs["vae"]}})
    stage = data_stages.encode_training_latents(ctx)
    with np.load(out) as entry, np.load(stage["path"]) as written:
        assert entry.files == written.files == ["latents", "actions", "sources"]
        for name in entry.files:
            assert entry[name].dtype == written[name].dtype and entry[name].shape == written[name].shape, name
            assert entry[name].tobytes() == written[name].tobytes(), name
    assert stage["episodes"] == 9 and stage["raw_episodes"] == 3 and stage["policy_episodes"] == 3


def test_the_latents_stage_marks_the_exploring_experts_episodes_apart(inputs):
    """With exploration episodes (data.exploration_episodes_per_task) the stage encodes them after the expert's and
    the policy's and marks them 2, so the trainer's training-policy split (sources 1) keeps only the policy's; the
    summary counts each kind, styled copies included; kinds that do not fit the files are refused."""
    root, cfg = inputs["root"], inputs["cfg"]
    expert, policy = inputs["files"]
    ctx = Context(cfg=cfg, workdir=str(root / "exploring"), results={
        "data": {"train": {"path": expert}, "heldout": {"path": policy}, "exploration": {"path": policy}},
        "policy_data": {"path": policy}, "vae": {"path": inputs["vae"]}})
    stage = data_stages.encode_training_latents(ctx)
    sources = load_sources(stage["path"], 12)
    np.testing.assert_array_equal(sources, [0, 0, 1, 2, 0, 0, 0, 0, 1, 1, 2, 2])
    assert stage["files"] == [expert, policy, policy]
    assert (stage["episodes"], stage["policy_episodes"], stage["exploration_episodes"]) == (12, 3, 3)
    from sword_jax.load import load_vae_params

    graphdef, state = load_vae_params(cfg.vae, inputs["vae"])
    with pytest.raises(ValueError, match="kinds"):
        data_stages.encode_episode_latents(cfg, graphdef, state, [expert, policy], ["expert"])
    with pytest.raises(ValueError, match="kinds"):
        data_stages.encode_episode_latents(cfg, graphdef, state, [expert], ["teacher"])


def test_the_entry_refuses_an_existing_out_missing_files_and_a_wrong_vae(inputs):
    """Each refusal is one line naming the problem (episodes too short for the world model too); an existing --out
    is left as it was."""
    root, files = inputs["root"], inputs["files"]
    kept = root / "kept.npz"
    kept.write_bytes(b"saved before")
    args = CONFIG + ["--vae", inputs["vae"]]
    with pytest.raises(SystemExit, match=f"{kept} exists; name a new file"):
        encode_latents.main(args + ["--out", str(kept), *files])
    assert kept.read_bytes() == b"saved before"
    fresh = str(root / "fresh.npz")
    with pytest.raises(SystemExit, match=f"no episode file at {root / 'nope.hdf5'}$"):
        encode_latents.main(args + ["--out", fresh, files[0], str(root / "nope.hdf5")])
    (root / "not_a_vae").mkdir(exist_ok=True)
    with pytest.raises(SystemExit, match=f"{root / 'not_a_vae'} is not a VAE folder"):
        encode_latents.main(CONFIG + ["--vae", str(root / "not_a_vae"), "--out", fresh, *files])
    with pytest.raises(SystemExit, match="holds a VAE of another architecture than the config's .*vae.dim=16"):
        encode_latents.main(CONFIG + ["--vae.dim=16", "--vae", inputs["vae"], "--out", fresh, *files])
    with pytest.raises(SystemExit, match="must end in .npz"):
        encode_latents.main(args + ["--out", str(root / "latents.h5"), *files])
    short = str(root / "short.hdf5")  # episodes shorter than the world model's: not padded, refused
    write_dataset(short, [_episode(FRAMES - 4, 5)], DatasetInfo(env_name="sword/LiberoSpatial-v0",
                                                                seg_class_names=("background", "table")))
    with pytest.raises(SystemExit, match=rf"^train.encode_latents: episode of task 0 has {FRAMES - 4} < {FRAMES}"):
        encode_latents.main(args + ["--out", fresh, short])
    assert not os.path.exists(fresh) and not os.path.exists(f"{fresh}.partial")
