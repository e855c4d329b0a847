"""A solve reported as converged satisfies the first-order conditions (issue 22, item 8).

The certificate (``ilqg.solver.first_order``): with lambda < 1e-5 the full step of the LQG model
promises g' H^-1 g / 2 < tol_cost |J| (projected with the limits). On the point mass the plant is
linear and the cost quadratic, so the model is exact and the check here is independent of the
solver: the gradient and Hessian of J(u) by autodiff through the rollout, projected on the
commands that are not held at a limit, with the right sign at the ones that are.
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import rollout, trajectory_cost
from delayed_ilqr.models import point_mass

# settings that each made a solve stop with CONVERGED_COST at the initial cost before the fix: a
# large lambda or tiny step sizes make every promise small (now such a stop is confirmed, or not,
# by a pass at lambda = 0)
FALSE_STOPS = [di.Options(reg_init=1e20), di.Options(reg_init=1e4), di.Options(alphas=(1e-300,), max_iterations=15),
               di.Options(z_min=0.99, max_iterations=15)]
PATHS = FALSE_STOPS + [di.Options(), di.Options(reg_init=1.0), di.Options(max_iterations=1),
                       di.Options(tol_cost=1e-3), di.Options(tol_grad=1e-2)]


def _first_order_gap(problem, u):
    """(Newton decrement g_F' H_FF^-1 g_F / 2 on the free commands, worst wrong-signed gradient at a limit)."""
    shape = u.shape
    J = lambda v: trajectory_cost(problem, rollout(problem, v.reshape(shape)), v.reshape(shape))
    v = jnp.ravel(u)
    g, H = np.asarray(jax.grad(J)(v)), np.asarray(jax.hessian(J)(v))
    lo, hi = np.ravel(np.broadcast_to(problem.u_min, shape)), np.ravel(np.broadcast_to(problem.u_max, shape))
    at_lo, at_hi = np.asarray(v) <= lo + 1e-9, np.asarray(v) >= hi - 1e-9
    free = ~(at_lo | at_hi)
    decrement = 0.5 * g[free] @ np.linalg.solve(H[np.ix_(free, free)], g[free])
    wrong_sign = max(np.max(-g[at_lo], initial=0.0), np.max(g[at_hi], initial=0.0))
    return float(decrement), float(wrong_sign)


@pytest.mark.parametrize("limited", [False, True])
@pytest.mark.parametrize("options", PATHS, ids=lambda o: f"{o.reg_init:g}-{o.alphas[0]:g}-{o.z_min:g}-{o.max_iterations}-"
                                                          f"{o.tol_cost:g}-{o.tol_grad:g}")
def test_a_converged_status_satisfies_the_first_order_conditions(options, limited):
    problem = point_mass(delay=0.03)
    if limited:
        problem = problem.replace(u_min=-np.full(2, 0.5), u_max=np.full(2, 0.5))
    sol = di.solve(problem, options=options)
    status = di.Status(int(sol.status))
    if not sol.converged:
        return
    decrement, wrong_sign = _first_order_gap(problem, sol.u)
    assert decrement < options.tol_cost * float(sol.cost), status
    assert wrong_sign <= 1e-9


@pytest.mark.parametrize("options", [di.Options(reg_init=1e4), di.Options(alphas=(1e-300,), max_iterations=15)])
def test_a_noisy_solve_is_not_reported_converged_without_a_newton_step(options):
    """With noise the merit is not J(u); a converged status must reach the default solve's merit."""
    problem = point_mass(delay=0.03, noise=True)
    sol = di.solve(problem, options=options)
    if sol.converged:
        np.testing.assert_allclose(float(sol.expected_cost), float(di.solve(problem).expected_cost), rtol=1e-8)
