"""Checkpoints and metric logging shared by the trainers.

:class:`Checkpointer` is the one orbax reader and writer of checkpoints: an orbax ``CheckpointManager``
with two items per step, ``state`` (the train-state pytree, latent cache included, restored straight
into its sharded layout) and ``meta`` (JSON: data-iterator position, RNG root key data, config).
A checkpoint that cannot be read, or does not fit what it is read into, raises :class:`CheckpointError`;
:func:`read_arrays` reads one back as flat host arrays, to compare runs. :class:`WriterLock` is a trainer's claim
on the directory it writes, so that a second process started on the same run is refused instead of writing
beside the first. :class:`MetricLogger` reads device metrics one log step late, so the host never waits on the
step it just dispatched, and writes them to ``metrics.jsonl`` and TensorBoard event files.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import socket
import sys
import time
import warnings
from collections.abc import Iterator
from typing import Any, TextIO

import jax
import numpy as np
import orbax.checkpoint as ocp


def abstract_like(tree: Any, shardings: Any | None = None) -> Any:
    """``ShapeDtypeStruct`` tree of ``tree`` carrying ``shardings`` (default: each array's own).

    A host leaf (a NumPy array or a Python scalar, e.g. policy weights read from ``.npz``) has no
    sharding of its own; it is restored onto the first local device, where its first use would put it.
    """
    if shardings is None:
        host = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        return jax.tree.map(lambda a: jax.ShapeDtypeStruct(np.shape(a), _dtype(a), sharding=getattr(a, "sharding", host)),
                            tree)
    return jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(np.shape(a), _dtype(a), sharding=s), tree, shardings)


def _dtype(leaf: Any) -> np.dtype:
    """A leaf's dtype; a Python scalar's as JAX would store it (float32, int32 without x64)."""
    return leaf.dtype if hasattr(leaf, "dtype") else jax.numpy.asarray(leaf).dtype


class CheckpointError(ValueError):
    """A checkpoint or weight file that is missing, unreadable, or does not match the model it is loaded into."""


class CheckpointInUse(CheckpointError):
    """A checkpoint directory that another live process is writing (:class:`WriterLock`)."""


class WriterLock:
    """The one writer's claim on a checkpoint directory: an exclusive, non-blocking ``flock`` on
    ``<directory>/.writer.lock`` (orbax ignores the file), holding the holder's pid, host and start time.

    A second claim while the first is held, from another process or another open in this one, raises
    :class:`CheckpointInUse` naming the holder, before anything is read or written. The kernel drops the claim
    when its process ends however it ends, so a killed run leaves no stale lock and the same command resumes.
    ``flock`` claims hold between processes of one host and on local file systems; a directory shared by
    several hosts is claimed by the one process that writes it (the trainers claim on process 0). On a file system
    without ``flock`` (some network and FUSE mounts) nothing is claimed and a warning says so.
    """

    FILE = ".writer.lock"

    def __init__(self, directory: str, owner: str):
        os.makedirs(directory, exist_ok=True)
        self.directory = os.path.abspath(directory)
        self._fd: int | None = os.open(os.path.join(self.directory, self.FILE), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(self._fd, 512, 0).decode(errors="replace").strip() or "a process that wrote no details"
            os.close(self._fd)
            self._fd = None
            raise CheckpointInUse(f"{owner}: {self.directory} is being written by another live process ({holder}); "
                                  f"wait for it or stop it (the same command then resumes from its last "
                                  f"checkpoint), or give this run another work dir") from None
        except OSError as error:  # a file system without flock (some network and FUSE mounts): no claim, a warning
            os.close(self._fd)
            self._fd = None
            warnings.warn(f"{owner}: {self.directory} cannot be claimed ({error}); a second process started on this "
                          f"run would not be refused", stacklevel=2)
            return
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, f"pid {os.getpid()} on {socket.gethostname()} since "
                            f"{time.strftime('%Y-%m-%d %H:%M:%S')}".encode(), 0)

    def release(self) -> None:
        """Gives the claim up (the file stays: removing it could race a process claiming it)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> "WriterLock":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.release()


class Checkpointer:
    """Saves and restores ``(state, meta)`` under ``directory`` (keeps the newest ``max_to_keep``).

    With ``read_only=True`` nothing is created, written or deleted, and the saved state can also be
    read in part (:meth:`restore_subtree`) or by its metadata alone (:meth:`state_metadata`): the
    reader behind :mod:`sword_jax.load`. Usable as a context manager (closes on exit).
    """

    def __init__(self, directory: str, *, max_to_keep: int | None = 2, read_only: bool = False):
        self.directory = os.path.abspath(directory)
        self.read_only = read_only
        if read_only:
            # Never saves (orbax's own read_only mode only adds a log warning); explicit handlers let
            # the state be read by metadata or in part.
            options = ocp.CheckpointManagerOptions(create=False, max_to_keep=None)
            handlers = {"state": ocp.PyTreeCheckpointHandler(), "meta": ocp.JsonCheckpointHandler()}
            self.manager = ocp.CheckpointManager(self.directory, options=options, item_handlers=handlers)
        else:
            options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
            self.manager = ocp.CheckpointManager(self.directory, options=options, item_names=("state", "meta"))

    def __enter__(self) -> "Checkpointer":
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def latest_step(self) -> int | None:
        return self.manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self.manager.all_steps())

    def save(self, step: int, state: Any, meta: dict[str, Any], *, wait: bool = True) -> None:
        """Writes checkpoint ``step``; ``meta`` must be JSON-serialisable."""
        if self.read_only:
            raise ValueError(f"checkpoint: {self.directory} was opened read-only")
        self.manager.save(step, args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)))
        if wait:
            self.manager.wait_until_finished()

    def restore(self, abstract_state: Any, step: int | None = None) -> tuple[Any, dict[str, Any]]:
        """Restores ``(state, meta)`` into the shapes/dtypes/shardings of ``abstract_state``.

        Raises:
          FileNotFoundError: no checkpoint in the directory.
          CheckpointError: the checkpoint does not match ``abstract_state`` (e.g. another config).
        """
        step = self.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"checkpoint: nothing to restore in {self.directory}")
        try:
            restored = self.manager.restore(step, args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract_state), meta=ocp.args.JsonRestore()))
        except (ValueError, KeyError, TypeError) as err:
            raise CheckpointError(f"checkpoint: step {step} in {self.directory} does not match this run's state "
                                  f"(different config?): {err}") from err
        return restored["state"], restored["meta"]

    def read_meta(self, step: int) -> dict[str, Any]:
        """The JSON metadata saved with checkpoint ``step`` (config, data position, kind ...)."""
        try:
            return self.manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
        except Exception as err:  # noqa: BLE001 - any failure to read a file is reported with its path
            raise CheckpointError(f"cannot read the metadata of step {step} in {self.directory}: "
                                  f"{type(err).__name__}: {err}") from err

    def state_metadata(self, step: int) -> Any:
        """The saved state's tree of array metadata (shapes, dtypes; None entries kept), read without
        reading any array."""
        try:
            with self._reading() as reader:
                node = reader.manager.item_metadata(step)["state"]
        except Exception as err:  # noqa: BLE001
            raise CheckpointError(f"cannot read checkpoint step {step} in {self.directory}: "
                                  f"{type(err).__name__}: {err}") from err
        return getattr(node, "tree", node)  # orbax's tree-metadata wrapper -> nested dict

    def restore_subtree(self, step: int, abstract: dict[str, Any]) -> dict[str, Any]:
        """Restores the entries of ``abstract`` (``ShapeDtypeStruct`` leaves with shardings) from ``step``.

        Entries of the saved state that ``abstract`` does not name are not read.
        """
        restore_args = ocp.checkpoint_utils.construct_restore_args(abstract)
        try:
            with self._reading() as reader:
                restored = reader.manager.restore(step, args=ocp.args.Composite(
                    state=ocp.args.PyTreeRestore(item=abstract, restore_args=restore_args, partial_restore=True)))
        except Exception as err:  # noqa: BLE001
            raise CheckpointError(f"cannot restore step {step} from {self.directory} (another config, or a damaged "
                                  f"checkpoint?): {type(err).__name__}: {err}") from err
        return restored["state"]

    def array_shape(self, name: str, step: int | None = None) -> tuple[int, ...]:
        """Shape of the saved state array ``name`` (dotted path, e.g. ``cache.latents``), from metadata only."""
        step = self.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"checkpoint: nothing saved in {self.directory}")
        node = self.state_metadata(step)
        for part in name.split("."):
            if part not in node:
                raise KeyError(f"checkpoint: {name!r} is not in the state saved at step {step} in {self.directory}")
            node = node[part]
        return tuple(node.shape)

    @contextlib.contextmanager
    def _reading(self) -> Iterator["Checkpointer"]:
        # Reading by metadata or in part needs the explicit handlers of a read-only manager.
        if self.read_only:
            yield self
            return
        self.manager.wait_until_finished()
        reader = Checkpointer(self.directory, read_only=True)
        try:
            yield reader
        finally:
            reader.close()

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def _abstract_from_metadata(node: Any, sharding: jax.sharding.Sharding) -> Any:
    """The saved state's metadata tree (dicts, lists, array metadata, None) as ``ShapeDtypeStruct`` leaves placed
    by ``sharding``; walked by hand, since whether orbax's metadata leaves are pytrees differs between versions."""
    if isinstance(node, dict):
        return {name: _abstract_from_metadata(value, sharding) for name, value in node.items()}
    if isinstance(node, (list, tuple)):
        return type(node)(_abstract_from_metadata(value, sharding) for value in node)
    if node is None:
        return None
    return jax.ShapeDtypeStruct(tuple(node.shape), node.dtype, sharding=sharding)


def read_arrays(directory: str, step: int | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Checkpoint ``step`` (default the newest) in ``directory`` as flat host arrays and its JSON meta.

    The state is restored onto this process's first device, whatever device count or process count
    wrote it, so two runs' checkpoints can be compared bit for bit. Nothing is written.

    Returns:
      ``({"/path/to/leaf": array}, meta)``; None entries of the state are left out.

    Raises:
      CheckpointError: no checkpoint, or one that cannot be read.
    """
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    with Checkpointer(directory, read_only=True) as reader:
        step = reader.latest_step() if step is None else step
        if step is None:
            raise CheckpointError(f"checkpoint: nothing to read in {reader.directory}")
        target = _abstract_from_metadata(reader.state_metadata(step), device)
        state, meta = reader.restore_subtree(step, target), reader.read_meta(step)
    flat: dict[str, np.ndarray] = {}

    def visit(prefix: str, tree: Any) -> None:
        if isinstance(tree, dict):
            for name, value in tree.items():
                visit(f"{prefix}/{name}", value)
        elif isinstance(tree, (list, tuple)):
            for i, value in enumerate(tree):
                visit(f"{prefix}/{i}", value)
        elif tree is not None:
            flat[prefix] = np.asarray(tree)

    visit("", state)
    return flat, meta


def _format(value: float) -> str:
    return f"{value:.4g}" if math.isfinite(value) else str(value)


_TENSORBOARD_WARNED = False


def _tensorboard_writer(logdir: str) -> Any | None:
    """A ``tensorboardX.SummaryWriter`` for ``logdir``, or None (with one warning per process)."""
    global _TENSORBOARD_WARNED
    try:
        from tensorboardX import SummaryWriter

        return SummaryWriter(logdir)
    except Exception as err:  # noqa: BLE001 - TensorBoard is optional: metrics.jsonl still has everything
        if not _TENSORBOARD_WARNED:
            _TENSORBOARD_WARNED = True
            warnings.warn(f"no TensorBoard event files ({type(err).__name__}: {err}); metrics.jsonl is still "
                          "written (pip install tensorboardX)", stacklevel=3)
        return None


class MetricLogger:
    """Logs scalar metrics one log step late, with progress and ETA (process 0 prints/writes).

    Call :meth:`push` after dispatching each step with that step's (device) metrics; on log steps
    they are kept, and fetched when the next step has been dispatched. :meth:`flush` fetches what
    is pending (end of run, before checkpoints). Rows go to ``jsonl_path`` and, as scalars named
    like the metrics, to TensorBoard event files in ``tensorboard_dir`` (skipped with a warning
    when tensorboardX is missing).
    """

    def __init__(self, total_steps: int, log_every: int, *, jsonl_path: str | None = None,
                 tensorboard_dir: str | None = None, stream: TextIO | None = None, first_step: int = 0):
        self.total_steps, self.log_every = total_steps, log_every
        self.jsonl_path = jsonl_path if jax.process_index() == 0 else None
        self.tensorboard_dir = tensorboard_dir if jax.process_index() == 0 else None
        self._tensorboard: Any | None = None  # made at the first row, so a logger that logs nothing writes nothing
        self.stream = stream
        self.pending: tuple[int, dict[str, Any]] | None = None
        self.start_time = time.perf_counter()
        self.start_step = first_step
        self.history: list[dict[str, float]] = []

    def push(self, step: int, metrics: dict[str, Any]) -> dict[str, float] | None:
        """Records metrics of ``step`` (1-based count of steps done); returns the row logged now, if any."""
        row = self.flush()
        if step % self.log_every == 0 or step == self.total_steps:
            self.pending = (step, metrics)
        return row

    def flush(self) -> dict[str, float] | None:
        if self.pending is None:
            return None
        step, metrics = self.pending
        self.pending = None
        return self.write(step, {name: float(np.asarray(v)) for name, v in jax.device_get(metrics).items()})

    def write(self, step: int, values: dict[str, float], *, eta_s: float | None = None) -> dict[str, float]:
        """Logs host ``values`` of ``step`` now and returns the row: what :meth:`flush` does, for a loop that
        reads its metrics itself (:func:`sword_jax.train_loop.run_steps`, which also knows the ETA)."""
        elapsed = time.perf_counter() - self.start_time
        done = max(step - self.start_step, 1)
        eta = elapsed / done * max(self.total_steps - step, 0) if eta_s is None else eta_s
        row = {"step": step, **values, "elapsed_s": elapsed, "eta_s": eta}
        self.history.append(row)
        if jax.process_index() == 0:
            text = " ".join(f"{k}={_format(v)}" for k, v in values.items())
            print(f"[{step}/{self.total_steps}] {text} | {elapsed:.0f}s elapsed, ETA {eta:.0f}s",
                  file=self.stream or sys.stdout, flush=True)
            if self.jsonl_path:
                with open(self.jsonl_path, "a") as out:
                    out.write(json.dumps(row) + "\n")
            if self.tensorboard_dir:
                self._write_tensorboard(step, values)
        return row

    def _write_tensorboard(self, step: int, values: dict[str, float]) -> None:
        if self._tensorboard is None:
            self._tensorboard = _tensorboard_writer(self.tensorboard_dir)
            if self._tensorboard is None:
                self.tensorboard_dir = None
                return
        for name, value in values.items():
            self._tensorboard.add_scalar(name, value, step)
        self._tensorboard.flush()  # readable while the run goes on

    def close(self) -> None:
        """Fetches what is pending and closes the event file."""
        self.flush()
        if self._tensorboard is not None:
            self._tensorboard.close()
            self._tensorboard = None
