"""The line search's model: the predicted merit change of the LQG against the merit of real
closed-loop rollouts on the nonlinear plant, and the noise-aware iteration that relies on it."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.backward import backward
from delayed_ilqr.ilqg.closed_loop import closed_loop_rollout
from delayed_ilqr.ilqg.line_search import candidate_scores, merit
from delayed_ilqr.ilqg.linearize import rollout
from delayed_ilqr.models import arm2


def _slope_ratios(problem, us, alphas, noise_at_candidate=False):
    """(merit(alpha) - merit(0)) / (alpha a + alpha^2 b) for rollouts of the backward pass's gains."""
    xs = rollout(problem, us)
    gains, S, _, ok, (a, b) = backward(problem, xs, us, 0.0, "structured", 1e-5)
    assert bool(ok)
    assert float(a) < 0                                       # a descent direction of the model
    m0 = merit(problem, xs, us, S, xs)[1]
    ratios = []
    for alpha in alphas:
        cand_xs, cand_us = closed_loop_rollout(problem, xs, us, gains, alpha)
        m = merit(problem, cand_xs, cand_us, S, cand_xs if noise_at_candidate else xs)[1]
        ratios.append(float((m - m0) / (alpha * a + alpha ** 2 * b)))
    return np.array(ratios)


@pytest.mark.parametrize("delay", [0.0, 0.05])
def test_predicted_change_is_the_first_order_merit_change_with_state_dependent_noise(delay):
    # P2-noisy: F = M(q)^-1 sigma diag(u) depends on the state, which the LQG (3) leaves out.
    # Nominal: the deterministic optimum, where the noise-aware feedforward is far from zero.
    noisy = arm2(delay=delay, noise=True)
    us = di.solve(arm2(delay=delay)).u
    alphas = [1e-2, 1e-3, 1e-4]
    ratios = _slope_ratios(noisy, us, alphas)
    # the model is exact to first order: the error shrinks like alpha
    assert np.all(np.abs(ratios - 1) < 0.1 * np.array(alphas)), ratios
    # the same rollouts scored with F at their own states have another slope (measured: 0.95 at
    # l = 0, 0.90 at l = 5): that merit is not the one the feedforward descends
    own = _slope_ratios(noisy, us, alphas, noise_at_candidate=True)
    assert np.all(np.abs(own - 1) > 0.03), own


@pytest.mark.parametrize("delay", [0.0, 0.05, 0.1])
def test_noise_aware_arm_converges_to_one_point_from_either_lambda(delay):
    # Before the merit froze F's state dependence, reg_init = 0 at l = 0 ran into the iteration
    # limit and the two starts stopped 0.3 % apart in cost
    problem = arm2(delay=delay, noise=True)
    sols = [di.solve(problem, options=di.Options(reg_init=reg)) for reg in (0.0, 1.0)]
    for sol in sols:
        assert sol.converged, sol.message
        assert int(sol.iterations) < 30
    np.testing.assert_allclose(float(sols[0].cost), float(sols[1].cost), rtol=1e-6)
    np.testing.assert_allclose(float(sols[0].expected_cost), float(sols[1].expected_cost), rtol=1e-8)
    # and the same commands, up to the stopping rule's tolerance
    np.testing.assert_allclose(sols[0].u, sols[1].u, atol=1e-3 * float(jnp.max(jnp.abs(sols[0].u))))


@pytest.mark.parametrize("delay, noise, limits", [(0.0, False, None), (0.1, False, 1.0), (0.05, True, None)])
def test_the_scored_candidates_are_the_single_rollouts(delay, noise, limits):
    """The line search scores all step sizes in one scan, as they run, without storing them; each
    score must be ``merit`` of the single-alpha rollout of the same law."""
    problem = arm2(delay=delay, noise=noise)
    if limits is not None:
        problem = problem.replace(u_min=[-limits] * 2, u_max=[limits] * 2)
    t = np.arange(problem.horizon)[:, None] * problem.dt
    us = jnp.asarray(1.5 * np.sin(2 * np.pi * t / 0.5 + np.array([0.0, 1.0])))    # a nominal far from optimal
    xs = rollout(problem, us)
    gains, S, *_ = jax.jit(lambda: backward(problem, xs, us, 0.0, "structured", 1e-5))()
    alphas = jnp.asarray(di.Options().alphas)
    cost, mer, finite = jax.jit(lambda: candidate_scores(problem, xs, us, gains, alphas, S))()
    assert bool(jnp.all(finite))
    single = jax.jit(lambda alpha: closed_loop_rollout(problem, xs, us, gains, alpha))   # one compile, not 11
    score = jax.jit(lambda x, u: merit(problem, x, u, S, xs))
    for i, alpha in enumerate(np.asarray(alphas)):
        c_i, m_i = score(*single(alpha))
        np.testing.assert_allclose([float(cost[i]), float(mer[i])], [float(c_i), float(m_i)], rtol=1e-12)
    assert len({float(c) for c in cost}) == len(alphas)      # the candidates differ: a real check
