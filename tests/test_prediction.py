"""The closed-loop prediction on the nonlinear plant (prediction.closed_loop_prediction).

On a linear plant with quadratic cost every rule is exact: its expected cost and state moments
are those of the exact linear-closed-loop propagation (lqg.policy_cost, lqg.closed_loop_moments),
an independent computation on the augmented state. On the torque arm, where the linearisation
leaves the plant's curvature out, it is checked against Monte Carlo of the plant.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import lqg, simulate, solve
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN
from delayed_ilqr.prediction import _sigma_points, closed_loop_prediction

from comparisons import rel_err

RULES = ("second_order", "fifth_degree", "cubature")


@pytest.mark.parametrize("delay", [0.0, 0.03])
def test_exact_on_a_linear_plant(delay):
    """P1-noisy (linear, quadratic cost, signal-dependent and additive noise): E[J] and Cov(x_k)
    equal lqg.policy_cost / closed_loop_moments to round-off, E[x_k] the nominal, for every rule
    and for a policy designed for another delay than the plant's (l_p != l, as simulate allows)."""
    problem = point_mass(delay=delay, noise=True)
    sol = solve(problem)
    model = linearize(problem, sol.x, sol.u)
    policy = sol.policy
    gains = lqg.Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    cost, moments = lqg.policy_cost(model, gains), lqg.closed_loop_moments(model, gains)
    assert float(cost) > 2 * float(sol.cost)           # the noise's share is not negligible
    for rule in RULES:
        pred = closed_loop_prediction(problem, policy, rule)
        assert abs(float(pred.expected_cost) / float(cost) - 1) < 1e-9, rule
        assert rel_err(pred.state.cov, moments.state_covariance(4)) < 1e-9, rule
        np.testing.assert_allclose(pred.state.mean, sol.x, rtol=0, atol=1e-12)
    if delay > 0:
        # the delay-ignorant policy (l_p = 0) on the delayed plant: the exact cost of that closed
        # loop is the LQG's at l = 0 with the plant's delay put back, here a Monte Carlo check
        ignorant = solve(point_mass(delay=0.0, noise=True)).policy
        runs = simulate(problem, ignorant, 20000, seed=2)
        pred = closed_loop_prediction(problem, ignorant)
        c = np.asarray(runs.cost)
        assert abs(float(pred.expected_cost) - c.mean()) < 4 * c.std() / np.sqrt(c.size)


@settings(max_examples=25, deadline=None)
@given(N=st.integers(1, 9), r=st.integers(1, 9), rank=st.integers(0, 9), seed=st.integers(0, 2 ** 31 - 1))
def test_points_in_the_inputs_reproduce_the_gaussian(N, r, rank, seed):
    """Eq. P5's decomposition z = mean + R eta + E-part, for random sizes, a random input map T [r, N]
    and a covariance of random rank (0 = a point, as at time 0): the points' mean is mean, their
    covariance plus E is cov, T E = 0, and the fifth-degree rule's fourth moments of y = T z are
    the Gaussian's, E[(a'(y - Tm))^4] = 3 (a' T P T' a)^2 (cubature, degree 3, is exact only up
    to the second moments). The rule runs in min(r, N) dimensions."""
    rng = np.random.default_rng(seed)
    mean = rng.normal(size=N)
    root = rng.normal(size=(N, min(rank, N)))
    cov, T, a = root @ root.T, rng.normal(size=(r, N)), rng.normal(size=r)
    scale = max(1.0, float(np.abs(cov).max()))
    for rule in RULES[1:]:
        Z, w, E = (np.asarray(v) for v in _sigma_points(jnp.asarray(mean), jnp.asarray(cov), rule, jnp.asarray(T)))
        dim = min(r, N)
        assert len(w) == (2 * dim ** 2 + 1 if rule == "fifth_degree" else 2 * dim), rule
        np.testing.assert_allclose(w.sum(), 1.0, atol=1e-13)
        np.testing.assert_allclose(w @ Z, mean, atol=1e-11 * scale)
        centred = Z - mean
        np.testing.assert_allclose(np.einsum("i,ij,ik->jk", w, centred, centred) + E, cov, atol=1e-11 * scale)
        np.testing.assert_allclose(T @ E, 0.0, atol=1e-10 * scale * np.abs(T).max())
        if rule == "fifth_degree":
            y = centred @ T.T @ a
            want = 3 * (a @ T @ cov @ T.T @ a) ** 2
            np.testing.assert_allclose(w @ y ** 4, want, rtol=1e-9, atol=1e-9 * scale ** 2 * np.abs(a @ T).sum() ** 4)


def test_chain_moments_on_a_linear_plant():
    """The moments of the whole chain z_k = [dx_k; du_{k-l}; ...; du_{k-1}] (P1) at l = 3 (30 ms,
    dt = 10 ms): on P1-noisy every rule's z equals closed_loop_moments' augmented state (same
    order, oldest pending command first; mean 0, so its second moment is the covariance) to
    round-off, pending-command block included."""
    problem = point_mass(delay=0.03, noise=True)
    assert problem.delay_steps >= 1
    sol = solve(problem)
    policy = sol.policy
    gains = lqg.Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    moments = lqg.closed_loop_moments(linearize(problem, sol.x, sol.u), gains)
    N = problem.n_states + problem.delay_steps * problem.n_controls
    assert moments.second.shape == (problem.horizon + 1, N, N)
    pending = moments.second[:, problem.n_states:, problem.n_states:]
    assert float(jnp.max(jnp.abs(pending))) > 0                   # the block is tested, not zeros
    for rule in RULES:
        z = closed_loop_prediction(problem, policy, rule).z
        assert z.cov.shape == moments.second.shape, rule
        np.testing.assert_allclose(z.mean, 0.0, rtol=0, atol=1e-12)
        assert rel_err(z.cov, moments.second) < 1e-9, rule
        assert rel_err(z.cov[:, problem.n_states:, problem.n_states:], pending) < 1e-9, rule


def test_closer_to_monte_carlo_on_the_torque_arm():
    """The torque arm at 100 ms, dt = 20 ms (a coarse version of the demo's plant, K = 25, l = 5),
    noise-aware design: the linearised prediction (Solution.expected_cost) is about half the
    Monte Carlo mean (2000 trials, standard error 3-5 %), the second-order prediction of the
    nonlinear closed loop closes at least half of that gap and the two Gaussian-closure rules
    (second order, fifth degree) agree (docs/results/noise_calibration.md §2)."""
    problem = arm2(delay=0.1, dt=0.02, noise=True, sigma_u=SIGMA_U_HUMAN)
    sol = solve(problem)
    c = np.asarray(simulate(problem, sol.policy, 2000, seed=1).cost)
    mc, se = c.mean(), c.std() / np.sqrt(c.size)
    assert se < 0.06 * mc
    linear = float(sol.expected_cost)
    second = float(closed_loop_prediction(problem, sol.policy, "second_order").expected_cost)
    fifth = float(closed_loop_prediction(problem, sol.policy, "fifth_degree").expected_cost)
    assert mc - linear > 0.3 * mc
    assert abs(second - mc) < 0.5 * abs(linear - mc)
    assert abs(fifth / second - 1) < 0.02


def test_exact_on_a_linear_plant_with_per_channel_delays():
    """P1-noisy with channel delays [1, 3] (the frame of 3 slots, channel 0's acting command two
    slots in): E[J] and Cov(x_k) by the Taylor rule and by sigma points in the inputs (the
    cheapest rule: the acting components' rows of eq. P5) equal the exact linear-closed-loop
    moments of the per-channel LQG (lqg.policy_cost / closed_loop_moments, themselves checked
    against augmentation in test_channels.py) to round-off."""
    problem = point_mass(noise=True).replace(delay_steps=[1, 3])
    sol = solve(problem)
    model = linearize(problem, sol.x, sol.u)
    policy = sol.policy
    gains = lqg.Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    cost, moments = lqg.policy_cost(model, gains), lqg.closed_loop_moments(model, gains)
    for rule in ("second_order", "cubature"):
        pred = closed_loop_prediction(problem, policy, rule)
        assert abs(float(pred.expected_cost) / float(cost) - 1) < 1e-9, rule
        assert rel_err(pred.state.cov, moments.state_covariance(4)) < 1e-9, rule
