"""Fitts' law: the model chooses its movement time as the shortest that meets an accuracy criterion;
is that time linear in the index of difficulty log2(2D/W), and how does it depend on the delay?

Published: movement time MT = a + b log2(2D/W) (Fitts 1954, J Exp Psychol 47:381: b about 100 ms/bit
for reciprocal tapping); in discrete aimed movements Schmidt, Zelaznik, Hawkins, Frank & Quinn 1979
(Psychol Rev 86:415) found the effective width proportional to D / MT; slopes of 100-200 ms/bit are
usual in pointing, and Beamish, Bhatti, MacKenzie & Wu 2006, cited by the seed
paper, explain the law by the feedback delay.

The model (after Harris & Wolpert 1998's account of Fitts' law by signal-dependent noise): a reach
of distance D (`reach_tasks.reach`, with the arm's signal-dependent motor noise and,
by default, delayed noisy proprioception) that must be on the target, at rest, from the movement
time T on (`reach_tasks.hold_from`). The reaches to every distance and movement time are
solved in **one compiled, vmapped call** (T and the target are cost parameters of one horizon), and
each runs ``trials`` times. A movement time meets the accuracy criterion for width W when the
endpoints at T lie within the target along the movement: |bias| + 4.133 SD / 2 <= W / 2 (the
effective width 4.133 SD, MacKenzie 1992). MT(D, W) is the shortest T that meets it
(`responses.shortest_meeting`, linear between the grid's times); MT = a + b ID is fitted by least
squares (`responses.fitts_fit`) over the conditions whose MT lies inside the grid: a condition met
already at the shortest time on the grid is censored (its MT is at most that time) and one never
met is NaN; both are left out of the fit.

**The floor.** The endpoint SD along the movement stops shrinking when more time is allowed: it is
the delayed filter's error in estimating the hand from noisy proprioception (with the state seen, the
same reaches scatter far less; measured in ``docs/gallery/fitts.md``), so a width below about 4.133
times that floor is never met. The default widths lie above it (`WIDTHS`); Fitts 1954's narrower
ones (`FITTS_1954_WIDTHS`) cost nothing more to judge on the same trials (`narrowest_width`).
"""
from __future__ import annotations

import itertools
from typing import NamedTuple, Optional, Sequence

import numpy as np

from .. import Options, Problem, Status
from ..models.arm2 import hand_position
from ..statistics import divergence_bound, diverged_trials, sample_stats
from .delay_text import delay_text, seconds
from .engine import monte_carlo, solve_batch, take
from .reach_tasks import MODEL_DEFAULT, hold_from, reach, reach_targets, solver_options
from .responses import EFFECTIVE_WIDTH_SD, FittsFit, fitts_fit, index_of_difficulty, shortest_meeting

__all__ = ["PUBLISHED", "SLOPE_RANGE", "DISTANCES", "WIDTHS", "FITTS_1954_WIDTHS", "MOVEMENT_TIMES", "FittsResult",
           "effective_width", "criterion_margin", "narrowest_width", "fitts_experiment", "comparison"]

PUBLISHED = (
    ("MT linear in log2(2D/W)", "Fitts 1954", "MT = a + b ID, b about 0.1 s/bit (tapping)"),
    ("slope in discrete pointing", "Fitts 1954; Schmidt et al. 1979; MacKenzie 1992", "b = 0.1-0.2 s/bit"),
    ("delay as a cause", "Beamish, Bhatti, MacKenzie & Wu 2006", "longer feedback delay, longer MT"),
)

#: The default grid: Fitts 1954's amplitudes (reciprocal tapping: A = 2, 4, 8, 16 in) with 12 in in place
#: of 16 in (41 cm to the right of the start would bring the arm to full extension; 30 cm is the upper end
#: of arm-scale discrete pointing), in metres; the widths 1, 1.5 and 2 in, those of Fitts 1954's widths
#: (0.25, 0.5, 1, 2 in, `FITTS_1954_WIDTHS`) that lie above the narrowest the model can meet at its
#: default delays (`narrowest_width`, the floor of the module docstring), with 1.5 in added to make
#: three; and the movement times (s) the model chooses from.
INCH = 0.0254
DISTANCES = tuple(round(a * INCH, 6) for a in (2, 4, 8, 12))
WIDTHS = tuple(round(w * INCH, 6) for w in (1, 1.5, 2))
FITTS_1954_WIDTHS = tuple(round(w * INCH, 6) for w in (0.25, 0.5, 1, 2))
MOVEMENT_TIMES = (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6)

#: The published range of the slope b (s/bit) that the docs compare with.
SLOPE_RANGE = (0.1, 0.2)


class FittsResult(NamedTuple):
    """One delay of the experiment.

    Attributes:
        delay, sensory_delay: motor and proprioceptive delays (s; sensory None: the state is seen).
        distances [D], widths [W], movement_times [T] (s): the grid.
        bias [D, T], sd [D, T]: mean and SD (m) of the endpoint along the movement at T.
        status [D, T]: the solves' Status names.
        mt [D, W]: the chosen movement time (s), NaN where no T on the grid meets the criterion.
        index [D, W]: log2(2D/W) (bits); fit: the `responses.FittsFit` over finite MT.
        mc_cost [D, T]: Monte Carlo mean cost; predicted_cost [D, T]: the local (linearised) prediction.
        problem: the first condition's problem (its record).
    """

    delay: float
    sensory_delay: Optional[float]
    distances: np.ndarray
    widths: np.ndarray
    movement_times: np.ndarray
    bias: np.ndarray
    sd: np.ndarray
    status: np.ndarray
    mt: np.ndarray
    index: np.ndarray
    fit: Optional[FittsFit]
    mc_cost: Optional[np.ndarray] = None
    predicted_cost: Optional[np.ndarray] = None
    problem: Optional[Problem] = None


def effective_width(bias, sd) -> np.ndarray:
    """4.133 SD + 2 |bias| (m): the narrowest target, centred on the aim, that holds the endpoints by the
    criterion of the module docstring."""
    return EFFECTIVE_WIDTH_SD * np.asarray(sd) + 2 * np.abs(bias)


def criterion_margin(bias, sd, width) -> np.ndarray:
    """W / 2 - (|bias| + 4.133 SD / 2): >= 0 where the endpoints lie within the width (module docstring)."""
    return 0.5 * (np.asarray(width) - effective_width(bias, sd))


def narrowest_width(result: "FittsResult") -> np.ndarray:
    """[D] the effective width (m) at the grid's longest movement time, where the endpoint SD has
    stopped shrinking: the narrowest width met on the grid (`shortest_meeting` gives NaN for any
    narrower one)."""
    return effective_width(result.bias[:, -1], result.sd[:, -1])


def fitts_experiment(arm: str = "arm2", distances: Sequence[float] = DISTANCES, widths: Sequence[float] = WIDTHS,
                     movement_times: Sequence[float] = MOVEMENT_TIMES,
                     delays: Sequence = (MODEL_DEFAULT, 0.12), sensory_delay=MODEL_DEFAULT,
                     hold: float = 0.1, trials: int = 100, seed: int = 0, direction: float = 0.0,
                     options: Optional[Options] = None) -> list[FittsResult]:
    """Runs the experiment of the module docstring, one `FittsResult` per motor delay.

    Args:
        arm: "arm2" or "arm2_muscle6".
        distances: movement distances (m).
        widths: target widths (m).
        movement_times: the grid of movement times (s, increasing) the model chooses from.
        delays: motor delays (s, or `reach_tasks.MODEL_DEFAULT`: the model's), one result each.
        sensory_delay: proprioceptive delay (s), None (the state is seen) or the model's default.
        hold: how long (s) the hand must stay on the target after T; the horizon is max(T) + hold.
        trials: Monte Carlo trials per (distance, movement time).
        seed: their seed (condition n uses seed + n).
        direction: of the movement (radians from +x; 0: to the right of the start).
        options: solver options (default `reach_tasks.solver_options`).
    """
    ts = np.asarray(movement_times, dtype=float)
    if ts.ndim != 1 or ts.size < 2 or np.any(np.diff(ts) <= 0):
        raise ValueError(f"movement_times must be at least 2 increasing times (s); got {movement_times!r}")
    ds, ws = np.asarray(distances, dtype=float), np.asarray(widths, dtype=float)
    final_time = float(ts[-1] + hold)
    results = []
    for delay in delays:
        grid = list(itertools.product(range(ds.size), range(ts.size)))
        problems = [hold_from(reach(arm, reach_targets(1, ds[i], start_angle=direction)[0], delay=delay,
                                    final_time=final_time, sensory_delay=sensory_delay), ts[j], hold)
                    for i, j in grid]
        sols = solve_batch(problems, solver_options(arm, options))
        bias, sd = np.full((ds.size, ts.size), np.nan), np.full((ds.size, ts.size), np.nan)
        status = np.empty((ds.size, ts.size), dtype=object)
        mc_cost = np.full((ds.size, ts.size), np.nan)
        unit = np.array([np.cos(direction), np.sin(direction)])
        for n, (i, j) in enumerate(grid):
            p = problems[n]
            runs = monte_carlo(p, take(sols.policy, n), trials, seed + n).runs
            k = int(round(ts[j] / p.dt))
            hand = np.asarray(hand_position(np.asarray(runs.x[:, k, :2])))
            along = (hand - np.asarray(p.cost.params["target"])) @ unit
            bias[i, j], sd[i, j] = float(np.mean(along)), float(np.std(along, ddof=1))
            status[i, j] = Status(int(sols.status[n])).name
            cost = np.asarray(runs.cost)
            mc_cost[i, j] = sample_stats(cost, diverged_trials(cost, divergence_bound(p))).mean
        mt = np.array([[shortest_meeting(ts, criterion_margin(bias[i], sd[i], w)) for w in ws]
                       for i in range(ds.size)])
        index = index_of_difficulty(ds[:, None], ws[None, :])
        inside = np.where(mt > ts[0], mt, np.nan)          # censored at the grid's shortest time: left out
        try:
            fit = fitts_fit(index, inside)
        except ValueError:
            fit = None
        predicted = np.asarray(sols.expected_cost, dtype=float).reshape(ds.size, ts.size)
        p0 = problems[0]
        results.append(FittsResult(seconds(p0), None if p0.observation is None
                                   else p0.observation.delay_steps * p0.dt, ds, ws, ts, bias, sd, status, mt, index,
                                   fit, mc_cost, predicted, p0))
    return results


def comparison(results: list) -> list[dict]:
    """Rows (finding, source, published, measured) of the docs' table: the fit at each delay, and the
    narrowest width the model meets (`narrowest_width`)."""
    rows = []
    for r in results:
        n_met = int(np.count_nonzero(r.mt > r.movement_times[0]))
        fit = "no fit (fewer than 3 conditions met the criterion)" if r.fit is None else \
            f"MT = {1e3 * r.fit.a:.0f} ms + {1e3 * r.fit.b:.0f} ms/bit x ID, R^2 = {r.fit.r2:.2f}"
        rows.append(dict(finding=f"motor delay {delay_text(r.delay)}", source="Fitts 1954; MacKenzie 1992",
                         published="MT linear in ID, b = 100-200 ms/bit",
                         measured=f"{fit} ({n_met} of {r.mt.size} conditions inside the grid; "
                                  f"mean MT {1e3 * np.nanmean(r.mt):.0f} ms)"))
        floor = 1e3 * narrowest_width(r)
        rows.append(dict(finding=f"narrowest width met, motor delay {delay_text(r.delay)}", source="Fitts 1954",
                         published="0.25 in (6.35 mm) met at every amplitude",
                         measured=f"{floor.min():.1f}-{floor.max():.1f} mm (the effective width at "
                                  f"T = {r.movement_times[-1]:g} s, D = {1e2 * r.distances.min():g}-"
                                  f"{1e2 * r.distances.max():g} cm)"))
    return rows
