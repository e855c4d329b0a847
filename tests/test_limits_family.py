"""Control limits must converge about as fast as the unbounded solve, to the bounded optimum.

A family of random bounded problems, drawn from a fixed list of seeds: two-link arm reaches (the P2
arm and cost) to random joint targets, point-mass reaches to random points, and cart-pole moves of
the balanced pole to a random cart position; delays of 0 to 10 steps; limits at 40-90 % of the
unbounded optimum's peak command (per control). Each bounded solve, with the default options, must
converge in at most 3 times the unbounded problem's iterations plus 10, to a cost within 1e-6
(relative) of the best of bounded L-BFGS-B started from zero and from the clipped unbounded optimum
(``tests/direct.py``).

Box-DDP (a box QP per step) missed two arm seeds (about 100 iterations against bounds of 43 and
46); the projected Newton step of ``ilqg.bounded`` takes at most as many iterations as the unbounded
solve on every seed (docs/derivation.md §15). The swing-ups of the pendulum, the cart-pole and the
acrobot from rest, with their default torque limits, must reach the cost of multi-start bounded
L-BFGS-B. With a tight elbow limit the acrobot's swing-up from rest has a poor local minimum that
L-BFGS-B from rest reaches too; the remedy, several starts (rest and the clipped solutions of looser
problems) solved at once under ``vmap``, must reach the best multi-start L-BFGS-B cost.
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.models import acrobot, arm2, cart_pole, pendulum, point_mass

from direct import direct_optimum   # tests/direct.py

def family_problem(seed: int):
    """(unbounded problem, its solution, bounded problem) of one member of the family."""
    rng = np.random.default_rng(seed)
    kind = ("arm", "arm", "point_mass", "cart_pole")[seed % 4]
    delay_steps = int(rng.integers(0, 11))
    if kind == "arm":
        target = (math.pi / 2 + rng.uniform(-0.4, 0.4), math.pi / 3 + rng.uniform(-0.4, 0.4), 0.0, 0.0)
        problem = arm2(delay=0.01 * delay_steps, x_target=target)
    elif kind == "point_mass":
        problem = point_mass(delay=0.01 * delay_steps, x_target=(*rng.uniform(-0.3, 0.3, 2), 0.0, 0.0))
    else:   # the balanced pole carried to a new cart position within 2 s
        problem = cart_pole(delay=0.02 * delay_steps, horizon=100, limits=False, x0=(0.0, math.pi, 0.0, 0.0),
                            x_target=(rng.uniform(-1.0, 1.0), math.pi, 0.0, 0.0))
    free = di.solve(problem)
    assert free.converged, free.message
    peak = np.max(np.abs(np.asarray(free.u)), axis=0)
    fraction = rng.uniform(0.4, 0.9)
    bounded = problem.replace(u_min=-fraction * peak, u_max=fraction * peak)
    return problem, free, bounded


# one member of each kind in the suite (an arm, a point mass, a cart-pole), the other five under make bench
SEEDS = [0, 2, 3] + [pytest.param(s, marks=pytest.mark.full) for s in (1, 4, 5, 6, 7)]


@pytest.mark.parametrize("seed", SEEDS)
def test_bounded_family_converges_fast_to_the_bounded_optimum(seed):
    _, free, bounded = family_problem(seed)
    sol = di.solve(bounded)
    u = np.asarray(sol.u)
    assert np.all((u >= np.asarray(bounded.u_min)) & (u <= np.asarray(bounded.u_max)))
    reference = min(direct_optimum(bounded), direct_optimum(bounded, u_init=free.u))
    assert abs(float(sol.cost) - reference) <= 1e-6 * reference, (float(sol.cost), reference)
    assert sol.converged, sol.message
    assert int(sol.iterations) <= 3 * int(free.iterations) + 10, (int(sol.iterations), int(free.iterations))


@pytest.mark.parametrize("factory", [pendulum, pytest.param(cart_pole, marks=pytest.mark.full), acrobot])
def test_swing_up_from_rest_reaches_the_multi_start_optimum(factory):
    # the torque-limited swing-ups of models.pendulum (4 N m), models.cart_pole (10 N) and
    # models.acrobot (5 N m at the elbow) from u_init = 0: the cost of bounded L-BFGS-B from zero and
    # from a random start in the box (five starts agree to 7 digits, docs/derivation.md §15; the
    # cart-pole's take minutes)
    problem = factory()
    sol = di.solve(problem, options=di.Options(max_iterations=200))
    assert sol.converged, sol.message
    rng = np.random.default_rng(0)
    lim = float(np.asarray(problem.u_max)[0])
    starts = [None, rng.uniform(-lim, lim, (problem.horizon, 1))]
    reference = min(direct_optimum(problem, u_init=u) for u in starts)
    assert abs(float(sol.cost) - reference) <= 1e-6 * reference, (float(sol.cost), reference)


def test_acrobot_tight_limit_poor_minimum_from_rest_and_the_several_starts_remedy():
    # the acrobot at |u| <= 2.2 N m (docs/derivation.md §15): from rest, iLQG and bounded L-BFGS-B
    # both stop at one local minimum (a partial swing, cost 379); L-BFGS-B from a random start in the
    # box finds a swing-up five times cheaper, which iLQG reaches from the solution at the default
    # 5 N m clipped to the tight limit (a continuation on the limit). The remedy solves from rest,
    # from the clipped unbounded optimum and from the clipped 5 N m solution at once (vmap) and
    # keeps the cheapest.
    options = di.Options(max_iterations=200)
    tight = acrobot(u_max=2.2)
    lim = float(np.asarray(tight.u_max)[0])
    rest = np.zeros((tight.horizon, 1))
    free = di.solve(acrobot(limits=False), options=options)
    loose = di.solve(acrobot(), options=options)
    assert free.converged and loose.converged
    starts = jnp.stack([jnp.asarray(rest), jnp.clip(free.u, -lim, lim), jnp.clip(loose.u, -lim, lim)])
    sols = jax.vmap(lambda u: di.solve(tight, u, options))(starts)
    costs = np.asarray(sols.cost)
    assert np.all(np.asarray(sols.converged)), np.asarray(sols.status)
    u = np.asarray(sols.u)
    assert np.all((u >= -lim) & (u <= lim))
    from_rest = direct_optimum(tight, u_init=rest)
    best = direct_optimum(tight, u_init=np.random.default_rng(0).uniform(-lim, lim, (tight.horizon, 1)))
    assert abs(costs[0] - from_rest) <= 1e-6 * from_rest, (costs[0], from_rest)   # the same local minimum
    assert best < 0.25 * from_rest, (best, from_rest)
    assert abs(costs.min() - best) <= 1e-6 * best, (costs, best)
