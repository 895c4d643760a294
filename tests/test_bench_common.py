"""benchmarks.common: the datasheet peaks MFU is also quoted against, and the MFU arithmetic."""

import pytest

from benchmarks import common


@pytest.mark.parametrize("kind,peak", [("NVIDIA H100 80GB HBM3", 989.4), ("NVIDIA H100 PCIe", 756.0),
                                       ("NVIDIA H200", 989.4), ("NVIDIA A100-SXM4-80GB", 312.0), ("cpu", None),
                                       ("TPU v5 lite", None)])
def test_nominal_peak_by_device_kind(kind, peak):
    assert common.nominal_peak_tflops(kind) == peak


def test_mfu_is_achieved_over_peak():
    # 2,803 GFLOP per frame at 156.6 frames/s on a 989.4 TFLOP/s part
    assert common.mfu(2803e9, 156.6, 989.4) == pytest.approx(2803e9 * 156.6 / 989.4e12)
    assert common.mfu(1e12, 1.0, None) is None
    assert common.nominal_peak_tflops() is None  # this CPU is no listed accelerator
