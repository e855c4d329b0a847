"""The estimator of an observed problem, designed at the solver's returned nominal.

iLQG designs the controller with the full state, as without sensors. At the returned nominal the
plant is linearised (eq. 3) and so are the sensors (``observation.linearized_observation``); the
delayed Kalman filter of that linear model (``lqg.delayed_kalman``, process noise the motor noise
c c' of eq. 3 at the nominal commands) is the estimator. With additive noise the pair is the
optimal output feedback of the linearisation (separation, ``docs/derivation.md`` §14). With
signal-dependent motor noise, Todorov's alternation (``lqg.alternation``) then redesigns the filter
and the feedback in turn, never raising the pair's exact cost; the feedforward and the nominal stay
iLQG's, and commands without feedback (at a limit) keep none. The expected cost of the pair is exact
on the linearisation (the joint second moments, signal-dependent motor noise included). This runs
once, after the solver's loop.

Sensors with different delays (a ``SensorList``) are fused without augmentation (``lqg.fusion``):
the filter is the Kalman filter for the motor noise that the law actually has in closed loop
(``lqg.fused_loop``, Todorov's filter for a fixed controller; with additive noise the separation
design). With signal-dependent noise the alternation of ``lqg.fused_alternation`` then redesigns
the law for that filter and the filter for the new law in turn, never raising the exact cost.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..lqg.alternation import _alternate
from ..fused_estimator import FusedEstimator
from ..lqg.estimator import _delayed_kalman, _process_cov
from ..lqg.fusion import stacked_sensors
from ..lqg.fused_alternation import _fused_alternate
from ..lqg.model import Gains
from ..observation import linearized_observation
from ..sensor_list import SensorList, linearized_sensors
from ..options import Options
from ..problem import Problem
from ..solution import Estimator, Solution, Status
from ..lqg.law import augmented_feedback
from .linearize import linearize

__all__ = ["design_estimator", "with_estimator", "without_observation", "all_finite"]


def design_estimator(problem: Problem, xs, us, gains: Gains, max_alternations: int = 0, tol=1e-10):
    """The delayed filter of ``problem.observation`` around the nominal (xs [K+1, n], us [K, d]),
    the law ``gains`` on its estimate after at most ``max_alternations`` of Todorov's alternation
    (run only when the motor noise is signal-dependent), and the pair's exact expected cost
    (linearised model).

    Returns:
        ([`Estimator`][delayed_ilqr.Estimator], the law [`Gains`][delayed_ilqr.lqg.Gains], expected cost []).
    """
    lqg = linearize(problem, xs, us)
    signal_dependent = jnp.any(lqg.C0 != 0) | jnp.any(lqg.C1 != 0)
    # iLQG gives no feedback to commands at a limit (derivation §13); the alternation keeps it so
    free = jnp.any(augmented_feedback(gains) != 0, axis=-1)
    if fused(problem):
        return _design_fused(lqg, problem.observation, xs, gains, free, max_alternations, tol, signal_dependent)
    obs, y_nominal = linearized_observation(problem.observation, xs)
    fgains, _ = _delayed_kalman(lqg, obs, _process_cov(lqg), obs.measurement_cov)
    alt = _alternate(lqg, obs, gains, fgains, free, max_alternations, jnp.asarray(tol, lqg.A.dtype),
                     signal_dependent)
    estimator = Estimator(lqg.A, lqg.B0, lqg.B1, obs.H, y_nominal, alt.filter_gains.delayed_gain,
                          alt.filter_gains.current_gain, alt.error_covariance, sensory_delay=obs.delay_steps)
    return estimator, alt.gains, jnp.asarray(alt.expected_cost)


def fused(problem: Problem) -> bool:
    """Whether the problem's sensors have different delays (the fused filter, ``lqg.fusion``)."""
    return isinstance(problem.observation, SensorList) and not problem.observation.equal_delays


def _design_fused(lqg, sensors: SensorList, xs, gains: Gains, free, max_alternations: int, tol, run):
    """The fused filter for the motor noise of the law in closed loop, after at most
    ``max_alternations`` of the fused alternation (when ``run``), and the pair's exact cost."""
    linear, y_nominal = linearized_sensors(sensors, xs)
    alt = _fused_alternate(lqg, linear, gains, free, max_alternations, jnp.asarray(tol, lqg.A.dtype), run)
    st = stacked_sensors(linear)
    estimator = FusedEstimator(lqg.A, lqg.B0, lqg.B1, st.H[st.window:], y_nominal, alt.filter_gains.base_gain,
                               alt.filter_gains.window_gain, alt.covariances.current, st.lags)
    return estimator, alt.gains, alt.expected_cost


def without_observation(problem: Problem) -> Problem:
    """The same problem with full-state feedback (a copy that shares every field but the sensors)."""
    new = object.__new__(Problem)
    new.__dict__.update(problem.__dict__)
    new.observation = None
    return new


def _without_updates(problem: Problem, xs, us, designed: Estimator) -> Estimator:
    """The stand-in for a filter that came out non-finite: no measurement updates (zero gains), so
    the estimate is the prediction from x0 and the commands sent, and its error covariance that
    prediction's, P_{k+1} = A_k P_k A_k' + sum_j c_j c_j' from P_0 = 0 (the additive motor noise of
    eq. 3 at the nominal). The sensor rows keep their finite entries (zeros elsewhere): with zero
    gains they do not enter the estimate."""
    lqg = linearize(problem, xs, us)

    def predict(P, data):
        A, Q = data
        P = A @ P @ A.T + Q
        return P, P

    nx = xs.shape[1]
    _, P = jax.lax.scan(predict, jnp.zeros((nx, nx), xs.dtype), (lqg.A, _process_cov(lqg)))
    finite = lambda a: jnp.where(jnp.isfinite(a), a, 0.0)
    P = jnp.concatenate([jnp.zeros((1, nx, nx), xs.dtype), P])
    if isinstance(designed, FusedEstimator):
        return designed.replace(A=lqg.A, B0=lqg.B0, B1=lqg.B1, H=finite(designed.H),
                                y_nominal=finite(designed.y_nominal), base_gain=jnp.zeros_like(designed.base_gain),
                                window_gain=jnp.zeros_like(designed.window_gain), error_covariance=P)
    return Estimator(lqg.A, lqg.B0, lqg.B1, finite(designed.H), finite(designed.y_nominal),
                     jnp.zeros_like(designed.delayed_gain), jnp.zeros_like(designed.current_gain),
                     P, sensory_delay=designed.sensory_delay)


def all_finite(tree):
    """Whether every leaf of ``tree`` is finite (a traced bool)."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(tree)]))


@partial(jax.jit, static_argnames=("max_alternations",))
def _with_estimator(problem: Problem, sol: Solution, max_alternations: int, tol):
    """(``sol`` with the estimator, whether the design came out finite)."""
    policy = sol.policy
    full_state = Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback)
    estimator, gains, cost = design_estimator(problem, sol.x, sol.u, full_state, max_alternations, tol)
    finite = all_finite((estimator, gains)) & all_finite((full_state,))
    # a non-finite filter (the sensors' h or G NaN along the nominal) is not returned: the
    # full-state feedback goes with a filter that makes no measurement updates
    estimator, gains = jax.lax.cond(finite, lambda: (estimator, gains),
                                    lambda: (_without_updates(problem, sol.x, sol.u, estimator), full_state))
    cost = jnp.where(finite, cost, jnp.nan)
    policy = policy._replace(state_feedback=gains.state_feedback, delay_feedback=gains.delay_feedback,
                             estimator=estimator)
    return sol._replace(expected_cost=cost, policy=policy), finite


def with_estimator(problem: Problem, sol: Solution, options: Options) -> Solution:
    """``sol`` (the full-state solve of ``problem``) with the estimator of ``problem.observation``
    in its policy (and, with signal-dependent noise, the feedback of Todorov's alternation) and
    the exact output-feedback cost as ``expected_cost``; the status is kept, unless the filter
    came out non-finite (``Status.NON_FINITE_FILTER``, with the stand-in of `_without_updates`)."""
    status = sol.status
    out, finite = _with_estimator(problem, sol._replace(status=jnp.asarray(status)), options.max_alternations,
                                  options.tol_cost)
    if isinstance(finite, jax.core.Tracer) or isinstance(status, jax.core.Tracer):
        status = jnp.where(finite, status, Status.NON_FINITE_FILTER).astype(jnp.int32)
    elif not bool(finite):
        status = Status.NON_FINITE_FILTER
    return out._replace(status=status)
