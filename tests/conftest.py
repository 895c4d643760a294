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
