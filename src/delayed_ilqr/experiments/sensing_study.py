"""The sensory-delay study: expected cost, endpoint spread and correction latency
against the sensory delay at a fixed motor delay, for the estimator-based design and for one that
ignores the sensory delay.

Per sensory delay l_s the plant is the model with its default sensors l_s late
(``sensory_delay=``). Both designs share iLQG's controller (the full-state design at the same
nominal); they differ in the filter:

* ``aware``: the delayed Kalman filter designed for l_s ([`solve`][delayed_ilqr.solve] on the plant);
  its ``expected_cost`` is exact on the linearisation;
* ``ignorant``: the Kalman filter designed for l_s = 0, run on the delayed sensors, so that it
  takes y_k for a measurement of x_k (no exact cost: only the Monte Carlo).

Both run the same trials (same seed: common motor and sensory noise) with and without a lateral
kick of the hand (`perturbation`), which gives the latency of the first command that
responds and of the half-peak of the mean command response. (The first command that *can* respond
is u_{kp+1+l_s} for both designs; with the muscles' limits 0 <= u <= 1 a response that every trial
clips away shows up later.)
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional, Sequence

import numpy as np

from .. import Observation, Options, Problem, Runs, Solution, simulate, solve
from ..models import REGISTRY
from ..models.metadata import default_u_init, task_position, task_target
from .perturbation import first_response, lateral_kick

__all__ = ["SensingResult", "sensory_delay_study", "study_rows", "study_warnings", "DESIGNS"]

DESIGNS = ("aware", "ignorant")


class SensingResult(NamedTuple):
    """One design at one sensory delay.

    Attributes:
        sensory_delay: seconds; design: "aware" or "ignorant"; problem: the plant;
        solution: the design's solve (its policy runs on the plant);
        expected_cost: the local (linearised) prediction of E[J], exact on the linearisation
            (aware), else None;
        runs, kicked: Monte Carlo without and with the kick (same seed);
        endpoint_sd: RMS distance of the final task positions from their mean (task units);
        endpoint_error: mean distance of the final task positions from the target;
        latency_s, half_s: first response and half-peak of the mean command response, seconds
        after the kick (None when none).
    """

    sensory_delay: float
    design: str
    problem: Problem
    solution: Solution
    expected_cost: Optional[float]
    runs: Runs
    kicked: Runs
    endpoint_sd: float
    endpoint_error: float
    latency_s: Optional[float]
    half_s: Optional[float]


def _ignoring_the_delay(problem: Problem) -> Problem:
    """The design problem of a filter that takes y_k for a measurement of x_k."""
    obs = problem.observation
    return problem.replace(observation=Observation(obs.output_fn or obs.H, obs.noise_fn or obs.G, 0))


def sensory_delay_study(sensory_delays: Sequence[float], delay: float = 0.05, model: str = "arm2_muscle6",
                        trials: int = 200, seed: int = 0, kick: float = 0.2, pulse_time: float = 0.15,
                        designs: Sequence[str] = DESIGNS, model_kwargs=None,
                        options: Optional[Options] = None) -> list[SensingResult]:
    """The study of the module docstring (``model`` a registry name whose factory takes
    ``sensory_delay``; ``delay`` the motor delay in seconds; ``options`` those of every solve)."""
    results = []
    for ls in sensory_delays:
        plant = REGISTRY[model].factory(delay=delay, sensory_delay=ls, **(model_kwargs or {}))
        kp = int(round(pulse_time / plant.dt))
        for design in designs:
            design_problem = plant if design == "aware" else _ignoring_the_delay(plant)
            sol = solve(design_problem, u_init=default_u_init(plant), options=options)
            W = lateral_kick(plant, np.asarray(sol.x), kp, kick)
            runs = simulate(plant, sol.policy, trials, seed=seed)
            kicked = simulate(plant, sol.policy, trials, seed=seed, disturbance=W)
            ends = task_position(plant, np.asarray(runs.x[:, -1]))
            ends = ends[np.all(np.isfinite(ends), axis=1)]
            spread = float(np.sqrt(np.mean(np.sum((ends - ends.mean(0)) ** 2, axis=1))))
            error = float(np.mean(np.linalg.norm(ends - task_target(plant), axis=1)))
            first, half = first_response(runs, kicked)
            after = lambda k: None if k is None else plant.dt * (k - kp)       # noqa: E731
            results.append(SensingResult(float(ls), design, plant, sol,
                                         float(sol.expected_cost) if design == "aware" else None, runs, kicked,
                                         spread, error, after(first), after(half)))
    return results


def study_rows(results: Sequence[SensingResult]) -> list[dict]:
    """One record per (sensory delay, design): the numbers of the study's table; the Monte Carlo
    cost as its mean with the bootstrap 95 % interval and its median (`tables.mc_record`),
    beside the local (linearised) prediction (None for the ignorant design, which has none)."""
    from ..statistics import divergence_bound, diverged_trials, sample_stats
    from .tables import PREDICTED, mc_record
    rows = []
    for r in results:
        cost = np.asarray(r.runs.cost)
        st = sample_stats(cost, diverged_trials(cost, divergence_bound(r.problem)))
        rows.append({"sensory delay [ms]": 1000 * r.sensory_delay, "design": r.design,
                     "status": str(r.solution.status), PREDICTED: r.expected_cost, **mc_record(st),
                     "endpoint SD [mm]": 1000 * r.endpoint_sd, "endpoint error [mm]": 1000 * r.endpoint_error,
                     "first response [ms]": None if r.latency_s is None else 1000 * r.latency_s,
                     "half-peak [ms]": None if r.half_s is None else 1000 * r.half_s})
    return rows


def study_warnings(results: Sequence[SensingResult]) -> list[str]:
    """One line per (sensory delay, design) whose Monte Carlo mean cost departs from its local
    prediction by more than the factor (`prediction_warning`)."""
    from ..statistics import prediction_warning
    from .tables import PREDICTED
    lines = [prediction_warning(f"{row['design']} at sensory delay {row['sensory delay [ms]']:g} ms",
                                math.nan if row["MC J mean"] is None else row["MC J mean"], row[PREDICTED])
             for row in study_rows(results)]
    return [w for w in lines if w]
