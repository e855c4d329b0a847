"""Control limits, the good minimum: the augmented-Lagrangian continuation on the limits as a start
(``ilqg.continuation``), and several starts under one ``vmap``.

The reference 50.282205 of the acrobot at 3 N m is independent of this code: google/trajax's
augmented-Lagrangian iLQR (``optimizers.constrained_ilqr``, commit c94a637c, test settings and
penalty rate 2) from rest on trajax's own acrobot, its commands clipped into the box and polished
by the bounded ``solve`` (``benchmarks/swing_up.py --trajax PATH``, docs/derivation.md §15); iLQG,
the several starts of looser limits and five bounded L-BFGS-B starts all stop at 50.836671
there. 74.495176 at 2.2 N m is bounded L-BFGS-B's best of five starts (same table).
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.continuation import _looser_limits, lifted_problem
from delayed_ilqr.ilqg.linearize import rollout, trajectory_cost
from delayed_ilqr.ilqg.solver import compiled_solver
from delayed_ilqr.models import acrobot, point_mass

from direct import direct_optimum   # tests/direct.py

OPTIONS = di.Options(max_iterations=100)
DELAYED = point_mass(delay=0.02)     # every point-mass case: 2 steps of delay, one compiled structure


@pytest.mark.parametrize("u_max, reference", [pytest.param(3.0, 50.282205, marks=pytest.mark.full), (2.2, 74.495176)])
def test_acrobot_from_rest_reaches_the_good_minimum(u_max, reference):
    problem = acrobot(u_max=u_max)
    starts = di.solve_from_starts(problem, OPTIONS, looser=(math.inf, 5.0 / u_max))
    assert starts.names == ("u_init", "unbounded", f"looser x{5.0 / u_max:g}", "augmented Lagrangian")
    costs = np.asarray(starts.solutions.cost)
    sol = starts.solution
    assert abs(float(sol.cost) - reference) <= 1e-6 * reference, (float(sol.cost), reference)
    assert abs(costs[3] - reference) <= 1e-6 * reference, costs      # the augmented-Lagrangian start alone
    assert costs[0] > 1.005 * reference, costs                        # rest: the poor minimum
    if u_max == 3.0:      # only the augmented-Lagrangian start: the others end at 50.836671 or above
        assert starts.best == 3 and np.all(costs[:3] > 1.005 * reference), costs
    assert sol.converged, sol.message
    assert isinstance(sol.status, di.Status) and sol.status == starts.solutions.status[starts.best]
    u = np.asarray(sol.u)
    assert np.all((u >= -u_max) & (u <= u_max))


def test_delayed_bounded_start_reaches_the_bounded_optimum():
    # the point mass with a 2-step delay and tight limits: the lifted problem has the delay, the
    # penalty acts on u_k; the polished start ends at bounded L-BFGS-B's optimum, as the solve from rest
    problem = DELAYED.replace(u_min=-0.5, u_max=0.5)
    assert problem.delay_steps == 2
    continuation = di.augmented_lagrangian_start(problem, options=OPTIONS)
    start = continuation.u
    assert np.all(np.abs(np.asarray(start)) <= 0.5)
    assert continuation.iterations.shape == continuation.violation.shape == (6,)
    assert float(continuation.violation[0]) > 1e-2 and float(continuation.violation[-1]) < 1e-6   # lifted, then held
    polished, rest = di.solve(problem, start, OPTIONS), di.solve(problem, options=OPTIONS)
    reference = direct_optimum(problem)
    assert polished.converged and rest.converged
    for sol in (polished, rest):
        assert abs(float(sol.cost) - reference) <= 1e-8 * reference, (float(sol.cost), reference)
    # the start is already near the optimum: the penalty ended at 1e5
    assert float(trajectory_cost(problem, rollout(problem, start), start)) <= (1 + 1e-3) * reference


@pytest.mark.full
def test_delayed_acrobot_start_beats_rest_at_a_minimum():
    # the acrobot at 2.2 N m with a 2-step (0.2 s) delay: the augmented-Lagrangian start ends below
    # the solve from rest, at a point bounded L-BFGS-B started there does not improve (a minimum
    # of the delayed bounded problem, not an artefact of the solver); rest's cost is L-BFGS-B's from zero
    problem = acrobot(delay=0.2, u_max=2.2)
    assert problem.delay_steps == 2
    starts = di.solve_from_starts(problem, OPTIONS, looser=())
    costs = np.asarray(starts.solutions.cost)
    assert np.all(np.asarray(starts.solutions.converged)), starts.solutions.status
    assert starts.best == 1 and costs[1] < 0.99 * costs[0], costs
    there = direct_optimum(problem, u_init=starts.solution.u)
    assert abs(costs[1] - there) <= 1e-6 * there, (costs[1], there)
    from_zero = direct_optimum(problem)
    assert abs(costs[0] - from_zero) <= 1e-6 * from_zero, (costs[0], from_zero)


def _phi(us, upper, lower, rho, lo, hi):
    """sum_k phi(u_k) of the module docstring, in NumPy."""
    total = 0.0
    for nu, g in ((upper, us - hi), (lower, lo - us)):
        total += np.sum(np.maximum(nu + rho * g, 0.0) ** 2 - nu ** 2) / (2 * rho)
    return total


# the gradient of J(u) through the rollout, compiled whole (outside a jit, the scan's derivative
# and its transpose compile apart, with every small operation around them)
_cost_gradient = jax.jit(jax.grad(lambda v, p: trajectory_cost(p, rollout(p, v), v)))


@pytest.mark.parametrize("case", ["quadratic, delay", "general", "general, time-dependent, one-sided"])
def test_lifted_cost_is_the_cost_plus_the_augmented_lagrangian_term(case):
    rng = np.random.default_rng(3)
    if case == "quadratic, delay":
        problem = DELAYED.replace(u_min=-0.5, u_max=0.5)
    elif case == "general":
        problem = acrobot(u_max=3.0)
    else:
        cost = di.GeneralCost(lambda x, u, p, t: (1 + t) * (x @ x + p["q"] * u @ u), lambda x, p, t: t * x @ x,
                              {"q": 0.3}, time_dependent=True)
        problem = acrobot(u_max=3.0).replace(cost=cost, u_min=(-np.inf,), u_max=(2.0,))
    K, d = problem.horizon, problem.n_controls
    us = rng.normal(size=(K, d))
    upper, lower, rho = rng.uniform(0, 1, (K, d)), rng.uniform(0, 1, (K, d)), 2.5
    lifted = lifted_problem(problem, upper, lower, rho)
    assert not lifted.has_limits and lifted.delay_steps == problem.delay_steps
    xs = rollout(problem, jnp.asarray(us))
    want = float(trajectory_cost(problem, xs, us)) + _phi(us, upper, lower, rho, np.asarray(problem.u_min),
                                                          np.asarray(problem.u_max))
    got = float(trajectory_cost(lifted, rollout(lifted, jnp.asarray(us)), us))
    assert abs(got - want) <= 1e-12 * abs(want), (got, want)
    # and its gradient in the commands: the cost's plus dphi/du = max(0, nu + rho g) dg/du
    lo, hi = np.asarray(problem.u_min), np.asarray(problem.u_max)
    dphi = np.maximum(upper + rho * (us - hi), 0.0) - np.maximum(lower + rho * (lo - us), 0.0)
    grads = [_cost_gradient(jnp.asarray(us), p) for p in (problem, lifted)]
    np.testing.assert_allclose(np.asarray(grads[1]), np.asarray(grads[0]) + dphi, rtol=1e-10, atol=1e-12)


def test_outer_iterations_share_one_compilation():
    # the multipliers and the penalty are data: the outer iterations, and a second continuation
    # with another penalty and other limits, run one compiled solver of the lifted problem (the
    # penalties are new to the process, so a penalty compiled in would add entries)
    problem = DELAYED.replace(u_min=-0.4, u_max=0.4)
    K, d = problem.horizon, problem.n_controls
    solver = compiled_solver(lifted_problem(problem, np.zeros((K, d)), np.zeros((K, d)), 1.0))
    before = solver._cache_size()
    di.augmented_lagrangian_start(problem, options=OPTIONS, penalty=0.37, penalty_growth=7.0, outer_iterations=4)
    after = solver._cache_size()
    assert after - before <= 1
    di.augmented_lagrangian_start(problem.replace(u_min=-0.3, u_max=0.35), options=OPTIONS, penalty=0.11,
                                  penalty_growth=3.0, outer_iterations=3)
    assert solver._cache_size() == after


def test_looser_limits():
    # the box widened s times about its centre where it is two-sided; one-sided components keep
    # their limits; math.inf lifts every limit
    problem = DELAYED.replace(u_min=(-0.5, 0.0), u_max=(1.5, np.inf))
    lo, hi = _looser_limits(problem, jnp.array([2.0, math.inf]))
    np.testing.assert_array_equal(np.asarray(lo), [[-1.5, 0.0], [-np.inf, -np.inf]])
    np.testing.assert_array_equal(np.asarray(hi), [[2.5, np.inf], [np.inf, np.inf]])


def test_bad_input():
    problem = DELAYED.replace(u_min=-0.5, u_max=0.5)
    with pytest.raises(ValueError, match="needs a problem with limits"):
        di.augmented_lagrangian_start(DELAYED)
    with pytest.raises(ValueError, match="needs a problem with limits"):
        di.solve_from_starts(DELAYED)
    with pytest.raises(TypeError, match="options must be a delayed_ilqr.Options; got dict"):
        di.solve_from_starts(problem, {})
    with pytest.raises(ValueError, match="penalty must be a positive finite number; got 0"):
        di.augmented_lagrangian_start(problem, penalty=0)
    with pytest.raises(ValueError, match="penalty_growth must be a finite number >= 1; got 0.5"):
        di.augmented_lagrangian_start(problem, penalty_growth=0.5)
    with pytest.raises(ValueError, match="outer_iterations must be a positive integer; got 0"):
        di.augmented_lagrangian_start(problem, outer_iterations=0)
    with pytest.raises(ValueError, match=r"looser must hold factors > 1 \(or math.inf\); got \(0.5,\)"):
        di.solve_from_starts(problem, looser=(0.5,))
    with pytest.raises(ValueError, match=r"u_init must have shape \(60, 2\); got shape \(3, 2\)"):
        di.augmented_lagrangian_start(problem, np.zeros((3, 2)))


def test_a_noisy_problem_keeps_the_start_of_lowest_expected_cost():
    """With noise the solver minimises the expected cost, not the nominal's: of the noisy delayed
    pendulum's two converged starts, the augmented-Lagrangian one has the lower nominal cost and
    the higher expected cost (measured 0.888 / 5.53 against 0.903 / 5.04 from rest), and the
    solution kept is the one from rest (before, the lower nominal cost won)."""
    from delayed_ilqr.models import pendulum
    starts = di.solve_from_starts(pendulum(delay=0.1, noise=True), OPTIONS, looser=())
    costs, expected = np.asarray(starts.solutions.cost), np.asarray(starts.solutions.expected_cost)
    assert np.all(np.asarray(starts.solutions.converged)), starts.solutions.status
    assert np.argmin(costs) != np.argmin(expected), (costs, expected)        # the case this test is about
    assert starts.best == int(np.argmin(expected)), (costs, expected)
    assert float(starts.solution.expected_cost) == float(np.min(expected))
