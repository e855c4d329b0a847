"""Derivatives of ``solve`` on the six-muscle arm (ilqg/implicit.py, docs/derivation.md §16): the
delayed commands' tangent in x0 against central differences of re-solves, without and with the
arm's signal-dependent noise, where about 40 excitations lie near their lower limit at an interior
optimum. The arm's tests of test_gradients.py, in a file of their own: each takes about a minute,
and ``make test`` runs files, not tests, in parallel."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr import Options, Problem, Status, solve
from delayed_ilqr.ilqg import implicit
from delayed_ilqr.ilqg.linearize import rollout, trajectory_cost
from delayed_ilqr.models import arm2_muscle6
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, rest_commands

from comparisons import WorstDifference

worst = WorstDifference("derivative against finite differences of re-solves")
report_worst = worst.fixture()


def _newton_polished(problem: Problem, u, held, iterations=2):
    """u [K, d] after Newton steps on the free commands (``held`` [K, d] stay): the dense exact
    Hessian of eq. (2) in the commands (``jax.hessian`` through the rollout), the independent
    reference that removes the solver's stopping error from a re-solve. Returns (u, G) with G the
    final gradient [K, d]."""
    free = ~np.asarray(held).ravel()
    v = np.asarray(u, float).ravel().copy()
    for _ in range(iterations):
        g, H = (np.asarray(a) for a in _gradient_hessian(problem, v))
        v[free] -= np.linalg.solve(H[np.ix_(free, free)], g[free])
    return v.reshape(u.shape), np.asarray(_gradient_hessian(problem, v)[0]).reshape(u.shape)


@jax.jit
def _gradient_hessian(problem: Problem, v):
    """(gradient [K d], Hessian [K d, K d]) of eq. (2) in the flattened commands v, noise-free rollout."""
    shape = (problem.horizon, problem.n_controls)
    cost = lambda v: trajectory_cost(problem, rollout(problem, v.reshape(shape)), v.reshape(shape))
    return jax.grad(cost)(v), jax.hessian(cost)(v)


def _muscle_arm_tangent_against_resolves(problem: Problem, steps, polish: bool):
    """du*/dx0 along the shoulder angle (forward mode) and the central differences of re-solves
    at the two ``steps``, for the six-muscle ``problem``: returns (relative error of the finer
    difference, relative difference of the two). Checks that the solves converge, that about 40
    excitations near 0 are free at the optimum (G ~ 0: the case of derivation §16's KKT held set)
    and that every re-solve keeps the held set. With ``polish``, each re-solve is made exact by
    dense Newton steps on its free commands and checked to be a KKT point with that set."""
    u_init = rest_commands(problem)
    options = Options(max_iterations=1000, tol_cost=1e-15, tol_grad=1e-11)
    margin = options.limit_margin
    e = jnp.zeros(problem.n_states).at[0].set(1.0)         # the shoulder angle
    # one compiled call for the base solve with its tangent and for the re-solves
    solve_at = jax.jit(lambda x0: jax.jvp(lambda x: solve(problem.replace(x0=x), u_init, options), (x0,), (e,)))
    held_at = jax.jit(lambda p, u: implicit.fixed_commands(p, u, margin)[0])
    base, tangent = solve_at(problem.x0)
    assert Status(int(base.status)).converged, base.status
    held = np.asarray(held_at(problem, base.u))
    assert int(np.sum((np.asarray(base.u) <= margin) & ~held)) > 10
    du = np.asarray(tangent.u)
    fds = []
    for h in steps:
        ends = []
        for x0 in (problem.x0 + h * e, problem.x0 - h * e):
            moved = problem.replace(x0=x0)
            sol, _ = solve_at(x0)
            assert Status(int(sol.status)).converged, sol.status
            np.testing.assert_array_equal(held_at(moved, sol.u), held)
            u = np.asarray(sol.u)
            if polish:
                u, G = _newton_polished(moved, sol.u, held)
                # a KKT point of the perturbed problem with the same held set: free commands inside
                # the box and stationary, held ones at 0 and pushed outward
                assert np.all(u[~held] > 0) and np.all(u[~held] < 1)
                assert np.max(np.abs(G[~held])) < 1e-16 and np.all(u[held] == 0) and np.all(G[held] >= 0)
            ends.append(u)
        fds.append((ends[0] - ends[1]) / (2 * h))
    scale = np.max(np.abs(du))
    return np.max(np.abs(fds[1] - du)) / scale, np.max(np.abs(fds[0] - fds[1])) / scale


@pytest.mark.full
def test_six_muscle_arm_delayed_commands_match_finite_differences():
    """The six-muscle arm at 50 ms without noise: du*/dx0 against central differences of re-solves
    made exact by dense Newton steps on their free commands (the solver stops with |G_free| ~ 4e-14
    where H's smallest eigenvalue is 8e-7, which leaves errors of ~1e-5 relative in the difference
    quotients of the raw re-solves). About 40 excitations lie within the solver's margin of 0 at an
    interior optimum (u from 1e-10 to 1e-5, G ~ 0); held there by distance alone, as before
    derivation §16's fix, one of them (u = 4.7e-6, derivative 1.2e-2) made the tangent err by
    4.9e-3. Held are the commands the KKT conditions hold (implicit.fixed_commands), and every
    re-solve, polished, is a KKT point with that set (measured error 5.4e-8)."""
    err, spread = _muscle_arm_tangent_against_resolves(arm2_muscle6(delay=0.05, noise=False, **LI_TODOROV), (5e-5, 2.5e-5),
                                                       polish=True)
    worst.record(err, "six-muscle arm 50 ms forward u")
    assert spread < 1e-6
    assert err < 1e-5, err


# Both six-muscle checks run under make bench (pytest -m full): the suite keeps the noise-aware fixed
# point's derivative with held commands against re-solves on the torque arm (test_gradients.py,
# test_arm_noisy_limited_delayed_matches_finite_differences, the same 1e-5)
@pytest.mark.full
def test_six_muscle_arm_delayed_noisy_commands_match_finite_differences():
    """The six-muscle arm at 50 ms with its signal-dependent noise (the noise-aware solve's fixed
    point, derivation §16): du*/dx0 in forward mode against central differences of re-solves, within
    1e-5 of the largest component (measured 1.0e-7 at h = 5e-5 and 2.6e-7 at 1e-4; the two quotients
    agree to 2.0e-7, and at 2.5e-5 the re-solves' stopping error shows, 1.4e-6). Unlike the
    noise-free case above the raw re-solves suffice: the noise terms add curvature to the free
    commands."""
    err, spread = _muscle_arm_tangent_against_resolves(arm2_muscle6(delay=0.05, noise=True, **LI_TODOROV), (1e-4, 5e-5),
                                                       polish=False)
    worst.record(err, "six-muscle arm 50 ms noisy forward u")
    assert spread < 1e-6
    assert err < 1e-5, err
