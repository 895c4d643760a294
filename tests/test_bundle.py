"""sword_jax.bundle / train.bundle: a pipeline's inference weights packed into checked parts and restored."""

import json
import os
import shutil

import pytest

import sword_jax
from sword_jax import bundle
from tests.support.checkpoints import trees_equal
from train import bundle as bundle_cli


def _reward(run):
    from sword_jax.rl.config import RewardModelConfig, RLConfig
    from sword_jax.rl.params_io import save_params
    from sword_jax.rl.reward_model import build_detector

    rl = RLConfig(image_size=32, reward_model=RewardModelConfig(width=8))
    _, params = build_detector(rl, seed=3)
    save_params(os.path.join(run, "rl", "reward_model"), params, rl, kind="reward_model", step=7)


def test_a_bundle_moves_the_inference_weights_in_checked_parts_and_refuses_damaged_ones(tiny_run, tmp_path):
    run, out, other = (str(tmp_path / n) for n in ("run", "out", "other"))
    shutil.copytree(tiny_run, run)
    _reward(run)
    manifest = bundle_cli.main(["pack", run, out, "--part-mib", "0.25"])
    assert manifest["contents"] == ["world_model", "vae_run/vae", "rl/reward_model"]
    parts = manifest["parts"]
    assert len(parts) > 2 and all(0 < p["bytes"] <= 2**18 for p in parts)
    assert sum(p["bytes"] for p in parts) == manifest["bytes"] and sorted(os.listdir(out)) == sorted(
        [bundle.MANIFEST, *(p["name"] for p in parts)])  # nothing else left in the folder
    # the parts travel in two folders; restored, every loader reads the same weights bit for bit
    os.makedirs(other)
    for p in parts[::2]:
        shutil.move(os.path.join(out, p["name"]), os.path.join(other, p["name"]))
    dest = str(tmp_path / "dest")
    bundle_cli.main(["unpack", dest, out, other])
    a = sword_jax.load_world_model(run, reward_model=os.path.join(run, "rl", "reward_model"))
    b = sword_jax.load_world_model(dest, reward_model=os.path.join(dest, "rl", "reward_model"))
    assert b.loaded_from.step == a.loaded_from.step == manifest["world_model"]["step"]
    for x, y in ((a.world_model_params, b.world_model_params), (a.vae_params, b.vae_params),
                 (a.reward_model.params, b.reward_model.params)):
        assert trees_equal(x, y)
    with open(os.path.join(dest, bundle.MANIFEST)) as f:
        assert json.load(f) == manifest  # where the weights came from, kept beside them
    with open(os.path.join(dest, "world_model", "config.json")) as f:
        assert json.load(f)["model"]["num_layers"] == a.spec.model.num_layers
    # a damaged part, a missing one, and folders that are not new are refused by name; nothing is written
    damaged = os.path.join(other, parts[0]["name"])
    with open(damaged, "r+b") as f:
        byte = f.read(1)
        f.seek(0)
        f.write(bytes([byte[0] ^ 1]))
    with pytest.raises(SystemExit, match=f"part {parts[0]['name']} .* does not match the manifest"):
        bundle_cli.main(["unpack", str(tmp_path / "d2"), out, other])
    assert not os.path.exists(tmp_path / "d2")
    os.remove(damaged)
    with pytest.raises(SystemExit, match=f"parts {parts[0]['name']} of {len(parts)} are in none of"):
        bundle_cli.main(["unpack", str(tmp_path / "d2"), out, other])
    with pytest.raises(SystemExit, match="exists and is not an empty folder"):
        bundle_cli.main(["unpack", dest, out, other])
    with pytest.raises(SystemExit, match="exists and is not an empty folder"):
        bundle_cli.main(["pack", run, out])
    alone = str(tmp_path / "alone" / "world_model")  # a world-model work dir with no pipeline around it
    shutil.copytree(os.path.join(run, "world_model"), alone)
    with pytest.raises(SystemExit, match="without its pipeline's VAE"):
        bundle_cli.main(["pack", alone, str(tmp_path / "o2")])
    with pytest.raises(SystemExit, match="part_bytes must be at least 64 KiB"):
        bundle_cli.main(["pack", run, str(tmp_path / "o3"), "--part-mib", "0.01"])
    with pytest.raises(SystemExit, match="no bundle.json"):
        bundle_cli.main(["unpack", str(tmp_path / "d3"), str(tmp_path)])
