"""The suite's XLA flags: a flag this jaxlib does not know is dropped (XLA aborts the process on one)."""

from tests.conftest import FAST_COMPILE, _accepted_by_xla


def test_flags_unknown_to_this_jaxlib_are_dropped():
    kept = _accepted_by_xla(["--xla_backend_optimization_level=0", "--xla_no_such_flag_in_any_release=1",
                             "--xla_llvm_disable_expensive_passes=true"])
    assert kept == ["--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true"]
    assert "xla_no_such_flag" not in FAST_COMPILE and "--xla_backend_optimization_level=0" in FAST_COMPILE
