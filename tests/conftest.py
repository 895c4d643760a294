"""Test setup: 8 fake CPU devices (set before jax is imported), fast compilation, strict dtype promotion, keys."""

import os
import platform

# The suite compiles hundreds of small programs and runs each a few times: LLVM's optimisation passes cost
# more compile time than they save in run time, and XLA:CPU's MLIR fusion emitters compile two to three times
# slower than its elemental emitter. With AVX2's FMA the elemental emitter rounds the same math differently in
# programs fused differently (test_dlb's read-probability-0 step is then not bitwise the teacher-forcing step);
# capped at AVX it rounds them the same. Child processes inherit the flags.
# XLA aborts the process on a flag it does not know, and newer jaxlib releases drop some (0.11 has no
# --xla_cpu_use_fusion_emitters, though its libraries still carry the name): a child process starts XLA with the
# flags first, and each flag it names as unknown is dropped. The result is passed to xdist's workers in XLA_FLAGS.
_FAST_FLAGS = ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true",
               "--xla_cpu_use_fusion_emitters=false"]
if platform.machine().lower() in ("x86_64", "amd64"):
    _FAST_FLAGS.append("--xla_cpu_max_isa=AVX")
_PROBED = "SWORD_TEST_XLA_FLAGS"  # set once the flags were probed: workers inherit the result


def _accepted_by_xla(flags: list[str], base: str = "") -> list[str]:
    """``flags`` less those XLA refuses: a child process initialises XLA's CPU backend with ``base`` and them, and
    each flag its abort message names is dropped until it starts (or fails for another reason, which the suite
    then reports itself)."""
    import subprocess
    import sys

    kept = list(flags)
    while kept:
        env = dict(os.environ, XLA_FLAGS=f"{base} {' '.join(kept)}".strip(), JAX_PLATFORMS="cpu")
        done = subprocess.run([sys.executable, "-c", "import jax; jax.devices()"], env=env, capture_output=True,
                              text=True, timeout=300)
        if done.returncode == 0:
            break
        refused = [f for f in kept if f"Unknown flag in XLA_FLAGS: {f.split('=', 1)[0]}" in done.stderr]
        if not refused:
            break
        kept = [f for f in kept if f not in refused]
    return kept


if os.environ.get(_PROBED) is None:
    _base = os.environ.get("XLA_FLAGS", "")
    os.environ[_PROBED] = " ".join(_accepted_by_xla(_FAST_FLAGS, _base))
    os.environ["XLA_FLAGS"] = f"{_base} {os.environ[_PROBED]} --xla_force_host_platform_device_count=8".strip()
FAST_COMPILE = os.environ[_PROBED]
os.environ.setdefault("JAX_PLATFORMS", "cpu")
# One persistent compilation cache for the test run (xdist's workers and the child processes inherit it): many
# tests build the same programs again in fresh jits (each trainer's main(), a second run to resume, a child
# process of the same config), and a program compiled once is then read back. Removed at the end of the run by
# the process that made it; a cache the environment names is used and kept.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    import atexit
    import shutil
    import tempfile

    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="sword-tests-xla-cache-")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.1")
    atexit.register(shutil.rmtree, os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)
if "MUJOCO_GL" not in os.environ:
    import ctypes.util

    # headless OpenGL where the machine has EGL; unset, mujoco's import leaves the choice to the renderer's first use
    # (MUJOCO_GL=egl without libEGL makes ``import mujoco`` itself fail)
    if ctypes.util.find_library("EGL"):
        os.environ["MUJOCO_GL"] = "egl"

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
LONG_FIRST = ("test_multihost.py::", "test_wm_entry.py::test_a_checkpoint_step_path",
              "test_reliability.py::test_sigkill", "test_sim_mjx_batch.py::test_mjx_episodes_continue",
              "test_sim_agreement.py::test_ground_truth_grpo_from_rest",
              "test_imagined_check.py::test_an_executed_step", "test_sim_render_static.py::",
              "test_rl_policy_learning.py::test_grpo_against_the_mujoco",
              "test_bench_multi_gpu.py::test_small_rows_of_every_kind", "test_bench_multi_gpu.py::test_sweep_rows",
              # the longest of those on the tiny run, first among them
              "test_examples.py::test_policy_grpo", "test_decoded_sft.py::test_a_trained_world_model_replays",
              "test_evaluate_world_model.py::test_a_trained_world_model_is_evaluated")


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
