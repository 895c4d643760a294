"""A tiny trained run for the examples when none is given.

A few steps of the tiny VAE (on moving squares) and the tiny world model (on synthetic latents),
through their commands (``python -m train.train_vae``, ``python -m train.train_world_model``), laid out
as a pipeline work dir
(``<run>/vae_run/vae``, ``<run>/world_model``) so that ``sword_jax.load_world_model(run)`` finds
both. Trained for seconds, such a model shows the plumbing, not good predictions: for a real one,
pass the work dir of ``python -m train.pipeline``.
"""

from __future__ import annotations

import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def tiny_run(run: str | None, *, workdir: str = "runs/examples-tiny", steps: int = 10) -> str:
    """``run`` if given, else a tiny run trained (or reused, if already trained) in ``workdir``."""
    if run:
        return run
    world_model = os.path.join(workdir, "world_model")
    done = os.path.isdir(os.path.join(workdir, "vae_run", "vae")) and os.path.isdir(
        os.path.join(world_model, "checkpoints", str(steps)))
    if not done:  # each command resumes what an interrupted run left
        config = ["--config", "sword:tiny", f"--vae.train_steps={steps}", f"--trainer.steps={steps}",
                  f"--trainer.checkpoint_every={steps}", "--model.num_layers=1"]
        print(f"[examples] no --run given: training a tiny VAE and world model for {steps} steps in {workdir}",
              flush=True)
        workdir = os.path.abspath(workdir)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [REPO, os.environ.get("PYTHONPATH")]))}
        for command in (["train.train_vae", *config, "--workdir", os.path.join(workdir, "vae_run"), "--synthetic",
                         "--clip-latents=1"],
                        ["train.train_world_model", *config, "--workdir", os.path.join(workdir, "world_model"),
                         "--synthetic"]):
            subprocess.run([sys.executable, "-m", *command], cwd=REPO, env=env, check=True)
    return workdir
