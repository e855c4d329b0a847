"""The ``delayed-ilqr`` console script: imports the command line and runs it.

A package of its own, importing nothing but the standard library, because importing
``delayed_ilqr`` (JAX with it) takes seconds, and a Ctrl-C in them would otherwise end in a
Python traceback: the command line's own handling of interrupts (``delayed_ilqr.cli.interrupts``)
is not installed yet. Here it is caught: one line on stderr and the shell's exit code for Ctrl-C,
130, as for an interrupt while a command runs. The process ends without the interpreter's teardown
(``os._exit``), for the reason ``delayed_ilqr.cli.interrupts`` gives: JAX may be half imported,
with XLA's threads started.
"""
from __future__ import annotations

import contextlib
import os
import sys

__all__ = ["main"]

#: 128 + SIGINT, the exit code a shell reports for a process ended by Ctrl-C
INTERRUPTED_EXIT = 130


def main() -> None:
    """The ``delayed-ilqr`` command (``delayed_ilqr.cli.main``), with a Ctrl-C while it is being
    imported turned into exit code 130 and one line on stderr."""
    try:
        from delayed_ilqr.cli import main as command
    except KeyboardInterrupt:
        print("\ninterrupted by SIGINT while starting: nothing was run", file=sys.stderr)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(INTERRUPTED_EXIT)
    command()
