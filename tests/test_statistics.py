"""One definition of a diverged trial, and intervals that respect the sign of a cost."""
import math

import numpy as np
import pytest

from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.statistics import (DIVERGENCE_FACTOR, divergence_bound, diverged_trials, sample_stats,
                                     summarize)


def test_a_trial_diverges_when_its_cost_is_not_finite_or_above_the_bound():
    cost = np.array([1.0, 2.0, np.inf, np.nan, 1e7, 5.0])
    np.testing.assert_array_equal(diverged_trials(cost), [False, False, True, True, False, False])
    np.testing.assert_array_equal(diverged_trials(cost, 1e6), [False, False, True, True, True, False])


def test_the_bound_is_a_hundred_times_the_cost_of_not_moving():
    # P1 with zero force: the mass stays at x0 = 0, so the cost is the final cost of the target error
    p = point_mass(noise=True)
    rest = 1e3 * (0.2 ** 2 + 0.1 ** 2)
    assert divergence_bound(p) == pytest.approx(DIVERGENCE_FACTOR * rest, rel=1e-12)
    # a plant that starts on its target has no finite bound: only non-finite costs diverge
    assert math.isinf(divergence_bound(arm2(x0=(math.pi / 2, math.pi / 3, 0.0, 0.0))))


def test_mean_leaves_diverged_trials_out_and_reports_their_count():
    cost = np.concatenate([np.full(97, 2.0), [1e9, np.inf, 3e9]])
    s = sample_stats(cost, diverged_trials(cost, 1e3))
    assert s.n == 100 and s.n_diverged == 3
    assert s.mean == 2.0 and s.ci95 == (2.0, 2.0)
    assert s.median == 2.0 and s.iqr == (2.0, 2.0)
    # an endpoint error judged by the same trials
    err = np.arange(100.0)
    e = sample_stats(err, diverged_trials(cost, 1e3))
    assert e.n_diverged == 3 and e.mean == pytest.approx(np.mean(err[:97]))


def test_intervals_of_a_heavy_tailed_positive_cost_stay_positive():
    rng = np.random.default_rng(1)
    cost = np.exp(3.0 * rng.standard_normal(200))         # log-normal: mean dominated by a few trials
    s = sample_stats(cost)
    assert s.mean - 1.96 * s.standard_error < 0             # the normal interval would go negative
    assert 0 < cost.min() <= s.ci95[0] < s.mean < s.ci95[1]
    assert s.iqr[0] < s.median < s.iqr[1]
    assert sample_stats(cost) == s                          # seeded: the same data, the same interval


def test_median_and_iqr_rank_diverged_trials_last():
    cost = np.concatenate([np.arange(1.0, 8.0), [np.inf] * 3])        # 10 trials, 3 diverged
    s = sample_stats(cost)
    assert s.median == pytest.approx(5.0) and s.iqr[0] == pytest.approx(3.0) and math.isinf(s.iqr[1])
    assert s.to_dict()["iqr"][1] is None


def test_summary_uses_the_same_trials():
    cost = np.array([1.0, 2.0, 3.0, 1e8])
    x = np.array([[0.0, 1.0], [0.0, 3.0], [0.0, 2.0], [1e6, 1e6]])
    s = summarize(cost, x, bound=1e3)
    assert s.n_diverged == 1 and s.mean_cost == 2.0
    np.testing.assert_allclose(s.final_state_mean, [0.0, 2.0])
