"""The command line's arguments: parameter types (delays, seeds, models, ``key=value`` pairs, grid
axes), a model factory's keyword arguments and problem, and the checks made before anything is
computed (every refusal is a usage error, exit code 2, that names the option)."""
from __future__ import annotations

import ast
import importlib
import json
import math
import os
import sys
from typing import Callable, NamedTuple, Optional

import click

from ..models import REGISTRY
from ..simulate import check_memory

SEED = click.IntRange(min=0, max=2 ** 63 - 1)       # what simulate accepts


class DelayFrame(click.ParamType):
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


class OneDelay(click.ParamType):
    """One delay in seconds (a float), for every command channel: a list is refused with the way
    to give per-channel delays (in Python, ``Problem(..., delay_steps=[l_1, ..., l_d])``)."""

    name = "SECONDS"

    def convert(self, value, param, ctx):
        if isinstance(value, float):
            return value
        if "," in str(value):
            self.fail("takes one delay in seconds for every command channel (per-channel delays are set in "
                      f"Python: Problem(..., delay_steps=[l_1, ..., l_d])); got {value!r}", param, ctx)
        try:
            return float(value)
        except ValueError:
            self.fail(f"must be a number of seconds; got {value!r}", param, ctx)


class DelayList(click.ParamType):
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


class Model(NamedTuple):
    """MODEL resolved: its name as given, the factory, a one-line description."""

    name: str
    factory: Callable
    description: str


def import_callable(value: str, what: str, param, ctx) -> Callable:
    """The callable named by ``package.module:name`` (the current folder on the path, as
    ``python -m`` finds a module); ``what`` names it in errors (e.g. "MODEL")."""
    module_name, _, attr = value.partition(":")
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise click.BadParameter(f"cannot import module {module_name!r} of {value!r}: {exc}", ctx, param) from None
    except Exception as exc:          # the user's module: a syntax error, or an error while it runs
        raise click.BadParameter(f"cannot import module {module_name!r} of {value!r}: {type(exc).__name__}: "
                                 f"{exc}", ctx, param) from None
    function = getattr(module, attr, None) if attr else None
    if not callable(function):
        raise click.BadParameter(f"{module_name!r} has no callable {attr!r}; {what} must name one as "
                                 f"package.module:name; got {value!r}", ctx, param)
    return function


class ModelType(click.ParamType):
    """A built-in model name or ``package.module:factory``."""

    name = "MODEL"

    def convert(self, value, param, ctx):
        if isinstance(value, Model):
            return value
        if value in REGISTRY:
            return Model(value, REGISTRY[value].factory, REGISTRY[value].description)
        if ":" not in value:
            self.fail(f"must be a built-in model ({', '.join(sorted(REGISTRY))}) or package.module:factory; "
                      f"got {value!r}", param, ctx)
        factory = import_callable(value, "MODEL", param, ctx)
        doc = (factory.__doc__ or "").strip().splitlines()
        return Model(value, factory, doc[0] if doc else value)


class ParamPair(click.ParamType):
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


def model_options(f):
    """--param (repeatable) and --dt: keyword arguments of the model's factory."""
    f = click.option("--dt", type=click.FloatRange(min=0.0, min_open=True), default=None,
                     help="Time step in seconds (the factory's dt; default: the model's).")(f)
    return click.option("--param", "params", type=ParamPair(), multiple=True, metavar="KEY=VALUE",
                        help="A keyword argument of the model's factory, the value a Python literal "
                             "(repeatable), e.g. --param sigma_u=0.01.")(f)


#: the values of --noise: "on" (the model's default noise, True to its factory: the human preset
#: of the human models), "off", or a preset by name (the factory's ``noise=NAME``)
NOISE_CHOICES = ("on", "off", "human", "benchmark")


def noise_option(f):
    """--noise [on|off|human|benchmark] and --no-noise: one default (on) for every command that
    builds a model's problem; `noise_value` turns them into the factory's ``noise``."""
    f = click.option("--no-noise", is_flag=True, help="The deterministic plant (the same as --noise off).")(f)
    return click.option("--noise", type=click.Choice(NOISE_CHOICES), is_flag=False, flag_value="on", default="on",
                        show_default=True,
                        help="The plant's motor noise: on, the model's default (for the arm models the human "
                             "preset, signal-dependent noise calibrated to human force variability, "
                             "docs/models.md); off; or a preset by name: human, or benchmark for the benchmark "
                             "problems' stress level (P1-noisy, P2-noisy).")(f)


def noise_value(noise: str, no_noise: bool):
    """The factory's ``noise`` argument of --noise / --no-noise: True, False or a preset's name."""
    if no_noise:
        if noise not in ("on", "off"):
            raise click.BadParameter(f"--no-noise contradicts --noise {noise}", param_hint="'--no-noise'")
        return False
    return {"on": True, "off": False}.get(noise, noise)


#: --progress of the commands that run for longer than a few seconds (as sweep's)
progress_option = click.option("--progress/--no-progress", default=True, show_default=True,
                               help="A progress bar on stderr (shown only when stderr is a terminal).")

#: --substeps of the commands that run Monte Carlo trials
substeps_option = click.option("--substeps", type=click.IntRange(min=1), default=1, show_default=True,
                               help="Euler-Maruyama sub-steps per control step.")


def factory_kwargs(params, dt) -> dict:
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


def build_problem(model: Model, delay: float, noise, kwargs: Optional[dict] = None, hint: str = "--delay"):
    """The model's problem (``noise``: True, False or a preset's name, `noise_value`); the
    factory's refusal of a delay, a noise preset or a parameter becomes a usage error (exit code
    2), naming the option."""
    from ..problem import Problem
    kwargs = kwargs or {}
    try:
        problem = model.factory(delay=delay, noise=noise, **kwargs)
    except (TypeError, ValueError) as exc:
        if str(exc).startswith("noise"):            # a preset the model does not have
            raise click.BadParameter(f"{model.name}: {exc}", param_hint="'--noise'") from exc
        if isinstance(exc, TypeError):
            raise click.BadParameter(f"{model.name}: {exc}", param_hint="'--param'") from exc
        # the factory says which argument; the hint names the options that set them
        options = [hint] + (["--dt"] if "dt" in kwargs else []) + (["--param"] if set(kwargs) - {"dt"} else [])
        raise click.BadParameter(f"{model.name}: {exc}", param_hint=" / ".join(f"'{o}'" for o in options)) from exc
    if not isinstance(problem, Problem):
        raise click.BadParameter(f"the factory must return a delayed_ilqr.Problem; {model.name} returned "
                                 f"{type(problem).__name__}", param_hint="'MODEL'")
    if problem.is_fractional:
        # the commands' reports, figures and controllers name one delay in whole steps; Python's
        # models and Problem take a delay between steps (docs/guide/own_plant.md)
        raise click.BadParameter(f"{model.name}: the delay must be a whole number of steps of dt={problem.dt!r} s on "
                                 f"the command line (a delay between steps is set in Python, e.g. delay_steps=2.5, "
                                 f"or make it whole with --dt); got {delay!r} s ({delay / problem.dt:.10g} steps)",
                                 param_hint=hint)
    return problem


def check_trials(problem, trials: int, substeps: int, runs: int = 1):
    """The Monte Carlo's memory, checked before any solve (``simulate.check_memory``)."""
    try:
        check_memory(problem, trials, substeps, what="--trials", runs=runs)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="'--trials'") from None


class GridAxis(click.ParamType):
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


class Setting(click.ParamType):
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


class IntList(click.ParamType):
    name = "N[,N...]"

    def convert(self, value, param, ctx):
        if isinstance(value, (list, tuple)):
            return list(value)
        try:
            return [int(v) for v in str(value).split(",") if v.strip()]
        except ValueError:
            self.fail(f"must be comma-separated non-negative integers such as 0,1,2; got {value!r}", param, ctx)
