"""Motor delays fitted by gradient, jointly with cost weights and noise, and their confidence
intervals by a parametric bootstrap (``docs/fitting.md``).

A delay that is not a whole number of steps is the zero-order hold of ``docs/derivation.md`` §20,
differentiable in the delay. So the delays become parameters of [`fit`][delayed_ilqr.experiments.fitting.fit] like the others:
[`DelayedModel`][delayed_ilqr.experiments.delay_fitting.DelayedModel] builds the problem at a starting delay and
replaces its delay by the traced parameters (in seconds, one for all channels or one per channel),
in a frame of slots that holds every delay up to ``max_delay``; one compilation serves the whole fit.

The confidence interval of a fitted parameter is the percentile interval of a parametric bootstrap:
the fitted model's policy is simulated on its plant with the data's number of trials (new noise
for each replicate), the statistics are recomputed and the fit is repeated from the estimate.
The replicates' spread is that of the estimator on data like the data, as far as the fitted model
describes the data.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import Problem, simulate, solve
from .fitting import Fit, ReachData, fit, observed_reach

__all__ = ["DelayedModel", "delay_names", "fit_delays", "Bootstrap", "bootstrap"]


def delay_names(n: int) -> tuple:
    """The parameter names of n fitted delays: ("delay",) for one, ("delay_0", ..., "delay_{n-1}")."""
    return ("delay",) if n == 1 else tuple(f"delay_{j}" for j in range(n))


@dataclass(frozen=True)
class DelayedModel:
    """``make_problem(params, condition, delay)`` with the motor delay as fitted parameters.

    ``make_problem`` is called at the fixed ``start`` delay (seconds, concrete: factories need a
    number), and its problem's delay is then replaced by the traced parameters ``delay`` (one for
    every channel) or ``delay_0``, ..., ``delay_{d-1}`` (one per channel, ``per_channel``), in
    seconds, as a fractional delay in a frame of ``frame`` slots (``docs/derivation.md`` §20). So
    the problem may depend on the delay only through its ``delay_steps``. Frozen and compared by
    value: fits with the same model share one compilation."""

    make_problem: Callable
    start: float
    frame: int
    per_channel: bool = False

    def names(self, n_controls: int) -> tuple:
        return delay_names(n_controls if self.per_channel else 1)

    def __call__(self, params, condition):
        others = {k: v for k, v in params.items() if not k.startswith("delay")}
        problem = self.make_problem(others, condition, self.start)
        names = self.names(problem.n_controls)
        tau = jnp.stack([jnp.asarray(params[k], jnp.float64) for k in names]) if self.per_channel \
            else jnp.asarray(params["delay"], jnp.float64)
        return problem.replace(delay_steps=tau / problem.dt, delay_frame=self.frame)


def _frame_for(max_delay: float, dt: float, horizon: int) -> int:
    """Slots that hold every delay up to ``max_delay`` s: its taps l and l + 1, below the horizon."""
    frame = int(np.floor(max_delay / dt + 1e-9)) + 1
    if frame >= horizon:
        raise ValueError(f"max_delay must be below the horizon less one step, {(horizon - 1) * dt:g} s (dt = {dt:g} s, "
                         f"K = {horizon}): a fractional delay's taps must act within it; got max_delay={max_delay!r}")
    return frame


def fit_delays(make_problem: Callable[[dict, object, float], Problem], conditions, data: ReachData, params0: dict,
               delay0, max_delay: float, per_channel: bool = False, **kwargs) -> tuple:
    """Fits the motor delay (seconds; one, or one per channel) with the parameters of ``params0``.

    Args:
        make_problem: ``make_problem(params, condition, delay)`` as for
            [`profile_delay`][delayed_ilqr.experiments.fitting.profile_delay], depending on the delay only through ``delay_steps``.
        conditions: as for [`fit`][delayed_ilqr.experiments.fitting.fit].
        data: as for [`fit`][delayed_ilqr.experiments.fitting.fit].
        params0: as for [`fit`][delayed_ilqr.experiments.fitting.fit], without the delays.
        delay0: the starting delay in seconds (positive), of every channel. A whole number of
            steps is a fine start: the derivative there is the one-sided one
            (``docs/derivation.md`` §20).
        max_delay: the longest delay the fit may reach (s): it sets the frame, and L-BFGS-B keeps
            every delay in (0, max_delay].
        per_channel: one delay per command channel, each from ``delay0``.
        kwargs: more arguments of [`fit`][delayed_ilqr.experiments.fitting.fit] (``u_init``, ``mean_scale``, ``options``, ...).

    Returns:
        (the [`Fit`][delayed_ilqr.experiments.fitting.Fit], whose ``params`` include the delays by the names of
        [`delay_names`][delayed_ilqr.experiments.delay_fitting.delay_names]; the [`DelayedModel`][delayed_ilqr.experiments.delay_fitting.DelayedModel] it used).
    """
    delay0, max_delay = float(delay0), float(max_delay)
    if not (np.isfinite(delay0) and 0 < delay0 <= max_delay):
        raise ValueError(f"delay0 must be a positive number of seconds up to max_delay={max_delay!r}; got {delay0!r}")
    first = make_problem({k: float(v) for k, v in params0.items()}, jax.tree_util.tree_map(lambda a: a[0], conditions),
                         delay0)
    model = DelayedModel(make_problem, delay0, _frame_for(max_delay, first.dt, first.horizon), bool(per_channel))
    names = model.names(first.n_controls)
    clash = sorted(k for k in params0 if k.startswith("delay"))
    if clash:
        raise ValueError(f"params0 must not name the delays (fit_delays adds {list(names)}); got {clash}")
    bounds = dict(kwargs.pop("bounds", None) or {}, **{k: (None, max_delay) for k in names})
    result = fit(model, conditions, data, dict(params0, **{k: delay0 for k in names}), bounds=bounds, **kwargs)
    return result, model


class Bootstrap(NamedTuple):
    """A parametric bootstrap of a fit ([`bootstrap`][delayed_ilqr.experiments.delay_fitting.bootstrap]).

    Attributes:
        estimates: [B, P] the refitted parameters of the B replicates, by ``names``' order.
        names: the parameters' names (sorted).
        low, high: dicts of the (1 - level) / 2 and (1 + level) / 2 percentiles of the converged
            replicates' estimates, by name.
        converged: [B] bool, each replicate's fit converged.
    """

    estimates: np.ndarray
    names: tuple
    low: dict
    high: dict
    converged: np.ndarray


def bootstrap(model: Callable, conditions, fitted: Fit, n_trials: int, replicates: int, seed: int = 0,
              level: float = 0.95, **kwargs) -> Bootstrap:
    """Percentile confidence intervals of ``fitted.params`` by a parametric bootstrap.

    For each replicate b: solve the model at the fitted parameters for every condition, simulate
    its policy on its plant (``n_trials`` trials, seed ``seed + b``), take the statistics
    ([`observed_reach`][delayed_ilqr.experiments.fitting.observed_reach]) and fit again from ``fitted.params``.

    Args:
        model: the ``make_problem(params, condition)`` of the fit (e.g. the
            [`DelayedModel`][delayed_ilqr.experiments.delay_fitting.DelayedModel] of [`fit_delays`][delayed_ilqr.experiments.delay_fitting.fit_delays]).
        conditions: the fit's conditions.
        fitted: the fit to bootstrap.
        n_trials: trials per condition, as in the data.
        replicates: B.
        level: the intervals' confidence level.
        kwargs: more arguments of [`fit`][delayed_ilqr.experiments.fitting.fit] (``options``, ``mean_scale``, ``bounds``, ...;
            ``u_init``, also used for the solves at the fitted parameters).
    """
    names = tuple(sorted(fitted.params))
    count = len(jax.tree_util.tree_leaves(conditions)[0])
    theta = {k: float(v) for k, v in fitted.params.items()}
    problems = [model(theta, jax.tree_util.tree_map(lambda a, c=c: a[c], conditions)) for c in range(count)]
    u_init = kwargs.get("u_init")
    options = kwargs.get("options")
    policies = [solve(p, u_init, options).policy for p in problems]
    estimates, converged = [], []
    for b in range(replicates):
        stats = [observed_reach(p, simulate(p, pol, n_trials, seed=seed + b)) for p, pol in zip(problems, policies)]
        data = ReachData(jnp.asarray(np.stack([s[0] for s in stats])), jnp.asarray(np.stack([s[1] for s in stats])))
        refit = fit(model, conditions, data, theta, **kwargs)
        estimates.append([refit.params[k] for k in names])
        converged.append(refit.converged)
    estimates, converged = np.asarray(estimates), np.asarray(converged)
    kept = estimates[converged] if np.any(converged) else estimates
    tail = 50 * (1 - level)
    low = dict(zip(names, np.percentile(kept, tail, axis=0).tolist()))
    high = dict(zip(names, np.percentile(kept, 100 - tail, axis=0).tolist()))
    return Bootstrap(estimates, names, low, high, converged)
