"""Minimal intervention (Todorov & Jordan 2002; Knill, Bondada & Chhabra 2011): with a bar target,
the endpoints scatter more along the bar (task-irrelevant) than across it (task-relevant).

Published: optimal feedback control corrects only task-relevant errors, so variability is larger
along task-irrelevant directions (Todorov & Jordan 2002, Nat Neurosci 5:1226); subjects corrected
"almost twice as much" for perturbations along the narrow dimension of a target as along its long
dimension (Knill et al. 2011, J Neurosci 31:1219).

The model: the same reach (`reach_tasks.reach`) with a point target and with a bar target
through the same point, the bar perpendicular to the movement (`reach_tasks.bar_target`:
only the error along the movement costs), each designed and run on the same noise. Measured
(`analyse`): the endpoint SD across the movement (the bar's long, task-irrelevant direction)
over the SD along it (task-relevant), for both targets, and the endpoint ellipses.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

from .. import Options, Problem, solve
from ..models.metadata import default_u_init
from .engine import monte_carlo
from .reach_tasks import MODEL_DEFAULT, bar_target, movement_direction, reach, solver_options
from .responses import Ellipse, axis_sd, ellipse

__all__ = ["PUBLISHED", "TargetScatter", "analyse", "minimal_intervention_experiment", "comparison"]

PUBLISHED = (
    ("task-irrelevant / task-relevant variability", "Todorov & Jordan 2002", "> 1, about 2 (bar target)"),
    ("corrections across / along the narrow dimension", "Knill, Bondada & Chhabra 2011", "about 2x"),
)


class TargetScatter(NamedTuple):
    """Endpoint scatter of one target (metres): ``irrelevant`` SD along the bar direction (across the
    movement), ``relevant`` SD along the movement, their ``ratio``, the `responses.Ellipse`,
    the endpoints [N, 2], the solver status and the problem."""

    name: str
    irrelevant: float
    relevant: float
    ratio: float
    ellipse: Ellipse
    endpoints: np.ndarray
    status: str
    problem: Problem
    mc_cost: Optional[np.ndarray] = None
    predicted_cost: float = float("nan")


def analyse(name: str, endpoints, bar_direction, status: str = "", problem=None, mc_cost=None,
            predicted_cost: float = float("nan")) -> TargetScatter:
    """The `TargetScatter` of endpoints [N, 2] with the bar along ``bar_direction`` [2]."""
    b = np.asarray(bar_direction, dtype=float)
    irrelevant = axis_sd(endpoints, b)
    relevant = axis_sd(endpoints, [-b[1], b[0]])
    return TargetScatter(name, irrelevant, relevant, irrelevant / relevant, ellipse(np.cov(np.asarray(endpoints).T)),
                         np.asarray(endpoints), status, problem, mc_cost, float(predicted_cost))


def minimal_intervention_experiment(arm: str = "arm2_muscle6", delay=MODEL_DEFAULT, sensory_delay=MODEL_DEFAULT,
                                    trials: int = 200, seed: int = 0, target=None, final_time: float = 0.5,
                                    options: Optional[Options] = None) -> list[TargetScatter]:
    """[point, bar]: the scatter of the two targets (module docstring); same noise for both.

    Args:
        arm: "arm2" or "arm2_muscle6".
        delay: motor delay (s); default the model's.
        sensory_delay: proprioceptive delay (s), None (the state is seen) or the model's default.
        trials: Monte Carlo trials per target (the same noise for both).
        seed: their seed.
        target: [2] the hand target (default 10 cm ahead).
        final_time: movement time (s).
        options: solver options (default `reach_tasks.solver_options`).
    """
    point = reach(arm, target, delay=delay, final_time=final_time, sensory_delay=sensory_delay)
    d = movement_direction(point)
    along_bar = np.array([-d[1], d[0]])
    out = []
    for name, problem in (("point", point), ("bar", bar_target(point, along_bar))):
        sol = solve(problem, u_init=default_u_init(problem), options=solver_options(arm, options))
        trials_ = monte_carlo(problem, sol.policy, trials, seed)
        out.append(analyse(name, trials_.endpoints, along_bar, str(sol.status), problem,
                           np.asarray(trials_.runs.cost), float(sol.expected_cost)))
    return out


def comparison(scatters: list) -> list[dict]:
    """Rows (finding, source, published, measured) of the docs' table."""
    point, bar = scatters

    def text(s):
        return f"{s.name}: SD across {1e3 * s.irrelevant:.2f} mm / along {1e3 * s.relevant:.2f} mm = {s.ratio:.2f}"

    return [dict(finding=PUBLISHED[0][0], source=PUBLISHED[0][1], published=PUBLISHED[0][2],
                 measured=f"{text(bar)}; {text(point)}; bar / point {bar.ratio / point.ratio:.2f}"),
            dict(finding=PUBLISHED[1][0], source=PUBLISHED[1][1], published=PUBLISHED[1][2],
                 measured="not measured (the model's feedback gains are in the policy; see the docs page)")]
