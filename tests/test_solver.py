"""The nonlinear solver against independent references: the exact LQG optimum, a direct method
(L-BFGS over the whole command sequence with autodiff gradients), the augmentation method, and
exact expected costs of policies on the (linear) noisy point mass."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import linearize, rollout, trajectory_cost
from delayed_ilqr.lqg import Gains, augmented_backward_pass, backward_pass, policy_cost
from delayed_ilqr.ilqg import solver as solver_module
from delayed_ilqr.ilqg.backward import backward
from delayed_ilqr.models import arm2, point_mass

from direct import direct_optimum   # tests/direct.py

DELAYS = [0.0, 0.03, 0.1]


@pytest.mark.parametrize("delay", DELAYS)
def test_linear_problem_converges_in_one_step_to_the_lqg_optimum(delay):
    problem = point_mass(delay=delay)
    sol = di.solve(problem)
    us0 = jnp.zeros((problem.horizon, problem.n_controls))
    optimum = backward_pass(linearize(problem, rollout(problem, us0), us0))[1].expected_cost
    assert sol.converged, sol.message
    assert float(sol.trace.step_size[1]) == 1.0                  # the full Newton step, first try
    np.testing.assert_allclose(float(sol.trace.cost[1]), float(optimum), rtol=1e-10)
    np.testing.assert_allclose(float(sol.cost), float(optimum), rtol=1e-10)
    assert int(sol.iterations) == 2                               # the second only confirms I = 0


@pytest.mark.parametrize("factory", [point_mass, arm2], ids=["P1", "P2"])
@pytest.mark.parametrize("delay", DELAYS)
def test_agrees_with_a_direct_method(factory, delay):
    problem = factory(delay=delay)
    sol = di.solve(problem)
    assert sol.converged, sol.message
    reference = direct_optimum(problem)
    # iLQG may only be better than the direct method, and by no more than round-off of the latter
    assert abs(float(sol.cost) - reference) <= 1e-7 * reference


def test_structured_and_augmented_give_the_same_iterates_on_the_delayed_arm():
    """Same LQG, two exact solutions: the iterations must coincide.

    On P2 the gains of the two methods agree to ~5e-11 relative (H is ill-conditioned: E = dt Q =
    1e-6), and steps that cut the cost by 80x (891 -> 11 in the first) amplify that round-off, so
    per-iteration costs agree to ~6e-8 (measured), not to machine precision. What must hold exactly:
    the same step sizes, statuses and iteration counts; the first backward pass to 1e-9; the
    converged cost to 1e-12.
    """
    problem = arm2(delay=0.1)
    us0 = jnp.zeros((problem.horizon, 2))
    lqg = linearize(problem, rollout(problem, us0), us0)
    for g_s, g_a in zip(backward_pass(lqg)[0], augmented_backward_pass(lqg)[0]):
        np.testing.assert_allclose(np.asarray(g_s), np.asarray(g_a), rtol=0, atol=1e-9 * float(jnp.max(jnp.abs(g_a))))
    a = di.solve(problem)
    b = di.solve(problem, options=di.Options(method="augmented"))
    assert int(a.iterations) == int(b.iterations) and int(a.status) == int(b.status)
    n = int(a.iterations) + 1
    np.testing.assert_array_equal(np.asarray(a.trace.step_size[:n]), np.asarray(b.trace.step_size[:n]))
    np.testing.assert_allclose(np.asarray(a.trace.cost[:n]), np.asarray(b.trace.cost[:n]), rtol=1e-7)
    np.testing.assert_allclose(float(a.cost), float(b.cost), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(a.policy.delay_feedback), np.asarray(b.policy.delay_feedback),
                               rtol=1e-7, atol=1e-9)


def test_zero_delay_is_ordinary_ilqg():
    """l = 0: the structured recursion has no pending commands; augmentation has no buffer, so it
    is the textbook Riccati iLQG. Both must produce the same iterates, and the delay feedback is empty."""
    problem = arm2(delay=0.0)
    a = di.solve(problem)
    b = di.solve(problem, options=di.Options(method="augmented"))
    n = int(a.iterations) + 1
    assert a.policy.delay_feedback.shape == (problem.horizon, 0, 2, 2)
    # both compute the same Newton step with operations in a different order; the first step cuts
    # the cost 1e4-fold (891 -> 0.098), so round-off of the initial cost's scale stays in iterate 1
    cost0 = float(a.trace.cost[0])
    np.testing.assert_allclose(np.asarray(a.trace.cost[:n]), np.asarray(b.trace.cost[:n]), rtol=1e-9,
                               atol=1e-12 * cost0)
    np.testing.assert_allclose(np.asarray(a.policy.state_feedback), np.asarray(b.policy.state_feedback),
                               rtol=1e-7, atol=1e-9)


def test_a_negligible_predicted_reduction_ends_the_solve_before_the_line_search(monkeypatch):
    """Without noise the solve stops once the LQG model promises less than tol_cost |cost| for
    every step size. The number it stops on must be that promise, recomputed here from the
    augmented backward pass and the forward model (``predicted_change``) at the returned nominal,
    and going on must not buy more than the tolerance."""
    problem = arm2(delay=0.1)
    # A line search that overstates every reduction can never end the solve by the cost test, so
    # a CONVERGED_COST with it can only come from the model's promise, before any line search.
    real = solver_module.line_search

    def overstating(*args, **kwargs):
        ls = real(*args, **kwargs)
        return ls._replace(actual=jnp.abs(ls.actual) + 1.0)

    monkeypatch.setattr(solver_module, "line_search", overstating)
    u0 = jnp.zeros((problem.horizon, 2))
    overstated = jax.jit(lambda p: solver_module._solve.__wrapped__(p, u0, di.Options()))(problem)  # a fresh trace
    monkeypatch.undo()
    options = di.Options()
    sol = di.solve(problem, options=options)
    last = int(sol.iterations)
    assert int(sol.status) == di.Status.CONVERGED_COST, sol.message
    assert int(overstated.status) == di.Status.CONVERGED_COST and int(overstated.iterations) == last
    assert float(sol.trace.step_size[last]) == 0.0                       # no step taken ...
    *_, (a, b) = backward(problem, sol.x, sol.u, float(sol.trace.reg[last]), "augmented", 1e-5)
    alphas = np.asarray(options.alphas)
    promised = float(np.max(-(alphas * float(a) + alphas ** 2 * float(b))))
    assert 0.0 <= promised < options.tol_cost * float(sol.cost)          # ... because none was promised
    np.testing.assert_allclose(float(sol.trace.expected_reduction[last]), promised, rtol=1e-6)
    longer = di.solve(problem, options=di.Options(tol_cost=1e-300, max_iterations=last + 3))
    assert int(longer.iterations) > last
    assert 0.0 <= float(sol.cost) - float(longer.cost) <= options.tol_cost * float(sol.cost)


@pytest.mark.parametrize("delay", [0.03, 0.1])
def test_cost_never_increases_over_accepted_iterations(delay):
    sol = di.solve(arm2(delay=delay), options=di.Options(reg_init=1.0))
    n = int(sol.iterations) + 1
    cost = np.asarray(sol.trace.cost[:n])
    assert np.all(np.diff(cost) <= 0.0)
    accepted = np.asarray(sol.trace.step_size[1:n]) > 0
    assert accepted.sum() >= 3                      # the test exercises several accepted steps


def _exact_cost_in_noise(noisy, policy):
    """E[J] of running ``policy`` (nominal + feedback, no feedforward) on the noisy plant.

    The point mass is linear with linear noise in the command, so the LQG around any nominal is
    exact, and policy_cost gives the exact expectation (no sampling).
    """
    lqg = linearize(noisy, policy.x_nominal, policy.u_nominal)
    gains = Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    return float(policy_cost(lqg, gains))


@pytest.mark.parametrize("delay", [0.0, 0.03, 0.1])
def test_noise_aware_policy_beats_the_deterministic_one_in_noise(delay):
    noisy = point_mass(delay=delay, noise=True)
    stochastic = di.solve(noisy)
    deterministic = di.solve(point_mass(delay=delay))
    assert stochastic.converged, stochastic.message
    j_stochastic = _exact_cost_in_noise(noisy, stochastic.policy)
    j_deterministic = _exact_cost_in_noise(noisy, deterministic.policy)
    np.testing.assert_allclose(j_stochastic, float(stochastic.expected_cost), rtol=1e-8)
    assert j_stochastic < 0.99 * j_deterministic     # signal-dependent noise: a real gain, not round-off


def test_noisy_point_mass_expected_cost_matches_the_independent_value():
    """docs/derivation.md §10 (E7) reports 11.61 for the stochastic point mass at tau = 0.03, computed by an
    independent implementation with the sqrt(dt) noise scaling."""
    sol = di.solve(point_mass(delay=0.03, noise=True))
    assert round(float(sol.expected_cost), 2) == 11.61


@pytest.mark.parametrize("delay_steps", [0, 3])
def test_indefinite_hessian_raises_lambda_then_converges(delay_steps):
    """The running cost (u^2 - 1)^2 is concave in u for |u| < 3^-1/2, so the first backward pass
    from u = 0.3 meets an H that is not positive definite: no line search is run with its gains,
    lambda is raised until H + lambda I is, and the solve then converges to the minimum u = 1."""
    cost = di.GeneralCost(lambda x, u, p: 10.0 * (u[0] ** 2 - 1.0) ** 2, lambda x, p: 0.0)
    problem = di.Problem(lambda x, u, ud: jnp.array([ud[0]]), x0=[0.0], dt=0.05, horizon=20,
                         delay_steps=delay_steps, cost=cost, n_controls=1)
    sol = di.solve(problem, u_init=np.full((20, 1), 0.3))
    assert sol.converged, sol.message
    assert float(sol.trace.step_size[1]) == 0.0 and float(sol.trace.reg[2]) > 0.0   # rejected, lambda up
    assert np.all(np.isfinite(np.asarray(sol.policy.state_feedback)))
    np.testing.assert_allclose(np.asarray(sol.u), 1.0, atol=1e-6)


def test_overflowing_initial_guess_reports_a_status():
    problem = arm2(delay=0.03)
    sol = di.solve(problem, u_init=np.full((problem.horizon, 2), 1e200))
    assert int(sol.status) == di.Status.NON_FINITE_INITIAL
    assert not sol.converged and "u_init" in sol.message
    assert int(sol.iterations) == 0


def test_iteration_limit_reports_a_status():
    sol = di.solve(arm2(delay=0.03), options=di.Options(max_iterations=2, reg_init=1.0))
    assert int(sol.status) == di.Status.MAX_ITERATIONS
    assert "max_iterations" in sol.message
    assert np.all(np.isfinite(np.asarray(sol.u)))


def _line_final(x, params):
    """A pure-line target on the muscle arm: the hand's distance to the line y = target_y (no cost
    along it) and its final speed."""
    from delayed_ilqr.models.arm2 import hand_position, hand_velocity
    v = hand_velocity(x[:2], x[2:4])
    return params["w_p"] * (hand_position(x[:2])[1] - params["target"][1]) ** 2 + params["w_v"] * (v @ v)


def _effort(x, u, params):
    return params["r"] * (u @ u)


def test_no_nan_in_the_policy_when_the_last_backward_pass_fails():
    """The muscle arm's noisy reach to a line (a GeneralCost without lateral cost) at 50 ms: the
    iteration limit is met at a nominal whose backward pass fails. Before, the policy carried NaN
    feedback gains (and a NaN expected cost) under MAX_ITERATIONS; now the solve returns the last
    nominal whose gains were finite, with them, and says so."""
    from delayed_ilqr.models import arm2_muscle6
    from delayed_ilqr.models.arm2_muscle6 import rest_commands
    from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV
    base = arm2_muscle6(delay=0.05, **LI_TODOROV)
    problem = base.replace(cost=di.GeneralCost(_effort, _line_final, base.cost.params))
    sol = di.solve(problem, rest_commands(problem), di.Options(max_iterations=20))
    assert sol.status == di.Status.NON_FINITE_GAINS, sol.status
    assert "last backward pass whose gains were finite" in sol.message and not sol.converged
    for leaf in jax.tree_util.tree_leaves(sol.policy):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.isfinite(float(sol.expected_cost))
    # the policy belongs to the nominal returned
    np.testing.assert_array_equal(sol.policy.x_nominal, sol.x)
    np.testing.assert_array_equal(sol.policy.u_nominal, sol.u)
    np.testing.assert_allclose(float(sol.cost), float(trajectory_cost(problem, sol.x, sol.u)), rtol=1e-12)


def test_vmap_over_initial_states_matches_separate_solves():
    problem = point_mass(delay=0.03)
    x0s = jnp.array([[0.0, 0.0, 0.0, 0.0], [0.05, -0.02, 0.1, 0.0], [-0.1, 0.1, 0.0, -0.2]])

    def solve_from(x0):
        return di.solve(problem.replace(x0=x0)).cost

    batched = jax.vmap(solve_from)(x0s)
    separate = [float(di.solve(problem.replace(x0=x0)).cost) for x0 in np.asarray(x0s)]
    np.testing.assert_allclose(np.asarray(batched), separate, rtol=1e-10)


def test_vmap_batches_agree_with_separate_solves_in_every_field():
    # on CPU a vmap of solve runs the problems one after another (ilqg.solver._one_after_another): each
    # must stop where its own solve stops, batched or not, under jit and nested vmaps alike
    problems = [arm2(delay=0.03, x_target=(np.pi / 2 + a, np.pi / 3, 0.0, 0.0)) for a in (0.0, 0.2)]
    u_inits = np.stack([np.zeros((50, 2)), np.full((50, 2), 0.05)])
    separate = [[di.solve(p, u) for u in u_inits] for p in problems]
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *problems)
    over_u = jax.vmap(di.solve, in_axes=(None, 0))
    nested = jax.jit(jax.vmap(over_u, in_axes=(0, None)))(stacked, u_inits)
    for i in range(2):
        for j in range(2):
            for field in ("cost", "iterations", "status", "u"):
                np.testing.assert_allclose(np.asarray(getattr(nested, field))[i, j],
                                           np.asarray(getattr(separate[i][j], field)), rtol=1e-12, atol=1e-15)
    assert len({int(s.iterations) for row in separate for s in row}) > 1   # the problems stop apart


def test_solution_fields_have_documented_shapes():
    problem = arm2(delay=0.03)
    sol = di.solve(problem)
    K, n, d, l = problem.horizon, 4, 2, problem.delay_steps
    assert sol.x.shape == (K + 1, n) and sol.u.shape == (K, d)
    assert sol.policy.state_feedback.shape == (K, d, n)
    assert sol.policy.delay_feedback.shape == (K, l, d, d)
    assert sol.x.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(sol.x), np.asarray(rollout(problem, sol.u)), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(float(sol.cost), float(trajectory_cost(problem, sol.x, sol.u)), rtol=1e-12)


# ------------------------------------------------------------------------------------------------
# validation: each rule names the argument, the rule and what was received
# ------------------------------------------------------------------------------------------------

def _f(x, u, ud):
    return jnp.concatenate([x[2:], ud])


COST = di.QuadraticCost(np.zeros((4, 4)), 1e-4 * np.eye(2), np.eye(4), np.zeros(4))


def _problem(**kw):
    args = dict(dynamics=_f, x0=np.zeros(4), dt=0.01, horizon=10, delay_steps=2, cost=COST)
    args.update(kw)
    return di.Problem(**args)


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(dynamics="f"), TypeError, r"dynamics must be callable as f\(x, u, ud\); got str"),
    (dict(noise=3), TypeError, r"noise must be None or callable as F\(x, u, ud\); got int"),
    (dict(dt=0.0), ValueError, r"dt must be a positive finite number; got 0.0"),
    (dict(dt=float("nan")), ValueError, r"dt must be a positive finite number; got nan"),
    (dict(horizon=0), ValueError, r"horizon must be a positive integer; got 0"),
    (dict(horizon=2.5), ValueError, r"horizon must be a positive integer; got 2.5"),
    (dict(delay_steps=-1), ValueError, r"delay_steps must be a non-negative integer number of steps; got -1"),
    (dict(delay_steps=-1.5), ValueError, r"delay_steps must be a finite, non-negative number of steps; got -1.5"),
    (dict(x0=np.zeros((4, 1))), ValueError, r"x0 must have shape \(\*,\); got shape \(4, 1\)"),
    (dict(x0=[0.0, np.nan, 0.0, 0.0]), ValueError, r"x0 must be finite; got a non-finite value at index \(1,\)"),
    (dict(cost="quadratic"), TypeError, r"cost must be a QuadraticCost or a GeneralCost; got str"),
    (dict(cost=COST._replace(Q=np.zeros((2, 2)))), ValueError,
     r"cost.Q must be positive definite; got a smallest eigenvalue of 0"),
    (dict(cost=COST._replace(P=-np.eye(4))), ValueError,
     r"cost.P must be positive semi-definite; got a smallest eigenvalue of -1"),
    (dict(cost=COST._replace(P_final=np.triu(np.ones((4, 4))))), ValueError, r"cost.P_final must be symmetric"),
    (dict(cost=COST._replace(x_target=np.zeros(3))), ValueError,
     r"cost.x_target must have shape \(4,\); got shape \(3,\)"),
    (dict(u_min=[1.0, 1.0], u_max=[0.0, 2.0]), ValueError, r"u_min must be below u_max in every component"),
    (dict(u_min=[0.0, 0.0, 0.0]), ValueError, r"the number of controls must agree across arguments"),
    (dict(dynamics=lambda x, u, ud: x[:3]), ValueError, r"dynamics\(x, u, ud\) must return shape \(4,\); got \(3,\)"),
    (dict(noise=lambda x, u, ud: jnp.ones(4)), ValueError, r"noise\(x, u, ud\) must return shape \(4, p\); got \(4,\)"),
    (dict(dynamics=lambda x, u, ud: x @ jnp.ones((3, 4))), ValueError, r"dynamics\(x, u, ud\) failed on x of shape \(4,\)"),
])
def test_problem_validation(kwargs, error, message):
    with pytest.raises(error, match=message):
        _problem(**kwargs)


def test_general_cost_needs_the_number_of_controls():
    cost = di.GeneralCost(lambda x, u, p: u @ u, lambda x, p: x @ x)
    with pytest.raises(ValueError, match=r"n_controls must be given when it cannot be read from cost.Q"):
        _problem(cost=cost)
    assert _problem(cost=cost, n_controls=2).n_controls == 2
    with pytest.raises(TypeError, match=r"running must be callable as running\(x, u, params\); got int"):
        di.GeneralCost(1, lambda x, p: 0.0)
    with pytest.raises(ValueError, match=r"cost.final\(x\) must return a scalar; got shape \(4,\)"):
        _problem(cost=di.GeneralCost(lambda x, u, p: u @ u, lambda x, p: x), n_controls=2)


@pytest.mark.parametrize("kwargs, error, message", [
    (dict(method="dense"), ValueError, r"method must be 'structured' or 'augmented'; got 'dense'"),
    (dict(max_iterations=0), ValueError, r"max_iterations must be a positive integer; got 0"),
    (dict(tol_cost=-1.0), ValueError, r"tol_cost must be a positive finite number; got -1.0"),
    (dict(reg_init=-1.0), ValueError, r"reg_init must be a finite number >= 0; got -1.0"),
    (dict(reg_factor=1.0), ValueError, r"reg_factor must be greater than 1; got 1.0"),
    (dict(limit_margin=0.5), ValueError, r"limit_margin must be a number in \[0, 0.5\); got 0.5"),
    (dict(alphas=(1.0, 2.0)), ValueError, r"alphas must be a non-empty sequence of step sizes in \(0, 1\]"),
])
def test_options_validation(kwargs, error, message):
    with pytest.raises(error, match=message):
        di.Options(**kwargs)


def test_solve_validation():
    problem = _problem()
    with pytest.raises(ValueError, match=r"u_init must have shape \(10, 2\); got shape \(10, 3\)"):
        di.solve(problem, u_init=np.zeros((10, 3)))
    with pytest.raises(TypeError, match=r"problem must be a delayed_ilqr.Problem; got dict"):
        di.solve({})
    with pytest.raises(TypeError, match=r"options must be a delayed_ilqr.Options; got dict"):
        di.solve(problem, options={})


@pytest.mark.parametrize("tol_cost", [1e-15, 1e-300])
def test_a_tolerance_below_round_off_leaves_the_stop_to_the_gradient_test(tol_cost):
    """P2-noisy at 50 ms: the merit cannot resolve the last steps (derivation §12). Asked for a
    tol_cost below ROUNDOFF, the solve takes full Newton steps there and ends CONVERGED_GRADIENT
    below tol_grad, instead of REGULARIZATION_LIMIT (1e-300) or CONVERGED_COST at a gradient
    measure of 3e-9 (1e-15); its fixed point is the default solve's to that solve's accuracy."""
    from delayed_ilqr.ilqg.solver import ROUNDOFF
    problem = arm2(delay=0.05, noise="benchmark")
    options = di.Options(tol_cost=tol_cost, tol_grad=1e-13, max_iterations=60)
    sol = di.solve(problem, options=options)
    n = int(sol.iterations)
    assert sol.status == di.Status.CONVERGED_GRADIENT, sol.message
    assert float(sol.trace.grad_norm[n]) < 1e-13 and float(sol.trace.reg[n]) == 0.0
    # the steps the merit could not resolve were full steps, and only they
    promised = np.asarray(sol.trace.expected_reduction[1:n])
    full = np.asarray(sol.trace.step_size[1:n]) == 1.0
    merit = np.abs(np.asarray(sol.trace.merit[:n - 1]))
    assert np.all(full[promised < ROUNDOFF * merit])
    default = di.solve(problem)
    assert default.converged
    np.testing.assert_allclose(sol.u, default.u, rtol=0, atol=1e-6 * float(np.max(np.abs(sol.u))))


def test_options_that_differ_in_their_numbers_share_one_compilation():
    """Options is a pytree: its numbers are traced arguments of the compiled solver, its structure
    (method, max_iterations, max_alternations, the number of alphas) static. A sweep over the
    numbers compiles once, and the numbers still act: a large reg_init takes the linear problem
    off its one-step Newton convergence."""
    problem = point_mass(delay=0.03)
    newton = di.solve(problem)
    compiled = solver_module._solve._cache_size()
    damped = di.solve(problem, options=di.Options(reg_init=1e3, reg_factor=2.0, tol_cost=1e-9, tol_grad=1e-6,
                                                  alphas=tuple(0.5 ** i for i in range(11)), z_min=0.1,
                                                  limit_margin=1e-3, reg_min=1e-7, reg_max=1e12))
    assert solver_module._solve._cache_size() == compiled
    assert int(newton.iterations) == 2 and int(damped.iterations) > 2
    assert float(damped.trace.reg[1]) == 1e3 and float(newton.trace.reg[1]) == 0.0
    np.testing.assert_allclose(float(damped.cost), float(newton.cost), rtol=1e-6)
    # a new structure compiles again
    di.solve(problem, options=di.Options(max_iterations=7))
    assert solver_module._solve._cache_size() == compiled + 1
    # an Options passed into jit as an argument: one compilation for two tolerances
    cost = jax.jit(lambda o: di.solve(problem, options=o).cost)
    np.testing.assert_allclose([float(cost(di.Options(tol_cost=t))) for t in (1e-10, 1e-6)], float(newton.cost),
                               rtol=1e-8)
    assert cost._cache_size() == 1
    # the numbers are Python floats whatever they were given as (one argument type: one compilation)
    assert type(di.Options(tol_cost=np.float64(1e-9), reg_init=1).reg_init) is float
