"""What a solution predicts about its own trials: the mean and covariance of the states, and of the
task-space point (the arms' hand), from the exact second moments of the linearised closed loop.

The policy runs on the plant as :func:`delayed_ilqr.simulate` runs it (eq. 6 without the
feedforward). Linearised at the nominal (eq. 3, the solver's model), the deviations
z_k = [dx_k, du_{k-l}, ..., du_{k-1}] of that closed loop start at 0, have mean 0 and the second
moments of :func:`delayed_ilqr.lqg.closed_loop_moments` (signal-dependent noise included). So, to
first order in the noise::

    E[x_k] = x_nominal_k,   Cov(x_k) = E[dx_k dx_k']
    E[e_k] = e(x_nominal_k),   Cov(e_k) = J_k Cov(x_k) J_k'     (e the task map, J_k = de/dx at x_nominal_k)

Everything is differentiable: through :func:`delayed_ilqr.solve` (``docs/derivation.md`` §16) these
are the model's predictions as functions of its parameters, which is what fitting a model to
measured reaches needs (``delayed_ilqr.experiments.fitting``). The prediction ignores what the
linearisation leaves out: the clipping of commands at their limits, and the plant's curvature
(``docs/fitting.md`` measures the gap against Monte Carlo).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .ilqg.linearize import linearize
from .lqg import Gains
from .lqg.exact import closed_loop_moments
from .models.metadata import task_space
from .problem import Problem
from .solution import Solution

__all__ = ["Prediction", "predict", "task_prediction"]


class Prediction(NamedTuple):
    """Predicted mean and covariance of a quantity along the trials.

    Attributes:
        mean: [K+1, m] E[y_k].
        cov: [K+1, m, m] Cov(y_k).
    """

    mean: jax.Array
    cov: jax.Array


def predict(problem: Problem, solution: Solution) -> Prediction:
    """The states' mean [K+1, n] and covariance [K+1, n, n] under ``solution.policy`` on ``problem``
    (module docstring). Full-state feedback only: a policy with an estimator raises ``ValueError``."""
    if problem.observation is not None or solution.policy.estimator is not None:
        raise ValueError("predict: problem.observation must be None (full-state feedback); got a policy with "
                         "an estimator, whose closed loop this function does not model")
    policy = solution.policy
    gains = Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    moments = closed_loop_moments(linearize(problem, solution.x, solution.u), gains)
    return Prediction(solution.x, moments.state_covariance(problem.n_states))


def task_prediction(problem: Problem, states: Prediction) -> Prediction:
    """The task-space point's mean [K+1, m] and covariance [K+1, m, m] (first order through the
    model's task map, ``ModelMetadata.task``); ``ValueError`` for a problem without a task space."""
    task = task_space(problem)
    if task is None:
        raise ValueError(f"task_prediction: problem {problem.name!r} has no task space (metadata.task is None)")
    J = jax.vmap(jax.jacobian(task.map))(states.mean)                   # [K+1, m, n]
    return Prediction(task.map(states.mean), J @ states.cov @ jnp.swapaxes(J, 1, 2))
