"""Several delayed sensors, each with its own delay and period (``lqg.fusion``, and the periods of
one sensor in ``lqg.estimator``), against the Kalman filter on the augmented state written
independently in tests/fused_sensing.py: the error covariances, the estimates of one record (the
filter as a linear map of the measurements, so its gains) and the exact expected cost of the
controller-filter pair, to round-off."""
from __future__ import annotations

import numpy as np
import pytest
from comparisons import rel_err
from fused_sensing import AugmentedSensors, random_fusion_problem
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr.lqg import (DelayedObservation, FilterGains, Gains, delayed_kalman, filter_estimates, fused_design, fused_estimates,
                              fused_kalman, fused_loop, output_feedback_cost, separation_design)

RTOL = 1e-9


def _against_augmented(lqg, sensors, seed, additive):
    """Relative differences of the fused filter and its pairs from the augmented ones."""
    K = lqg.horizon
    aug = AugmentedSensors(lqg, sensors)
    design = fused_design(lqg, sensors)
    rng = np.random.default_rng(seed)
    errs = {}
    if additive:
        Lz, posts, terminal = aug.kalman()
        now = aug.block(0)
        du = rng.standard_normal((K, lqg.n_controls))
        dys = [rng.standard_normal((K, s.n_outputs)) for s in sensors]
        x_hat = fused_estimates(lqg, sensors, design.filter_gains, du, dys)
        Kh, _, _ = aug.policy(design.gains, np.zeros((K, lqg.n_states, 1)))
        errs = {
            "current": rel_err(design.covariances.current,
                               np.concatenate([posts[:, now, now], terminal[None, now, now]])),
            "x_hat": rel_err(x_hat, aug.estimates(Lz, du, np.concatenate(dys, axis=1))[:, now]),
            "separation cost": rel_err(design.expected_cost, aug.output_feedback_cost(Kh, Lz)),
        }
    # any law, and the filter for the motor noise of its own loop (signal-dependent if not additive)
    gains = Gains(*(np.asarray(g) + 0.2 * rng.standard_normal(np.shape(g)) for g in design.gains))
    loop = fused_loop(lqg, sensors, gains)
    cost, current = aug.loop_kalman_cost(aug.policy(gains, np.zeros((K, lqg.n_states, 1)))[0])
    errs["loop cost"] = rel_err(loop.expected_cost, cost)
    errs["loop current"] = rel_err(loop.covariances.current[:-1], current)
    if additive:
        errs["loop gains"] = rel_err(loop.filter_gains.window_gain, design.filter_gains.window_gain) + rel_err(
            loop.filter_gains.base_gain, design.filter_gains.base_gain)
    return errs


# (K, n, d, p, l, sensors as (m, q, delay, period)): delays 0, 1, equal, >= K; periods 1..3
CASES = [
    (6, 2, 1, 1, 0, [(1, 1, 0, 1), (1, 2, 2, 1), (1, 1, 8, 1)]),    # delays 0 and > K (never arrives)
    (8, 2, 1, 1, 1, [(1, 1, 2, 1), (2, 2, 2, 3)]),                  # equal delays, different periods
    (9, 2, 2, 2, 2, [(2, 2, 1, 2), (1, 1, 4, 1), (1, 1, 9, 3)]),    # delays 1 and = K
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"K{c[0]}-l{c[4]}-" + "-".join(
    f"ls{s[2]}m{s[3]}" for s in c[5]))
@settings(max_examples=1, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_fused_filter_matches_augmented_kalman(case, seed):
    K, n, d, p, l, specs = case
    lqg, sensors = random_fusion_problem(seed, K, n, d, p, l, specs)
    errs = _against_augmented(lqg, sensors, seed, additive=True)
    assert all(e <= RTOL for e in errs.values()), errs


@st.composite
def _structures(draw):
    K = draw(st.integers(3, 9))
    delay = st.one_of(st.just(0), st.just(1), st.integers(0, K - 1), st.integers(K, K + 2))
    specs = draw(st.lists(st.tuples(st.integers(1, 2), st.integers(1, 2), delay, st.integers(1, 3)),
                          min_size=1, max_size=3))
    specs = [(m, max(q, m), ls, period) for m, q, ls, period in specs]
    return K, draw(st.integers(1, 3)), draw(st.integers(1, 2)), draw(st.integers(0, 2)), specs


@settings(max_examples=4, deadline=None)
@given(structure=_structures(), seed=st.integers(0, 2**31 - 1))
def test_fused_loop_matches_augmented_kalman_random_structures(structure, seed):
    """Random sizes, delays and periods, signal-dependent motor noise: the filter for the loop's
    own noise and the exact cost of the pair."""
    K, n, d, l, specs = structure
    lqg, sensors = random_fusion_problem(seed, K, n, d, 1, l, specs, mult_noise=0.3)
    errs = _against_augmented(lqg, sensors, seed, additive=False)
    assert all(e <= RTOL for e in errs.values()), (structure, errs)


def test_equal_delays_stack_into_one_delayed_filter():
    """Sensors with one delay are one DelayedObservation with per-row periods: the delayed filter
    (no window) and the fused one agree, and a list of one sensor is that sensor."""
    lqg, sensors = random_fusion_problem(3, 8, 2, 1, 1, 1, [(1, 1, 2, 1), (2, 2, 2, 3)])
    stacked = DelayedObservation(np.concatenate([s.H for s in sensors], axis=1),
                                 np.concatenate([np.pad(sensors[0].G, ((0, 0), (0, 0), (0, 2))),
                                                 np.pad(sensors[1].G, ((0, 0), (0, 0), (1, 0)))], axis=1),
                                 delay_steps=2, period=(1, 3, 3))
    _, cov = delayed_kalman(lqg, stacked)
    _, fused = fused_kalman(lqg, sensors)
    assert rel_err(cov.current, fused.current) <= RTOL
    _, one = fused_kalman(lqg, sensors[:1])
    assert rel_err(delayed_kalman(lqg, sensors[0])[1].current, one.current) <= RTOL


@pytest.mark.parametrize("ls, period", [(0, 2), (2, 3)])
def test_one_sampled_sensor_through_the_delayed_filter(ls, period):
    """A sensor sampled every m steps through the single-sensor machinery: the filter's estimates
    and covariance, and the exact cost of a pair that is not the optimal one (the joint second
    moments), against the augmented filter with absent rows."""
    lqg, (obs,) = random_fusion_problem(5, 9, 2, 1, 1, 1, [(1, 2, ls, period)])
    fgains, cov = delayed_kalman(lqg, obs)
    aug = AugmentedSensors(lqg, [obs])
    Lz, posts, terminal = aug.kalman()
    now = aug.block(0)
    assert rel_err(cov.current, np.concatenate([posts[:, now, now], terminal[None, now, now]])) <= RTOL
    rng = np.random.default_rng(0)
    du, dy = rng.standard_normal((9, 1)), rng.standard_normal((9, 1))
    assert rel_err(filter_estimates(lqg, obs, fgains, du, dy)[0], aug.estimates(Lz, du, dy)[:, now]) <= RTOL
    # a perturbed pair (delayed gain nonzero on absent rows, which must be ignored there) under
    # signal-dependent motor noise: the joint second moments against the augmented ones
    lqg, (obs,) = random_fusion_problem(5, 9, 2, 1, 1, 1, [(1, 2, ls, period)], mult_noise=0.3)
    design = separation_design(lqg, obs)
    Kd = 1.3 * np.asarray(design.filter_gains.delayed_gain) + 0.1
    Kh, Lz, Kc = aug.policy(design.gains, Kd)
    present = np.asarray(obs.present)[:, None, :]
    got = output_feedback_cost(lqg, obs, design.gains, FilterGains(Kd, Kc))
    assert rel_err(got, AugmentedSensors(lqg, [obs]).output_feedback_cost(Kh, Lz * present)) <= RTOL


def test_the_exact_cost_of_the_fused_pair_has_gradients():
    """d/dtheta of fused_loop's exact cost, theta scaling the slow sensor's noise and the motor
    noise (signal-dependent), by autodiff against central finite differences."""
    import jax

    lqg, sensors = random_fusion_problem(2, 6, 2, 1, 1, 1, [(1, 1, 0, 1), (1, 1, 3, 2)], mult_noise=0.3)
    gains = fused_design(lqg, sensors).gains

    def cost(theta):
        slow = DelayedObservation(sensors[1].H, theta[0] * sensors[1].G, 3, 2)
        return fused_loop(lqg.replace(c=theta[1] * lqg.c), [sensors[0], slow], gains).expected_cost

    theta, h = np.array([1.1, 0.9]), 1e-5
    grad = np.asarray(jax.grad(cost)(jax.numpy.asarray(theta)))
    fd = [(cost(theta + h * e) - cost(theta - h * e)) / (2 * h) for e in np.eye(2)]
    assert rel_err(grad, np.array(fd)) <= 1e-7, (grad, fd)
