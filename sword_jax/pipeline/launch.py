"""One process per GPU on one host: the ``jax.distributed`` processes of one job, started, watched and
stopped together.

:func:`launch` starts ``processes`` copies of a command, rank ``i`` with ``JAX_COORDINATOR_ADDRESS``
(``127.0.0.1`` and a free port), ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID=i`` (what
``train.distributed.initialize`` reads with ``--mesh.distributed=true``) and one GPU,
``CUDA_VISIBLE_DEVICES`` = the ``i``-th of ``gpus``; with ``cpu_devices=K`` instead each rank runs on
``K`` CPU devices (``JAX_PLATFORMS=cpu``, gloo collectives), which is how the tests run it. NVLink
multicast stays off in every rank (:data:`NO_MULTICAST`). Each output line of a rank comes out
prefixed ``[rank i]``, and is also kept in ``<log_dir>/rank<i>.log`` when a log dir is given.

Faults: when a rank exits with a non-zero status or is killed, the others get SIGTERM (their whole
process group) and, those still running after ``grace_s`` seconds, SIGKILL. The call returns at most
``grace_s + STOP_MARGIN_S`` seconds after the first rank failed, with that rank named and a non-zero
status; nothing waits on a collective the dead rank will never join. Processes joined by
``jax.distributed`` take SIGTERM as a preemption notice and keep running, so they end by the SIGKILL;
checkpoints are written atomically, so the rerun resumes from the last complete one. Without the
launcher, a rank left in a collective with a dead peer waits for JAX's heartbeat timeout (about 100 s on
CPU) or longer.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from typing import IO

# NVLink multicast stays off in every process the project starts on GPUs (a program using it can take a
# shared host's GPUs down).
NO_MULTICAST = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}

# XLA's deterministic ops on GPUs: no atomic adds whose order varies, so a run (and an evaluation repeated on the same
# policy) gives the same numbers every time
DETERMINISTIC_OPS = "--xla_gpu_deterministic_ops=true"


def with_flag(flags: str, flag: str) -> str:
    """``flags`` (an ``XLA_FLAGS`` value) with ``flag`` added once."""
    words = flags.split()
    return " ".join(words if flag in words else [*words, flag])


DEFAULT_GRACE_S = 10.0  # SIGTERM -> SIGKILL
POLL_S = 0.1  # how often the ranks' exit statuses are read
STOP_MARGIN_S = 2.0  # beyond the grace: the poll, the SIGKILL and reaping the ranks
_DEVICE_COUNT_FLAG = "--xla_force_host_platform_device_count"


@dataclasses.dataclass(frozen=True)
class LaunchResult:
    """How a launched job ended.

    Attributes:
      returncode: 0 when every rank exited 0; else the first failed rank's status (``128 + signal`` for a
        rank killed by a signal, the shell's convention), or ``128 + signal`` when the launcher itself was
        stopped by SIGINT / SIGTERM.
      failed_rank: the rank that failed first, ``None`` if none did.
      rank_returncodes: each rank's status as ``subprocess`` reports it (negative: killed by that signal).
      stop_seconds: from the first failure seen to the last rank reaped; ``None`` if nothing failed.
      stop_signal: the signal (SIGINT / SIGTERM) that stopped the launcher itself, ``None`` if none did. The
        launcher's own handlers are gone when it returns, so a caller that runs several jobs re-raises it
        (``signal.raise_signal``) to stop as it was told instead of going on with the next job.
    """

    returncode: int
    failed_rank: int | None
    rank_returncodes: tuple[int, ...]
    stop_seconds: float | None
    stop_signal: int | None = None


def join(environ: Mapping[str, str] = os.environ) -> None:
    """Joins the ``jax.distributed`` job this process is a rank of: the one :func:`launch` started (its
    ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``; the coordinator JAX reads from ``JAX_COORDINATOR_ADDRESS``), or
    one JAX detects (SLURM, Open MPI, Cloud TPU). On CPU (``JAX_PLATFORMS=cpu``) the collectives go through gloo.
    The library never calls it: a process joins before it builds a mesh (``train.distributed.initialize``).

    Raises:
      ValueError / RuntimeError: JAX's, when no job can be joined.
    """
    import jax

    kwargs = {}
    if environ.get("JAX_NUM_PROCESSES"):
        kwargs["num_processes"] = int(environ["JAX_NUM_PROCESSES"])
    if environ.get("JAX_PROCESS_ID"):
        kwargs["process_id"] = int(environ["JAX_PROCESS_ID"])
    if environ.get("JAX_PLATFORMS", "").startswith("cpu"):
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(**kwargs)


def free_port() -> int:
    """A TCP port free on the loopback now (the coordinator binds it a moment later)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def parse_gpus(text: str) -> list[str]:
    """``"0,1,2,3"`` -> ``["0", "1", "2", "3"]``: ``CUDA_VISIBLE_DEVICES`` values (indices or UUIDs), each once.

    Raises:
      argparse.ArgumentTypeError: an empty list or entry, or a GPU named twice.
    """
    import argparse

    gpus = [g.strip() for g in text.split(",")]
    if not text.strip() or "" in gpus or len(set(gpus)) < len(gpus):
        raise argparse.ArgumentTypeError(f"--gpus takes comma-separated GPUs (CUDA_VISIBLE_DEVICES values), each "
                                         f"once, got {text!r}")
    return gpus


def default_gpus(processes: int, environ: Mapping[str, str] = os.environ) -> list[str]:
    """The GPUs ranks ``0 .. processes-1`` take: the first ``processes`` of this process's
    ``CUDA_VISIBLE_DEVICES`` if it is set, else ``0 .. processes-1``."""
    visible = [g for g in environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if g.strip()]
    if "CUDA_VISIBLE_DEVICES" in environ:
        if len(visible) < processes:
            raise ValueError(f"launch: {processes} processes but CUDA_VISIBLE_DEVICES="
                             f"{environ['CUDA_VISIBLE_DEVICES']!r} names {len(visible)} GPUs")
        return visible[:processes]
    return [str(i) for i in range(processes)]


def rank_env(rank: int, processes: int, coordinator: str, *, gpu: str | None = None, cpu_devices: int | None = None,
             environ: Mapping[str, str] = os.environ) -> dict[str, str]:
    """The environment of rank ``rank``: ``environ`` plus the ``jax.distributed`` variables, one GPU
    (``gpu``) or ``cpu_devices`` CPU devices, NVLink multicast off and unbuffered Python output."""
    env = dict(environ, JAX_COORDINATOR_ADDRESS=coordinator, JAX_NUM_PROCESSES=str(processes),
               JAX_PROCESS_ID=str(rank), PYTHONUNBUFFERED="1", **NO_MULTICAST)
    return with_devices(env, gpus=gpu, cpu_devices=cpu_devices)


def with_devices(env: dict[str, str], *, gpus: str | None = None, cpu_devices: int | None = None) -> dict[str, str]:
    """``env`` set to run a process on ``cpu_devices`` CPU devices (``JAX_PLATFORMS=cpu`` and the host device
    count in ``XLA_FLAGS``, replacing any count there) or else on ``gpus`` (``CUDA_VISIBLE_DEVICES``)."""
    if cpu_devices is not None:
        flags = [f for f in env.get("XLA_FLAGS", "").split() if not f.startswith(_DEVICE_COUNT_FLAG)]
        env.update(JAX_PLATFORMS="cpu", XLA_FLAGS=" ".join([*flags, f"{_DEVICE_COUNT_FLAG}={cpu_devices}"]))
    elif gpus is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpus
    return env


def _signal_status(code: int) -> int:
    """``subprocess``'s status (negative for a signal) as a shell exit status (``128 + signal``)."""
    return 128 - code if code < 0 else code


def _describe(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


def _pump(rank: int, stream: IO[bytes], out: IO[str], lock: threading.Lock, log_path: str | None) -> None:
    """Copies a rank's output to ``out`` line by line, prefixed with its rank, and to its log file."""
    log = open(log_path, "ab") if log_path else None
    try:
        for raw in iter(stream.readline, b""):
            if log is not None:
                log.write(raw)
                log.flush()
            line = raw.decode("utf-8", errors="replace").rstrip("\n")
            with lock:
                out.write(f"[rank {rank}] {line}\n")
                out.flush()
    finally:
        if log is not None:
            log.close()
        stream.close()


def _signal_group(proc: subprocess.Popen, signum: int) -> None:
    """``signum`` to the process group of a rank that has not been reaped (its own session)."""
    if proc.returncode is None:
        try:
            os.killpg(proc.pid, signum)
        except ProcessLookupError:
            pass


def launch(command: Sequence[str], processes: int, *, gpus: Sequence[str] | None = None,
           cpu_devices: int | None = None, log_dir: str | None = None, grace_s: float = DEFAULT_GRACE_S,
           port: int | None = None, out: IO[str] | None = None,
           environ: Mapping[str, str] | None = None) -> LaunchResult:
    """Runs ``command`` as ``processes`` ranks of one ``jax.distributed`` job and waits for them.

    Args:
      command: the argv every rank runs (e.g. ``python -m train.train_world_model ... --mesh.distributed=true``).
      processes: the number of ranks (one per GPU).
      gpus: the GPU of each rank (``CUDA_VISIBLE_DEVICES`` values); default :func:`default_gpus`.
      cpu_devices: run on CPU instead, with this many devices per rank.
      log_dir: also keep each rank's output in ``<log_dir>/rank<i>.log`` (appended).
      grace_s: seconds between SIGTERM and SIGKILL when the job is stopped.
      port: the coordinator's port on 127.0.0.1 (default: a free one).
      out: where the prefixed output and the launcher's own lines go (default ``sys.stdout``).
      environ: the ranks' base environment (default ``os.environ``).

    Returns:
      The :class:`LaunchResult`. SIGINT / SIGTERM to the launcher (when called from the main thread) stop
      the ranks the same way.
    """
    if processes < 1:
        raise ValueError(f"launch: processes must be >= 1, got {processes}")
    if not command:
        raise ValueError("launch: no command to run")
    out = sys.stdout if out is None else out
    environ = os.environ if environ is None else environ
    if cpu_devices is None:
        gpus = list(default_gpus(processes, environ) if gpus is None else gpus)
        if len(gpus) < processes:
            raise ValueError(f"launch: {processes} processes but {len(gpus)} GPUs given ({','.join(gpus)})")
    elif cpu_devices < 1:
        raise ValueError(f"launch: cpu_devices must be >= 1, got {cpu_devices}")
    coordinator = f"127.0.0.1:{port or free_port()}"
    if log_dir:
        os.makedirs(log_dir, exist_ok=True)
    lock = threading.Lock()

    def say(line: str) -> None:
        with lock:
            out.write(f"[launch] {line}\n")
            out.flush()

    where = f"CPU, {cpu_devices} devices each" if cpu_devices is not None else f"GPUs {','.join(gpus[:processes])}"
    say(f"{processes} processes ({where}), coordinator {coordinator}: {' '.join(command)}")
    stop_signal: list[int] = []
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, lambda s, _frame: stop_signal.append(s))
    procs: list[subprocess.Popen] = []
    pumps: list[threading.Thread] = []
    try:
        for rank in range(processes):
            env = rank_env(rank, processes, coordinator, gpu=None if cpu_devices is not None else gpus[rank],
                           cpu_devices=cpu_devices, environ=environ)
            # each rank in its own session: stopping it reaches whatever it started
            proc = subprocess.Popen(list(command), env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, start_new_session=True)
            procs.append(proc)
            log_path = os.path.join(log_dir, f"rank{rank}.log") if log_dir else None
            pump = threading.Thread(target=_pump, args=(rank, proc.stdout, out, lock, log_path), daemon=True)
            pump.start()
            pumps.append(pump)
            say(f"rank {rank}: pid {proc.pid}" + (f", log {log_path}" if log_path else ""))
        failed_rank = None
        while not stop_signal:
            codes = [p.poll() for p in procs]
            failed = [rank for rank, code in enumerate(codes) if code not in (None, 0)]
            if failed:
                failed_rank = failed[0]
                break
            if all(code == 0 for code in codes):
                break
            time.sleep(POLL_S)
        stop_seconds = None
        if failed_rank is not None or stop_signal:
            stop_seconds = _stop(procs, grace_s, say, failed_rank, stop_signal)
    finally:
        for proc in procs:  # an exception above leaves no rank behind
            if proc.poll() is None:
                _signal_group(proc, signal.SIGKILL)
                proc.wait()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    for pump in pumps:
        pump.join(timeout=1.0)  # output of a rank's leftover children may hold a pipe open
    codes = tuple(p.returncode for p in procs)
    if stop_signal:
        returncode = 128 + stop_signal[0]
    elif failed_rank is not None:
        returncode = _signal_status(codes[failed_rank]) or 1
    else:
        returncode = 0
    if returncode:
        cause = (f"stopped by {signal.Signals(stop_signal[0]).name}" if stop_signal else
                 f"rank {failed_rank} failed first ({_describe(codes[failed_rank])})")
        say(f"job FAILED: {cause}; ranks ended {stop_seconds:.1f} s later "
            f"({', '.join(f'rank {r}: {_describe(c)}' for r, c in enumerate(codes))}); exit status {returncode}")
    return LaunchResult(returncode, failed_rank, codes, stop_seconds, stop_signal[0] if stop_signal else None)


def _stop(procs: list[subprocess.Popen], grace_s: float, say, failed_rank: int | None,
          stop_signal: list[int]) -> float:
    """SIGTERM to the ranks still running, SIGKILL to those left after ``grace_s``; returns the seconds taken."""
    start = time.monotonic()
    running = [rank for rank, p in enumerate(procs) if p.poll() is None]
    cause = (f"rank {failed_rank} failed ({_describe(procs[failed_rank].returncode)})" if failed_rank is not None
             else f"{signal.Signals(stop_signal[0]).name} received")
    say(f"{cause}: SIGTERM to rank(s) {running or 'none'}, SIGKILL after {grace_s:g} s")
    for rank in running:
        _signal_group(procs[rank], signal.SIGTERM)
    deadline = start + grace_s
    while time.monotonic() < deadline and any(p.poll() is None for p in procs):
        time.sleep(POLL_S)
    left = [rank for rank, p in enumerate(procs) if p.poll() is None]
    if left:
        say(f"SIGKILL to rank(s) {left}")
        for rank in left:
            _signal_group(procs[rank], signal.SIGKILL)
        for rank in left:
            procs[rank].wait()
    return time.monotonic() - start
