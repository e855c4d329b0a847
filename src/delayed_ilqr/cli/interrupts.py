"""Ctrl-C (SIGINT) and SIGTERM while a command runs: a clean stop with the shell's exit code.

While a command runs, both signals raise `Interrupted` (a ``KeyboardInterrupt``) in the
main thread, so that the command unwinds as for any error: the ``--out`` staging folder is removed
and ``--out`` stays as it was (a sweep's store keeps the cells it finished). The signal is also
recorded, so that an interrupt whose exception a library swallowed still stops the command before
it writes its results (`check`); one that lands where Python drops exceptions (a
garbage-collector callback, which JAX registers, a weakref callback or a ``__del__``: Python
reports it to ``sys.unraisablehook``) is raised again just after, in the main thread. The process then exits with 128 + the signal's number (130
for Ctrl-C, 143 for SIGTERM), as a shell reports a process killed by it.

A Ctrl-C before these handlers exist, while the console script imports the library (JAX with it,
seconds), is caught by the console script's own entry (``delayed_ilqr_entry``, standard library
only), which exits 130 the same way.

The real process exits with ``os._exit`` after flushing its output (`exit_now`): an
interrupt can come while XLA still computes on its own threads (asynchronous dispatch,
compilation), and the interpreter's teardown destroying JAX's objects under them can end in a
segmentation fault. Nothing is left to tear down: the outputs are written or removed already.
"""
from __future__ import annotations

import _thread
import contextlib
import os
import signal
import sys
import threading
from typing import Iterator, Optional

__all__ = ["Interrupted", "SIGNALS", "exit_code", "handled", "check", "deferred", "exit_now"]

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A command stopped by a signal; ``signum`` is the signal."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(signal.Signals(signum).name)


class _State:
    received: Optional[int] = None      # the signal that came while a command ran
    deferring: bool = False             # in a block that must not be cut (the final renames)
    written: Optional[str] = None       # what the command had written when it was stopped
    installed: bool = False             # this module's handlers are the process's


def exit_code(signum: int) -> int:
    """128 + the signal's number: 130 for SIGINT, 143 for SIGTERM."""
    return 128 + int(signum)


def _handler(signum, frame):
    _State.received = signum
    if not _State.deferring:
        raise Interrupted(signum)


def _unraisable(previous):
    """A ``sys.unraisablehook`` that raises an `Interrupted` that Python dropped (raised in
    a garbage-collector or weakref callback or a ``__del__``) again just after, in the main thread."""
    def hook(unraisable):
        if isinstance(unraisable.exc_value, Interrupted):
            threading.Timer(0.01, _raise_again, (unraisable.exc_value.signum,)).start()
        else:
            previous(unraisable)
    return hook


def _raise_again(signum: int) -> None:
    if _State.installed:               # the command still runs (else check() has stopped it)
        _thread.interrupt_main(signum)


@contextlib.contextmanager
def handled() -> Iterator[None]:
    """SIGINT and SIGTERM raise `Interrupted` in the block (the main thread only; the
    previous handlers are restored after it, so that running a command from Python, e.g. click's
    test runner, leaves the process's handlers as they were)."""
    _State.received, _State.deferring, _State.written = None, False, None
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous, hook = {s: signal.signal(s, _handler) for s in SIGNALS}, sys.unraisablehook
    sys.unraisablehook, _State.installed = _unraisable(hook), True
    try:
        yield
    finally:
        sys.unraisablehook, _State.installed = hook, False
        for s, h in previous.items():
            signal.signal(s, h)


def check() -> None:
    """Raises `Interrupted` when a signal came (also one whose exception was lost)."""
    if _State.received is not None:
        raise Interrupted(_State.received)


@contextlib.contextmanager
def deferred(written: str) -> Iterator[None]:
    """A block that a signal must not cut (renaming the staging folder to ``--out``): a signal
    that comes in it is raised at its end, and the message says that ``written`` was written."""
    check()
    _State.deferring = True
    try:
        yield
    finally:
        _State.deferring = False
    if _State.received is not None:
        _State.written = written
        check()


def message(signum: int, command: Optional[str]) -> str:
    """What an interrupted command says on stderr."""
    name = signal.Signals(signum).name
    if _State.written is not None:
        return f"interrupted by {name} after the results were written to {_State.written}"
    if command == "sweep":
        return (f"interrupted by {name}: stopped; the store keeps the cells finished so far, and the same command "
                "resumes it")
    return f"interrupted by {name}: stopped; nothing was written (--out is as it was)"


def exit_now(code: int) -> None:
    """Ends the process at once with ``code``, after flushing stdout and stderr (see the module
    docstring: no interpreter teardown under XLA's running threads)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)
