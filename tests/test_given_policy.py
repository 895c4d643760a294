"""``rl.sft.init``: the pipeline starts from a trained policy instead of behaviour cloning one."""

import dataclasses
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from flax import nnx

import configs
from sim.policy_training import given_policy
from sword_jax.rl.params_io import load_params, save_params_npz
from sword_jax.rl.policy import build_policy
from tests.conftest import REPO, example_env


def _cfg(tmp_path, **rl_policy):
    cfg = configs.get("sword:tiny")
    rl = dataclasses.replace(cfg.rl, policy=dataclasses.replace(cfg.rl.policy, **rl_policy))
    return dataclasses.replace(cfg, rl=rl, workdir=str(tmp_path / "run"))


def _saved_policy(tmp_path, cfg, seed=3):
    _, params = build_policy(cfg.rl, seed=seed)
    path = str(tmp_path / "given.npz")
    save_params_npz(path, params)
    return path, params


def test_the_given_policy_is_copied_into_the_run_and_loads_there(tmp_path):
    cfg = _cfg(tmp_path)
    source, params = _saved_policy(tmp_path, cfg)
    result = given_policy(cfg, source)
    os.remove(source)  # the run no longer needs the original
    assert result["path"].startswith(os.path.abspath(cfg.workdir)) and result["given"] == source
    _, fresh = build_policy(cfg.rl, seed=0)  # other initial weights: the load must replace them
    loaded, _ = load_params(result["path"], fresh, kind="policy")
    got, want = jax.tree.leaves(nnx.to_pure_dict(loaded)), jax.tree.leaves(nnx.to_pure_dict(params))
    assert len(got) == len(want)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with open(os.path.join(cfg.workdir, "rl", "sft_result.json")) as f:
        assert json.load(f)["given"] == source


def test_a_missing_policy_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="rl.sft.init: no such policy"):
        given_policy(_cfg(tmp_path), str(tmp_path / "nowhere.npz"))


def test_a_policy_of_another_architecture_is_refused_and_leaves_nothing(tmp_path):
    cfg = _cfg(tmp_path)
    source, _ = _saved_policy(tmp_path, _cfg(tmp_path, width=cfg.rl.policy.width * 2))
    with pytest.raises(ValueError, match="does not load into this config's policy"):
        given_policy(cfg, source)
    assert not [n for n in os.listdir(os.path.join(cfg.workdir, "rl")) if n.startswith("policy_given")]


@pytest.mark.slow
def test_the_pipeline_records_rollouts_of_the_given_policy(tmp_path):
    """The supervised-policy stage takes the given policy, and the policy-rollout stage acts with it."""
    cfg = _cfg(tmp_path)
    source, _ = _saved_policy(tmp_path, cfg)
    work = tmp_path / "pipe"
    proc = subprocess.run([sys.executable, "-m", "train.pipeline", "--config", "sword:tiny", "--workdir", str(work),
                           "--stop-after", "policy_data", "--skip", "vae", f"--rl.sft.init={source}",
                           "--data.policy_rollouts_per_task=1"], cwd=REPO, env=example_env(), capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "starting from the given policy" in proc.stdout
    assert not os.path.exists(work / "rl" / "policy_sft") and os.path.exists(work / "rl" / "policy_given.npz")
    assert os.path.exists(work / "data" / "policy_rollouts.hdf5")
