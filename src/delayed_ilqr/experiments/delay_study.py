"""Delay studies: what ignoring the delay costs, measured by Monte Carlo on the nonlinear plant.

For each input delay tau the study builds the problem and evaluates controllers on the same
(delayed, possibly noisy) plant (designs: `designs`):

|  |  |
|---|---|
| aware | ``solve(problem)``: iLQG with the delay (Theorem 1, structured backward pass) |
| ignorant | ``solve(problem.replace(delay_steps=0))``: designed as if the commands acted at once, then run on the delayed plant (its policy has l_p = 0, see [`simulate`][delayed_ilqr.simulate]) |
| augmented | ``solve(problem, Options(method="augmented"))``: the state-augmentation reference |

Each policy is run ``n_trials`` times by [`simulate`][delayed_ilqr.simulate] with the same seed, so all
controllers at one delay see the same noise samples (common random numbers). A result reports the
controller's own prediction of its expected cost (``Solution.expected_cost`` of the problem it was
designed for: for the delay-ignorant controller, the plant without delay), the Monte Carlo cost
with 95 % intervals, the endpoint error in the model's task space (`engine.endpoint_error`:
the hand's distance from the target for the arms, the position error for the point mass, the final
cost for a plant without metadata), iterations and solve time.

Everything here returns plain data; tables and files are `report`'s, figures
[`delayed_ilqr.plot`][delayed_ilqr.plot]'s.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Callable, Optional, Sequence, Union

import numpy as np

from .. import Options, Problem, Runs, Solution, Status
from ..models.metadata import default_u_init
from ..problem import shared_delay_frame
from ..statistics import SampleStats, Summary, divergence_bound, diverged_trials, sample_stats, summarize
from . import designs
from .engine import endpoint_description, monte_carlo, timed_solve
from .delay_text import delay_text
from .progress import progress_bar
from .records import delay_values

__all__ = ["CONTROLLERS", "ControllerResult", "evaluate", "compare_delays"]

#: The controllers a delay study compares (descriptions: ``designs.REGISTRY[name].description``).
CONTROLLERS = ("aware", "ignorant", "augmented")


@dataclasses.dataclass(frozen=True)
class ControllerResult:
    """One controller at one delay: solve diagnostics and Monte Carlo statistics.

    Attributes:
        model: the problem's name; delay, delay_steps: tau in seconds and l, lists of one per
            channel for per-channel delays and delays between steps (l_j + phi_j steps;
            ``records.delay_values``); noise: whether the plant is stochastic; controller: one of
            `CONTROLLERS`.
        converged, status, message, iterations: from the solve (``status`` is the Status name).
        solve_time: seconds for a solve once compiled; first_solve_time: the first call's seconds
            (compilation included, about zero when an equal-shaped problem was compiled before).
        nominal_cost: eq. (2) on the controller's nominal, noise-free trajectory (on the plant it was
            designed for).
        predicted_cost: ``Solution.expected_cost``, the controller's own prediction of E[J].
        cost: [`SampleStats`][delayed_ilqr.statistics.SampleStats] of the Monte Carlo cost on the delayed
            plant (mean over the trials that did not diverge, their count, median and IQR).
        endpoint_error: SampleStats of the final endpoint error (see `engine.endpoint_error`)
            over the same trials (the diverged ones are those of ``cost``).
        divergence_bound: the cost above which a trial diverged
            ([`divergence_bound`][delayed_ilqr.statistics.divergence_bound] of the plant; inf: only non-finite).
        endpoint_label, endpoint_unit: what the endpoint error measures, and in which unit.
        summary: the [`Summary`][delayed_ilqr.statistics.Summary] of the runs (final-state statistics).
        n_trials, seed, substeps: the Monte Carlo settings.
        problem, solution, runs: the plant, the [`Solution`][delayed_ilqr.Solution] and the
            [`Runs`][delayed_ilqr.Runs] (for figures and files; left out of [`to_dict`][delayed_ilqr.experiments.delay_study.ControllerResult.to_dict]).
    """

    model: str
    delay: Union[float, list]
    delay_steps: Union[int, float, list]
    noise: bool
    controller: str
    converged: bool
    status: str
    message: str
    iterations: int
    solve_time: float
    first_solve_time: float
    nominal_cost: float
    predicted_cost: float
    cost: SampleStats
    endpoint_error: SampleStats
    divergence_bound: float
    endpoint_label: str
    endpoint_unit: str
    summary: Summary
    n_trials: int
    seed: int
    substeps: int
    problem: Problem = dataclasses.field(repr=False, compare=False)
    solution: Solution = dataclasses.field(repr=False, compare=False)
    runs: Runs = dataclasses.field(repr=False, compare=False)

    def to_dict(self) -> dict:
        """Plain Python types for JSON (non-finite numbers as ``None``); no trajectories."""
        out = {}
        for f in dataclasses.fields(self):
            if f.name in ("problem", "solution", "runs"):
                continue
            value = getattr(self, f.name)
            if hasattr(value, "to_dict"):
                value = value.to_dict()
            elif isinstance(value, float) and not math.isfinite(value):
                value = None
            out[f.name] = value
        return out


def _controller(name: str) -> str:
    if name not in CONTROLLERS:
        raise ValueError(f"controller must be one of {sorted(CONTROLLERS)}; got {name!r}")
    return name


def evaluate(problem: Problem, controller: str = "aware", n_trials: int = 1000, seed: int = 0, *,
             options: Optional[Options] = None, substeps: int = 1, u_init=None) -> ControllerResult:
    """Designs one controller for ``problem`` and runs it ``n_trials`` times on ``problem``'s plant.

    Args:
        problem: the (delayed, possibly noisy) plant.
        controller: "aware", "ignorant" or "augmented" (see `CONTROLLERS`).
        n_trials: Monte Carlo trials, passed to [`simulate`][delayed_ilqr.simulate].
        seed: the seed of the Monte Carlo noise.
        substeps: Euler-Maruyama sub-steps per control step.
        options: solver options; default ``Options()`` (``method`` is forced to "augmented" for the
            augmented controller).
        u_init: initial commands [K, d] for the solve (default: the model's, ``metadata.u_init``;
            zeros for a plant without one).

    Returns:
        A [`ControllerResult`][delayed_ilqr.experiments.delay_study.ControllerResult].
    """
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
    design, options = designs.design(problem, _controller(controller), options)
    if u_init is None:
        u_init = default_u_init(design)
    sol, solve_time, first = timed_solve(design, options, u_init)
    trials = monte_carlo(problem, sol.policy, n_trials, seed, substeps)
    label, unit = endpoint_description(problem)
    status = Status(int(sol.status))
    bound = divergence_bound(problem)
    delay, delay_steps = delay_values(problem)
    diverged = diverged_trials(trials.runs.cost, bound)
    return ControllerResult(
        model=problem.name, delay=delay, delay_steps=delay_steps, noise=problem.noise is not None,
        controller=controller, converged=bool(status.converged), status=status.name, message=status.message,
        iterations=int(sol.iterations), solve_time=solve_time, first_solve_time=first,
        nominal_cost=float(sol.cost), predicted_cost=float(sol.expected_cost), cost=sample_stats(trials.runs.cost, diverged),
        endpoint_error=sample_stats(trials.errors, diverged), divergence_bound=bound, endpoint_label=label,
        endpoint_unit=unit, summary=summarize(trials.runs.cost, trials.runs.x[:, -1], bound), n_trials=int(n_trials), seed=int(seed), substeps=int(substeps),
        problem=problem, solution=sol, runs=trials.runs)


def _factory(model) -> Callable:
    if isinstance(model, str):
        from ..models import REGISTRY
        if model not in REGISTRY:
            raise ValueError(f"model must be one of {sorted(REGISTRY)} or a factory; got {model!r}")
        return REGISTRY[model].factory
    if callable(model):
        return model
    raise TypeError(f"model must be a model name or a factory(delay=..., noise=...) -> Problem; "
                    f"got {type(model).__name__}")


def _delays(delays) -> list[float]:
    if isinstance(delays, (str, bytes)) or not hasattr(delays, "__iter__"):
        raise TypeError(f"delays must be a sequence of delays in seconds; got {delays!r}")
    out = []
    for tau in delays:
        if isinstance(tau, bool) or not isinstance(tau, (numbers.Real, np.integer, np.floating)) \
                or not math.isfinite(float(tau)) or float(tau) < 0:
            raise ValueError(f"delays must hold non-negative finite numbers of seconds; got {tau!r}")
        out.append(float(tau))
    if not out:
        raise ValueError("delays must hold at least one delay; got an empty sequence")
    return out


def _controllers(controllers) -> list[str]:
    controllers = list(controllers)
    for c in controllers:
        if c not in CONTROLLERS:
            raise ValueError(f"controllers must be among {sorted(CONTROLLERS)}; got {c!r}")
    if not controllers:
        raise ValueError("controllers must name at least one controller; got an empty sequence")
    return controllers


def compare_delays(model, delays: Sequence[float], n_trials: int = 1000, seed: int = 0, *, noise=True,
                   controllers: Sequence[str] = ("aware", "ignorant"), options: Optional[Options] = None,
                   substeps: int = 1, u_init=None, model_kwargs: Optional[dict] = None,
                   progress: bool = False, delay_frame=None) -> list[ControllerResult]:
    """For each delay, designs each controller and measures it by Monte Carlo on the delayed plant.

    Args:
        model: a name in [`delayed_ilqr.models.REGISTRY`][delayed_ilqr.models.REGISTRY] or a factory
            ``factory(delay=seconds, noise=bool, **model_kwargs) -> Problem``.
        delays: input delays tau in seconds (each a whole number of the model's steps).
        n_trials: Monte Carlo trials per controller and delay.
        seed: the seed of every Monte Carlo run (common random numbers across controllers).
        noise: the factory's ``noise``: True (the model's default noise, the human preset of the
            arms), False (the deterministic plant) or a preset's name (e.g. ``"benchmark"``).
        controllers: names in `CONTROLLERS`, in the order to report them.
        options: solver options (see [`evaluate`][delayed_ilqr.experiments.delay_study.evaluate]).
        substeps: Euler-Maruyama sub-steps per control step.
        u_init: initial commands for every solve, or a callable ``u_init(problem)`` (default: the
            model's, see [`evaluate`][delayed_ilqr.experiments.delay_study.evaluate]).
        model_kwargs: further keyword arguments of the factory (e.g. ``dt``).
        progress: show a ``tqdm`` progress bar on stderr (when it is a terminal, `progress`).
        delay_frame: None (each delay compiles its solvers and its Monte Carlo), an int L, or
            "auto" (L = the longest delay in steps, when the delays differ): every problem gets
            ``delay_frame=L``, so the delays share one compilation of each (docs/derivation.md §17). Results equal the
            unframed ones to round-off; ``first_solve_time`` then holds the compilation at the
            first delay only.

    Returns:
        A list of [`ControllerResult`][delayed_ilqr.experiments.delay_study.ControllerResult], delay-major in the order given.

    Raises:
        ValueError, TypeError: for an unknown model or controller, or a delay the factory refuses
            (e.g. not a whole number of steps); all problems are built before anything is solved.
    """
    factory = _factory(model)
    delays = _delays(delays)
    controllers = _controllers(controllers)
    kwargs = dict(model_kwargs or {})
    problems = [factory(delay=tau, noise=noise, **kwargs) for tau in delays]
    if delay_frame == "auto":
        delay_frame = shared_delay_frame(problems)
    if delay_frame is not None:
        problems = [p.replace(delay_frame=delay_frame) for p in problems]
    results = []
    with progress_bar(len(problems) * len(controllers), "delay study", "controller", progress) as bar:
        for problem in problems:
            init = u_init(problem) if callable(u_init) else u_init
            for c in controllers:
                bar.set_postfix_str(f"{delay_text(problem)}, {c}")
                results.append(evaluate(problem, c, n_trials, seed, options=options, substeps=substeps, u_init=init))
                bar.update()
    return results
