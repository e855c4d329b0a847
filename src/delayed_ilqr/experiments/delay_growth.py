"""Delay makes control worse, monotonically: the cost, the endpoint error and the endpoint scatter
of a reach against the motor delay (the sensory delay at the model's default) and against the
sensory delay (the motor delay at the model's default).

Expected (the seed paper's question, and the premise of every account of motor control by delayed
feedback; Beamish et al. 2006, Crevecoeur & Scott 2013): a longer delay leaves the controller less
recent information, so each of the three grows with each delay; the model's own local (linearised)
prediction must say so too.

The model: the gallery's reach (`reach_tasks.reach`, the model's defaults) to ``targets`` hand
targets; per delay pair the reaches to all targets are solved in one compiled, vmapped call and
each policy runs ``trials`` times on its plant with the same seed at every delay (common random
numbers, so that the differences between delays are not sampling noise).

Measured per delay pair (`DelayPoint`): the Monte Carlo cost (`SampleStats`: mean with its 95 %
interval, median), the median endpoint error and the endpoint scatter (the RMS distance of the
endpoints from their mean, sqrt(trace Cov)), pooled over the targets; beside them the **local
(linearised) prediction**: the solver's ``expected_cost`` and, with full-state feedback, the
endpoint RMS error and scatter of the linearised closed loop (`delayed_ilqr.prediction`; with
sensors only the cost is predicted, the linearised moments model full-state feedback only).
"""
from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import numpy as np

from .. import Options, Problem, Status
from ..prediction import predict, task_prediction
from ..statistics import SampleStats, divergence_bound, diverged_trials, sample_stats
from .delay_text import seconds
from .engine import monte_carlo, solve_batch, take
from .reach_tasks import MODEL_DEFAULT, loop_latency, reach, reach_targets, solver_options

__all__ = ["EXPECTED", "MOTOR_DELAYS", "SENSORY_DELAYS", "DelayPoint", "DelayGrowth", "monotone",
           "delay_growth_experiment", "comparison"]

#: (finding, source, expected) rows of the docs' table.
EXPECTED = (
    ("cost grows with the delay", "Bhushan & Shadmehr 1999; Crevecoeur & Scott 2013",
     "monotone increase with the motor and with the sensory delay"),
    ("endpoint error grows with the delay", "Beamish et al. 2006", "monotone increase"),
    ("endpoint scatter grows with the delay", "Beamish et al. 2006", "monotone increase"),
)

#: The default grids (s): each sweep holds the other delay at the model's default.
MOTOR_DELAYS = (0.0, 0.04, 0.08, 0.12)
SENSORY_DELAYS = (0.0, 0.04, 0.08, 0.12)


class DelayPoint(NamedTuple):
    """One delay pair, pooled over the targets.

    Attributes:
        delay, sensory_delay: motor and sensory delays (s; sensory None: the state is seen).
        loop_latency: their sum (s).
        cost: `SampleStats` of the Monte Carlo cost per trial.
        error_median: median endpoint error (m).
        scatter: RMS distance of the endpoints from their target's mean endpoint (m).
        predicted_cost: mean over the targets of the local (linearised) prediction ``expected_cost``.
        predicted_error, predicted_scatter: the linearised closed loop's RMS endpoint error and
            scatter (m), None with sensors.
        statuses: the solves' Status names.
    """

    delay: float
    sensory_delay: Optional[float]
    loop_latency: float
    cost: SampleStats
    error_median: float
    scatter: float
    predicted_cost: float
    predicted_error: Optional[float]
    predicted_scatter: Optional[float]
    statuses: tuple


class DelayGrowth(NamedTuple):
    """The two sweeps: ``motor`` (points over the motor delay) and ``sensory`` (over the sensory
    delay), and a representative ``problem`` (the model at its default delays, first target)."""

    motor: list
    sensory: list
    problem: Problem


def monotone(values) -> bool:
    """Whether ``values`` increase strictly from each to the next (None or NaN breaks it)."""
    v = [np.nan if x is None else float(x) for x in values]
    return bool(len(v) > 1 and np.all(np.isfinite(v)) and np.all(np.diff(v) > 0))


def _point(arm, targets, delay, sensory_delay, trials, seed, final_time, options) -> DelayPoint:
    problems = [reach(arm, t, delay=delay, sensory_delay=sensory_delay, final_time=final_time) for t in targets]
    sols = solve_batch(problems, solver_options(arm, options))
    costs, errors, deviations, p_err, p_scatter = [], [], [], [], []
    for j, p in enumerate(problems):
        trials_ = monte_carlo(p, take(sols.policy, j), trials, seed)
        cost = np.asarray(trials_.runs.cost)
        costs.append(np.where(diverged_trials(cost, divergence_bound(p)), np.inf, cost))
        errors.append(trials_.errors)
        deviations.append(trials_.endpoints - np.nanmean(trials_.endpoints, axis=0))
        if p.observation is None:
            hand = task_prediction(p, predict(p, take(sols, j)))
            bias = np.asarray(hand.mean[-1]) - np.asarray(p.cost.params["target"])
            spread = float(np.trace(np.asarray(hand.cov[-1])))
            p_err.append(bias @ bias + spread)
            p_scatter.append(spread)
    cost = np.concatenate(costs)
    dev = np.concatenate(deviations)
    p0 = problems[0]
    return DelayPoint(
        seconds(p0), None if p0.observation is None else p0.observation.delay_steps * p0.dt,
        loop_latency(p0), sample_stats(cost, ~np.isfinite(cost)), float(np.nanmedian(np.concatenate(errors))),
        float(np.sqrt(np.nanmean(np.sum(dev ** 2, axis=1)))), float(np.mean(np.asarray(sols.expected_cost))),
        float(np.sqrt(np.mean(p_err))) if p_err else None, float(np.sqrt(np.mean(p_scatter))) if p_scatter else None,
        tuple(Status(int(s)).name for s in np.atleast_1d(np.asarray(sols.status))))


def delay_growth_experiment(arm: str = "arm2_muscle6", motor_delays: Sequence[float] = MOTOR_DELAYS,
                            sensory_delays: Sequence[Optional[float]] = SENSORY_DELAYS, targets: int = 4,
                            trials: int = 100, seed: int = 0, final_time: float = 0.5,
                            options: Optional[Options] = None) -> DelayGrowth:
    """The two sweeps of the module docstring.

    Args:
        arm: "arm2" or "arm2_muscle6".
        motor_delays: motor delays (s) of the first sweep, at the model's default sensory delay.
        sensory_delays: sensory delays (s) of the second, at the model's default motor delay (empty:
            no second sweep).
        targets: hand targets on the 10 cm circle (`reach_tasks.reach_targets`), pooled.
        trials: Monte Carlo trials per target and delay pair (the same seed at every pair).
        seed: their seed.
        final_time: movement time (s).
        options: solver options (default `reach_tasks.solver_options`).
    """
    goals = reach_targets(targets, 0.1)
    run = lambda d, s: _point(arm, goals, d, s, trials, seed, final_time, options)      # noqa: E731
    motor = [run(d, MODEL_DEFAULT) for d in motor_delays]
    sensory = [run(MODEL_DEFAULT, s) for s in sensory_delays]
    return DelayGrowth(motor, sensory, reach(arm, goals[0], final_time=final_time))


def comparison(result: DelayGrowth) -> list[dict]:
    """Rows (finding, source, expected, measured) of the docs' table: per sweep, each quantity's values
    and whether they grow monotonically (Monte Carlo, then the linearised prediction)."""
    rows = []
    for name, points, key in (("motor delay", result.motor, "delay"), ("sensory delay", result.sensory,
                                                                         "sensory_delay")):
        if not points:
            continue
        grid = ", ".join("none" if getattr(p, key) is None else f"{1e3 * getattr(p, key):.0f}" for p in points)
        series = (("cost", [p.cost.mean for p in points], [p.predicted_cost for p in points], "{:.3g}", 1.0),
                  ("endpoint error", [p.error_median for p in points], [p.predicted_error for p in points],
                   "{:.2f}", 1e3),
                  ("endpoint scatter", [p.scatter for p in points], [p.predicted_scatter for p in points],
                   "{:.2f}", 1e3))
        for (finding, source, expected), (label, mc, pred, fmt, scale) in zip(EXPECTED, series):
            unit = "" if label == "cost" else " mm"
            text = ", ".join(fmt.format(scale * v) for v in mc)
            measured = (f"Monte Carlo {'mean' if label == 'cost' else 'median' if label == 'endpoint error' else 'RMS'}"
                        f" {text}{unit} at {grid} ms: {'monotone' if monotone(mc) else 'NOT monotone'}")
            if all(v is not None for v in pred):
                measured += (f"; linearised prediction {', '.join(fmt.format(scale * v) for v in pred)}{unit}: "
                             f"{'monotone' if monotone(pred) else 'NOT monotone'}")
            else:
                measured += "; linearised prediction: not available with sensors"
            rows.append(dict(finding=f"{finding} ({name})", source=source, published=expected, measured=measured))
    return rows
