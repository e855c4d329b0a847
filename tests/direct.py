"""An independent reference for the nonlinear solver: direct single shooting.

L-BFGS-B (SciPy) over all K d commands at once, with exact gradients from ``jax.grad`` of the
rollout cost (2). It shares nothing with iLQG but the rollout and the cost, which is what makes it
a check. Needs SciPy (the ``test`` extra); it is for tests and benchmarks, not a solver to use.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from delayed_ilqr.ilqg.linearize import rollout, trajectory_cost
from delayed_ilqr.problem import Problem

__all__ = ["direct_optimum"]


def _cost(problem: Problem, flat):
    us = flat.reshape(problem.horizon, problem.n_controls)
    return trajectory_cost(problem, rollout(problem, us), us)


# the problem is an argument, not a closure: calls on problems of one structure (the same sizes,
# callables and delay) share one compilation
_fun, _grad = jax.jit(_cost), jax.jit(jax.grad(_cost, argnums=1))


def direct_optimum(problem: Problem, max_restarts: int = 30, rtol: float = 1e-10, u_init=None) -> float:
    """The cost (2) of the best command sequence L-BFGS-B finds, within ``problem``'s limits.

    L-BFGS-B's ftol test has an absolute floor of 1, and motor-task costs are ~1e-4, so the
    objective is rescaled to O(1) at the point found and the search restarted there, until a
    restart improves the cost by less than ``rtol`` (relative) or ``max_restarts`` are used. With
    tight limits a single run stops early (its limited-memory Hessian is poor where the active
    set changes): on the arm at +-2 N m and 30 ms, 3 runs end 1% above the optimum, 10 at it.
    ``u_init`` ([K, d], clipped into the limits; default zeros) is the first run's start.
    """
    import scipy.optimize  # lazy: SciPy is a test dependency

    K, nd = problem.horizon, problem.n_controls

    fun, grad = (lambda v: _fun(problem, v)), (lambda v: _grad(problem, v))
    lower, upper = (np.tile(np.asarray(b), K) for b in (problem.u_min, problem.u_max))
    bounds = list(zip(np.where(np.isfinite(lower), lower, None), np.where(np.isfinite(upper), upper, None)))
    u = np.clip(np.zeros(K * nd) if u_init is None else np.asarray(u_init, float).ravel(), lower, upper)
    best = float(fun(jnp.asarray(u)))
    for _ in range(max_restarts):
        scale = 1.0 / best
        u = scipy.optimize.minimize(lambda v: scale * float(fun(v)), u, jac=lambda v: scale * np.asarray(grad(v)),
                                    method="L-BFGS-B", bounds=bounds,
                                    options=dict(maxiter=50000, maxfun=100000, ftol=1e-16, gtol=1e-14,
                                                 maxcor=50)).x
        cost = float(fun(jnp.asarray(u)))
        if best - cost <= rtol * abs(cost):
            return min(cost, best)
        best = cost
    return best
