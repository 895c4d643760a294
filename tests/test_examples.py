"""The examples run as a user runs them (``python examples/X.py``, one CPU device), on a tiny run."""

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO, example_env


def _example(name, *args, timeout=300):
    proc = subprocess.run([sys.executable, os.path.join("examples", name), *args], cwd=REPO, env=example_env(),
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{name} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


def test_imagine_rollout_writes_a_gif(tiny_run, tmp_path):
    from PIL import Image

    out = tmp_path / "rollout.gif"
    printed = _example("imagine_rollout.py", "--run", tiny_run, "--chunks", "2", "--out", str(out))
    # tiny: 1 given + 4 context frames, then 2 chunks of 8 predicted frames, 2 videos of 32 x 32
    assert "imagined (2, 21, 32, 32, 3) from 5 given frames and 21 actions" in printed
    with Image.open(out) as gif:
        assert gif.n_frames > 1 and gif.size[0] > gif.size[1]  # real and imagined side by side


def test_policy_grpo_updates_a_user_policy(tiny_run):
    printed = _example("policy_grpo.py", "--run", tiny_run, "--steps", "2")
    assert "grpo step 2/2" in printed
    moved = float(re.search(r"moved by ([0-9.eE+-]+)", printed).group(1))
    assert moved > 0  # the GRPO update reached the user's parameters


def test_score_video_folders(tmp_path):
    printed = _example("score_video_folders.py", "--demo-dir", str(tmp_path), "--out", str(tmp_path / "s.json"))
    result = json.load(open(tmp_path / "s.json"))
    assert json.loads(printed) == result
    assert result["videos"] == ["video0", "video1", "video2"] and result["frames"] == 17  # GIF repeats restored
    scores = result["scores"]
    assert 0.05 < scores["lpips"] < 1.0 and 10.0 < scores["psnr"] < 30.0 and scores["ssim"] < 0.9  # noisy copy
    assert result["random_weight_networks"] == [] and "lpips" in result["weights"]


def test_score_video_folders_reads_pairs_by_name(tmp_path):
    sys.path.insert(0, os.path.join(REPO, "examples"))
    try:
        import score_video_folders as score
    finally:
        sys.path.pop(0)
    real_dir, generated_dir = score.write_demo_folders(str(tmp_path / "demo"))
    names, real, generated = score.read_pairs(real_dir, generated_dir)
    assert names == ["video0", "video1", "video2"] and real.shape == generated.shape == (3, 17, 64, 64, 3)
    assert 0 < np.abs(real - generated).mean() < 0.2
    os.remove(os.path.join(generated_dir, "video2.npy"))
    try:
        score.read_pairs(real_dir, generated_dir)
    except SystemExit as err:
        assert "unpaired: ['video2']" in str(err)
    else:
        raise AssertionError("an unpaired video must be refused")


TINY_PPO = ["--num-envs", "2", "--unroll-length", "2", "--iterations", "2", "--episode-length", "2", "--hidden", "16",
            "--cnn-channels", "4"]


def _brax_ppo(monkeypatch):
    """The example as a module, with ``examples/`` on the path while the test runs (it imports its siblings)."""
    monkeypatch.syspath_prepend(os.path.join(REPO, "examples"))
    import brax_ppo

    return brax_ppo


@pytest.mark.slow  # ~50 s in the suite (the tiny run's world model inside the env); the toy world's runs by default
def test_brax_ppo_trains_two_iterations_inside_a_world_model(tiny_run, monkeypatch):
    """The example's brax PPO call against the learned simulator's brax env over the tiny trained world model,
    in this process (brax's wrappers under standard promotion). PPO on the MJX env is ``-m slow`` too (MJX
    compiles for minutes on a CPU)."""
    import jax

    brax_ppo = _brax_ppo(monkeypatch)
    with jax.numpy_dtype_promotion("standard"):
        result = brax_ppo.main(["--env", "learned", "--run", tiny_run, *TINY_PPO])
    assert result["env"] == "learned" and [it["env_steps"] for it in result["iterations"]] == [4, 8]
    assert all(np.isfinite(it["policy_loss"]) and it["steps_per_s"] > 0 for it in result["iterations"])


def test_brax_ppo_trains_two_iterations_over_the_toy_world(monkeypatch):
    """What CI runs of the example: the same brax PPO call, two iterations on tiny shapes, against the learned
    simulator's brax env (``ImaginedPoolEnv``) over the analytic toy world, in this process (~14 s on a 2-core
    CPU, most of it compilation). The env over the tiny trained world model is ``-m slow``; the MJX env's side
    of the swap is checked by ``tests/test_brax_envs.py`` (brax's wrappers step it)."""
    import jax

    brax_ppo = _brax_ppo(monkeypatch)
    with jax.numpy_dtype_promotion("standard"):
        result = brax_ppo.main(["--env", "toy", *TINY_PPO])
    assert result["env"] == "toy" and [it["env_steps"] for it in result["iterations"]] == [4, 8]
    assert all(np.isfinite(it["policy_loss"]) and it["steps_per_s"] > 0 for it in result["iterations"])


@pytest.mark.slow
def test_brax_ppo_runs_as_a_user_runs_it(tiny_run):
    """``python examples/brax_ppo.py --env learned`` in its own process, as the README gives it."""
    printed = _example("brax_ppo.py", "--env", "learned", "--run", tiny_run, *TINY_PPO)
    assert "backend learned_simulator): action_size 56" in printed and "ppo iteration 2/2: 8 env steps" in printed
