"""The ``delayed-ilqr`` command line: parses arguments, runs the studies of
`delayed_ilqr.experiments`, prints their tables and hands results to the report writer
(`delayed_ilqr.experiments.report`) and the figures ([`delayed_ilqr.plot`][delayed_ilqr.plot]).

Subcommands: ``models``, ``solve``, ``simulate``, ``compare``, ``demo``, ``center-out``, ``perturb``,
``sweep``, ``fit``, ``mpc`` and the gallery's ``kick``, ``target-jump``, ``fitts`` and ``minimal-intervention``
(``delayed-ilqr --help``). Exit codes: 0 success; 1 when some solve did not converge (results are
still written); 2 for bad arguments (unknown model, a delay that is not a whole number of steps or
not below the horizon, a non-positive trial count, more trials than memory holds, an ``--out``
that cannot be created or is not empty without ``--overwrite``); 3 for any other error, reported
in one line (``--debug`` shows the traceback); 130 (Ctrl-C) or 143 (SIGTERM) when interrupted,
with nothing written (`interrupts`).

MODEL is a built-in model (``delayed-ilqr models``) or your own factory as
``package.module:factory`` (imported with the current folder on the path), called like the
built-ins as ``factory(delay=seconds, noise=bool, **params)`` and returning a
[`Problem`][delayed_ilqr.Problem]; ``--param key=value`` (repeatable, the value a Python literal)
adds keyword arguments and ``--dt`` sets the time step (``dt=``), so that delays that are not
multiples of the model's default step can be studied.

Outputs are atomic: a command writes into a hidden folder beside ``--out`` and renames it to
``--out`` at the end, with a ``manifest.json`` listing the files, the command and the version; an
interrupted run leaves ``--out`` as it was. ``--overwrite`` replaces a non-empty ``--out`` whole.

The package: `arguments` (parameter types and the checks made before computing),
`output` (the atomic ``--out`` folder), one module per group of commands (`solve`,
`studies`, `fit`, `sweep`, `gallery`, `mpc`), and here the group that runs them.
"""
from __future__ import annotations

import pathlib
import signal

import click
import jax

from .._cache import CACHE_DIR_ENV, NO_CACHE_ENV, enable_compilation_cache
from .._cpu import configure_cpu
from . import fit, gallery, interrupts, mpc, solve, studies, sweep

__all__ = ["main", "ERROR_EXIT"]

ERROR_EXIT = 3      # neither a usage error (2) nor a solve that did not converge (1)


class _Main(click.Group):
    """The command group: an error that is not click's becomes one line and exit code 3 (with
    ``--debug``, the traceback); a staging folder left by it is removed by the command. Ctrl-C
    and SIGTERM stop the command cleanly with exit code 130 or 143 (`interrupts`)."""

    def main(self, args=None, **kwargs):
        if args is not None:                  # run from Python (click's test runner): exits as click does
            return super().main(args, **kwargs)
        try:
            return super().main(args, **kwargs)
        except SystemExit as exc:             # the process's own command line
            if exc.code in tuple(interrupts.exit_code(s) for s in interrupts.SIGNALS):
                interrupts.exit_now(exc.code)
            raise

    def invoke(self, ctx):
        try:
            with interrupts.handled():
                result = super().invoke(ctx)
                interrupts.check()            # a signal whose exception a library swallowed
                return result
        except KeyboardInterrupt as exc:
            signum = getattr(exc, "signum", signal.SIGINT)
            click.echo(f"\n{interrupts.message(signum, ctx.invoked_subcommand)}", err=True)
            ctx.exit(interrupts.exit_code(signum))
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as exc:
            if ctx.params.get("debug"):
                raise
            text = str(exc).strip().splitlines()
            click.echo(f"error: {type(exc).__name__}: {text[0] if text else ''} (--debug shows the traceback)",
                       err=True)
            ctx.exit(ERROR_EXIT)


@click.group(cls=_Main, invoke_without_command=True, context_settings=dict(help_option_names=["-h", "--help"]))
@click.version_option(package_name="delayed-ilqr")
@click.option("--debug", is_flag=True, help="Show the traceback of an unexpected error.")
@click.option("--no-cache", is_flag=True, envvar=NO_CACHE_ENV, show_envvar=True,
              help="Do not use the persistent compilation cache (every process compiles its solvers again).")
@click.option("--cache-dir", type=click.Path(file_okay=False, path_type=pathlib.Path), envvar=CACHE_DIR_ENV,
              show_envvar=True, default=None,
              help="Folder of the persistent compilation cache [default: jax in the user cache folder, "
                   "e.g. ~/.cache/delayed-ilqr/jax].")
@click.pass_context
def main(ctx, debug, no_cache, cache_dir):
    """iLQG with control (input) delay: solve, Monte Carlo, delay studies and figures.

    Delays are given in seconds and must be whole numbers of the model's time step. Exit codes:
    0 success, 1 when a solve did not converge (results are still written), 2 for bad arguments
    (including an --out that cannot be created, or is not empty without --overwrite), 3 for any
    other error, 130 (Ctrl-C) or 143 (SIGTERM) when interrupted (--out is left as it was).

    Compiled solvers are kept in a persistent cache folder (--cache-dir), so that the next process
    does not compile them again; --no-cache turns that off. Without a command, prints this help.
    """
    if ctx.invoked_subcommand is None:      # a question, not an error: the help, exit code 0
        click.echo(ctx.get_help())
        ctx.exit(0)
    # the process is the command's own: float64 and XLA's small-loop flags, before any computation
    jax.config.update("jax_enable_x64", True)
    configure_cpu()
    if not no_cache:        # a second process reads the compiled solvers instead of compiling them
        try:
            enable_compilation_cache(cache_dir)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--cache-dir'") from None


for _command in (solve.models_command, solve.solve_command, solve.simulate_command, studies.compare_command,
                 studies.demo_command, studies.center_out_command, fit.fit_command, studies.perturb_command,
                 sweep.sweep_command, mpc.mpc_command, *gallery.COMMANDS):
    main.add_command(_command)
