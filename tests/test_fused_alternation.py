"""Todorov's alternation with several sensors of different delays and periods
(``lqg.fused_alternation``), against the alternation written on the augmented pair in
tests/fused_sensing.py (the state [dx_k, ..., dx_{k-L}, pending] and its Kalman estimate, dense
numpy, nothing of the library's recursions):

* the controller for a fixed filter: its law equals the augmented Todorov controller's (whose gains
  on the estimates of past states come out zero), and its value at time 0 is the exact cost of the
  new law with that filter (the augmented second moments);
* the window's error filter has the fused filter's covariance (the same information);
* with additive noise, one sweep from any feedback returns Theorem 1's law (separation);
* the alternation's costs, law and error covariances equal the augmented alternation's.
"""
from __future__ import annotations

import numpy as np
import pytest
from comparisons import rel_err
from fused_sensing import AugmentedSensors, random_fusion_problem

from delayed_ilqr.lqg import Gains, backward_pass, fused_design, fused_kalman, fused_loop
from delayed_ilqr.lqg.fused_alternation import error_kalman, fused_alternate, fused_controller_sweep

RTOL = 1e-9

# (K, n, d, p, l, sensors as (m, q, delay, period)), the shapes of test_fusion.py
CASES = [
    (6, 2, 1, 1, 0, [(1, 1, 0, 1), (1, 2, 2, 1), (1, 1, 8, 1)]),    # delays 0 and > K (never arrives)
    (9, 2, 2, 2, 2, [(2, 2, 1, 2), (1, 1, 4, 1), (1, 1, 9, 3)]),    # delays 1 and = K, periods 2, 3
]
IDS = ["K6-l0-ls0-2-8", "K9-l2-ls1-4-9"]


def _perturbed(gains, seed, scale=0.2):
    rng = np.random.default_rng(seed)
    return Gains(*(np.asarray(g) + scale * rng.standard_normal(np.shape(g)) for g in gains))


def _kh(aug, gains):
    return aug.policy(gains, np.zeros((aug.K, aug.n, 1)))[0]


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_sweep_equals_the_augmented_todorov_controller(case):
    """Signal-dependent noise, a perturbed law, the filter of that law's loop: the sweep's law and
    value against the augmented ones; the error filter's Sigma_k against fused_kalman's."""
    K, n, d, p, l, specs = case
    lqg, sensors = random_fusion_problem(4, K, n, d, p, l, specs, mult_noise=0.5)
    gains = _perturbed(fused_design(lqg, sensors).gains, 1)
    Q = fused_loop(lqg, sensors, gains).motor_cov
    _, Sigma = error_kalman(lqg, sensors, Q)
    assert rel_err(Sigma, fused_kalman(lqg, sensors, process_cov=Q)[1].current[:-1]) <= RTOL
    new, value = fused_controller_sweep(lqg, sensors, gains, Q)
    np.testing.assert_array_equal(new.feedforward, gains.feedforward)
    aug = AugmentedSensors(lqg, sensors)
    Lz = aug.kalman_for(Q)
    Kh_ref, F_ref, value_ref = aug.todorov_sweep(_kh(aug, gains), Lz)
    past = slice(n, n * (aug.ls + 1))              # the estimates of dx_{k-1}..dx_{k-L}: no gain
    assert np.max(np.abs(F_ref[:, :, past])) <= 1e-10 * np.max(np.abs(F_ref))
    assert rel_err(_kh(aug, new), Kh_ref) <= RTOL
    assert rel_err(value, value_ref) <= RTOL
    assert rel_err(value, aug.output_feedback_cost(_kh(aug, new), Lz)) <= RTOL


def test_with_additive_noise_the_sweep_returns_theorem_1_law():
    """Separation: from a perturbed feedback, on the fused Kalman filter, one sweep gives Theorem 1's
    L and M and the separation design's cost."""
    lqg, sensors = random_fusion_problem(6, *CASES[1][:5], CASES[1][5])
    design = fused_design(lqg, sensors)
    perturbed = _perturbed(design.gains, 2, 0.5)._replace(feedforward=design.gains.feedforward)
    new, value = fused_controller_sweep(lqg, sensors, perturbed, fused_loop(lqg, sensors, design.gains).motor_cov)
    full, _ = backward_pass(lqg)
    scale = np.max(np.abs(full.state_feedback))
    np.testing.assert_allclose(new.state_feedback, full.state_feedback, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(new.delay_feedback, full.delay_feedback, rtol=0, atol=1e-10 * scale)
    assert rel_err(value, design.expected_cost) <= RTOL


@pytest.mark.parametrize("case", CASES, ids=IDS)
def test_alternation_equals_the_augmented_alternation(case):
    """From a perturbed law with strongly signal-dependent noise: the
    costs after each alternation, the returned law and the estimation error's covariance equal the
    augmented alternation's; the costs never rise and the first alternation lowers the cost."""
    K, n, d, p, l, specs = case
    lqg, sensors = random_fusion_problem(7, K, n, d, p, l, specs, mult_noise=1.0)
    start = _perturbed(fused_design(lqg, sensors).gains, 3, 0.3)
    alt = fused_alternate(lqg, sensors, start)
    aug = AugmentedSensors(lqg, sensors)
    Kh_ref, costs_ref, current_ref = aug.alternate(_kh(aug, start))
    n_alt = int(alt.alternations)
    costs = np.asarray(alt.costs)[:n_alt + 1]
    assert n_alt == len(costs_ref) - 1 and n_alt >= 2
    assert rel_err(costs, costs_ref) <= RTOL and np.all(np.diff(costs) <= 0) and costs[1] < costs[0]
    assert rel_err(_kh(aug, alt.gains), Kh_ref) <= 1e-8
    assert rel_err(alt.covariances.current[:-1], current_ref) <= 1e-8
    assert float(alt.expected_cost) == costs[-1]
    # commands not free keep their rows; max_alternations=0 is the starting pair
    free = np.ones((K, d), bool)
    free[2:4, 0] = False
    part = fused_alternate(lqg, sensors, start, free=free)
    np.testing.assert_array_equal(part.gains.state_feedback[2:4, 0], np.asarray(start.state_feedback)[2:4, 0])
    none = fused_alternate(lqg, sensors, start, max_alternations=0)
    assert int(none.alternations) == 0 and float(none.expected_cost) == costs[0]


def test_the_alternated_cost_has_gradients():
    """d/dtheta of the alternated pair's exact cost, theta scaling the motor noise (signal-dependent),
    by autodiff through three alternations against central finite differences."""
    import jax

    K, n, d, p, l, specs = CASES[0]
    lqg, sensors = random_fusion_problem(7, K, n, d, p, l, specs, mult_noise=1.0)
    start = _perturbed(fused_design(lqg, sensors).gains, 3, 0.3)
    cost = lambda theta: fused_alternate(lqg.replace(c=theta * lqg.c), sensors, start,
                                         max_alternations=3).expected_cost
    h = 1e-5
    assert rel_err(jax.grad(cost)(1.1), (cost(1.1 + h) - cost(1.1 - h)) / (2 * h)) <= 1e-7
