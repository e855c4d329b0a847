"""The line search's model: the predicted merit change of the LQG against the merit of real
closed-loop rollouts on the nonlinear plant, and the noise-aware iteration that relies on it; the
one delayed-law step of ``lqg.law`` against eq. (6) written out."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.backward import backward
from delayed_ilqr.ilqg.candidates import closed_loop_rollout
from delayed_ilqr.lqg.law import augmented_feedback, closed_loop_affine, delayed_law
from delayed_ilqr.ilqg.line_search import candidate_scores, merit
from delayed_ilqr.ilqg.linearize import rollout
from delayed_ilqr.lqg import Gains
from delayed_ilqr.lqg.frame import to_slots
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
    noisy = arm2(delay=delay, noise="benchmark")
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
    problem = arm2(delay=delay, noise="benchmark")
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


def _random_gains(rng, K, n, d, l):
    return Gains(jnp.asarray(rng.standard_normal((K, d))), jnp.asarray(rng.standard_normal((K, d, n))),
                 jnp.asarray(rng.standard_normal((K, l, d, d))))


@pytest.mark.parametrize("l", [0, 1, 3])
def test_the_law_is_eq_6_in_both_frames_and_in_affine_form(l):
    """``delayed_law`` is du_k = I_k + L_k dx_k + sum_i M_k^i du_{k+i-l} (eq. 6 written out) with
    [L, M] in time order (``augmented_feedback``, the policy cost's) and in the slot frame
    (``SlotGains``, the closed loops'), and ``closed_loop_affine`` substitutes it into a map."""
    rng = np.random.default_rng(3 + l)
    K, n, d = 7, 3, 2
    gains = _random_gains(rng, K, n, d, l)
    slots = to_slots(gains)
    time_ordered = augmented_feedback(gains)
    du = {j: rng.standard_normal(d) for j in range(-l, K)}
    for k in range(K):
        dx = rng.standard_normal(n)
        want = np.asarray(gains.feedforward[k] + gains.state_feedback[k] @ dx)
        for i in range(l):
            want = want + np.asarray(gains.delay_feedback[k, i]) @ du[k + i - l]
        pending_time = np.concatenate([du[k + i - l] for i in range(l)] + [np.zeros(0)])
        pending_slot = np.zeros(l * d)
        for j in range(k - l, k):
            pending_slot[(j % l) * d:(j % l + 1) * d] = du[j]
        z_time, z_slot = np.concatenate([dx, pending_time]), np.concatenate([dx, pending_slot])
        got_time = delayed_law(gains.feedforward[k], time_ordered[k], z_time)
        got_slot = delayed_law(slots.feedforward[k], slots.feedback[k], z_slot)
        np.testing.assert_allclose(np.asarray(got_time), want, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(got_slot), want, rtol=1e-12, atol=1e-12)
        Mz, Mu = rng.standard_normal((5, n + l * d)), rng.standard_normal((5, d))
        closed, constant = closed_loop_affine(Mz, Mu, gains.feedforward[k], time_ordered[k])
        np.testing.assert_allclose(np.asarray(closed @ z_time + constant), Mz @ z_time + Mu @ want,
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("delay_steps", [0, 3])
def test_closed_loop_rollout_is_the_law_written_out(delay_steps):
    """The candidates' rollout (``closed_loop_step`` in the slot frame) against the law written out
    step by step in NumPy, in time order: u_k = clip(u_bar_k + alpha I_k + L_k (x_k - x_bar_k)
    + sum_i M_k^i (u_{k+i-l} - u_bar_{k+i-l})), the plant acting on u_{k-l}; limits that bind."""
    problem = arm2(delay=delay_steps * 0.01, horizon=25).replace(u_min=[-0.5, -0.4], u_max=[0.5, 0.6])
    K, n, d, l = problem.horizon, problem.n_states, problem.n_controls, problem.delay_steps
    rng = np.random.default_rng(11)
    us_bar = jnp.asarray(0.3 * rng.standard_normal((K, d)))
    xs_bar = rollout(problem, us_bar) + 0.01 * rng.standard_normal((K + 1, n))
    gains = _random_gains(rng, K, n, d, l)
    gains = gains._replace(delay_feedback=0.3 * gains.delay_feedback)
    alpha = 0.4
    xs, us = closed_loop_rollout(problem, xs_bar, us_bar, to_slots(gains), alpha)

    f = jax.jit(problem.dynamics)
    I, L, M = (np.asarray(a) for a in gains)
    x, sent, want_xs, want_us = np.asarray(problem.x0), {}, [np.asarray(problem.x0)], []
    zero = np.zeros(d)
    for k in range(K):
        u = np.asarray(us_bar[k]) + alpha * I[k] + L[k] @ (x - np.asarray(xs_bar[k]))
        for i in range(l):
            j = k + i - l
            u = u + M[k, i] @ ((sent[j] - np.asarray(us_bar[j])) if j >= 0 else zero)
        u = np.clip(u, np.asarray(problem.u_min), np.asarray(problem.u_max))
        sent[k] = u
        ud = sent.get(k - l, zero)
        x = x + problem.dt * np.asarray(f(x, u, ud))
        want_xs.append(x)
        want_us.append(u)
    assert np.any(np.abs(np.array(want_us)) >= 0.4)         # the limits bind: the clipped deviation is fed back
    np.testing.assert_allclose(np.asarray(us), np.array(want_us), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(xs), np.array(want_xs), rtol=1e-12, atol=1e-12)
