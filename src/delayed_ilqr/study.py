"""Delay studies: what ignoring the delay costs, measured by Monte Carlo on the nonlinear plant.

For each input delay tau the study builds the problem and evaluates controllers on the same
(delayed, possibly noisy) plant:

==========  =====================================================================================
aware       ``solve(problem)``: iLQG with the delay (Theorem 1, structured backward pass)
ignorant    ``solve(problem.replace(delay_steps=0))``: designed as if the commands acted at once,
            then run on the delayed plant (its policy has l_p = 0, see :func:`~delayed_ilqr.simulate`)
augmented   ``solve(problem, Options(method="augmented"))``: the state-augmentation reference
==========  =====================================================================================

Each policy is run ``n_trials`` times by :func:`~delayed_ilqr.simulate` with the same seed, so all
controllers at one delay see the same noise samples (common random numbers). A result reports the
controller's own prediction of its expected cost (``Solution.expected_cost`` of the problem it was
designed for: for the delay-ignorant controller, the plant without delay), the Monte Carlo cost
with 95 % intervals, the endpoint error (hand distance to the target for the arms, position
error for the point mass, else the norm of x_K - x_target), iterations and solve time.

Everything here returns plain data; printing, files and figures are the CLI's and :mod:`.plot`'s.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
import time
from typing import Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .problem import Problem, QuadraticCost
from .simulate import Runs, SampleStats, Summary, sample_stats, simulate
from .solution import Solution, Status
from .ilqg.solver import solve
from .options import Options

__all__ = ["CONTROLLERS", "ControllerResult", "evaluate", "compare_delays", "design_problem", "endpoint_error",
           "endpoint_description", "arm_kinematics", "timed_solve", "default_u_init", "format_table", "format_markdown", "to_records"]

CONTROLLERS = {
    "aware": "delay-aware iLQG (Theorem 1)",
    "ignorant": "delay-ignorant iLQG (designed for tau = 0, run on the delayed plant)",
    "augmented": "delay-aware iLQG by state augmentation (reference)",
}


@dataclasses.dataclass(frozen=True)
class ControllerResult:
    """One controller at one delay: solve diagnostics and Monte Carlo statistics.

    Attributes:
        model: the problem's name; delay: tau in seconds; delay_steps: l; noise: whether the plant
            is stochastic; controller: a key of :data:`CONTROLLERS`.
        converged, status, message, iterations: from the solve (``status`` is the Status name).
        solve_time: seconds for a solve once compiled; first_solve_time: the first call's seconds
            (compilation included, about zero when an equal-shaped problem was compiled before).
        nominal_cost: eq. (2) on the controller's nominal, noise-free trajectory (on the plant it was
            designed for).
        predicted_cost: ``Solution.expected_cost``, the controller's own prediction of E[J].
        cost: :class:`~delayed_ilqr.simulate.SampleStats` of the Monte Carlo cost on the delayed plant.
        endpoint_error: SampleStats of the final endpoint error (see :func:`endpoint_error`).
        endpoint_label, endpoint_unit: what the endpoint error measures, and in which unit.
        summary: the :class:`~delayed_ilqr.simulate.Summary` of the runs (final-state statistics).
        n_trials, seed, substeps: the Monte Carlo settings.
        problem, solution, runs: the plant, the :class:`~delayed_ilqr.Solution` and the
            :class:`~delayed_ilqr.Runs` (for figures and files; left out of :meth:`to_dict`).
    """

    model: str
    delay: float
    delay_steps: int
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


# ------------------------------------------------------------------------------------------------
# endpoint errors
# ------------------------------------------------------------------------------------------------

def arm_kinematics(problem: Problem):
    """(arm parameters, hand target [2] in m) for the two-link arms, or None for other models.

    Recognises ``models.arm2`` (target: the hand position of the target joint angles) and
    ``models.arm2_muscle6`` (target: ``cost.params["target"]``) by the problem's name.
    """
    from .models.arm2 import ARM2_PARAMS, hand_position
    if problem.name == "arm2" and isinstance(problem.cost, QuadraticCost):
        params = getattr(problem.dynamics, "params", ARM2_PARAMS)
        return params, np.asarray(hand_position(jnp.asarray(problem.cost.x_target[:2]), params))
    if problem.name == "arm2_muscle6":
        params = getattr(problem.cost.final_fn, "arm", ARM2_PARAMS)
        try:
            target = np.asarray(problem.cost.params["target"])
        except (TypeError, KeyError):
            return None
        return params, target
    return None


def endpoint_description(problem: Problem) -> tuple[str, str]:
    """(label, unit) of :func:`endpoint_error` for this problem."""
    if arm_kinematics(problem) is not None:
        return "hand position error", "m"
    if problem.name == "point_mass":
        return "position error", "m"
    return "final state error |x_K - x_target|", ""


def endpoint_error(problem: Problem, final_states) -> np.ndarray:
    """The distance of each final state [N, n] from the task's goal: [N].

    Arms: |hand(q_K) - hand target| in metres; point mass: |(px, py) - target| in metres; other
    models with a :class:`~delayed_ilqr.QuadraticCost`: |x_K - x_target| (mixed units); NaN otherwise.
    """
    x = np.asarray(final_states, dtype=np.float64)
    arm = arm_kinematics(problem)
    if arm is not None:
        from .models.arm2 import hand_position
        params, target = arm
        with np.errstate(invalid="ignore"):
            hand = np.asarray(hand_position(jnp.asarray(x[..., :2]), params))
        return np.linalg.norm(hand - target, axis=-1)
    if not isinstance(problem.cost, QuadraticCost):
        return np.full(x.shape[:-1], np.nan)
    target = np.asarray(problem.cost.x_target)
    if problem.name == "point_mass":
        return np.linalg.norm(x[..., :2] - target[:2], axis=-1)
    return np.linalg.norm(x - target, axis=-1)


# ------------------------------------------------------------------------------------------------
# evaluation
# ------------------------------------------------------------------------------------------------

def design_problem(problem: Problem, controller: str) -> tuple[Problem, Options]:
    """The problem and options a controller is designed with (the plant stays ``problem``)."""
    if controller not in CONTROLLERS:
        raise ValueError(f"controller must be one of {sorted(CONTROLLERS)}; got {controller!r}")
    design = Options()
    if controller == "ignorant":
        return problem.replace(delay_steps=0), design
    if controller == "augmented":
        return problem, dataclasses.replace(design, method="augmented")
    return problem, design


def default_u_init(problem: Problem):
    """The model's recommended warm start: rest excitations for ``arm2_muscle6`` (whose zero
    commands give a zero first step), else None (zeros)."""
    if problem.name == "arm2_muscle6":
        from .models import rest_commands
        return rest_commands(problem)
    return None


def timed_solve(problem: Problem, options: Optional[Options] = None, u_init=None) -> tuple[Solution, float, float]:
    """(solution, seconds of a compiled solve, seconds of the first call including compilation).

    Solves twice: the first call compiles (about free when an equal-shaped problem was solved
    before), the second is timed alone.
    """
    start = time.perf_counter()
    sol = jax.block_until_ready(solve(problem, u_init=u_init, options=options))
    first = time.perf_counter() - start
    start = time.perf_counter()
    sol = jax.block_until_ready(solve(problem, u_init=u_init, options=options))
    return sol, time.perf_counter() - start, first


def evaluate(problem: Problem, controller: str = "aware", n_trials: int = 1000, seed: int = 0, *,
             options: Optional[Options] = None, substeps: int = 1, u_init=None) -> ControllerResult:
    """Designs one controller for ``problem`` and runs it ``n_trials`` times on ``problem``'s plant.

    Args:
        problem: the (delayed, possibly noisy) plant.
        controller: "aware", "ignorant" or "augmented" (see :data:`CONTROLLERS`).
        n_trials, seed, substeps: passed to :func:`~delayed_ilqr.simulate`.
        options: solver options; default ``Options()`` (``method`` is forced to "augmented" for the
            augmented controller).
        u_init: initial commands [K, d] for the solve (default :func:`default_u_init`: zeros except
            for the muscle arm).

    Returns:
        A :class:`ControllerResult`.
    """
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
    design, default = design_problem(problem, controller)
    if options is None:
        options = default
    elif not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    elif controller == "augmented":
        options = dataclasses.replace(options, method="augmented")
    if u_init is None:
        u_init = default_u_init(design)
    sol, solve_time, first = timed_solve(design, options, u_init)
    runs = simulate(problem, sol.policy, n_trials, seed=seed, substeps=substeps)
    label, unit = endpoint_description(problem)
    status = Status(int(sol.status))
    return ControllerResult(
        model=problem.name, delay=problem.delay, delay_steps=problem.delay_steps, noise=problem.noise is not None,
        controller=controller, converged=bool(status.converged), status=status.name, message=status.message,
        iterations=int(sol.iterations), solve_time=solve_time, first_solve_time=first,
        nominal_cost=float(sol.cost), predicted_cost=float(sol.expected_cost), cost=sample_stats(runs.cost),
        endpoint_error=sample_stats(endpoint_error(problem, runs.x[:, -1])), endpoint_label=label,
        endpoint_unit=unit, summary=runs.summary(), n_trials=int(n_trials), seed=int(seed), substeps=int(substeps),
        problem=problem, solution=sol, runs=runs)


def _factory(model) -> Callable:
    if isinstance(model, str):
        from .models import REGISTRY
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


def compare_delays(model, delays: Sequence[float], n_trials: int = 1000, seed: int = 0, *, noise: bool = True,
                   controllers: Sequence[str] = ("aware", "ignorant"), options: Optional[Options] = None,
                   substeps: int = 1, u_init=None, model_kwargs: Optional[dict] = None,
                   progress: bool = False) -> list[ControllerResult]:
    """For each delay, designs each controller and measures it by Monte Carlo on the delayed plant.

    Args:
        model: a name in :data:`delayed_ilqr.models.REGISTRY` or a factory
            ``factory(delay=seconds, noise=bool, **model_kwargs) -> Problem``.
        delays: input delays tau in seconds (each a whole number of the model's steps).
        n_trials: Monte Carlo trials per controller and delay.
        seed: the seed of every Monte Carlo run (common random numbers across controllers).
        noise: build the stochastic plant (``noise=True``) or the deterministic one.
        controllers: keys of :data:`CONTROLLERS`, in the order to report them.
        options: solver options (see :func:`evaluate`).
        substeps: Euler-Maruyama sub-steps per control step.
        u_init: initial commands for every solve, or a callable ``u_init(problem)`` (default
            :func:`default_u_init`).
        model_kwargs: further keyword arguments of the factory (e.g. ``dt``).
        progress: show a ``tqdm`` progress bar on stderr.

    Returns:
        A list of :class:`ControllerResult`, delay-major in the order given.

    Raises:
        ValueError, TypeError: for an unknown model or controller, or a delay the factory refuses
            (e.g. not a whole number of steps); all problems are built before anything is solved.
    """
    factory = _factory(model)
    delays = _delays(delays)
    controllers = list(controllers)
    for c in controllers:
        if c not in CONTROLLERS:
            raise ValueError(f"controllers must be among {sorted(CONTROLLERS)}; got {c!r}")
    if not controllers:
        raise ValueError("controllers must name at least one controller; got an empty sequence")
    kwargs = dict(model_kwargs or {})
    problems = [factory(delay=tau, noise=noise, **kwargs) for tau in delays]
    from tqdm.auto import tqdm
    results = []
    with tqdm(total=len(problems) * len(controllers), disable=not progress, unit="controller",
              desc="delay study") as bar:
        for problem in problems:
            init = u_init(problem) if callable(u_init) else u_init
            for c in controllers:
                bar.set_postfix_str(f"tau={problem.delay:g} s, {c}")
                results.append(evaluate(problem, c, n_trials, seed, options=options, substeps=substeps, u_init=init))
                bar.update()
    return results


# ------------------------------------------------------------------------------------------------
# tables (strings only)
# ------------------------------------------------------------------------------------------------

def _num(value: float, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.{digits}g}"


def _unit_scale(unit: str) -> tuple[float, str]:
    return (1e3, "mm") if unit == "m" else (1.0, unit)


def _rows(results: Sequence[ControllerResult]) -> tuple[list[str], list[list[str]]]:
    scale, unit = _unit_scale(results[0].endpoint_unit) if results else (1.0, "")
    label = results[0].endpoint_label if results else "endpoint error"
    header = ["delay [s]", "controller", "converged", "iter", "solve [ms]", "predicted E[J]",
              "MC mean J [95% CI]", "MC median J", "diverged", f"{label}" + (f" [{unit}]" if unit else "")]
    rows = []
    for r in results:
        c, e = r.cost, r.endpoint_error
        mean = f"{_num(c.mean)} [{_num(c.ci95[0])}, {_num(c.ci95[1])}]" if math.isfinite(c.mean) else _num(c.mean)
        err = f"{_num(scale * e.mean, 3)} +- {_num(1.96 * scale * e.standard_error, 2)}" \
            if math.isfinite(e.mean) else f"median {_num(scale * e.median, 3)}"
        rows.append([f"{r.delay:g}", r.controller, "yes" if r.converged else "NO", str(r.iterations),
                     f"{1e3 * r.solve_time:.1f}", _num(r.predicted_cost), mean, _num(c.median),
                     f"{c.n_diverged}/{c.n}", err])
    return header, rows


def format_table(results: Sequence[ControllerResult]) -> str:
    """A plain-text table with aligned columns, one row per result."""
    header, rows = _rows(results)
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in rows]
    return "\n".join(line.rstrip() for line in lines)


def format_markdown(results: Sequence[ControllerResult]) -> str:
    """The same table in GitHub markdown."""
    header, rows = _rows(results)
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def to_records(results: Sequence[ControllerResult]) -> list[dict]:
    """``[r.to_dict() for r in results]``: JSON-ready records."""
    return [r.to_dict() for r in results]
