"""The delayed Kalman filter (``lqg.estimator``) against the Kalman filter on the augmented state
[dx_k, ..., dx_{k-l_s}, du_{k-l}, ..., du_{k-1}], written independently in
tests/delayed_sensing.py: gains, covariances and the estimates of one record, to round-off."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from comparisons import WorstDifference, rel_err
from delayed_sensing import Augmented, random_problem
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr.lqg import DelayedObservation, delayed_kalman, filter_estimates
from delayed_ilqr.lqg.estimator import transition_windows

RTOL = 1e-9
_WORST = WorstDifference("test_estimator: worst delayed-vs-augmented filter relative difference")
_report_worst = _WORST.fixture()


SHAPES = [  # (K, n, d, m, q, p, l, l_s): l_s in {0, 1, 5, >= K}, with and without motor delay l
    (5, 2, 1, 1, 1, 1, 0, 0),
    (8, 3, 2, 2, 3, 2, 0, 1),
    (8, 3, 2, 2, 3, 2, 2, 1),
    (12, 2, 2, 1, 2, 1, 1, 5),
    (12, 3, 1, 2, 2, 2, 0, 5),
    (20, 4, 2, 3, 3, 2, 3, 7),
    (6, 2, 1, 2, 2, 1, 2, 6),      # l_s = K: no measurement ever arrives
    (6, 2, 1, 2, 2, 1, 0, 9),      # l_s > K
]


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: "K{}-n{}-d{}-m{}-q{}-p{}-l{}-ls{}".format(*s))
@settings(max_examples=3)
@given(seed=st.integers(0, 2**31 - 1))
def test_delayed_filter_matches_augmented_kalman(shape, seed):
    lqg, obs = random_problem(seed, *shape)
    K, ls = lqg.horizon, obs.delay_steps
    fgains, cov = delayed_kalman(lqg, obs)
    aug = Augmented(lqg, obs)
    Lz, priors, posts, innov, terminal = aug.kalman()
    now, late = aug.block(0), aug.block(ls)
    errs = {
        "delayed_gain": rel_err(fgains.delayed_gain, Lz[:, late]),
        "current_gain": rel_err(fgains.current_gain, Lz[:, now]),
        # every state after k - l_s is estimated by prediction from the delayed estimate
        "all_gains": rel_err(aug.policy(_zero_gains(lqg), fgains.delayed_gain)[1], Lz),
        "prior": rel_err(cov.prior, priors[:, late, late]),
        "posterior": rel_err(cov.posterior, posts[:, late, late]),
        "innovation": rel_err(cov.innovation, innov),
        "current": rel_err(cov.current, np.concatenate([posts[:, now, now], terminal[None, now, now]])),
    }
    # one record: arbitrary commands and measurements, estimates of dx_k and dx_{k-l_s}
    rng = np.random.default_rng(seed)
    du, dy = rng.standard_normal((K, lqg.n_controls)), rng.standard_normal((K, obs.n_outputs))
    x_hat, x_del = filter_estimates(lqg, obs, fgains, du, dy)
    Zh = aug.estimates(Lz, du, dy)
    errs["x_hat"] = rel_err(x_hat, Zh[:, now])
    errs["x_del"] = rel_err(x_del, Zh[:, late])
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, shape {shape}")
    assert all(e <= RTOL for e in errs.values()), errs
    assert not np.any(np.asarray(fgains.delayed_gain)[:ls]) and not np.any(np.asarray(fgains.current_gain)[:ls])


def _zero_gains(lqg):
    K, n, d, l = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.delay_steps
    return np.zeros((K, d)), np.zeros((K, d, n)), np.zeros((K, l, d, d))


@pytest.mark.parametrize("window", [0, 1, 2, 3, 7, 8, 13, 40])
def test_transition_windows_equal_direct_products(window):
    """Phi_k = A_{k-1} ... A_{k-w} and Pi_k = sum_j Phi(k, j+1) Q_j Phi(k, j+1)' by doubling equal
    the products and sums written out (transitions before time 0 are (I, 0))."""
    rng = np.random.default_rng(window)
    K, n = 12, 3
    A = rng.standard_normal((K, n, n))
    X = rng.standard_normal((K, n, n))
    Q = X @ np.swapaxes(X, 1, 2)
    Phi, Pi = transition_windows(jnp.asarray(A), jnp.asarray(Q), window)
    for k in range(K + 1):
        P, S = np.eye(n), np.zeros((n, n))
        for j in range(max(k - window, 0), k):
            P, S = A[j] @ P, A[j] @ S @ A[j].T + Q[j]
        assert rel_err(Phi[k], P) <= 1e-12 and rel_err(Pi[k], S) <= 1e-12, k


def test_observation_checks():
    """Shapes are checked, and every measurement that arrives must be noisy (G G' definite); rows
    before the first arrival are not used."""
    K, m, n = 4, 2, 3
    H, G = np.ones((K, m, n)), np.tile(np.eye(m), (K, 1, 1))
    with pytest.raises(ValueError, match="G must have shape"):
        DelayedObservation(H, G[:, :1, :], 0)
    G_silent = G.copy()
    G_silent[2] = 0.0
    with pytest.raises(ValueError, match="positive definite"):
        DelayedObservation(H, G_silent, 1)
    G_silent[2:] = G[2:]
    G_silent[:2] = 0.0
    obs = DelayedObservation(H, G_silent, 2)
    assert obs.delay_steps == 2 and obs.n_outputs == m
    DelayedObservation(H, np.zeros((K, m, m)), K)       # nothing ever arrives
