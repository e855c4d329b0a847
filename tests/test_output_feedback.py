"""Output feedback with delayed sensors (``lqg.output_feedback``).

* separation: Theorem 1's law on the delayed filter's estimate costs exactly the optimum of the
  augmented-state LQG with output feedback (augmented LQR + augmented Kalman filter + exact second
  moments of (Z, Z_hat), tests/delayed_sensing.py), for additive noise;
* the exact cost of any controller-estimator pair equals the augmented second moments (where the
  pair is representable there) and Monte Carlo (always), with signal-dependent motor noise;
* perturbing the optimal pair never lowers its exact cost.
"""
from __future__ import annotations

import numpy as np
import pytest
from comparisons import WorstDifference, rel_err
from delayed_sensing import Augmented, random_problem
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr.lqg import (FilterGains, Gains, output_feedback_cost, separation_cost, separation_design,
                              simulate_output_feedback)

RTOL = 1e-9
_WORST = WorstDifference("test_output_feedback: worst library-vs-augmented relative difference")
_report_worst = _WORST.fixture()


def _record(err, where):
    _WORST.record(err, where)
    return err


SHAPES = [  # (K, n, d, m, q, p, l, l_s)
    (5, 2, 1, 1, 1, 1, 0, 0),
    (8, 3, 2, 2, 3, 2, 2, 1),
    (12, 2, 2, 1, 2, 1, 1, 5),
    (12, 3, 1, 2, 2, 2, 0, 5),
    (15, 3, 2, 2, 2, 2, 3, 4),
    (6, 2, 1, 2, 2, 1, 2, 9),      # l_s >= K: open loop in the measurements
]
IDS = ["K{}-n{}-d{}-m{}-q{}-p{}-l{}-ls{}".format(*s) for s in SHAPES]


@pytest.mark.parametrize("shape", SHAPES, ids=IDS)
@settings(max_examples=3)
@given(seed=st.integers(0, 2**31 - 1))
def test_separation_equals_augmented_output_feedback_optimum(shape, seed):
    """Additive noise: the separation design's exact cost is the optimum of output feedback on the
    augmented state, and so is J(0) + sum_k tr(L'H L Sigma_k)."""
    lqg, obs = random_problem(seed, *shape)
    design = separation_design(lqg, obs)
    aug = Augmented(lqg, obs)
    Kh, full_info = aug.lqr()
    optimum = aug.output_feedback_cost(Kh, aug.kalman()[0])
    assert _record(rel_err(design.value.expected_cost, full_info), f"J(0), {shape}") <= RTOL
    assert _record(rel_err(design.expected_cost, optimum), f"expected_cost, {shape}") <= RTOL
    cheap = separation_cost(lqg, design.value, design.gains, design.covariances)
    assert _record(rel_err(cheap, optimum), f"separation_cost, {shape}") <= RTOL
    assert float(design.expected_cost) >= float(design.value.expected_cost)     # seeing less costs


def _perturbed(arrays, rng, scale):
    return [np.asarray(a) + scale * rng.standard_normal(np.shape(a)) for a in arrays]


@pytest.mark.parametrize("shape", SHAPES, ids=IDS)
def test_exact_cost_of_any_pair_matches_augmented_moments(shape):
    """Perturbed law and perturbed delayed gain (the current gain predicted from it, the family the
    augmented filter can represent), with signal-dependent motor noise: exact to round-off."""
    lqg, obs = random_problem(11, *shape, mult_noise=0.3)
    design = separation_design(lqg, obs)
    aug = Augmented(lqg, obs)
    rng = np.random.default_rng(5)
    gains = Gains(*_perturbed(design.gains, rng, 0.2))
    Kd = _perturbed([design.filter_gains.delayed_gain], rng, 0.2)[0]
    Kh, Lz, Kc = aug.policy(gains, Kd)
    got = output_feedback_cost(lqg, obs, gains, FilterGains(Kd, Kc))
    assert _record(rel_err(got, aug.output_feedback_cost(Kh, Lz)), f"perturbed pair, {shape}") <= RTOL


@pytest.mark.parametrize("shape, mult_noise", [(SHAPES[1], 0.0), (SHAPES[2], 0.3), (SHAPES[4], 0.3)],
                         ids=["ls1-additive", "ls5-signal-dependent", "ls4-l3-signal-dependent"])
def test_exact_cost_matches_monte_carlo(shape, mult_noise):
    """The optimal pair and an arbitrary one (current gain unrelated to the delayed gain, rows before
    the first measurement nonzero: they must be ignored): Monte Carlo within 4 standard errors."""
    lqg, obs = random_problem(3, *shape, mult_noise=mult_noise)
    design = separation_design(lqg, obs)
    rng = np.random.default_rng(9)
    pairs = [(design.gains, design.filter_gains),
             (Gains(*_perturbed(design.gains, rng, 0.2)), FilterGains(*_perturbed(design.filter_gains, rng, 0.3)))]
    for gains, fgains in pairs:
        exact = float(output_feedback_cost(lqg, obs, gains, fgains))
        cost = np.asarray(simulate_output_feedback(lqg, obs, gains, fgains, 20000, seed=1).cost)
        sem = cost.std(ddof=1) / np.sqrt(cost.size)
        assert abs(cost.mean() - exact) <= 4 * sem, (cost.mean(), exact, sem)


def test_monte_carlo_estimates_are_conditional_means():
    """In closed loop, the estimate is unbiased and its error covariance is the filter's Sigma_k."""
    lqg, obs = random_problem(4, *SHAPES[2])
    design = separation_design(lqg, obs)
    runs = simulate_output_feedback(lqg, obs, design.gains, design.filter_gains, 20000, seed=2)
    err = np.asarray(runs.dx[:, :-1] - runs.x_hat)
    Sigma = np.asarray(design.covariances.current[:-1])
    sem = np.sqrt(np.einsum("knn->kn", Sigma) / err.shape[0])
    assert np.all(np.abs(err.mean(axis=0)) <= 5 * sem + 1e-12)
    emp = np.einsum("tkn,tkm->knm", err, err) / err.shape[0]
    assert np.max(np.abs(emp - Sigma)) <= 0.05 * np.max(np.abs(Sigma))


def test_perturbations_never_lower_the_cost():
    """Additive noise: the separation design is optimal among causal policies, so no perturbation of
    its law (I, L, M), its delayed gain or its current gain, alone or together, of either sign and
    of two sizes, lowers the exact cost."""
    lqg, obs = random_problem(8, *SHAPES[4])
    design = separation_design(lqg, obs)
    best = float(design.expected_cost)
    parts = list(design.gains) + list(design.filter_gains)
    rng = np.random.default_rng(0)
    for which in [[0], [1], [2], [3], [4], [0, 1, 2, 3, 4]]:
        direction = [rng.standard_normal(np.shape(p)) if i in which else np.zeros(np.shape(p))
                     for i, p in enumerate(parts)]
        for step in (-0.3, -1e-3, 1e-3, 0.3):
            moved = [np.asarray(p) + step * v for p, v in zip(parts, direction)]
            cost = float(output_feedback_cost(lqg, obs, Gains(*moved[:3]), FilterGains(*moved[3:])))
            assert cost >= best * (1 - 1e-12), (which, step, cost, best)
