"""Command-line plumbing shared by every entry point: one-line errors, exit codes, ``--debug``.

An entry point keeps ``main(argv)`` for callers in Python and ends with::

    if __name__ == "__main__":
        from sword_jax.cli import run

        run(main)

``run`` calls ``main`` and reports the errors a user can fix as one line on stderr, without a
traceback: a ``UsageError`` (a bad flag, an unknown config key, an invalid value;
``configs.ConfigError`` is one) exits 2; ``SystemExit("message")`` and the errors raised on
purpose for bad files or weights (``RUNTIME_ERRORS``) exit 1. ``--debug`` anywhere on the
command line prints the traceback as well. Any other exception is a bug: it propagates with
its traceback. Nothing here runs at import.

A stop can be asked for from outside: under ``run``, ``SIGUSR1`` (:data:`STOP_SIGNAL`; e.g. a launcher's
deadline, or SLURM's ``--signal=USR1@300``) sets the process's stop request (:func:`request_stop`). A training
loop (:func:`sword_jax.train_loop.run_steps`) then finishes the step in flight, checkpoints it as it would at a
checkpoint step (GRPO evaluates it) and raises :class:`StopRequested`, which ``run`` reports as one line with
exit status 75 (:data:`STOPPED_EXIT`, "try again"): the same command resumes from that checkpoint.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

USAGE_EXIT, RUNTIME_EXIT = 2, 1
STOPPED_EXIT = 75  # EX_TEMPFAIL: stopped on request after a checkpoint; the same command resumes
STOP_SIGNAL = signal.SIGUSR1
_stop = threading.Event()


class StopRequested(Exception):
    """A command stopped on request (:func:`request_stop`) after checkpointing its last step."""


def request_stop(*_: Any) -> None:
    """Asks this process's training loops to stop at the end of their step in flight (``STOP_SIGNAL``'s
    handler under :func:`run`)."""
    _stop.set()


def stop_requested() -> bool:
    """Whether a stop was asked for (:func:`request_stop`)."""
    return _stop.is_set()


def clear_stop_request() -> None:
    _stop.clear()


def ask_to_stop(procs: Any) -> int:
    """Passes a stop request on to child processes (``subprocess.Popen``s, each a command under :func:`run`): sends
    ``STOP_SIGNAL`` to each one still running (one that ends meanwhile is skipped by ``send_signal``); returns how
    many were asked."""
    asked = 0
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(STOP_SIGNAL)
            asked += 1
    return asked

# Errors raised on purpose with a message meant for the user, named rather than imported (a class
# whose module was never imported cannot have been raised, and importing them all would be slow).
RUNTIME_ERRORS = (
    "sim.dataset.DatasetError",
    "sim.render_gl.GLUnavailableError",
    "sword_jax.augment.ingest.StyledEpisodeError",
    "sword_jax.augment.style.HeldOutStyleError",
    "sword_jax.checkpoint.CheckpointError",
    "sword_jax.metrics.networks.MissingWeightsError",
    "sword_jax.train_loop.AnotherRunsCheckpoint",
    "sword_jax.train_loop.NonFiniteLoss",
)


class UsageError(ValueError):
    """A bad command line: an unknown flag or config key, or a value that is not allowed."""


class ArgumentParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors raise ``UsageError`` instead of printing usage and exiting.

    Sub-parsers made with ``add_subparsers`` share the class. Every parser documents ``--debug``
    (``run`` consumes it).
    """

    def __init__(self, *args: Any, **kwargs: Any):
        if not args and "prog" not in kwargs and _prog() != sys.argv[0]:
            kwargs["prog"] = f"python -m {_prog()}"
        super().__init__(*args, **kwargs)
        self.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                          help="on an error, print the full traceback too")

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{message} (see --help)")


def not_dotted_overrides(args: Sequence[str]) -> list[str]:
    """The arguments that are not ``--section.key=value`` config overrides (what an entry point that
    passes its overrides on to other commands refuses)."""
    return [a for a in args if not (a.startswith("--") and "." in a.split("=", 1)[0] and "=" in a)]


def _resolve(names: Sequence[str | type]) -> tuple[type, ...]:
    classes = []
    for name in names:
        if isinstance(name, type):
            classes.append(name)
            continue
        module_name, _, cls_name = name.rpartition(".")
        cls = getattr(sys.modules.get(module_name), cls_name, None)
        if isinstance(cls, type):
            classes.append(cls)
    return tuple(classes)


def _prog() -> str:
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    return spec.name if spec is not None and spec.name != "__main__" else sys.argv[0]


def run(main: Callable[[list[str]], Any], argv: Sequence[str] | None = None, *,
        runtime_errors: Sequence[str | type] = ()) -> NoReturn:
    """Runs ``main(argv)`` as a command and exits; while it runs, ``STOP_SIGNAL`` asks its training loops to
    stop (module docstring), and a :class:`StopRequested` exits ``STOPPED_EXIT``.

    Args:
      main: the entry point; an int it returns is the exit status, anything else means 0.
      argv: the arguments (default ``sys.argv[1:]``); ``--debug`` is taken out before ``main``.
      runtime_errors: exception classes (or dotted names) besides ``RUNTIME_ERRORS`` whose
        message alone is reported, with exit status 1.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [arg for arg in argv if arg != "--debug"]
    prog = _prog()

    def fail(message: str, status: int, *, prefix: bool = True) -> NoReturn:
        if debug:
            traceback.print_exc()
        print(f"{prog}: error: {message}" if prefix else message, file=sys.stderr)
        sys.exit(status)

    if threading.current_thread() is threading.main_thread():  # signal handlers live in the main thread
        signal.signal(STOP_SIGNAL, request_stop)
    try:
        result = main(argv)
    except UsageError as err:
        fail(str(err), USAGE_EXIT)
    except StopRequested as err:
        if debug:
            traceback.print_exc()
        print(f"{prog}: {err}", file=sys.stderr)
        sys.exit(STOPPED_EXIT)
    except SystemExit as err:
        if isinstance(err.code, str):  # raise SystemExit("message"): a deliberate runtime error
            fail(err.code, RUNTIME_EXIT, prefix=False)  # such messages name their entry point
        raise
    except Exception as err:
        if isinstance(err, _resolve((*RUNTIME_ERRORS, *runtime_errors))):
            fail(str(err), RUNTIME_EXIT)
        raise
    sys.exit(result if isinstance(result, int) and not isinstance(result, bool) else 0)
