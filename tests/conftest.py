"""Test setup: 8 fake CPU devices (set before jax is imported), fast compilation, strict dtype promotion, keys."""

import os
import platform

# The suite compiles hundreds of small programs and runs each a few times: LLVM's optimisation passes cost
# more compile time than they save in run time, and XLA:CPU's MLIR fusion emitters compile two to three times
# slower than its elemental emitter. With AVX2's FMA the elemental emitter rounds the same math differently in
# programs fused differently (test_dlb's read-probability-0 step is then not bitwise the teacher-forcing step);
# capped at AVX it rounds them the same. Child processes inherit the flags.
# XLA aborts the process on a flag it does not know, and newer jaxlib releases drop some (0.11 has no
# --xla_cpu_use_fusion_emitters): a flag is kept only where jaxlib's own libraries name it.
_FAST_FLAGS = ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true",
               "--xla_cpu_use_fusion_emitters=false"]
if platform.machine().lower() in ("x86_64", "amd64"):
    _FAST_FLAGS.append("--xla_cpu_max_isa=AVX")


def _known_to_xla(flags: list[str]) -> list[str]:
    """``flags`` whose names appear in jaxlib's shared libraries (all of them where none can be read)."""
    import importlib.util
    import mmap

    spec = importlib.util.find_spec("jaxlib")
    names = {f: f.lstrip("-").split("=", 1)[0].encode() for f in flags}
    found: set[str] = set()
    seen_any = False
    for root, _, files in os.walk(os.path.dirname(spec.origin) if spec and spec.origin else ""):
        for name in files:
            if not name.endswith(".so"):
                continue
            try:
                with open(os.path.join(root, name), "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                    seen_any = seen_any or m.find(b"xla_force_host_platform_device_count") >= 0
                    found.update(flag for flag, key in names.items() if flag not in found and m.find(key) >= 0)
            except (OSError, ValueError):
                continue
    return [f for f in flags if f in found] if seen_any else list(flags)


FAST_COMPILE = " ".join(_known_to_xla(_FAST_FLAGS))
os.environ["XLA_FLAGS"] = (
    os.environ.get("XLA_FLAGS", "") + f" {FAST_COMPILE} --xla_force_host_platform_device_count=8"
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


def _skip_gpu(items):
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


def _tiny_run_root(tmp_path_factory):
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # xdist: the test run's dir, shared


def _start_tiny_run(root) -> None:
    """Starts building the tiny run in the background, unless a process of this test run already did."""
    import subprocess
    import sys

    try:
        os.close(os.open(root / "tiny_run.started", os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return
    code = ("import sys, traceback; sys.path.insert(0, 'examples')\n"
            "try:\n    from _tiny_run import tiny_run\n"
            f"    tiny_run(None, workdir={str(root / 'tiny_run')!r}, steps=2); marker = 'done'\n"
            "except BaseException:\n    traceback.print_exc(); marker = 'failed'\n"
            f"open({str(root / 'tiny_run.')!r} + marker, 'w').close()\n")
    with open(root / "tiny_run.log", "w") as log:
        subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=example_env(), stdout=log,
                         stderr=subprocess.STDOUT, start_new_session=True)


# The longest default tests (30-90 s each on 2 cores), started first so that none of them is left running
# alone at the end of a parallel run (with --dist worksteal the others fill in around them).
LONG_FIRST = ("test_multihost.py::", "test_rl_resume.py::test_grpo_sigkill", "test_reliability.py::test_sigkill",
              "test_grpo.py::test_grpo_improves_policy_on_toy_simulator", "test_sim_render_static.py::",
              "test_rl_policy_learning.py::test_grpo_against_the_mujoco",
              "test_bench_multi_gpu.py::test_small_rows_of_every_kind", "test_bench_multi_gpu.py::test_sweep_rows")


def pytest_collection_modifyitems(config, items):
    _skip_gpu(items)
    # tests on the tiny run go last, so its background build (see _build_tiny_run) overlaps the others;
    # the longest ones first
    items.sort(key=lambda item: ("tiny_run" in getattr(item, "fixturenames", ()),
                                 not any(name in item.nodeid for name in LONG_FIRST)))


@pytest.fixture(scope="session", autouse=True)
def _build_tiny_run(request, tmp_path_factory):
    if any("tiny_run" in getattr(item, "fixturenames", ()) for item in request.session.items):
        _start_tiny_run(_tiny_run_root(tmp_path_factory))


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A tiny trained run (pipeline layout: vae_run/vae, world_model) made by ``examples/_tiny_run.py``
    (2 steps each of the tiny VAE and world model, one CPU device), built once per test session in
    the background from its start and shared by the xdist workers."""
    import time

    root = _tiny_run_root(tmp_path_factory)
    _start_tiny_run(root)
    deadline = time.monotonic() + 900
    while not (root / "tiny_run.done").exists():
        if (root / "tiny_run.failed").exists() or time.monotonic() > deadline:
            pytest.fail(f"building the tiny run failed:\n{(root / 'tiny_run.log').read_text()[-4000:]}")
        time.sleep(0.5)
    return str(root / "tiny_run")
