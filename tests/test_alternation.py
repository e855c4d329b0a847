"""Todorov's alternation with motor and sensory delays (``lqg.alternation``).

The references are independent of the controller pass:

* the pass's value at time 0 is the exact cost of the law it returns, and that cost comes from
  the forward second moments of the joint system (``output_feedback_cost``, itself checked against
  the augmented state and Monte Carlo in test_output_feedback.py), for any filter;
* with additive noise and the Kalman filter, the pass returns Theorem 1's law (``backward_pass``),
  from any starting feedback: the separation principle;
* with perfect sensors (l_s = 0, H = I, G -> 0) it returns the full-state law with
  signal-dependent noise (Theorem 1 with C0, C1), however much the noise depends on the commands;
* the alternation's exact cost never increases, ends at or below the separation design's, and
  agrees with Monte Carlo of the linear closed loop, as does the estimation error's covariance.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from comparisons import rel_err
from delayed_sensing import random_problem
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr.lqg import (DelayedObservation, FilterGains, Gains, backward_pass, delayed_kalman,
                              output_feedback_cost, separation_design, simulate_output_feedback)
from delayed_ilqr.lqg.alternation import alternate, controller_sweep, filter_step

RTOL = 1e-9

SHAPES = [  # (K, n, d, m, q, p, l, l_s), from test_output_feedback.py
    (5, 2, 1, 1, 1, 1, 0, 0),      # no delay
    (12, 2, 2, 1, 2, 1, 1, 5),     # l_s > l
    (15, 3, 2, 2, 2, 2, 3, 4),     # both delays
    (6, 2, 1, 2, 2, 1, 2, 9),      # l_s >= K: no measurement arrives
]
IDS = ["K{}-n{}-d{}-m{}-q{}-p{}-l{}-ls{}".format(*s) for s in SHAPES]


def _perturbed(arrays, rng, scale):
    return [np.asarray(a) + scale * rng.standard_normal(np.shape(a)) for a in arrays]


@pytest.mark.parametrize("shape", SHAPES, ids=IDS)
def test_controller_pass_value_is_the_exact_cost_of_its_law(shape):
    """Signal-dependent noise, a perturbed law and an arbitrary filter (Kc unrelated to Kd): the
    pass's value at time 0 equals the joint second moments' cost of the pair it returns."""
    lqg, obs = random_problem(11, *shape, mult_noise=0.4)
    design = separation_design(lqg, obs)
    rng = np.random.default_rng(2)
    gains = Gains(*_perturbed(design.gains, rng, 0.2))
    fgains = FilterGains(*_perturbed(design.filter_gains, rng, 0.2))
    new, value = controller_sweep(lqg, obs, gains, fgains)
    np.testing.assert_array_equal(new.feedforward, gains.feedforward)          # the feedforward is held
    assert rel_err(value, output_feedback_cost(lqg, obs, new, fgains)) <= RTOL


@pytest.mark.parametrize("shape", SHAPES, ids=IDS)
def test_with_additive_noise_the_pass_returns_theorem_1_law(shape):
    """Separation: on the Kalman filter, from a perturbed feedback, one pass gives Theorem 1's L and
    M, and the separation design's cost."""
    lqg, obs = random_problem(5, *shape)
    design = separation_design(lqg, obs)
    rng = np.random.default_rng(3)
    L, M = _perturbed(design.gains[1:], rng, 0.5)
    new, value = controller_sweep(lqg, obs, Gains(design.gains.feedforward, L, M), design.filter_gains)
    scale = np.max(np.abs(design.gains.state_feedback))
    np.testing.assert_allclose(new.state_feedback, design.gains.state_feedback, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(new.delay_feedback, design.gains.delay_feedback, rtol=0, atol=1e-10 * scale)
    assert rel_err(value, design.expected_cost) <= RTOL


@pytest.mark.parametrize("l", [0, 2])
def test_with_perfect_sensors_the_pass_returns_the_full_state_noisy_law(l):
    """l_s = 0, H = I, G = 1e-5 I and process noise of full rank (so the Kalman gain is ~I): the
    pass charges a command's noise at the full-state value function and returns Theorem 1's law
    with signal-dependent noise; its cost tends to J(0) as G -> 0."""
    K, n = 10, 3
    lqg, _ = random_problem(4, K, n, 2, n, n, 4, l, 0, mult_noise=0.5)
    obs = DelayedObservation(np.broadcast_to(np.eye(n), (K, n, n)), 1e-5 * np.broadcast_to(np.eye(n), (K, n, n)), 0)
    full, value = backward_pass(lqg)
    new, cost = controller_sweep(lqg, obs, full, delayed_kalman(lqg, obs)[0])
    scale = np.max(np.abs(full.state_feedback))
    np.testing.assert_allclose(new.state_feedback, full.state_feedback, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(new.delay_feedback, full.delay_feedback, rtol=0, atol=1e-9 * scale)
    assert rel_err(cost, value.expected_cost) <= 1e-8


@pytest.mark.parametrize("shape", SHAPES, ids=IDS)
@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), mult_noise=st.sampled_from([0.0, 0.3, 1.0]))
def test_alternation_never_raises_the_exact_cost(shape, seed, mult_noise):
    """From the separation design: the recorded costs never increase, the returned pair costs the
    last of them exactly, it is at most the separation design's, and with additive noise the
    separation design is a fixed point (optimal: nothing is gained)."""
    lqg, obs = random_problem(seed, *shape, mult_noise=mult_noise)
    design = separation_design(lqg, obs)
    alt = alternate(lqg, obs, design.gains, design.filter_gains)
    n_alt = int(alt.alternations)
    costs = np.asarray(alt.costs)[:n_alt + 1]
    assert 1 <= n_alt <= 20 and np.all(np.isfinite(costs)) and np.all(np.isnan(np.asarray(alt.costs)[n_alt + 1:]))
    assert costs[0] == pytest.approx(float(design.expected_cost), rel=1e-12)
    assert np.all(np.diff(costs) <= 0)
    assert rel_err(alt.expected_cost, output_feedback_cost(lqg, obs, alt.gains, alt.filter_gains)) <= RTOL
    assert float(alt.expected_cost) == costs[-1]
    if mult_noise == 0:
        assert n_alt == 1 and rel_err(alt.expected_cost, design.expected_cost) <= 1e-12


def test_alternation_gains_with_signal_dependent_noise_and_keeps_fixed_rows():
    """On a problem whose noise depends strongly on the commands, with both delays, the alternation
    lowers the exact cost (the filter step alone already does), and commands marked not free keep
    their feedback row."""
    lqg, obs = random_problem(7, *SHAPES[2], mult_noise=1.0)
    design = separation_design(lqg, obs)
    refiltered = filter_step(lqg, obs, design.gains, design.filter_gains)
    assert float(output_feedback_cost(lqg, obs, design.gains, refiltered)) < float(design.expected_cost)
    alt = alternate(lqg, obs, design.gains, design.filter_gains)
    assert float(alt.expected_cost) < (1 - 1e-4) * float(design.expected_cost)
    free = np.ones(design.gains.feedforward.shape, bool)
    free[3:6, 0] = False
    part = alternate(lqg, obs, design.gains, design.filter_gains, free=free)
    np.testing.assert_array_equal(part.gains.state_feedback[3:6, 0], design.gains.state_feedback[3:6, 0])
    np.testing.assert_array_equal(part.gains.delay_feedback[3:6, :, 0], design.gains.delay_feedback[3:6, :, 0])
    assert float(part.expected_cost) < float(design.expected_cost)
    with pytest.raises(ValueError, match="max_alternations must be a non-negative integer; got -1"):
        alternate(lqg, obs, design.gains, design.filter_gains, max_alternations=-1)


def test_alternated_pair_agrees_with_monte_carlo():
    """The alternated pair's exact cost and estimation-error covariance (signal-dependent noise,
    where the Kalman filter's own Sigma_k is wrong) against 20000 trials of the linear loop;
    max_alternations=0 returns the starting pair."""
    lqg, obs = random_problem(7, *SHAPES[2], mult_noise=1.0)
    design = separation_design(lqg, obs)
    alt = alternate(lqg, obs, design.gains, design.filter_gains)
    runs = simulate_output_feedback(lqg, obs, alt.gains, alt.filter_gains, 20000, seed=4)
    cost = np.asarray(runs.cost)
    assert abs(cost.mean() - float(alt.expected_cost)) <= 4 * cost.std(ddof=1) / np.sqrt(cost.size)
    err = np.asarray(runs.dx[:, :-1] - runs.x_hat)
    Sigma = np.asarray(alt.error_covariance[:-1])
    emp = np.einsum("tkn,tkm->knm", err, err) / err.shape[0]
    assert np.max(np.abs(emp - Sigma)) <= 0.05 * np.max(np.abs(Sigma))
    # the separation design's filter assumed the nominal noise: its own Sigma_k is not its error's
    none = alternate(lqg, obs, design.gains, design.filter_gains, max_alternations=0)
    assert int(none.alternations) == 0 and float(none.expected_cost) == float(design.expected_cost)
    exact = np.asarray(none.error_covariance)
    assert np.max(np.abs(exact - np.asarray(design.covariances.current))) > 0.05 * np.max(np.abs(exact))


# under make bench: two compiled solves of the arm with its estimator and 4000 paired trials; the suite
# holds the alternation's exact cost and its descent on random problems above
@pytest.mark.full
def test_solve_alternates_on_the_noisy_arm_with_both_delays():
    """P2-noisy's torque noise (proportional to the delayed command) with 30 ms motor and 50 ms
    sensory delay: ``solve`` returns the alternation of the LQG layer at its nominal, at least a
    tenth cheaper than the separation design, and the nonlinear plant's Monte Carlo cost falls too
    (paired trials, same seed)."""
    import delayed_ilqr as di
    from delayed_ilqr.ilqg.estimation import with_estimator
    from delayed_ilqr.ilqg.linearize import linearize
    from delayed_ilqr.models import arm2
    from delayed_ilqr.observation import linearized_observation

    problem = arm2(delay=0.03, noise="benchmark", sensory_delay=0.05, horizon=40)
    sol = di.solve(problem)
    full = di.solve(problem.replace(observation=None))
    assert sol.status == full.status and sol.converged
    np.testing.assert_array_equal(sol.u, full.u)
    sep = with_estimator(problem, full, dataclasses.replace(di.Options(), max_alternations=0))
    assert float(sol.expected_cost) < 0.9 * float(sep.expected_cost)
    # the LQG layer's alternation from the separation pair at the same linearisation
    lqg = linearize(problem, full.x, full.u)
    obs = linearized_observation(problem.observation, full.x)[0]
    p = full.policy
    alt = alternate(lqg, obs, Gains(p.feedforward, p.state_feedback, p.delay_feedback), delayed_kalman(lqg, obs)[0])
    assert rel_err(sol.expected_cost, alt.expected_cost) <= 1e-12
    assert rel_err(sep.expected_cost, alt.costs[0]) <= 1e-12
    cost_alt = np.asarray(di.simulate(problem, sol.policy, 4000, seed=1).cost)
    cost_sep = np.asarray(di.simulate(problem, sep.policy, 4000, seed=1).cost)
    diff = cost_alt - cost_sep
    assert diff.mean() + 4 * diff.std(ddof=1) / np.sqrt(diff.size) < 0
