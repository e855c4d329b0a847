"""Statistics of Monte Carlo trials, with one definition of a diverged trial used everywhere.

A trial **diverged** when its cost is not finite (the closed loop blew up to inf or NaN) or exceeds
a bound: by default `DIVERGENCE_FACTOR` times the cost of not moving at all (the plant's cost
with every command zero, [`divergence_bound`][delayed_ilqr.statistics.divergence_bound]). A controller that does a hundred times worse
than doing nothing has lost control of the plant; its trial carries no information about the
controller's typical performance, and a single one makes a sample mean meaningless (a mean of
5.8e252 is a blow-up, not an expected cost). Tables, figures and JSON records all take the diverged
count from [`diverged_trials`][delayed_ilqr.statistics.diverged_trials], so they always agree.

Every statistic is then computed as follows ([`sample_stats`][delayed_ilqr.statistics.sample_stats]):

- the **mean** (and standard deviation, standard error) over the trials that did not diverge, with
  ``n_diverged`` reported next to it;
- its 95 % interval by a seeded percentile **bootstrap** of those trials: an interval of resampled
  means, so it lies within the range of the data and never has a negative bound for a positive
  cost (the normal approximation does, for heavy-tailed costs);
- the **median** and **inter-quartile range** over all trials, a diverged trial ranking as +inf
  (they stay finite while fewer than half, or a quarter, of the trials diverged), with the
  distribution-free 95 % interval of the median (order statistics).

The Monte Carlo is the measurement. ``Solution.expected_cost`` is the **local (linearised)
prediction** of E[J]: exact for the LQG approximation at the nominal, blind to the plant's
higher-order terms (``docs/results/noise_calibration.md``). Every study compares the two
(`prediction_warning`) and warns when the Monte Carlo mean departs from the prediction by
more than `PREDICTION_FACTOR` either way: the prediction then does not describe the trials.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .ilqg.linearize import rollout, trajectory_cost

__all__ = ["PREDICTION_FACTOR", "prediction_ratio", "prediction_warning", "DIVERGENCE_FACTOR", "BOOTSTRAP_RESAMPLES",
           "BOOTSTRAP_SEED", "divergence_bound", "diverged_trials",
           "SampleStats", "sample_stats", "Summary", "summarize"]

_Z95 = 1.959963984540054  # the 97.5 % quantile of the standard normal

#: A trial whose cost exceeds this multiple of the cost of not moving (all commands zero) diverged.
DIVERGENCE_FACTOR = 100.0

#: A study warns when its Monte Carlo mean cost is more than this factor above, or below 1 / this
#: factor of, the local (linearised) prediction ``Solution.expected_cost``.
PREDICTION_FACTOR = 2.0

#: Resamples of the bootstrap interval of a mean; its seed (the same data give the same interval).
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0


def prediction_ratio(mc_mean: float, predicted: float) -> float:
    """The Monte Carlo mean over the local (linearised) prediction; NaN where either is not finite
    or the prediction is not positive (no ratio is meaningful)."""
    mc_mean, predicted = float(mc_mean), float(predicted)
    if not (math.isfinite(mc_mean) and math.isfinite(predicted)) or predicted <= 0:
        return math.nan
    return mc_mean / predicted


def prediction_warning(label: str, mc_mean: float, predicted: Optional[float],
                       factor: float = PREDICTION_FACTOR) -> Optional[str]:
    """One line of warning when the Monte Carlo mean cost departs from the local prediction by
    more than ``factor`` either way (ratio > factor or < 1 / factor), else None.

    Args:
        label: what was measured, e.g. ``"aware at 100 ms"``; starts the sentence.
        mc_mean: the Monte Carlo mean cost (over the trials that did not diverge).
        predicted: the local (linearised) prediction E[J] (``Solution.expected_cost``); None for a
            design without one (no warning).
        factor: the tolerated ratio, > 1.

    Returns:
        ``"warning: <label>: Monte Carlo mean cost M is R x the local (linearised) prediction P ..."``,
        or None when the ratio lies within [1 / factor, factor]. A prediction that is not positive
        and finite against a finite mean warns too (it cannot describe the trials).
    """
    if not factor > 1:
        raise ValueError(f"factor must be greater than 1; got {factor!r}")
    if predicted is None or not math.isfinite(float(mc_mean)):
        return None
    ratio = prediction_ratio(mc_mean, predicted)
    if math.isfinite(ratio) and 1 / factor <= ratio <= factor:
        return None
    how = f"{ratio:.3g}x" if math.isfinite(ratio) else "not comparable with"
    return (f"warning: {label}: the Monte Carlo mean cost {float(mc_mean):.4g} is {how} the local (linearised) "
            f"prediction E[J] = {float(predicted):.4g} (more than {factor:g}x either way): the prediction does "
            "not describe these trials; trust the Monte Carlo")


def divergence_bound(problem) -> float:
    """The cost above which a trial of ``problem``'s plant counts as diverged.

    `DIVERGENCE_FACTOR` times the cost (eq. 2) of the noise-free Euler trajectory with every
    command zero, the cost of not moving at all. Where that cost is zero or not finite (a plant that
    starts at its target, or blows up by itself), no finite bound is meaningful and only non-finite
    costs count (``inf`` is returned).
    """
    rest = float(_rest_cost(problem))
    return DIVERGENCE_FACTOR * rest if math.isfinite(rest) and rest > 0 else math.inf


@jax.jit
def _rest_cost(problem):
    """The cost of all commands zero; compiled once per problem structure (an eager ``lax.scan``
    compiles its loop again on every call, a sweep's largest cost per cell)."""
    us = jnp.zeros((problem.horizon, problem.n_controls), problem.x0.dtype)
    return trajectory_cost(problem, rollout(problem, us), us)


def diverged_trials(cost, bound: float = math.inf) -> np.ndarray:
    """[N] bool: which trials diverged (cost not finite, or above ``bound``; see the module docstring)."""
    c = np.asarray(cost, dtype=np.float64).ravel()
    with np.errstate(invalid="ignore"):
        return ~np.isfinite(c) | (c > bound)


class SampleStats(NamedTuple):
    """Statistics of one per-trial quantity (a cost, an endpoint error) over N trials.

    Attributes:
        n: N.
        n_diverged: trials that diverged ([`diverged_trials`][delayed_ilqr.statistics.diverged_trials]), left out of the mean.
        mean: sample mean over the N - n_diverged other trials (NaN when every trial diverged).
        std: their sample standard deviation (ddof = 1; NaN for fewer than 2).
        standard_error: std / sqrt(N - n_diverged).
        ci95: (low, high), the seeded percentile-bootstrap 95 % interval of the mean (within the
            range of the data: positive for a positive quantity).
        median: sample median over all N trials, a diverged trial ranking as +inf.
        median_ci95: (low, high), its distribution-free 95 % interval (order statistics of ranks
            N/2 -/+ 1.96 sqrt(N)/2, clipped to the sample).
        iqr: (25th, 75th percentile) over all N trials, diverged ones as +inf.
    """

    n: int
    n_diverged: int
    mean: float
    std: float
    standard_error: float
    ci95: tuple
    median: float
    median_ci95: tuple
    iqr: tuple

    def to_dict(self) -> dict:
        """Plain Python types; non-finite numbers become ``None`` (strict JSON has no inf or NaN)."""
        return dict(n=int(self.n), n_diverged=int(self.n_diverged), mean=_json_float(self.mean),
                    std=_json_float(self.std), standard_error=_json_float(self.standard_error),
                    ci95=[_json_float(v) for v in self.ci95], median=_json_float(self.median),
                    median_ci95=[_json_float(v) for v in self.median_ci95], iqr=[_json_float(v) for v in self.iqr])


def _json_float(value):
    value = float(value)
    return value if math.isfinite(value) else None


def _bootstrap_ci(kept: np.ndarray) -> tuple:
    """Percentile-bootstrap 95 % interval of the mean of ``kept`` (seeded; chunked to bound memory)."""
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    m = kept.shape[0]
    chunk = max(1, 2_000_000 // m)
    means = np.concatenate([kept[rng.integers(0, m, (min(chunk, BOOTSTRAP_RESAMPLES - s), m))].mean(axis=1)
                            for s in range(0, BOOTSTRAP_RESAMPLES, chunk)])
    lo, hi = np.percentile(means, [2.5, 97.5])
    return float(lo), float(hi)


def sample_stats(values, diverged: Optional[np.ndarray] = None) -> SampleStats:
    """The [`SampleStats`][delayed_ilqr.statistics.SampleStats] of a 1-D sample [N].

    Args:
        values: [N] per-trial values.
        diverged: [N] bool, the trials that diverged (default: those whose value is not finite;
            pass [`diverged_trials`][delayed_ilqr.statistics.diverged_trials] of the costs to judge an endpoint error by the same trials).
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    n = v.shape[0]
    if n == 0:
        raise ValueError("values must hold at least one trial; got an empty array")
    bad = ~np.isfinite(v) if diverged is None else (np.asarray(diverged, dtype=bool).ravel() | ~np.isfinite(v))
    if bad.shape != v.shape:
        raise ValueError(f"diverged must have one entry per value ({n}); got shape {np.shape(diverged)}")
    kept = v[~bad]
    m = kept.shape[0]
    mean = float(np.mean(kept)) if m else math.nan
    with np.errstate(over="ignore", invalid="ignore"):
        std = float(np.std(kept, ddof=1)) if m > 1 else math.nan
    se = std / math.sqrt(m) if m else math.nan
    ci = _bootstrap_ci(kept) if m > 1 else (mean, mean)
    ranked = np.where(bad, np.inf, v)
    ordered = np.sort(ranked)
    half_width = _Z95 * math.sqrt(n) / 2
    lo = min(max(int(math.floor(n / 2 - half_width)), 1), n)     # 1-based ranks
    hi = min(max(int(math.ceil(n / 2 + half_width)), 1), n)
    # with diverged trials (+inf) a quantile is an order statistic (no inf - inf interpolation): it is
    # inf once that fraction of the trials diverged
    method = "inverted_cdf" if np.any(bad) else "linear"
    q25, q50, q75 = np.percentile(ranked, [25.0, 50.0, 75.0], method=method)
    return SampleStats(n=n, n_diverged=int(np.count_nonzero(bad)), mean=mean, std=std, standard_error=se, ci95=ci,
                       median=float(q50), median_ci95=(float(ordered[lo - 1]), float(ordered[hi - 1])),
                       iqr=(float(q25), float(q75)))


class Summary(NamedTuple):
    """Sample statistics of a Monte Carlo run (see [`summary`][delayed_ilqr.Runs.summary]).

    Attributes:
        n_trials: N.
        n_diverged: trials that diverged ([`diverged_trials`][delayed_ilqr.statistics.diverged_trials]: cost not finite or above the bound).
        mean_cost: the sample mean of the per-trial cost (eq. 2) over the trials that did not diverge.
        std_cost: their sample standard deviation (ddof = 1; NaN for fewer than 2).
        standard_error: std_cost / sqrt(N - n_diverged), the standard error of ``mean_cost``.
        ci95: (low, high), the bootstrap 95 % interval of ``mean_cost`` (see [`SampleStats`][delayed_ilqr.statistics.SampleStats]).
        median_cost, median_ci95: the median cost over all trials (diverged as +inf) and its
            distribution-free 95 % interval.
        final_state_mean: [n] sample mean of x_K over the trials that did not diverge.
        final_state_cov: [n, n] sample covariance of x_K (ddof = 1) over the same trials.
    """

    n_trials: int
    n_diverged: int
    mean_cost: float
    std_cost: float
    standard_error: float
    ci95: tuple
    median_cost: float
    median_ci95: tuple
    final_state_mean: np.ndarray
    final_state_cov: np.ndarray

    def to_dict(self) -> dict:
        """Plain Python types (floats, nested lists; non-finite numbers as ``None``), ready for ``json.dump``."""
        def matrix(a):
            return [_json_float(v) for v in a] if np.ndim(a) == 1 else [matrix(row) for row in a]
        return dict(n_trials=int(self.n_trials), n_diverged=int(self.n_diverged),
                    mean_cost=_json_float(self.mean_cost), std_cost=_json_float(self.std_cost),
                    standard_error=_json_float(self.standard_error), ci95=[_json_float(v) for v in self.ci95],
                    median_cost=_json_float(self.median_cost),
                    median_ci95=[_json_float(v) for v in self.median_ci95],
                    final_state_mean=matrix(np.asarray(self.final_state_mean)),
                    final_state_cov=matrix(np.asarray(self.final_state_cov)))


def summarize(cost, final_state, bound: float = math.inf) -> Summary:
    """The [`Summary`][delayed_ilqr.statistics.Summary] of per-trial costs [N] and final states [N, n]; a trial whose cost is
    above ``bound`` (e.g. [`divergence_bound`][delayed_ilqr.statistics.divergence_bound] of the plant) or not finite diverged."""
    diverged = diverged_trials(cost, bound)
    stats = sample_stats(cost, diverged)
    final_state = np.asarray(final_state, dtype=np.float64)
    final_state = final_state[~diverged & np.all(np.isfinite(final_state), axis=1)]
    nx = final_state.shape[1]
    mean = np.mean(final_state, axis=0) if final_state.shape[0] else np.full(nx, np.nan)
    with np.errstate(over="ignore", invalid="ignore"):      # finite but huge states of near blow-ups
        cov = np.atleast_2d(np.cov(final_state, rowvar=False, ddof=1)) if final_state.shape[0] > 1 \
            else np.full((nx, nx), np.nan)
    return Summary(n_trials=stats.n, n_diverged=stats.n_diverged, mean_cost=stats.mean, std_cost=stats.std,
                   standard_error=stats.standard_error, ci95=stats.ci95, median_cost=stats.median,
                   median_ci95=stats.median_ci95, final_state_mean=mean, final_state_cov=cov)
