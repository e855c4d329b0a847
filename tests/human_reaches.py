"""Center-out reaches of the six-muscle arm's human preset, measured as a motor-control study does
(a test helper, also used by ``benchmarks/studies/center_out_human.py``).

For targets on a circle around the start hand position (any number, radius and starting angle),
the noise-aware design of ``arm2_muscle6(target=...)`` with its defaults (the human preset: motor
and sensory delay, proprioception, motor noise) is solved for all targets in one compiled,
vmapped call, and each target's policy runs ``n_trials`` times on the noisy plant. Everything
reported is measured on those Monte Carlo trials; the LQG's expected cost is reported beside the
Monte Carlo mean and labelled as the local (linearised) prediction.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.signal import find_peaks

from delayed_ilqr import Status
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS, PEAK_PROMINENCE, _solve, reach_shape
from delayed_ilqr.experiments.engine import monte_carlo, take
from delayed_ilqr.models.arm2_muscle6 import arm2_muscle6, center_out_targets
from delayed_ilqr.models.metadata import task_position


class Reach(NamedTuple):
    """One target's Monte Carlo (lengths in metres, angles in degrees).

    Attributes:
        direction: movement direction, counter-clockwise from +x; distance: start-target distance.
        status: the solver's status name.
        peaks, peak_to_mean: of the trial-mean hand speed profile (`reach_shape`'s definitions).
        single_peaked: fraction of trials whose own speed has one peak.
        trial_peak_to_mean: median over trials of peak / mean speed.
        deviation: largest lateral deviation of the trial-mean hand path over the distance (the
            average path, as published paths are).
        trial_deviation: median over trials of each trial's own deviation.
        sd_major, sd_minor: endpoint SDs along the principal axes of the endpoint covariance.
        angle: between the major axis and the movement direction, in [0, 90].
        orientation: of the major axis, counter-clockwise from +x, in [0, 180).
        bias: distance of the mean endpoint from the target.
        estimate_sd_major, estimate_orientation: SD along the major axis and its orientation (from
            +x, in [0, 180)) of the filter's hand error at the last command, e(x_{K-1}) - e(x_hat_{K-1})
            (x_hat the delayed Kalman filter's estimate the command u_{K-1} was computed from).
        estimate_share: fraction of the endpoint variance that this estimation error explains
            (multivariate linear regression of the endpoints on it; 0 without a filter).
        mc_cost, predicted_cost: Monte Carlo mean cost and the LQG's expected cost (linearised).
        at_bound: fraction of the nominal's (step, muscle) excitations at a bound (0 or 1).
        zero_rows: fraction of (step, muscle) rows of the state feedback that are exactly zero.
    """

    direction: float
    distance: float
    status: str
    peaks: int
    peak_to_mean: float
    single_peaked: float
    trial_peak_to_mean: float
    deviation: float
    trial_deviation: float
    sd_major: float
    sd_minor: float
    angle: float
    orientation: float
    bias: float
    estimate_sd_major: float
    estimate_orientation: float
    estimate_share: float
    mc_cost: float
    predicted_cost: float
    at_bound: float
    zero_rows: float


def center_out_reaches(n_targets=8, radius=0.1, start_angle=0.0, n_trials=200, seed=0, **model) -> list[Reach]:
    """The measured reaches to ``center_out_targets(n_targets, radius, start_angle=start_angle)``."""
    return reaches(center_out_targets(n_targets, radius, start_angle=start_angle), n_trials, seed, **model)


def reaches(targets, n_trials=200, seed=0, **model) -> list[Reach]:
    """The measured reaches from the start posture to ``targets`` [J, 2] (m), solved in one batch;
    target j's trials use seed + j. ``model``: extra arguments of ``arm2_muscle6`` (none: the
    human preset)."""
    plants = [arm2_muscle6(target=tuple(t), **model) for t in np.asarray(targets)]
    sols = _solve("noise-aware", plants, DEFAULT_OPTIONS).solution
    return [_measure(plant, take(sols, j), n_trials, seed + j) for j, plant in enumerate(plants)]


def _measure(plant, sol, n_trials: int, seed: int) -> Reach:
    trials = monte_carlo(plant, sol.policy, n_trials, seed)
    u = np.asarray(sol.u)
    x = np.asarray(trials.runs.x)                                   # [N, K+1, n]
    hand = np.asarray(task_position(plant, x))                      # [N, K+1, 2]
    start, target = hand[0, 0], np.asarray(plant.cost.params["target"])
    chord = target - start
    direction = np.arctan2(chord[1], chord[0])
    shapes = [reach_shape(plant, xi) for xi in x]
    path = hand.mean(axis=0) - start
    speed = np.linalg.norm(np.diff(hand, axis=1), axis=2).mean(axis=0) / plant.dt
    peaks, _ = find_peaks(np.concatenate([[0.0], speed, [0.0]]), prominence=PEAK_PROMINENCE * speed.max())
    ends = hand[:, -1]
    eigval, eigvec = np.linalg.eigh(np.cov(ends, rowvar=False))
    major = eigvec[:, -1]
    est = _estimation_error(plant, trials.runs, ends)
    angle = np.degrees(np.arccos(min(1.0, abs(np.cos(np.arctan2(major[1], major[0]) - direction)))))
    return Reach(direction=float(np.degrees(direction)), distance=float(np.linalg.norm(chord)),
                 status=Status(int(sol.status)).name, peaks=len(peaks), peak_to_mean=float(speed.max() / speed.mean()),
                 single_peaked=float(np.mean([s.peaks == 1 for s in shapes])),
                 trial_peak_to_mean=float(np.median([s.peak_to_mean for s in shapes])),
                 deviation=float(np.max(np.abs(path[:, 0] * chord[1] - path[:, 1] * chord[0])) / (chord @ chord)),
                 trial_deviation=float(np.median([s.deviation for s in shapes])),
                 sd_major=float(np.sqrt(eigval[-1])), sd_minor=float(np.sqrt(eigval[0])), angle=float(angle),
                 orientation=float(np.degrees(np.arctan2(major[1], major[0])) % 180.0),
                 bias=float(np.linalg.norm(ends.mean(axis=0) - target)), **est,
                 mc_cost=float(np.mean(np.asarray(trials.runs.cost))), predicted_cost=float(sol.expected_cost),
                 at_bound=float(np.mean((u <= np.asarray(plant.u_min)) | (u >= np.asarray(plant.u_max)))),
                 zero_rows=float(np.mean(np.all(np.asarray(sol.policy.state_feedback) == 0.0, axis=-1))))


def _estimation_error(plant, runs, ends) -> dict:
    """The filter's hand error at the last command (`Reach`'s estimate_* fields) and the share of the
    endpoint variance [N, 2] ``ends`` that it explains; NaN and 0 under full-state feedback."""
    if runs.x_hat is None:
        return dict(estimate_sd_major=float("nan"), estimate_orientation=float("nan"), estimate_share=0.0)
    err = np.asarray(task_position(plant, np.asarray(runs.x)[:, -2])) - np.asarray(task_position(plant, np.asarray(runs.x_hat)[:, -1]))
    cov = np.cov(np.hstack([ends, err]), rowvar=False)       # [4, 4]: endpoints, then errors
    c_ee, c_ye, c_yy = cov[2:, 2:], cov[:2, 2:], cov[:2, :2]
    explained = np.trace(c_ye @ np.linalg.solve(c_ee, c_ye.T)) / np.trace(c_yy)
    eigval, eigvec = np.linalg.eigh(c_ee)
    major = eigvec[:, -1]
    return dict(estimate_sd_major=float(np.sqrt(eigval[-1])),
                estimate_orientation=float(np.degrees(np.arctan2(major[1], major[0])) % 180.0),
                estimate_share=float(explained))


def markdown(reaches: list[Reach], label: str = "target") -> str:
    """A table of the reaches (mm and degrees)."""
    head = (f"| {label} | direction [deg] | distance [cm] | status | speed peaks (mean) | peak/mean (mean) | "
            "single-peaked trials | peak/mean (median trial) | path deviation (mean path) | path deviation (median trial) | "
            "endpoint SD major / minor [mm] | major axis vs movement [deg] | major axis from +x [deg] | "
            "filter's final hand error SD major [mm], from +x [deg] | endpoint variance it explains | "
            "MC mean cost / linearised prediction |")
    rows = [head, "|" + "---|" * 16]
    for j, r in enumerate(reaches, 1):
        rows.append(f"| {j} | {r.direction:.0f} | {100 * r.distance:.0f} | {r.status} | {r.peaks} | {r.peak_to_mean:.2f} | "
                    f"{100 * r.single_peaked:.0f} % | {r.trial_peak_to_mean:.2f} | {100 * r.deviation:.1f} % | "
                    f"{100 * r.trial_deviation:.1f} % | "
                    f"{1e3 * r.sd_major:.1f} / {1e3 * r.sd_minor:.1f} | {r.angle:.0f} | {r.orientation:.0f} | "
                    f"{1e3 * r.estimate_sd_major:.1f}, {r.estimate_orientation:.0f} | {100 * r.estimate_share:.0f} % | "
                    f"{r.mc_cost / r.predicted_cost:.2f} |")
    return "\n".join(rows)
