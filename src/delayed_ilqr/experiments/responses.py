"""Analysis functions of the gallery: response onsets, endpoint ellipses and Fitts' law fits.

Each takes plain arrays (the experiments' Monte Carlo, or synthetic data in the tests) and returns
numbers; none runs a solve.

**Detection rule of a response** (`first_change`, `onset`). A perturbed run and an
unperturbed one share their noise samples (the same seed), so their difference is the response
alone, zero until the perturbation can act. `first_change` is the first sample at which that
difference is non-zero in some trial (beyond round-off: ``tol`` times its largest magnitude);
`onset` is the first sample at which the magnitude of the *mean* difference reaches
``threshold`` (default 10 %) of its peak, the rule used for human EMG and kinematic latencies
(a fixed fraction of the peak response).
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional, Sequence

import numpy as np

__all__ = ["ONSET_THRESHOLD", "first_change", "onset", "Ellipse", "ellipse", "axis_sd", "FittsFit", "fitts_fit",
           "index_of_difficulty", "EFFECTIVE_WIDTH_SD", "shortest_meeting", "believed_fraction"]

#: The fraction of the peak mean response at which `onset` detects it.
ONSET_THRESHOLD = 0.1

#: The effective target width in standard deviations of the endpoints along the movement
#: (MacKenzie 1992: W_e = 4.133 SD, the width holding 96 % of a normal scatter).
EFFECTIVE_WIDTH_SD = 4.133


def _magnitude(diff) -> np.ndarray:
    d = np.asarray(diff, dtype=np.float64)
    return np.abs(d) if d.ndim == 1 else np.linalg.norm(d.reshape(d.shape[0], -1), axis=1)


def first_change(diff, start: int = 0, tol: float = 1e-9) -> Optional[int]:
    """The first index k >= ``start`` at which the difference is non-zero in some trial.

    Args:
        diff: [N, K, ...] perturbed minus unperturbed (same noise) per trial, or [K, ...] one run.
        start: the first index searched.
        tol: round-off: a change counts when it exceeds ``tol`` times the largest |diff|.

    Returns:
        The index, or None when nothing changes.
    """
    d = np.abs(np.asarray(diff, dtype=np.float64))
    if d.ndim == 1:
        d = d[None, :]
    per_step = d.reshape(d.shape[0], d.shape[1], -1).max(axis=(0, 2))
    peak = float(per_step.max()) if per_step.size else 0.0
    if peak == 0:
        return None
    hits = np.flatnonzero(per_step[start:] > tol * peak)
    return int(hits[0]) + start if hits.size else None


def onset(mean_diff, start: int = 0, threshold: float = ONSET_THRESHOLD) -> Optional[int]:
    """The first index k >= ``start`` at which |mean_diff_k| reaches ``threshold`` x its peak over
    k >= start (module docstring).

    Args:
        mean_diff: [K] or [K, d] the mean response (a vector's magnitude is its Euclidean norm).
        start: the first index searched (e.g. the perturbation's step).
        threshold: fraction of the peak, in (0, 1].

    Returns:
        The index, or None when the response is zero.
    """
    if not 0 < threshold <= 1:
        raise ValueError(f"threshold must lie in (0, 1]; got {threshold!r}")
    m = _magnitude(mean_diff)[start:]
    peak = float(m.max()) if m.size else 0.0
    if peak == 0:
        return None
    return int(np.flatnonzero(m >= threshold * peak)[0]) + start


def believed_fraction(true_shift, believed_shift, k: int) -> float:
    """How much of a perturbation a filter believes at sample k: the projection of the mean shift
    of its estimate ``believed_shift`` [K, m] on the mean shift of the true state ``true_shift``
    [K, m] (perturbed minus unperturbed, same noise), over the latter's squared length (1: all of
    it; NaN where the true shift is zero)."""
    t, b = np.asarray(true_shift, dtype=np.float64)[k], np.asarray(believed_shift, dtype=np.float64)[k]
    norm = float(t @ t)
    return float(b @ t) / norm if norm > 0 else math.nan


class Ellipse(NamedTuple):
    """The 1-sigma ellipse of a 2-D covariance: ``major``, ``minor`` standard deviations along the
    principal axes and ``angle`` of the major axis (radians, counter-clockwise from +x, in
    (-pi/2, pi/2])."""

    major: float
    minor: float
    angle: float


def ellipse(cov) -> Ellipse:
    """The `Ellipse` of a [2, 2] covariance."""
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (2, 2) or not np.all(np.isfinite(c)):
        raise ValueError(f"cov must be a finite [2, 2] covariance; got shape {c.shape}")
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    major = v[:, 1]
    angle = math.atan2(major[1], major[0])
    if angle <= -math.pi / 2:
        angle += math.pi
    elif angle > math.pi / 2:
        angle -= math.pi
    return Ellipse(float(np.sqrt(max(w[1], 0.0))), float(np.sqrt(max(w[0], 0.0))), float(angle))


def axis_sd(points, direction) -> float:
    """Standard deviation (ddof = 1) of the points [N, 2] projected on the unit ``direction`` [2]."""
    d = np.asarray(direction, dtype=np.float64)
    return float(np.std(np.asarray(points, dtype=np.float64) @ (d / np.linalg.norm(d)), ddof=1))


def index_of_difficulty(distance, width) -> np.ndarray:
    """Fitts' index of difficulty log2(2 D / W) in bits (Fitts 1954)."""
    return np.log2(2 * np.asarray(distance, dtype=np.float64) / np.asarray(width, dtype=np.float64))


class FittsFit(NamedTuple):
    """MT = a + b ID by least squares: ``a`` (s), ``b`` (s/bit), ``r2`` the coefficient of determination."""

    a: float
    b: float
    r2: float


def fitts_fit(index, movement_time) -> FittsFit:
    """The least-squares line MT = a + b ID through finite pairs (at least 3, two distinct IDs)."""
    x, y = np.asarray(index, dtype=np.float64).ravel(), np.asarray(movement_time, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"index and movement_time must have the same size; got {x.size} and {y.size}")
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    if x.size < 3 or np.ptp(x) == 0:
        raise ValueError(f"a Fitts fit needs at least 3 finite pairs with distinct indices; got {x.size}")
    b, a = np.polyfit(x, y, 1)
    ss_res = float(np.sum((y - (a + b * x)) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return FittsFit(float(a), float(b), 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0)


def shortest_meeting(times: Sequence[float], margin) -> float:
    """The shortest time at which ``margin`` (criterion met where >= 0) becomes and stays
    non-negative, interpolated linearly between the grid ``times`` [T] (increasing); NaN when the
    criterion is not met at the longest time, ``times[0]`` when it is met throughout."""
    t, m = np.asarray(times, dtype=np.float64), np.asarray(margin, dtype=np.float64)
    if t.shape != m.shape or t.ndim != 1:
        raise ValueError(f"times and margin must be 1-D of one size; got {t.shape} and {m.shape}")
    if not m[-1] >= 0:
        return math.nan
    failing = np.flatnonzero(~(m >= 0))
    if failing.size == 0:
        return float(t[0])
    i = int(failing[-1])              # the last failing time; i + 1 meets it and every later one does
    return float(t[i] + (t[i + 1] - t[i]) * (-m[i]) / (m[i + 1] - m[i])) if math.isfinite(m[i]) else float(t[i + 1])
