"""A solve reported as converged satisfies the first-order conditions, and a
noisy solve that does not converge returns its best iterate.

The certificate (``ilqg.solver.first_order``): with lambda < 1e-5 the full step of the LQG model
promises g' H^-1 g / 2 < tol_cost |J| (projected with the limits). On the point mass the plant is
linear and the cost quadratic, so the model is exact and the check here is independent of the
solver: the gradient and Hessian of J(u) by autodiff through the rollout, projected on the
commands that are not held at a limit, with the right sign at the ones that are. With noise the
function is the merit of derivation §12 (S and F's states frozen at the returned nominal), by
autodiff as well.
"""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.backward import backward
from delayed_ilqr.ilqg.line_search import merit
from delayed_ilqr.ilqg.linearize import noise_columns, rollout, trajectory_cost
from delayed_ilqr.models import arm2, point_mass

# settings that each made a solve stop with CONVERGED_COST at the initial cost before the fix: a
# large lambda, tiny step sizes or a z_min near 1 make every promise (or every accepted step) small
FALSE_STOPS = [di.Options(reg_init=1e20), di.Options(reg_init=1e4), di.Options(alphas=(1e-300,), max_iterations=15),
               di.Options(z_min=0.99, max_iterations=15), di.Options(z_min=0.999999, max_iterations=15)]
PATHS = FALSE_STOPS + [di.Options(), di.Options(reg_init=1.0), di.Options(max_iterations=1),
                       di.Options(tol_cost=1e-3), di.Options(tol_grad=1e-2)]
_id = lambda o: f"{o.reg_init:g}-{o.alphas[0]:g}-{o.z_min:g}-{o.max_iterations}-{o.tol_cost:g}-{o.tol_grad:g}"


def _cost(problem, u):
    return trajectory_cost(problem, rollout(problem, u), u)


def _frozen_merit(problem, S, x_bar, u):
    """J(u) + sum c(x_bar, u)' S c(x_bar, u), S and x_bar of the returned nominal (derivation §12)."""
    c = noise_columns(problem, x_bar, u)
    return _cost(problem, u) + jnp.einsum("kpn,knm,kpm->", c, S[1:], c)


# compiled once per problem structure for the whole file (eagerly, every call traced and compiled
# the rollout's scan and its derivatives anew)
_value = jax.jit(lambda f, *args: f(*args), static_argnums=0)


@functools.partial(jax.jit, static_argnums=0)
def _gradient_and_hessian(f, *args):
    """Gradient and Hessian of u -> f(*args[:-1], u) in the flattened commands u = args[-1]."""
    *data, u = args
    F = lambda v: f(*data, v.reshape(u.shape))
    v = jnp.ravel(u)
    return jax.grad(F)(v), jax.hessian(F)(v)


def _own_merit(problem, x, u, S):
    """The merit of the nominal (x, u) under its own S (line_search.merit)."""
    return merit(problem, x, u, S, x)[1]


@jax.jit
def _value_hessians(problem, x, u):
    """S [K+1, n, n] of the structured backward pass at the nominal (x, u), lambda = 0."""
    return backward(problem, x, u, 0.0, "structured", 1e-5).S


def _first_order_gap(f, args, u, lo, hi):
    """(Newton decrement g_F' H_FF^-1 g_F / 2 of u -> f(*args, u) on the free commands, worst
    wrong-signed gradient at a limit)."""
    shape = u.shape
    g, H = (np.asarray(a) for a in _gradient_and_hessian(f, *args, jnp.asarray(u)))
    v = np.ravel(np.asarray(u))
    lo, hi = np.ravel(np.broadcast_to(lo, shape)), np.ravel(np.broadcast_to(hi, shape))
    at_lo, at_hi = v <= lo + 1e-9, v >= hi - 1e-9
    free = ~(at_lo | at_hi)
    decrement = 0.5 * g[free] @ np.linalg.solve(H[np.ix_(free, free)], g[free])
    wrong_sign = max(np.max(-g[at_lo], initial=0.0), np.max(g[at_hi], initial=0.0))
    return float(decrement), float(wrong_sign)


@pytest.mark.parametrize("limited", [False, True])
@pytest.mark.parametrize("options", PATHS, ids=_id)
def test_a_converged_status_satisfies_the_first_order_conditions(options, limited):
    problem = point_mass(delay=0.03)
    if limited:
        problem = problem.replace(u_min=-np.full(2, 0.5), u_max=np.full(2, 0.5))
    sol = di.solve(problem, options=options)
    if options in FALSE_STOPS[:3]:
        # the step cannot get anywhere (or the model is nowhere near: z_min): no convergence may be claimed at u_init
        assert not (sol.converged and float(sol.cost) >= float(sol.trace.cost[0]))
    if not sol.converged:
        assert sol.status in (di.Status.MAX_ITERATIONS, di.Status.REGULARIZATION_LIMIT), sol.status
        return
    decrement, wrong_sign = _first_order_gap(_cost, (problem,), sol.u, problem.u_min, problem.u_max)
    assert decrement < options.tol_cost * float(sol.cost), sol.status
    assert wrong_sign <= 1e-9


@pytest.mark.parametrize("options", [di.Options(reg_init=1e20), di.Options(alphas=(1e-300,), max_iterations=15),
                                     di.Options(z_min=0.999999, max_iterations=15), di.Options(max_iterations=2, reg_init=1.0)],
                         ids=_id)
def test_the_false_stops_are_not_converged(options):
    """False stops: every step rejected (or none possible) must not end as converged."""
    problem = point_mass(delay=0.03)
    sol = di.solve(problem, options=options)
    if sol.converged:       # reg_init=1e20 is confirmed at lambda = 0 and then solves the problem
        decrement, _ = _first_order_gap(_cost, (problem,), sol.u, -np.inf, np.inf)
        assert decrement < options.tol_cost * float(sol.cost)
    else:
        assert float(sol.cost) <= float(sol.trace.cost[0])
    if options.alphas == (1e-300,) or options.max_iterations == 2:
        assert not sol.converged, sol.status


@pytest.mark.parametrize("options", [di.Options(), di.Options(reg_init=1e4), di.Options(alphas=(1e-300,), max_iterations=15),
                                     di.Options(reg_init=1.0), di.Options(tol_cost=1e-6)], ids=_id)
@pytest.mark.parametrize("limited", [False, True])
def test_a_converged_noisy_solve_satisfies_the_first_order_conditions_of_its_merit(options, limited):
    """P2-noisy (signal-dependent noise): converged means a first-order point of the merit with
    S frozen at the returned nominal, measured here by autodiff (independent of the LQG)."""
    problem = arm2(delay=0.03, noise="benchmark")
    if limited:
        problem = problem.replace(u_min=-np.full(2, 4.0), u_max=np.full(2, 4.0))
    sol = di.solve(problem, options=options)
    if not sol.converged:
        assert sol.status in (di.Status.MAX_ITERATIONS, di.Status.REGULARIZATION_LIMIT), sol.status
        return
    frozen = (problem, _value_hessians(problem, sol.x, sol.u), sol.x)
    decrement, wrong_sign = _first_order_gap(_frozen_merit, frozen, sol.u, problem.u_min, problem.u_max)
    # the merit's Hessian here is the exact one (with the dynamics' second derivatives), the
    # solver's the LQG's: the decrements agree to first order, a factor 10 is the margin
    assert decrement < 10 * options.tol_cost * abs(float(_value(_frozen_merit, *frozen, sol.u))), (sol.status, decrement)
    assert wrong_sign <= 1e-9


def test_a_noisy_solve_that_stops_early_returns_its_best_iterate():
    """With noise the merit of successive nominals (each under its own S) need not fall: a stop
    without convergence returns the nominal of lowest merit seen, with the policy of that nominal."""
    problem = arm2(delay=0.03, noise="benchmark").replace(u_min=-np.full(2, 4.0), u_max=np.full(2, 4.0))

    def own_merit(x, u):
        return float(_value(_own_merit, problem, x, u, _value_hessians(problem, x, u)))

    u0 = np.zeros((problem.horizon, 2))
    best = own_merit(_value(rollout, problem, u0), u0)
    for n in range(1, 5):
        sol = di.solve(problem, options=di.Options(max_iterations=n, reg_init=1.0))
        assert sol.status == di.Status.MAX_ITERATIONS
        m = own_merit(sol.x, sol.u)
        assert m <= best * (1 + 1e-12), (n, m, best)
        best = m
        # the policy is the one of the returned nominal
        np.testing.assert_array_equal(sol.policy.u_nominal, sol.u)
        np.testing.assert_array_equal(sol.policy.x_nominal, sol.x)
        np.testing.assert_allclose(sol.x, _value(rollout, problem, sol.u), rtol=1e-12, atol=1e-12)


def _window(latch, merits, toggle):
    """The latch after one LATCH_STALL window of backward passes with the given merits, the
    feedback of command (0, 0) switching every pass when ``toggle``."""
    from delayed_ilqr.ilqg import solver
    from delayed_ilqr.lqg.frame import SlotGains
    for i, m in enumerate(merits):
        on = bool(i % 2) if toggle else True
        gains = SlotGains(jnp.zeros((1, 1)), jnp.full((1, 1, 1), float(on)))
        latch = solver._latched(latch, gains, jnp.asarray(True), jnp.asarray(False), jnp.asarray(m))
    return latch


def test_latch_fires_on_a_recurring_window_only():
    """The feedback latch (derivation §12) holds a toggling command only when the merits of a
    stalled window recur in the next: a cycle; a window whose range moves is a transient."""
    from delayed_ilqr.ilqg import solver
    assert solver.LATCH_STALL == 10
    fresh = solver._Latch(jnp.ones((1, 1), bool), jnp.zeros((1, 1), jnp.int32), jnp.asarray(0, jnp.int32),
                          jnp.zeros((1, 1), bool), jnp.asarray(jnp.inf), jnp.asarray(-jnp.inf), jnp.full(2, jnp.nan))
    cycle = [1.0, 1.03, 1.01, 1.05, 1.02] * 2                 # period 5, range 5 %
    first = _window(fresh, cycle, True)
    assert not bool(first.held[0, 0])                         # nothing to compare with yet
    assert bool(_window(first, cycle, True).held[0, 0])       # the same range again: a cycle
    assert not bool(_window(first, [1.3 * m for m in cycle], True).held[0, 0])   # moved: a transient
    assert not bool(_window(first, cycle, False).held[0, 0])  # recurring, but the feedback does not toggle
