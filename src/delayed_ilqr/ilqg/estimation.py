"""The estimator of an observed problem, designed at the solver's returned nominal (issue 20).

iLQG designs the controller with the full state, as without sensors. At the returned nominal the
plant is linearised (eq. 3) and so are the sensors (``observation.linearized_observation``); the
delayed Kalman filter of that linear model (``lqg.delayed_kalman``, process noise the additive
part c c' of eq. 3 at the nominal) is the estimator, and the expected cost of the pair is exact on
the linearisation (``lqg.output_feedback_cost``, the joint second moments, signal-dependent motor
noise included). With additive noise the pair is the optimal output feedback of the linearisation
(separation, ``docs/derivation.md`` §14). This runs once, after the solver's loop.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ..lqg.estimator import _delayed_kalman, _process_cov
from ..lqg.model import Gains
from ..lqg.output_feedback import _output_feedback_cost
from ..observation import linearized_observation
from ..problem import Problem
from ..solution import Estimator, Solution
from .linearize import linearize

__all__ = ["design_estimator", "with_estimator", "without_observation"]


def design_estimator(problem: Problem, xs, us, gains: Gains):
    """The delayed filter of ``problem.observation`` around the nominal (xs [K+1, n], us [K, d])
    and the exact expected cost of the law ``gains`` on its estimate (linearised model).

    Returns:
        (:class:`~delayed_ilqr.Estimator`, expected cost []).
    """
    lqg = linearize(problem, xs, us)
    obs, y_nominal = linearized_observation(problem.observation, xs)
    fgains, cov = _delayed_kalman(lqg, obs, _process_cov(lqg), obs.measurement_cov)
    cost = _output_feedback_cost(lqg, obs, gains, fgains)
    estimator = Estimator(lqg.A, lqg.B0, lqg.B1, obs.H, y_nominal, fgains.delayed_gain, fgains.current_gain,
                          cov.current, sensory_delay=obs.delay_steps)
    return estimator, jnp.asarray(cost)


def without_observation(problem: Problem) -> Problem:
    """The same problem with full-state feedback (a copy that shares every field but the sensors)."""
    new = object.__new__(Problem)
    new.__dict__.update(problem.__dict__)
    new.observation = None
    return new


@jax.jit
def _with_estimator(problem: Problem, sol: Solution) -> Solution:
    policy = sol.policy
    gains = Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback)
    estimator, cost = design_estimator(problem, sol.x, sol.u, gains)
    return sol._replace(expected_cost=cost, policy=policy._replace(estimator=estimator))


def with_estimator(problem: Problem, sol: Solution) -> Solution:
    """``sol`` (the full-state solve of ``problem``) with the estimator of ``problem.observation``
    in its policy and the exact output-feedback cost as ``expected_cost``; the status is kept."""
    status = sol.status
    out = _with_estimator(problem, sol._replace(status=jnp.asarray(status)))
    return out._replace(status=status)
