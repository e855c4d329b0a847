"""Control limits: the box-QP backward pass (Tassa, Mansard & Todorov 2014) inside the delayed
recursion, checked at the LQG level (exactness under clamped gains, structured == augmented) and
on the nonlinear problems against a bounded direct method (L-BFGS-B over all commands)."""
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.lqg import DelayedLQG, Gains, policy_cost
from delayed_ilqr.ilqg.bounded import bounded_step, linear_plan, model_cost
from delayed_ilqr.lqg.augmented import augmented_scan
from delayed_ilqr.lqg.frame import from_slots, to_slots
from delayed_ilqr.lqg.gains import boxed_gains, unconstrained_gains, unregularized_feedback
from delayed_ilqr.lqg.structured import structured_scan
from delayed_ilqr.models import arm2, point_mass

from direct import direct_optimum   # tests/direct.py


def _random_lqg(K, nx, nd, p, l, seed):
    rng = np.random.default_rng(seed)

    def spd(m, *shape):
        X = rng.normal(size=shape + (m, m))
        return X @ np.swapaxes(X, -1, -2) / m + 0.1 * np.eye(m)

    return DelayedLQG(np.eye(nx) + 0.3 * rng.normal(size=(K, nx, nx)), rng.normal(size=(K, nx, nd)),
                      rng.normal(size=(K, nx, nd)), 0.3 * rng.normal(size=(K, p, nx)),
                      0.2 * rng.normal(size=(K, p, nx, nd)), 0.2 * rng.normal(size=(K, p, nx, nd)),
                      rng.normal(size=K + 1), rng.normal(size=(K + 1, nx)), spd(nx, K + 1),
                      rng.normal(size=(K, nd)), spd(nd, K), l)


@pytest.mark.parametrize("l", [0, 1, 3, 20])
def test_clamped_recursion_is_exact_and_matches_augmentation(l):
    lqg = _random_lqg(12, 3, 2, 1, l, seed=l)
    free_gains = structured_scan(lqg, store_value=False)[0]
    half = 0.5 * float(jnp.max(jnp.abs(free_gains.feedforward)))
    bounds = (jnp.full((12, 2), -half), jnp.full((12, 2), half))
    gains, (s_tilde, _, _), ok = structured_scan(lqg, store_value=False, gains_fn=boxed_gains, bounds=bounds)
    gains_aug, value_aug = augmented_scan(lqg, gains_fn=boxed_gains, bounds=bounds)
    assert bool(ok)
    clamped = np.abs(np.asarray(gains.feedforward)) >= half * (1 - 1e-12)
    assert clamped.any()                                           # the bounds do bind
    assert np.all(np.abs(np.asarray(gains.feedforward)) <= half * (1 + 1e-12))
    # feedback only in free directions
    assert np.all(np.asarray(gains.state_feedback)[clamped] == 0.0)
    assert np.all(np.moveaxis(np.asarray(gains.delay_feedback), 1, 2)[clamped] == 0.0)
    # the value is the exact expected cost of the clamped policy, and both recursions agree
    np.testing.assert_allclose(float(s_tilde[0]), float(policy_cost(lqg, gains)), rtol=1e-10)
    np.testing.assert_allclose(float(s_tilde[0]), float(value_aug.s_tilde[0]), rtol=1e-10)
    for a, b in zip(gains, gains_aug):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("limited", [False, True])
@pytest.mark.parametrize("l", [0, 4])
def test_unregularized_feedback_keeps_the_value_hessians_of_lambda_zero(l, limited):
    # with noise the merit is cost + sum c'S c, so S must not move with lambda (solver with noise)
    K = 10
    lqg = _random_lqg(K, 3, 2, 2, l, seed=7 + l)
    gains_fn, kw = unconstrained_gains, {}
    if limited:
        half = 0.5 * float(jnp.max(jnp.abs(structured_scan(lqg, store_value=False)[0].feedforward)))
        gains_fn = partial(boxed_gains, margin=1e-5)
        kw = dict(bounds=(jnp.full((K, 2), -half), jnp.full((K, 2), half)))
    exact, (_, _, S_exact), _ = structured_scan(lqg, 0.0, store_value=False, gains_fn=gains_fn, **kw)
    plain, (_, _, S_plain), _ = structured_scan(lqg, 3.0, store_value=False, gains_fn=gains_fn, **kw)
    gains, (s_tilde, _, S), ok = structured_scan(lqg, 3.0, store_value=False, gains_fn=unregularized_feedback(gains_fn),
                                                 **kw)
    assert bool(ok)
    assert float(jnp.max(jnp.abs(S_plain - S_exact))) > 1e-3 * float(jnp.max(jnp.abs(S_exact)))   # lambda matters
    np.testing.assert_allclose(S, S_exact, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(gains.state_feedback, exact.state_feedback, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(gains.delay_feedback, exact.delay_feedback, rtol=1e-10, atol=1e-12)
    # lambda still shortens the feedforward, and the value is the exact cost of the mixed policy
    assert float(jnp.linalg.norm(gains.feedforward)) < float(jnp.linalg.norm(exact.feedforward))
    np.testing.assert_allclose(float(s_tilde[0]), float(policy_cost(lqg, gains)), rtol=1e-10)


@pytest.mark.parametrize("delay", [0.0, 0.03, 0.1])
def test_bounded_point_mass_matches_bounded_direct_method(delay):
    problem = point_mass(delay=delay).replace(u_min=[-1.0, -1.0], u_max=[1.0, 1.0])
    sol = di.solve(problem)
    assert sol.converged, sol.message
    assert np.all(np.abs(np.asarray(sol.u)) <= 1.0)
    assert np.isclose(float(jnp.max(jnp.abs(sol.u))), 1.0)          # the limit binds
    reference = direct_optimum(problem)
    assert abs(float(sol.cost) - reference) <= 1e-6 * reference


@pytest.mark.parametrize("limit, delay", [(1.5, 0.0), (2.0, 0.0), (2.0, 0.03), (1.5, 0.03), (1.5, 0.1)])
def test_bounded_arm_matches_bounded_direct_method(limit, delay):
    # +-1.5 N m with no delay is the slowest case (217 iterations: the active set settles late)
    problem = arm2(delay=delay).replace(u_min=[-limit, -limit], u_max=[limit, limit])
    sol = di.solve(problem, options=di.Options(max_iterations=400))
    assert sol.converged, sol.message
    assert np.all(np.abs(np.asarray(sol.u)) <= limit)
    assert np.isclose(float(jnp.max(jnp.abs(sol.u))), limit)          # the limit binds
    reference = direct_optimum(problem)
    assert abs(float(sol.cost) - reference) <= 1e-6 * reference


def test_commands_at_or_near_a_bound_get_no_feedback():
    # one step's quadratic; the gradient pulls command 0 inward (the QP frees it), command 1 is far
    # inside. Command 0's nominal sits at, or 1e-7 inside, its upper bound (du <= upper_0).
    H = jnp.array([[2.0, 0.5], [0.5, 1.0]])
    g = jnp.array([0.3, -0.2])
    G = jnp.array([[1.0, -2.0, 0.5], [0.3, 0.1, -1.0]])
    full = -jnp.linalg.solve(H, G)
    alone = -G[1] / H[1, 1]                                     # command 1's feedback with command 0 fixed
    # upper_0 = inf: command 0 bounded below only, far from its bound (a margin relative to an
    # infinite range would take its feedback however far it is)
    for upper_0, margin, feedback_0 in [(0.0, 0.0, False), (1e-7, 0.0, True), (1e-7, 1e-5, False),
                                        (1.0, 1e-5, True), (jnp.inf, 1e-5, True)]:
        bounds = (jnp.array([-2.0, -2.0]), jnp.array([upper_0, 2.0]))
        ok, I, K = boxed_gains(H, 0.0, g, G, bounds, jnp.zeros(2), margin=margin)
        assert bool(ok)
        np.testing.assert_allclose(I, -jnp.linalg.solve(H, g), rtol=1e-12)   # interior optimum, moves inward
        assert float(I[0]) < 0
        if feedback_0:
            np.testing.assert_allclose(K, full, rtol=1e-12)
        else:
            assert np.all(np.asarray(K[0]) == 0.0)
            np.testing.assert_allclose(K[1], alone, rtol=1e-12)


@pytest.mark.parametrize("noise", [False, True])
@pytest.mark.parametrize("u_max", [1e5, np.inf])
def test_limits_that_never_bind_change_nothing(u_max, noise):
    # u_max = inf: limits on one side only (the bounded step without noise, the box QP with it)
    problem = point_mass(delay=0.03, noise=noise)
    free = di.solve(problem)
    wide = di.solve(problem.replace(u_min=[-1e5, -1e5], u_max=[u_max, u_max]))
    assert float(jnp.max(jnp.abs(wide.trace.grad_norm[1]))) < 1e3     # the first step stays far inside
    assert int(free.iterations) == int(wide.iterations)
    np.testing.assert_allclose(np.asarray(wide.u), np.asarray(free.u), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(np.asarray(wide.policy.delay_feedback), np.asarray(free.policy.delay_feedback),
                               rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("l", [0, 3])
def test_model_cost_is_the_exact_cost_of_the_open_loop_plan(l):
    # ilqg.bounded minimises model_cost; lqg.exact.policy_cost is the independent statement of it
    K, nd = 9, 2
    lqg = _random_lqg(K, 3, nd, 0, l, seed=20 + l)
    du = jnp.asarray(np.random.default_rng(l).normal(size=(K, nd)))
    open_loop = lambda I: Gains(I, jnp.zeros((K, nd, 3)), jnp.zeros((K, l, nd, nd)))
    want = policy_cost(lqg, open_loop(du)) - policy_cost(lqg, open_loop(jnp.zeros_like(du)))
    np.testing.assert_allclose(float(jax.jit(model_cost)(lqg, du)), float(want), rtol=1e-10)


@pytest.mark.parametrize("method", ["structured", "augmented"])
@pytest.mark.parametrize("l", [0, 3])
def test_bounded_step_plans_the_minimiser_over_the_box(l, method):
    """The law of ``bounded_step`` has as its linear plan the minimiser of the LQG over the box
    (bounded L-BFGS-B on the model's cost, an independent solve), lies in the box for every alpha,
    and its expected cost and predicted change are those of the law (``policy_cost``)."""
    import scipy.optimize

    K, nd = 12, 2
    lqg = _random_lqg(K, 3, nd, 0, l, seed=30 + l)
    plan_of = jax.jit(linear_plan)
    free_plan = plan_of(lqg, to_slots(structured_scan(lqg, store_value=False)[0]))
    rng = np.random.default_rng(l)
    half = 0.4 * np.max(np.abs(np.asarray(free_plan)), axis=0)
    shift = rng.uniform(-0.5, 0.5, size=(K, nd)) * half            # nominal not centred in its box
    lower, upper = jnp.asarray(-half - shift), jnp.asarray(half - shift)
    step = jax.jit(bounded_step, static_argnames="method")
    gains, expected, ok, (a, b) = step(lqg, 0.0, lower, upper, jnp.full(nd, 1e-9), method=method)
    assert bool(ok)
    plan = np.asarray(plan_of(lqg, gains))
    fun = jax.jit(lambda v: model_cost(lqg, v.reshape(K, nd)))
    grad = jax.jit(jax.grad(lambda v: model_cost(lqg, v.reshape(K, nd))))
    ref = scipy.optimize.minimize(lambda v: float(fun(v)), np.zeros(K * nd), jac=lambda v: np.asarray(grad(v)),
                                  method="L-BFGS-B", bounds=list(zip(np.ravel(lower), np.ravel(upper))),
                                  options=dict(ftol=1e-15, gtol=1e-12, maxiter=10000))
    at_bound = np.isclose(plan, np.asarray(lower), atol=1e-12) | np.isclose(plan, np.asarray(upper), atol=1e-12)
    assert at_bound.any() and not at_bound.all()                   # the box binds, not everywhere
    assert np.all((plan >= np.asarray(lower) - 1e-12) & (plan <= np.asarray(upper) + 1e-12))
    assert float(fun(jnp.asarray(plan.ravel()))) <= ref.fun + 1e-9 * abs(ref.fun)
    np.testing.assert_allclose(plan, ref.x.reshape(K, nd), atol=1e-5 * np.max(half))
    # clamped commands get no feedback; the value and the prediction are the law's
    feedback = np.asarray(gains.feedback)
    assert np.all(feedback[at_bound] == 0.0)
    exact = float(policy_cost(lqg, from_slots(gains, 3)))
    np.testing.assert_allclose(float(expected), exact, rtol=1e-10)
    np.testing.assert_allclose(float(a + b), exact - float(jnp.sum(lqg.d_tilde)), rtol=1e-9)


def test_an_empty_box_under_vmap_is_flagged_in_the_status():
    """u_min < u_max is checked when the limits are concrete; traced limits (a vmap over them)
    cannot be refused, so the solve says so: an empty box (or a NaN limit) ends
    INVALID_TRACED_INPUT without solving, beside a valid box in the same batch (before, it ended
    converged with commands outside the box)."""
    problem = point_mass(delay=0.03)

    def solve_in(lo, hi):
        return di.solve(problem.replace(u_min=lo, u_max=hi))

    lo = jnp.array([[-1.0, -1.0], [1.0, -1.0], [jnp.nan, -1.0]])
    hi = jnp.array([[1.0, 1.0], [-1.0, 1.0], [1.0, 1.0]])
    sols = jax.vmap(solve_in)(lo, hi)
    assert [di.Status(int(s)) for s in sols.status] == [di.Status.CONVERGED_GRADIENT, di.Status.INVALID_TRACED_INPUT,
                                                        di.Status.INVALID_TRACED_INPUT], sols.status
    assert "u_min >= u_max" in sols.message[1] and int(sols.iterations[1]) == 0
    for leaf in jax.tree_util.tree_leaves(sols.policy):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert not np.any(np.asarray(sols.policy.state_feedback[1]))         # nothing was solved
    ref = di.solve(problem.replace(u_min=-1.0, u_max=1.0))
    np.testing.assert_allclose(sols.u[0], ref.u, rtol=1e-9, atol=1e-12)
