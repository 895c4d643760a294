"""Test setup: 8 fake CPU devices (set before jax is imported), strict dtype promotion, keys."""

import os

os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=8"
).strip()
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_numpy_dtype_promotion", "strict")

SHARED = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "shared"))


def _has_gpu() -> bool:
    try:
        return any(d.platform == "gpu" for d in jax.devices())
    except RuntimeError:
        return False


def pytest_collection_modifyitems(config, items):
    if _has_gpu():
        return
    skip_gpu = pytest.mark.skip(reason="needs a GPU")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture
def key():
    return jax.random.key(0)


@pytest.fixture
def keys():
    return jax.random.split(jax.random.key(1234), 8)


@pytest.fixture(scope="session")
def shared_dir():
    """``../shared`` beside the checkout (reference data for parity tests)."""
    path = os.environ.get("SWORD_SHARED_DIR", SHARED)
    if not os.path.isdir(path):
        pytest.skip(f"shared reference data not found at {path}")
    return path


REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))


def example_env() -> dict:
    """Environment for running the examples (and the tiny run) as a user would: this checkout
    first on the path, one CPU device (the fake device count of these tests is dropped)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([REPO, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
               JAX_PLATFORMS="cpu")
    flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join(flags)
    return env


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A tiny trained run (pipeline layout: vae_run/vae, world_model), built once per test session
    by ``examples/_tiny_run.py`` (2 steps each of the tiny VAE and world model) and shared by the
    xdist workers through a file lock."""
    import fcntl
    import subprocess
    import sys

    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # xdist: the session's dir, shared
    run = root / "tiny_run"
    with open(root / "tiny_run.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "tiny_run.done").exists():
            code = ("import sys; sys.path.insert(0, 'examples'); from _tiny_run import tiny_run; "
                    f"tiny_run(None, workdir={str(run)!r}, steps=2)")
            proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=example_env(), capture_output=True,
                                  text=True, timeout=600)
            assert proc.returncode == 0, f"building the tiny run failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
            (root / "tiny_run.done").write_text("ok")
    return str(run)
