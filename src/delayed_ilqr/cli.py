"""The ``delayed-ilqr`` command line: parses arguments, runs the studies of
:mod:`delayed_ilqr.experiments`, prints their tables and hands results to the report writer
(:mod:`delayed_ilqr.experiments.report`) and the figures (:mod:`delayed_ilqr.plot`).

Subcommands: ``models``, ``solve``, ``simulate``, ``compare``, ``demo``, ``center-out``, ``perturb``,
``sweep`` and ``fit`` (``delayed-ilqr --help``). Exit codes: 0 success; 1 when some solve did not converge (results are
still written); 2 for bad arguments (unknown model, a delay that is not a whole number of steps or
not below the horizon, a non-positive trial count, more trials than memory holds, an ``--out``
that cannot be created or is not empty without ``--overwrite``); 3 for any other error, reported
in one line (``--debug`` shows the traceback).

MODEL is a built-in model (``delayed-ilqr models``) or your own factory as
``package.module:factory`` (imported with the current folder on the path), called like the
built-ins as ``factory(delay=seconds, noise=bool, **params)`` and returning a
:class:`~delayed_ilqr.Problem`; ``--param key=value`` (repeatable, the value a Python literal)
adds keyword arguments and ``--dt`` sets the time step (``dt=``), so that delays that are not
multiples of the model's default step can be studied.

Outputs are atomic: a command writes into a hidden folder beside ``--out`` and renames it to
``--out`` at the end, with a ``manifest.json`` listing the files, the command and the version; an
interrupted run leaves ``--out`` as it was. ``--overwrite`` replaces a non-empty ``--out`` whole.
"""
from __future__ import annotations

import ast
import dataclasses
import datetime
import importlib
import importlib.metadata
import json
import math
import os
import pathlib
import shutil
import sys
import time
from typing import Callable, NamedTuple, Optional

import click
import jax
import numpy as np

from . import Options, Status
from ._cache import CACHE_DIR_ENV, NO_CACHE_ENV, enable_compilation_cache
from ._cpu import configure_cpu
from .simulate import check_memory
from .experiments import center_out, delay_study, designs, engine, perturbation, report, tables
from .models import REGISTRY, arm2_muscle6
from .models.arm2 import SIGMA_U_HUMAN
from .models.metadata import default_u_init

__all__ = ["main"]

DEMO_DELAYS = (0.0, 0.05, 0.1, 0.15)
_SEED = click.IntRange(min=0, max=2 ** 63 - 1)       # what simulate accepts
_OUT_TYPE = click.Path(file_okay=False, dir_okay=True, writable=True, path_type=pathlib.Path)


class _DelayFrame(click.ParamType):
    """``auto``, ``none`` or a whole number of steps: the ``delay_frame`` of ``sweep`` and ``compare``
    ("none" stays a string here: click would take a None for a missing value and use the default)."""

    name = "auto|none|N"

    def convert(self, value, param, ctx):
        if value in ("auto", "none") or isinstance(value, int):
            return value
        if str(value).lower() in ("auto", "none"):
            return str(value).lower()
        try:
            steps = int(value)
        except ValueError:
            steps = -1
        if steps < 0:
            self.fail(f"must be auto, none or a non-negative whole number of steps; got {value!r}", param, ctx)
        return steps


class _DelayList(click.ParamType):
    """A comma-separated list of non-negative delays in seconds, e.g. ``0,0.05,0.1``."""

    name = "SECONDS[,SECONDS...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (list, tuple)):
            return list(value)
        try:
            delays = [float(v) for v in str(value).split(",") if v.strip()]
        except ValueError:
            self.fail(f"must be comma-separated numbers of seconds such as 0,0.05,0.1; got {value!r}", param, ctx)
        if not delays:
            self.fail(f"must name at least one delay; got {value!r}", param, ctx)
        bad = [d for d in delays if not math.isfinite(d) or d < 0]
        if bad:
            self.fail(f"delays must be non-negative finite numbers of seconds; got {bad[0]!r}", param, ctx)
        return delays


class _Model(NamedTuple):
    """MODEL resolved: its name as given, the factory, a one-line description."""

    name: str
    factory: Callable
    description: str


def _import_callable(value: str, what: str, param, ctx) -> Callable:
    """The callable named by ``package.module:name`` (the current folder on the path, as
    ``python -m`` finds a module); ``what`` names it in errors (e.g. "MODEL")."""
    module_name, _, attr = value.partition(":")
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise click.BadParameter(f"cannot import module {module_name!r} of {value!r}: {exc}", ctx, param) from None
    function = getattr(module, attr, None) if attr else None
    if not callable(function):
        raise click.BadParameter(f"{module_name!r} has no callable {attr!r}; {what} must name one as "
                                 f"package.module:name; got {value!r}", ctx, param)
    return function


class _ModelType(click.ParamType):
    """A built-in model name or ``package.module:factory``."""

    name = "MODEL"

    def convert(self, value, param, ctx):
        if isinstance(value, _Model):
            return value
        if value in REGISTRY:
            return _Model(value, REGISTRY[value].factory, REGISTRY[value].description)
        if ":" not in value:
            self.fail(f"must be a built-in model ({', '.join(sorted(REGISTRY))}) or package.module:factory; "
                      f"got {value!r}", param, ctx)
        factory = _import_callable(value, "MODEL", param, ctx)
        doc = (factory.__doc__ or "").strip().splitlines()
        return _Model(value, factory, doc[0] if doc else value)


class _ParamPair(click.ParamType):
    """``key=value`` with the value a Python literal (ast.literal_eval)."""

    name = "KEY=VALUE"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        key, sep, text = value.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            self.fail(f"must be key=value with key a Python name, e.g. sigma_u=0.01; got {value!r}", param, ctx)
        try:
            return key, ast.literal_eval(text.strip())
        except (ValueError, SyntaxError, TypeError, MemoryError, RecursionError):
            self.fail(f"the value of {key} must be a Python literal (a number, True/False/None, a tuple or list, "
                      f"a quoted string such as {key}=\"'text'\"); got {text!r}", param, ctx)


def _model_options(f):
    """--param (repeatable) and --dt: keyword arguments of the model's factory."""
    f = click.option("--dt", type=click.FloatRange(min=0.0, min_open=True), default=None,
                     help="Time step in seconds (the factory's dt; default: the model's).")(f)
    return click.option("--param", "params", type=_ParamPair(), multiple=True, metavar="KEY=VALUE",
                        help="A keyword argument of the model's factory, the value a Python literal "
                             "(repeatable), e.g. --param sigma_u=0.01.")(f)


def _model_kwargs(params, dt) -> dict:
    kwargs = {}
    for key, value in params:
        if key in kwargs:
            raise click.BadParameter(f"{key} is given twice", param_hint="'--param'")
        if key in ("delay", "noise"):
            raise click.BadParameter(f"{key} is set by its own option, not by --param", param_hint="'--param'")
        kwargs[key] = value
    if dt is not None:
        if "dt" in kwargs:
            raise click.BadParameter("dt is given both as --dt and as --param dt=...", param_hint="'--dt'")
        kwargs["dt"] = dt
    return kwargs


def _problem(model: _Model, delay: float, noise: bool, kwargs: Optional[dict] = None, hint: str = "--delay"):
    """The model's problem; the factory's refusal of a delay or a parameter becomes a usage error
    (exit code 2), naming the option."""
    from .problem import Problem
    kwargs = kwargs or {}
    try:
        problem = model.factory(delay=delay, noise=noise, **kwargs)
    except TypeError as exc:
        raise click.BadParameter(f"{model.name}: {exc}", param_hint="'--param'") from exc
    except ValueError as exc:       # the factory says which argument; the hint names the options that set them
        options = [hint] + (["--dt"] if "dt" in kwargs else []) + (["--param"] if set(kwargs) - {"dt"} else [])
        raise click.BadParameter(f"{model.name}: {exc}", param_hint=" / ".join(f"'{o}'" for o in options)) from exc
    if not isinstance(problem, Problem):
        raise click.BadParameter(f"the factory must return a delayed_ilqr.Problem; {model.name} returned "
                                 f"{type(problem).__name__}", param_hint="'MODEL'")
    return problem


ERROR_EXIT = 3      # neither a usage error (2) nor a solve that did not converge (1)


class _Output:
    """An ``--out`` folder written atomically: :meth:`open` (before computing) checks it and
    makes a hidden staging folder beside it; the command writes into ``staging``; :meth:`commit`
    adds manifest.json and renames the staging folder to ``out``, replacing an old one whole."""

    def __init__(self, out: Optional[pathlib.Path], overwrite: bool):
        self.out, self.overwrite, self.staging = out, overwrite, None

    def open(self) -> "_Output":
        if self.out is None:
            return self
        out = self.out
        if out.exists() and not out.is_dir():
            raise click.BadParameter(f"{out} exists and is not a folder", param_hint="'--out'")
        if out.is_dir() and any(out.iterdir()) and not self.overwrite:
            raise click.BadParameter(f"{out} is not empty; pass --overwrite to replace it whole",
                                     param_hint="'--out'")
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
            self.staging = out.parent / f".{out.name}.partial-{os.getpid()}"
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging.mkdir()
        except OSError as exc:
            raise click.BadParameter(f"cannot create {out}: {exc.strerror or exc}", param_hint="'--out'") from None
        return self

    def commit(self, settings: dict) -> list[str]:
        """Writes manifest.json, moves the staging folder to ``out``; returns the file names."""
        files = sorted(str(f.relative_to(self.staging)) for f in self.staging.rglob("*") if f.is_file())
        manifest = dict(command=["delayed-ilqr"] + sys.argv[1:], version=importlib.metadata.version("delayed-ilqr"),
                        created=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                        settings=settings, files={f: (self.staging / f).stat().st_size for f in files})
        (self.staging / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
        old = None
        if self.out.exists():
            old = self.out.parent / f".{self.out.name}.old-{os.getpid()}"
            self.out.rename(old)
        self.staging.rename(self.out)
        self.staging = None
        if old is not None:
            shutil.rmtree(old)
        return files + ["manifest.json"]

    def __enter__(self) -> "_Output":
        return self.open()

    def __exit__(self, *exc_info):       # an error or an interrupt: the staging folder goes
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None


def _out_option(**kwargs):
    def decorate(f):
        f = click.option("--overwrite", is_flag=True,
                         help="Replace a non-empty --out folder whole (its old files are removed).")(f)
        return click.option("--out", type=_OUT_TYPE, **kwargs)(f)
    return decorate


def _check_trials(problem, trials: int, substeps: int, runs: int = 1):
    """The Monte Carlo's memory, checked before any solve (``simulate.check_memory``)."""
    try:
        check_memory(problem, trials * runs, substeps, what="--trials" if runs == 1 else f"{runs} runs x --trials")
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--trials'") from None


def _warn_not_converged(results) -> bool:
    failed = [r for r in results if not r.converged]
    for r in failed:
        click.echo(f"warning: the {r.controller} solve at delay {r.delay:g} s did not converge "
                   f"({r.status}): {r.message}", err=True)
    return bool(failed)


def _settings(model, noise, trials, seed, substeps) -> dict:
    return dict(model=model, noise=bool(noise), trials=int(trials), seed=int(seed), substeps=int(substeps))


class _Main(click.Group):
    """The command group: an error that is not click's becomes one line and exit code 3 (with
    ``--debug``, the traceback); a staging folder left by it is removed by the command."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (click.exceptions.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except Exception as exc:
            if ctx.params.get("debug"):
                raise
            text = str(exc).strip().splitlines()
            click.echo(f"error: {type(exc).__name__}: {text[0] if text else ''} (--debug shows the traceback)",
                       err=True)
            ctx.exit(ERROR_EXIT)


@click.group(cls=_Main, context_settings=dict(help_option_names=["-h", "--help"]))
@click.version_option(package_name="delayed-ilqr")
@click.option("--debug", is_flag=True, help="Show the traceback of an unexpected error.")
@click.option("--no-cache", is_flag=True, envvar=NO_CACHE_ENV, show_envvar=True,
              help="Do not use the persistent compilation cache (every process compiles its solvers again).")
@click.option("--cache-dir", type=click.Path(file_okay=False, path_type=pathlib.Path), envvar=CACHE_DIR_ENV,
              show_envvar=True, default=None,
              help="Folder of the persistent compilation cache [default: jax in the user cache folder, "
                   "e.g. ~/.cache/delayed-ilqr/jax].")
def main(debug, no_cache, cache_dir):
    """iLQG with control (input) delay: solve, Monte Carlo, delay studies and figures.

    Delays are given in seconds and must be whole numbers of the model's time step. Exit codes:
    0 success, 1 when a solve did not converge (results are still written), 2 for bad arguments
    (including an --out that cannot be created, or is not empty without --overwrite), 3 for any
    other error.

    Compiled solvers are kept in a persistent cache folder (--cache-dir), so that the next process
    does not compile them again; --no-cache turns that off.
    """
    # the process is the command's own: float64 and XLA's small-loop flags, before any computation
    jax.config.update("jax_enable_x64", True)
    configure_cpu()
    if not no_cache:        # a second process reads the compiled solvers instead of compiling them
        try:
            enable_compilation_cache(cache_dir)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--cache-dir'") from None


@main.command("models")
def models_command():
    """List the built-in models with their descriptions."""
    width = max(len(name) for name in REGISTRY)
    for name, info in REGISTRY.items():
        click.echo(f"{name.ljust(width)}  {info.description}")


@main.command("solve")
@click.argument("model", type=_ModelType(), metavar="MODEL")
@click.option("--delay", type=float, default=0.0, show_default=True,
              help="Input delay tau in seconds (a whole number of the model's time steps).")
@click.option("--noise/--no-noise", default=False, show_default=True,
              help="Solve the stochastic problem (signal-dependent noise) or the deterministic one.")
@click.option("--method", type=click.Choice(["structured", "augmented"]), default="structured", show_default=True,
              help="Backward pass: Theorem 1's structured recursion, or the state-augmentation reference.")
@_model_options
@_out_option(default=None, help="Folder for solution.json, solution.npz (the Solution, for delayed_ilqr.load) "
                                "and figures.")
def solve_command(model, delay, noise, method, params, dt, out, overwrite):
    """Solve MODEL with iLQG and report the nominal solution and its convergence.

    MODEL is one of the names that `delayed-ilqr models` lists, or your own factory as
    package.module:factory (called as factory(delay=..., noise=..., **params)).
    """
    kwargs = _model_kwargs(params, dt)
    problem = _problem(model, delay, noise, kwargs)
    with _Output(out, overwrite) as output:
        timed = engine.timed_solve(problem, Options(method=method), default_u_init(problem))
        sol = timed[0]
        label, unit = engine.endpoint_description(problem)
        endpoint = (label, unit, engine.endpoint_error(problem, np.asarray(sol.x[-1])[None])[0])
        click.echo(tables.pairs(tables.solve_summary(problem, model.description, noise, method, timed, endpoint)))
        if out is not None:
            from . import plot
            report.write_solution(output.staging, model.name, problem, method, timed, endpoint)
            report.save_figures({"trajectories.png": plot.plot_trajectories(problem, sol),
                                 "convergence.png": plot.plot_convergence({model.name: sol})}, output.staging)
            written = output.commit(dict(model=model.name, delay=delay, noise=noise, method=method,
                                         **_kwargs_settings(kwargs)))
            click.echo(f"wrote {', '.join(written)} to {out}")
    status = Status(int(sol.status))
    if not status.converged:
        click.echo(f"error: the solve did not converge ({status.name}): {status.message}", err=True)
        sys.exit(1)


@main.command("simulate")
@click.argument("model", type=_ModelType(), metavar="MODEL")
@click.option("--delay", type=float, default=0.0, show_default=True,
              help="Input delay tau in seconds (a whole number of the model's time steps).")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Number of Monte Carlo trials (a positive integer).")
@click.option("--seed", type=_SEED, default=0, show_default=True,
              help="Seed of the Monte Carlo noise (the same seed gives the same trials).")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="Simulate (and design for) the stochastic plant, or the deterministic one.")
@click.option("--controller", type=click.Choice(sorted(delay_study.CONTROLLERS)), default="aware", show_default=True,
              help="aware: designed with the delay; ignorant: designed for no delay and run on the delayed "
                   "plant; augmented: delay-aware by state augmentation.")
@click.option("--substeps", type=click.IntRange(min=1), default=1, show_default=True,
              help="Euler-Maruyama sub-steps per control step.")
@_model_options
@_out_option(default=None, help="Folder for simulate.json (summary), runs.npz (trials, nominal, gains), "
                                "solution.npz (for delayed_ilqr.load) and figures.")
def simulate_command(model, delay, trials, seed, noise, controller, substeps, params, dt, out, overwrite):
    """Solve MODEL and run its feedback policy on the (noisy, delayed) plant --trials times.

    MODEL is one of the names that `delayed-ilqr models` lists, or your own factory as
    package.module:factory (called as factory(delay=..., noise=..., **params)).
    """
    kwargs = _model_kwargs(params, dt)
    problem = _problem(model, delay, noise, kwargs)
    _check_trials(problem, trials, substeps)
    with _Output(out, overwrite) as output:
        r = delay_study.evaluate(problem, controller, trials, seed, substeps=substeps)
        click.echo(tables.pairs(tables.simulate_summary(r, model.description)))
        if out is not None:
            from . import plot
            settings = dict(_settings(model.name, noise, trials, seed, substeps), delay=problem.delay,
                            controller=controller, **_kwargs_settings(kwargs))
            report.write_runs(output.staging, r, settings)
            figures = {"trajectories.png": plot.plot_trajectories(problem, r.solution, r.runs)}
            if plot.draws_paths(problem):
                figures["hand_paths.png"] = plot.plot_hand_paths([r])
            report.save_figures(figures, output.staging)
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")
    if _warn_not_converged([r]):
        sys.exit(1)


def _check_study(model, delays, trials, noise, controllers, substeps, kwargs=None):
    """Every delay and the memory of all the trials, checked before anything is solved."""
    problems = [_problem(model, tau, noise, kwargs, hint="--delays") for tau in delays]
    _check_trials(problems[-1], trials, substeps, runs=len(delays) * len(controllers))


def _kwargs_settings(kwargs: dict) -> dict:
    """The factory's keyword arguments for the JSON settings (absent when there are none)."""
    if not kwargs:
        return {}
    return dict(params={k: v if _json_ready(v) else repr(v) for k, v in kwargs.items()})


def _json_ready(value) -> bool:
    try:
        json.dumps(value, allow_nan=False)          # tuples become lists
    except (TypeError, ValueError):
        return False
    return True


def _run_study(model, delays, trials, seed, noise, controllers, substeps, model_kwargs=None, delay_frame="none"):
    model = model.factory if isinstance(model, _Model) else model
    return delay_study.compare_delays(model, delays, trials, seed, noise=noise, controllers=controllers,
                                      substeps=substeps, model_kwargs=model_kwargs, progress=True,
                                      delay_frame=None if delay_frame == "none" else delay_frame)


def _study_outputs(results, out: pathlib.Path, settings: dict, stem: str) -> list[str]:
    """Writes the JSON records, the NPZ of all trials and gains, and the figures; returns file names."""
    from . import plot
    written = report.write_delay_study(results, out, settings, stem)
    return written + report.save_figures(plot.delay_study_figures(results), out)


@main.command("compare")
@click.argument("model", type=_ModelType(), metavar="MODEL")
@click.option("--delays", type=_DelayList(), default="0,0.05,0.1", show_default=True,
              help="Comma-separated input delays in seconds, each a whole number of the model's time steps.")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Monte Carlo trials per controller and delay (a positive integer).")
@click.option("--seed", type=_SEED, default=0, show_default=True,
              help="Seed of the Monte Carlo noise; all controllers see the same noise samples.")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="Design for and simulate the stochastic plant, or the deterministic one.")
@click.option("--augmented/--no-augmented", default=False, show_default=True,
              help="Also evaluate the state-augmentation solution (delay-aware reference).")
@click.option("--substeps", type=click.IntRange(min=1), default=1, show_default=True,
              help="Euler-Maruyama sub-steps per control step.")
@click.option("--delay-frame", type=_DelayFrame(), default="none", show_default=True,
              help="auto: the delays share one compiled solver and Monte Carlo (the delay as data, in a frame "
                   "of the longest delay; results equal to round-off, first-call times at the first delay "
                   "only); none: each delay compiles its own; N: a frame of N steps.")
@_model_options
@_out_option(default=None, help="Folder for compare.json, compare.md, compare_runs.npz and figures.")
def compare_command(model, delays, trials, seed, noise, augmented, substeps, delay_frame, params, dt, out,
                    overwrite):
    """Delay-aware vs delay-ignorant control of MODEL at several delays, by Monte Carlo.

    MODEL is one of the names that `delayed-ilqr models` lists, or your own factory as
    package.module:factory (called as factory(delay=..., noise=..., **params)). Prints one table
    row per delay and controller. With --dt the delays are whole numbers of that step, e.g.
    --dt 0.005 --delays 0,0.025,0.05,0.075,0.1,0.125,0.15.
    """
    controllers = ["aware", "ignorant"] + (["augmented"] if augmented else [])
    kwargs = _model_kwargs(params, dt)
    _check_study(model, delays, trials, noise, controllers, substeps, kwargs)
    with _Output(out, overwrite) as output:
        try:
            results = _run_study(model, delays, trials, seed, noise, controllers, substeps, kwargs, delay_frame)
        except ValueError as exc:       # a frame shorter than a delay
            raise click.UsageError(str(exc)) from None
        table = tables.delay_study_rows(results)
        click.echo(tables.text_table(table))
        if out is not None:
            settings = dict(_settings(model.name, noise, trials, seed, substeps), delays=list(delays),
                            controllers=controllers, delay_frame=delay_frame, **_kwargs_settings(kwargs))
            _study_outputs(results, output.staging, settings, "compare")
            (output.staging / "compare.md").write_text(tables.markdown_table(table) + "\n")
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")
    if _warn_not_converged(results):
        sys.exit(1)


@main.command("demo")
@_out_option(default=pathlib.Path("out"), show_default=True,
             help="Folder for the report (report.md, report.json, report_runs.npz, figures).")
@click.option("--trials", type=click.IntRange(min=1), default=1000, show_default=True,
              help="Monte Carlo trials per controller and delay (a positive integer).")
@click.option("--seed", type=_SEED, default=0, show_default=True,
              help="Seed of the Monte Carlo noise.")
def demo_command(out, overwrite, trials, seed):
    """The arm reaching study: delay-aware vs delay-ignorant iLQG on the noisy two-link arm.

    The P2 reach with signal-dependent torque noise at the human level (models.arm2(noise=True,
    sigma_u=SIGMA_U_HUMAN), calibrated to human force variability, docs/models.md §4.5; P2-noisy's
    0.2 is a numerical stress test), input delays 0, 50, 100 and 150 ms, --trials noisy trials per
    controller and delay. Prints the table and writes a markdown report with figures.
    """
    _check_study(_ModelType().convert("arm2", None, None), list(DEMO_DELAYS), trials, True, ["aware", "ignorant"], 1)
    with _Output(out, overwrite) as output:
        start = time.perf_counter()
        results = _run_study("arm2", list(DEMO_DELAYS), trials, seed, True, ["aware", "ignorant"], 1,
                             dict(sigma_u=SIGMA_U_HUMAN))
        elapsed = time.perf_counter() - start
        click.echo(tables.text_table(tables.delay_study_rows(results)))
        settings = dict(_settings("arm2", True, trials, seed, 1), sigma_u=SIGMA_U_HUMAN, delays=list(DEMO_DELAYS),
                        controllers=["aware", "ignorant"], elapsed_seconds=elapsed)
        _study_outputs(results, output.staging, settings, "report")
        report.write_demo_report(output.staging, results, REGISTRY["arm2"].description, DEMO_DELAYS, trials, seed,
                                 elapsed)
        written = output.commit(settings)
        click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    if _warn_not_converged(results):
        sys.exit(1)


@main.command("center-out")
@click.option("--delays", type=_DelayList(), default=",".join(str(d) for d in DEMO_DELAYS), show_default=True,
              help="Comma-separated input delays in seconds (whole multiples of the 10 ms step).")
@click.option("--targets", "n_targets", type=click.IntRange(min=1), default=8, show_default=True,
              help="Number of targets on the circle.")
@click.option("--radius", type=click.FloatRange(min=0.0, min_open=True), default=0.1, show_default=True,
              help="Circle radius in metres around the start hand position.")
@click.option("--trials", type=click.IntRange(min=2), default=200, show_default=True,
              help="Noisy trials per target and delay.")
@click.option("--seed", type=_SEED, default=0, show_default=True, help="Seed of the noise.")
@click.option("--sigma-u", type=click.FloatRange(min=0.0), default=center_out.SIGMA_U, show_default=True,
              help="Excitation noise of the plant the policies run on.")
@click.option("--design", "designs", type=click.Choice(center_out.DESIGNS), multiple=True,
              help="Controller design, repeatable: noise-aware (iLQG, made for the noisy plant), "
                   "deterministic (iLQR, made for the noise-free arm) or statistical (the noise-aware "
                   "design with its feedback re-designed by statistical linearisation; full-state "
                   "feedback only, not with --sensory-delay).  [default: "
                   f"{', '.join(center_out.DESIGNS)}; {', '.join(center_out.SENSING_DESIGNS)} with --sensory-delay]")
@click.option("--max-iterations", type=click.IntRange(min=1), default=center_out.DEFAULT_OPTIONS.max_iterations,
              show_default=True, help="Iteration limit of each reach's solve.")
@click.option("--sensory-delay", type=click.FloatRange(min=0.0), default=None,
              help="Controllers see the arm's proprioception (joint angles and velocities, with sensory noise) "
                   "this many seconds late through a delayed Kalman filter, instead of the state; a whole "
                   "number of 10 ms steps, 0 allowed.  [default: the state is seen]")
@click.option("--allow-unconverged", is_flag=True,
              help="Exit 0 even when some reaches did not converge (they are flagged in the table and on stderr).")
@_out_option(default=None, help="Folder for center_out.md/.json and the figures.")
def center_out_command(delays, n_targets, radius, trials, seed, sigma_u, designs, max_iterations, sensory_delay,
                       allow_unconverged, out, overwrite):
    """Center-out reaching with the six-muscle arm (arm2_muscle6) at several input delays.

    Per delay and design: one vectorised solve of the reaches to all targets (excitations limited
    to [0, 1]), then --trials noisy trials per target. Prints iterations, solve time, the
    nominal's final hand error, predicted and Monte Carlo costs and the endpoint spread; writes
    hand paths with endpoint ellipses and the excitation patterns per target. Exits 1 when a
    reach did not converge, unless --allow-unconverged.
    """
    try:
        for d in delays:
            arm2_muscle6(delay=d)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--delays'") from exc
    if sensory_delay is not None:
        try:
            arm2_muscle6(sensory_delay=sensory_delay)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="'--sensory-delay'") from exc
    try:
        designs = center_out.designs_for(designs or None, sensory_delay)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--design'") from exc
    with _Output(out, overwrite) as output:
        start = time.perf_counter()
        options = dataclasses.replace(center_out.DEFAULT_OPTIONS, max_iterations=max_iterations)
        results = center_out.center_out(delays, n_targets, radius, trials, seed, options=options, sigma_u=sigma_u,
                                        designs=designs, sensory_delay=sensory_delay)
        elapsed = time.perf_counter() - start
        table = tables.markdown_table(tables.center_out_rows(results))
        click.echo(table)
        if out is not None:
            from . import plot
            figures = report.save_figures(plot.center_out_figures(results), output.staging)
            settings = dict(delays=list(delays), targets=n_targets, radius=radius, trials=trials, seed=seed,
                            sigma_u=sigma_u, designs=list(designs), max_iterations=max_iterations,
                            sensory_delay=sensory_delay, elapsed_seconds=elapsed)
            report.write_center_out_report(output.staging, results, settings, table, figures)
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    failed = [(r.delay, r.design, j) for r in results for j, t in enumerate(r.targets) if not t.converged]
    for delay, design, j in failed:
        click.echo(f"warning: the {design} reach to target {j + 1} at delay {delay:g} s did not converge", err=True)
    if failed and not allow_unconverged:
        sys.exit(1)


@main.command("fit")
@click.argument("function", metavar="FUNCTION")
@click.argument("data", type=click.Path(exists=True, dir_okay=False, path_type=pathlib.Path))
@click.option("--start", "starts", type=_ParamPair(), multiple=True, required=True,
              help="name=value: a fitted parameter and its starting value (a positive number); repeatable.")
@click.option("--delays", type=_DelayList(), required=True,
              help="Comma-separated candidate delays in seconds (the profile: one fit per delay).")
@click.option("--mean-scale", type=click.FloatRange(min=0.0, min_open=True), default=1e-3, show_default=True,
              help="Precision of a mean path in task units (e.g. its standard error).")
@click.option("--max-iterations", type=click.IntRange(min=1), default=100, show_default=True,
              help="L-BFGS-B iterations per delay.")
@click.option("--gtol", type=click.FloatRange(min=0.0, min_open=True), default=1e-8, show_default=True,
              help="L-BFGS-B's tolerance on the projected gradient of the loss in log parameters.")
@_out_option(default=None, help="Folder for fit.json.")
def fit_command(function, data, starts, delays, mean_scale, max_iterations, gtol, out, overwrite):
    """Fit cost weights and noise scales to reach data, and the delay by a profile (docs/fitting.md).

    FUNCTION is package.module:name, called as name(params, condition, delay) with params a dict
    of the --start names (traced scalars), condition one row of DATA's conditions and delay in
    seconds, and returning a delayed_ilqr.Problem. DATA is an NPZ file with the arrays conditions
    [C, ...], mean [C, K+1, m] (mean task-space paths) and endpoint_cov [C, m, m]
    (delayed_ilqr.experiments.fitting.save_reach_data writes one). Prints the loss and parameters
    fitted at each delay and the delay of the smallest loss; exits 1 when that fit did not
    converge (results are still written).
    """
    from .experiments import fitting

    try:
        make_problem = _import_callable(function, "FUNCTION", None, None)
    except click.BadParameter as exc:
        exc.param_hint = "'FUNCTION'"
        raise
    try:
        conditions, reach_data = fitting.load_reach_data(data)
    except (ValueError, OSError) as exc:
        raise click.BadParameter(str(exc), param_hint="'DATA'") from None
    params0 = dict(starts)
    bad = {k: v for k, v in params0.items()
           if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0)}
    if bad:
        raise click.BadParameter(f"starting values must be positive finite numbers; got {bad}", param_hint="'--start'")
    for delay in delays:
        try:
            make_problem({k: float(v) for k, v in params0.items()}, conditions[0], delay)
        except ValueError as exc:
            raise click.BadParameter(f"{function} refused delay {delay:g} s: {exc}", param_hint="'--delays'") from None
    with _Output(out, overwrite) as output:
        start = time.perf_counter()
        best, fits = fitting.profile_delay(make_problem, delays, conditions, reach_data,
                                           {k: float(v) for k, v in params0.items()}, mean_scale=mean_scale,
                                           max_iterations=max_iterations, gtol=gtol)
        elapsed = time.perf_counter() - start
        names = sorted(params0)
        header = ["delay [s]", "loss", *names, "converged", "L-BFGS-B iterations", "evaluations"]
        rows = [[f"{d:g}", f"{f.loss:.4g}", *(f"{f.params[k]:.6g}" for k in names), "yes" if f.converged else "no",
                 str(f.iterations), str(f.evaluations)] for d, f in zip(delays, fits)]
        click.echo(tables.markdown_table((header, rows)))
        chosen = fits[delays.index(best)]
        click.echo(f"delay {best:g} s (smallest loss); " + ", ".join(f"{k} = {chosen.params[k]:.6g}" for k in names))
        if out is not None:
            settings = dict(function=function, data=str(data), start=params0, delays=list(delays),
                            mean_scale=mean_scale, max_iterations=max_iterations, gtol=gtol,
                            elapsed_seconds=elapsed)
            records = [dict(delay=d, loss=f.loss, params=f.params, converged=f.converged, message=f.message,
                            iterations=f.iterations, evaluations=f.evaluations) for d, f in zip(delays, fits)]
            report.write_json(output.staging / "fit.json", dict(settings=settings, best_delay=best, fits=records))
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out} ({elapsed:.1f} s)")
    if not chosen.converged:
        click.echo(f"warning: the fit at delay {best:g} s did not converge: {chosen.message}", err=True)
        sys.exit(1)


def _perturb_rows(results) -> list[dict]:
    """One table row per sensory delay: design, costs, and the latencies after the kick."""
    rows = []
    for r in results:
        dt, kp = r.problem.dt, r.pulse_step
        after = lambda k: None if k is None else 1000 * dt * (k - kp)          # noqa: E731
        rows.append({"sensory delay [ms]": 1000 * r.sensory_delay, "status": str(r.solution.status),
                     "expected cost": float(r.solution.expected_cost),
                     "MC cost": float(r.base.summary().mean_cost),
                     "MC cost kicked": float(r.perturbed.summary().mean_cost),
                     "first response [ms after kick]": after(r.latency_steps),
                     "half-peak response [ms after kick]": after(r.half_steps)})
    return rows


def _perturb_outputs(results, staging: pathlib.Path, settings: dict, table_rows) -> None:
    from .plot import perturbation_figures
    records = [{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}
               for row in table_rows]
    report.write_json(staging / "perturb.json", dict(settings=settings, results=records))
    (staging / "perturb.md").write_text(tables.markdown_table(tables.records_table(table_rows)) + "\n")
    arrays = {}
    for r in results:
        tag = f"ls{int(round(1000 * r.sensory_delay))}ms"
        arrays[f"{tag}_x_mean"] = np.asarray(r.base.x).mean(axis=0)
        arrays[f"{tag}_x_kicked_mean"] = np.asarray(r.perturbed.x).mean(axis=0)
        arrays[f"{tag}_u_mean"] = np.asarray(r.base.u).mean(axis=0)
        arrays[f"{tag}_u_kicked_mean"] = np.asarray(r.perturbed.u).mean(axis=0)
        arrays[f"{tag}_disturbance"] = r.disturbance
    np.savez_compressed(staging / "perturb_means.npz", **arrays)
    report.save_figures(perturbation_figures(results), staging)


@main.command("perturb")
@click.argument("model", type=click.Choice(perturbation.PERTURB_MODELS), metavar="MODEL")
@click.option("--delay", type=float, default=0.05, show_default=True,
              help="Input (motor) delay in seconds (a whole number of the model's time steps).")
@click.option("--sensory-delays", type=_DelayList(), default="0,0.05,0.1", show_default=True,
              help="Comma-separated sensory delays in seconds, each a whole number of the model's time steps.")
@click.option("--pulse-time", type=click.FloatRange(min=0.0), default=0.15, show_default=True,
              help="When the kick hits, in seconds from the start of the movement.")
@click.option("--kick", type=click.FloatRange(min=0.0, min_open=True), default=0.2, show_default=True,
              help="Size of the kick: the change of the hand's (point's) velocity in m/s, perpendicular "
                   "to the nominal movement.")
@click.option("--trials", type=click.IntRange(min=1), default=200, show_default=True,
              help="Monte Carlo trials per sensory delay (each run twice: without and with the kick).")
@click.option("--seed", type=_SEED, default=0, show_default=True, help="Seed of the motor and sensory noise.")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="Motor noise in the plant (the sensors are always noisy).")
@_out_option(default=None, help="Folder for perturb.json, perturb.md, perturb_means.npz and perturbation.png.")
def perturb_command(model, delay, sensory_delays, pulse_time, kick, trials, seed, noise, out, overwrite):
    """Perturbation experiments: kick the hand of MODEL mid-reach and measure the correction
    against the sensory delay.

    MODEL is point_mass, arm2 (torque noise at the human level, SIGMA_U_HUMAN) or arm2_muscle6,
    with their default sensors (docs/models.md). Per sensory delay the controller and the
    delayed filter are designed, and --trials trials run without and with the kick on the same
    noise; the first command that differs is (1 + l_s) steps after the kick.
    """
    kwargs = dict(sigma_u=SIGMA_U_HUMAN) if model == "arm2" else {}
    try:
        problems = [REGISTRY[model].factory(delay=delay, noise=noise, sensory_delay=ls, **kwargs)
                    for ls in sensory_delays]
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--delay' / '--sensory-delays'") from exc
    final = problems[0].horizon * problems[0].dt
    if pulse_time >= final:
        raise click.BadParameter(f"must be within the movement, below {final:g} s; got {pulse_time:g}",
                                 param_hint="'--pulse-time'")
    _check_trials(problems[-1], trials, 1, runs=2 * len(sensory_delays))
    with _Output(out, overwrite) as output:
        results = perturbation.perturbation_study(model, sensory_delays, delay, pulse_time, kick, trials, seed,
                                                  noise=noise, model_kwargs=kwargs)
        rows = _perturb_rows(results)
        click.echo(tables.text_table(tables.records_table(rows)))
        if out is not None:
            settings = dict(model=model, delay=delay, sensory_delays=list(sensory_delays), pulse_time=pulse_time,
                            kick=kick, trials=trials, seed=seed, noise=noise, **kwargs)
            _perturb_outputs(results, output.staging, settings, rows)
            written = output.commit(settings)
            click.echo(f"wrote {', '.join(written)} to {out}")
    failed = [r for r in results if not r.converged]
    for r in failed:
        click.echo(f"warning: the solve at sensory delay {r.sensory_delay:g} s did not converge "
                   f"({r.solution.status})", err=True)
    if failed:
        sys.exit(1)


class _GridAxis(click.ParamType):
    """``NAME=VALUES``: one grid dimension of ``sweep``. VALUES is ``a,b,c`` (numbers, true/false or
    words), ``start:stop:step`` (numbers from start to stop inclusive), or vectors ``[..];[..]``."""

    name = "NAME=VALUES"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        name, sep, text = str(value).partition("=")
        name = name.strip()
        if not sep or not name.isidentifier() or not text.strip():
            self.fail(f"must be NAME=VALUES such as delay=0,0.05,0.1 or delay=0:0.15:0.01; got {value!r}", param, ctx)
        try:
            if text.count(":") == 2 and "[" not in text:
                start, stop, step = (float(v) for v in text.split(":"))
                if not (step > 0 and stop >= start):
                    raise ValueError("start:stop:step needs step > 0 and stop >= start")
                count = int(math.floor((stop - start) / step + 1e-9)) + 1
                values = [round(start + i * step, 12) for i in range(count)]
            elif "[" in text:
                values = [tuple(json.loads(v)) for v in text.split(";") if v.strip()]
            else:
                values = [_scalar(v) for v in text.split(",") if v.strip()]
        except (ValueError, TypeError) as exc:
            self.fail(f"cannot read the values of {name!r} in {value!r}: {exc}", param, ctx)
        return name, values


def _scalar(text: str):
    """A command-line value: a JSON number, true/false, or else the word itself."""
    try:
        return json.loads(text.strip())
    except ValueError:
        return text.strip()


class _Setting(click.ParamType):
    """``NAME=VALUE``: a factory argument held fixed over the sweep."""

    name = "NAME=VALUE"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        name, sep, text = str(value).partition("=")
        if not sep or not name.strip().isidentifier():
            self.fail(f"must be NAME=VALUE such as sigma_u=0.01; got {value!r}", param, ctx)
        text = text.strip()
        return name.strip(), tuple(json.loads(text)) if text.startswith("[") else _scalar(text)


class _IntList(click.ParamType):
    name = "N[,N...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (list, tuple)):
            return list(value)
        try:
            return [int(v) for v in str(value).split(",") if v.strip()]
        except ValueError:
            self.fail(f"must be comma-separated non-negative integers such as 0,1,2; got {value!r}", param, ctx)


SWEEP_STORE, SWEEP_FIGURE = "store", "sweep.png"


@main.command("sweep")
@click.argument("model", type=_ModelType(), metavar="MODEL")
@click.option("--grid", "axes", type=_GridAxis(), multiple=True, required=True,
              help="A grid dimension over an argument of the model's factory, repeatable: NAME=a,b,c, "
                   "NAME=start:stop:step (inclusive) or NAME=[..];[..] for vectors, e.g. --grid delay=0:0.15:0.01 "
                   "--grid sigma_u=0.01,0.02.")
@click.option("--set", "settings_", type=_Setting(), multiple=True,
              help="A factory argument held fixed, repeatable: NAME=VALUE, e.g. --set sigma_u=0.01.")
@click.option("--noise/--no-noise", default=True, show_default=True,
              help="The stochastic plant or the deterministic one (the factory's noise argument).")
@click.option("--seeds", type=_IntList(), default="0", show_default=True,
              help="Comma-separated Monte Carlo seeds (the Dataset's seed dimension).")
@click.option("--trials", type=click.IntRange(min=1), default=100, show_default=True,
              help="Monte Carlo trials per cell and seed.")
@click.option("--design", type=click.Choice(sorted(designs.REGISTRY)), default="aware", show_default=True,
              help="The controller design (experiments.designs): aware is Theorem 1 on the plant.")
@click.option("--batch-size", type=click.IntRange(min=1), default=16, show_default=True,
              help="At most this many cells of equal structure per vmapped solve.")
@click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
              help="Run on a dask.distributed LocalCluster of this many worker processes (0: in this process).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on the Dask cluster of this scheduler, e.g. tcp://host:8786 (docs/sweeps.md).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="A progress bar over the cells.")
@click.option("--delay-frame", type=_DelayFrame(), default="auto", show_default=True,
              help="auto: the delay is data, in a frame of the grid's longest delay, so all delays share one "
                   "compiled solver (results equal to round-off; each solve costs one at the longest delay), "
                   "when no delay has more than 1000 cells; none: one solver per delay; N: a frame of N steps "
                   "(docs/sweeps.md).")
@_out_option(required=True, help="Folder of the sweep: store/ (results.zarr and completion markers; a second "
                                 "run of the same command resumes it), sweep.png, manifest.json.")
def sweep_command(model, axes, settings_, noise, seeds, trials, design, batch_size, workers, scheduler, progress,
                  delay_frame, out, overwrite):
    """Solve and simulate MODEL on every cell of a grid over its factory's arguments.

    Each cell is solved (cells of equal structure together, one vmap), run --trials times per seed,
    and its statistics written to --out/store as soon as its batch is done: an interrupted sweep
    resumes where it stopped when the same command runs again, and finished cells are not
    computed twice. Prints a summary table and draws --out/sweep.png against the first --grid
    dimension. Exits 1 when some cell did not converge.
    """
    from . import plot
    from .sweeps import sweep
    grid = dict(axes)
    if len(grid) != len(axes):
        raise click.BadParameter("names a dimension twice", param_hint="'--grid'")
    fixed = dict(settings_)
    if "noise" not in grid and "noise" not in fixed:
        fixed["noise"] = noise
    if workers and scheduler:
        raise click.BadParameter("give either --workers (a LocalCluster) or --scheduler (a running cluster)",
                                 param_hint="'--workers'")
    executor = scheduler if scheduler else ("local" if workers else None)
    store = out / SWEEP_STORE
    if out.is_dir() and any(out.iterdir()) and not (store / "sweep.json").is_file() and not overwrite:
        raise click.BadParameter(f"{out} is not empty and holds no sweep; pass --overwrite to replace it whole",
                                 param_hint="'--out'")
    if overwrite and out.is_dir() and not (store / "sweep.json").is_file():
        shutil.rmtree(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise click.BadParameter(f"cannot create {out}: {exc.strerror or exc}", param_hint="'--out'") from None
    start = time.perf_counter()
    try:
        # a built-in model by name (what the store records); a user's factory as the function
        ds = sweep(model.name if model.name in REGISTRY else model.factory, grid, seeds, trials, fixed=fixed,
                   design=design, store=store, overwrite=overwrite,
                   scheduler=executor, n_workers=max(workers, 1), batch_size=batch_size, progress=progress,
                   # a LocalCluster's workers share this process's cache; a remote cluster's use their own
                   cache_dir=None if scheduler else jax.config.jax_compilation_cache_dir,
                   cache=jax.config.jax_compilation_cache_dir is not None,
                   delay_frame=None if delay_frame == "none" else delay_frame)
    except (ValueError, TypeError) as exc:
        raise click.UsageError(str(exc)) from None
    elapsed = time.perf_counter() - start
    click.echo(tables.text_table(tables.sweep_rows(ds)))
    figure = plot.plot_sweep(ds)
    tmp = out / f".{SWEEP_FIGURE}.tmp-{os.getpid()}.png"
    figure.savefig(tmp, dpi=report.DPI)
    os.replace(tmp, out / SWEEP_FIGURE)
    files = sorted(str(f.relative_to(out)) for f in out.rglob("*") if f.is_file() and f.name != "manifest.json")
    manifest = dict(command=["delayed-ilqr"] + sys.argv[1:], version=importlib.metadata.version("delayed-ilqr"),
                    created=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                    settings=dict(model=model.name, grid={k: [list(v) if isinstance(v, tuple) else v for v in vs]
                                                     for k, vs in grid.items()},
                                  fixed=fixed, seeds=seeds, trials=trials, design=design, batch_size=batch_size,
                                  elapsed_seconds=elapsed), files=len(files))
    tmp = out / f".manifest.json.tmp-{os.getpid()}"
    tmp.write_text(json.dumps(manifest, indent=2, default=repr) + "\n")
    os.replace(tmp, out / "manifest.json")
    n_failed = int((ds.converged.values != 1).sum())
    click.echo(f"wrote {SWEEP_STORE}/, {SWEEP_FIGURE}, manifest.json to {out} ({elapsed:.1f} s)")
    if n_failed:
        click.echo(f"warning: {n_failed} of {ds.converged.size} cells did not converge (status in the Dataset)",
                   err=True)
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover
    main()
