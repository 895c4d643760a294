"""MetricLogger: one log step late, metrics.jsonl and TensorBoard event files."""

import glob
import io
import json
import struct
import sys

import jax.numpy as jnp
import pytest

from sword_jax import checkpoint


def _tensorboard_scalars(logdir: str) -> dict[str, list[tuple[int, float]]]:
    """``{tag: [(step, value), ...]}`` read from the TFRecord event files in ``logdir``."""
    from tensorboardX.proto import event_pb2

    scalars: dict[str, list[tuple[int, float]]] = {}
    for path in sorted(glob.glob(f"{logdir}/events.out.tfevents.*")):
        with open(path, "rb") as f:
            data = f.read()
        offset = 0
        while offset < len(data):
            (length,) = struct.unpack("<Q", data[offset:offset + 8])
            event = event_pb2.Event.FromString(data[offset + 12:offset + 12 + length])
            offset += 12 + length + 4  # length, its crc, the record, its crc
            for value in event.summary.value:
                scalars.setdefault(value.tag, []).append((event.step, value.simple_value))
    return scalars


def _run(logger: checkpoint.MetricLogger, steps: int) -> None:
    for step in range(1, steps + 1):
        logger.push(step, {"loss": jnp.float32(1.0 / step), "grad_norm": jnp.float32(step)})
    logger.close()


def test_metric_logger_writes_jsonl_and_tensorboard(tmp_path):
    pytest.importorskip("tensorboardX")
    logger = checkpoint.MetricLogger(5, 2, jsonl_path=str(tmp_path / "metrics.jsonl"),
                                     tensorboard_dir=str(tmp_path / "tensorboard"), stream=io.StringIO())
    _run(logger, 5)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [row["step"] for row in rows] == [2, 4, 5]
    scalars = _tensorboard_scalars(str(tmp_path / "tensorboard"))
    assert sorted(scalars) == ["grad_norm", "loss"]
    assert scalars["loss"] == [(row["step"], pytest.approx(row["loss"])) for row in rows]
    assert [value for _, value in scalars["grad_norm"]] == [2.0, 4.0, 5.0]


def test_metric_logger_without_tensorboardx_warns_once_and_keeps_jsonl(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "tensorboardX", None)  # import fails as if not installed
    monkeypatch.setattr(checkpoint, "_TENSORBOARD_WARNED", False)
    with pytest.warns(UserWarning, match="no TensorBoard event files") as record:
        for run in range(2):
            logger = checkpoint.MetricLogger(3, 1, jsonl_path=str(tmp_path / f"m{run}.jsonl"),
                                             tensorboard_dir=str(tmp_path / f"tb{run}"), stream=io.StringIO())
            _run(logger, 3)
    assert len([w for w in record if "TensorBoard" in str(w.message)]) == 1
    assert len((tmp_path / "m1.jsonl").read_text().splitlines()) == 3
    assert not glob.glob(str(tmp_path / "tb*" / "events*"))


def test_prefetched_batches_arrive_in_step_order_and_errors_at_their_step():
    import threading

    import pytest

    from sword_jax.prefetch import prefetched

    threads = set()

    def make(step):
        threads.add(threading.current_thread().name)
        if step == 7:
            raise RuntimeError("bad episode at step 7")
        return step * 10

    got = []
    with pytest.raises(RuntimeError, match="step 7"):
        for batch in prefetched(make, range(3, 12), depth=3):
            got.append(batch)
    assert got == [30, 40, 50, 60]  # everything before the failing step, in order
    assert all(name.startswith("prefetch") for name in threads)
    assert list(prefetched(lambda s: -s, range(1, 6), depth=1)) == [-1, -2, -3, -4, -5]
    with pytest.raises(ValueError, match="depth"):
        next(prefetched(make, range(3), depth=0))
