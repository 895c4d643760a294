"""The VAE entry point on the shared loop: a run stopped and resumed from its work dir ends bit-identical
to an uninterrupted one (state, metrics.jsonl), and logs its compile time apart from the step rate."""

import json
import os

import jax
import numpy as np
import pytest

from sim import vae_training
from train import train_vae

ARGS = ["--config", "sword:tiny", "--synthetic", "--clip-latents=1", "--vae.batch_size=2", "--trainer.log_every=1",
        "--trainer.checkpoint_every=1", "--mesh.data=2", "--mesh.tensor=4"]
STEPS = 3


def _final_state(workdir: str) -> list[np.ndarray]:
    import orbax.checkpoint as ocp

    path = os.path.join(workdir, "checkpoints", str(STEPS), "state")
    return [np.asarray(x) for x in jax.tree.leaves(ocp.StandardCheckpointer().restore(path))]


def _rows(workdir: str) -> list[dict]:
    rows = [json.loads(line) for line in open(os.path.join(workdir, "metrics.jsonl"))]
    return [{k: v for k, v in row.items() if k not in ("elapsed_s", "eta_s")} for row in rows]


@pytest.mark.slow  # three compiles of the sharded VAE step
def test_train_vae_resumed_equals_uninterrupted(tmp_path, capsys):
    straight, split = str(tmp_path / "straight"), str(tmp_path / "split")
    summary = train_vae.main(ARGS + ["--workdir", straight, f"--vae.train_steps={STEPS}"])
    assert "first step (compile included)" in capsys.readouterr().out
    train_vae.main(ARGS + ["--workdir", split, "--vae.train_steps=1"])
    resumed = train_vae.main(ARGS + ["--workdir", split, f"--vae.train_steps={STEPS}"])
    assert "resumed from step 1" in capsys.readouterr().out
    want, got = _final_state(straight), _final_state(split)
    assert len(want) == len(got) > 10
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)
    assert _rows(split) == _rows(straight) and [r["step"] for r in _rows(split)] == [1, 2, 3]
    assert resumed["first_loss"] == summary["first_loss"] and resumed["final_loss"] == summary["final_loss"]
    assert os.path.isdir(os.path.join(split, "vae"))


@pytest.mark.slow  # 37 s; the loop's refusal of another run's checkpoint is checked in the default run by GRPO's
def test_a_checkpoint_of_another_vae_run_is_refused_naming_the_keys_and_kept(tmp_path):
    """Resuming a VAE work dir with another learning rate is refused before any step, naming the key;
    the checkpoint there is left as it was. A longer run (more ``vae.train_steps``) is the same run."""
    import configs
    from sword_jax import checkpoint
    from sword_jax import sharding as shd
    from sword_jax.train_loop import AnotherRunsCheckpoint
    from sword_jax.vae import train as vae_train

    workdir = str(tmp_path / "vae_run")
    cfg, _ = configs.from_argv(ARGS[:1] + ARGS[1:2] + ARGS[4:] + ["--workdir", workdir, "--vae.train_steps=2"])
    _, state = vae_train.init_train_state(cfg.vae, key=jax.random.key(cfg.seed), mesh=shd.make_mesh(cfg.mesh),
                                          rules=cfg.mesh.rules)
    saved_id = vae_training.vae_run_id(cfg, clip_latents=1, synthetic=True)
    assert vae_training.vae_run_id(configs.from_argv(ARGS[:2] + ["--vae.train_steps=9"])[0], clip_latents=1,
                                    synthetic=True)["vae.learning_rate"] == saved_id["vae.learning_rate"]
    saved_id["vae.learning_rate"] = cfg.vae.learning_rate * 10
    ckpt = checkpoint.Checkpointer(os.path.join(workdir, "checkpoints"), max_to_keep=1)
    ckpt.save(1, state, {"step": 1, "history": [], "run": saved_id})
    ckpt.close()
    before = sorted(os.listdir(os.path.join(workdir, "checkpoints")))
    with pytest.raises(AnotherRunsCheckpoint, match=r"differs in \['vae.learning_rate'\]"):
        vae_training.run_vae(cfg, synthetic=True, clip_latents=1)
    assert sorted(os.listdir(os.path.join(workdir, "checkpoints"))) == before
    assert not os.path.exists(os.path.join(workdir, "vae"))
