"""Several sensors in the nonlinear API: ``Problem(observation=[Observation, ...])``, each sensor
with its own delay and period; ``solve`` designs the fused filter, ``simulate`` runs it, and
``save``/``load`` keep it.

References, independent of the code under test:
* on a LINEAR plant with additive noise the solve equals the LQG layer on the linearisation (whose
  fused filter tests/test_fusion.py checks against the augmented Kalman filter): the filter of
  ``lqg.fused_kalman`` on DelayedObservations built here by hand, and the separation design's cost;
  ``simulate``'s Monte Carlo cost lies within its CI of it and the estimation errors have the
  filter's covariance;
* sensors with one delay equal one observation with the outputs stacked by hand.
"""
from __future__ import annotations

import math
from functools import cache

import jax.numpy as jnp
import numpy as np
import pytest
from comparisons import rel_err
from test_sensing import AdditiveForceNoise

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.lqg import DelayedObservation, Gains, fused_design, fused_loop
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.models.arm2 import hand_position
from delayed_ilqr.sensor_list import SensorList

K = 30
POS, VEL = np.eye(4)[:2], np.eye(4)[2:]
SD_POS, SD_VEL = np.diag([0.004, 0.004]), np.diag([0.03, 0.03])
# vision-like: position, late and every other step; proprioception-like: velocity, early
SENSORS = ((POS, SD_POS, 6, 2), (VEL, SD_VEL, 2, 1))


def sensors(specs=SENSORS):
    return [di.Observation(H, G, delay_steps=ls, period=m) for H, G, ls, m in specs]


def linear_problem(observation):
    return point_mass(delay=0.02, dt=0.01, horizon=K).replace(noise=AdditiveForceNoise(), observation=observation)


@cache
def fused_solution():
    problem = linear_problem(sensors())
    return problem, di.solve(problem)


def test_the_fused_solve_equals_the_lqg_layer():
    problem, sol = fused_solution()
    assert sol.converged, sol.message
    est = sol.policy.estimator
    assert isinstance(est, di.FusedEstimator) and est.lags == (6, 6, 2, 2)
    lqg = linearize(problem.replace(observation=None), sol.x, sol.u)
    by_hand = [DelayedObservation(np.broadcast_to(H, (K,) + H.shape), np.broadcast_to(G, (K,) + G.shape), ls, m)
               for H, G, ls, m in SENSORS]
    design = fused_design(lqg, by_hand)
    assert rel_err(est.error_covariance, design.covariances.current) < 1e-12
    assert rel_err(est.window_gain, design.filter_gains.window_gain) < 1e-12
    assert rel_err(sol.expected_cost, design.expected_cost) < 1e-9
    gains = Gains(sol.policy.feedforward, sol.policy.state_feedback, sol.policy.delay_feedback)
    assert rel_err(fused_loop(lqg, by_hand, gains).expected_cost, sol.expected_cost) < 1e-12
    # a second sensor helps: the fast one alone costs more
    alone = di.solve(linear_problem(sensors()[1]))
    assert float(sol.expected_cost) < float(alone.expected_cost)


def test_monte_carlo_matches_the_expected_cost_and_the_filter_covariance(tmp_path):
    problem, sol = fused_solution()
    runs = di.simulate(problem, sol.policy, n_trials=2000, seed=3)
    s = runs.summary()
    assert abs(s.mean_cost - float(sol.expected_cost)) < 4 * s.standard_error, (s.mean_cost, float(sol.expected_cost))
    err = np.asarray(runs.x[:, :-1] - runs.x_hat)
    Sigma = np.asarray(sol.policy.estimator.error_covariance)
    for k in (3, 7, 20, 29):
        sd = np.sqrt(np.diag(Sigma[k]))
        assert np.all(np.abs(err[:, k].mean(0)) <= 4 * sd / math.sqrt(err.shape[0]) + 1e-12)
        sample = np.var(err[:, k], axis=0, ddof=1)
        assert np.all(np.abs(sample - sd ** 2) <= 4 * sd ** 2 * math.sqrt(2 / (err.shape[0] - 1)) + 1e-15)
    # saved and loaded, the fused filter runs the same trials
    path = tmp_path / "fused.npz"
    di.saving.save(path, sol, problem=problem)
    back = di.load(path)
    assert back.policy.estimator.lags == sol.policy.estimator.lags
    again = di.simulate(problem, back.policy, n_trials=2000, seed=3)
    np.testing.assert_array_equal(again.cost, runs.cost)


def test_one_sensor_in_a_list_is_that_sensor_and_equal_delays_stack():
    obs = sensors()[1]
    assert linear_problem([obs]).observation is obs
    # two sensors with one delay: one observation with the outputs stacked and the noise block-diagonal
    same = [di.Observation(POS, SD_POS, delay_steps=2), di.Observation(VEL, SD_VEL, delay_steps=2)]
    listed = di.solve(linear_problem(same))
    stacked = di.solve(linear_problem(di.Observation(np.eye(4), np.diag([0.004, 0.004, 0.03, 0.03]), delay_steps=2)))
    assert isinstance(listed.policy.estimator, di.Estimator)
    assert rel_err(listed.expected_cost, stacked.expected_cost) < 1e-12
    assert rel_err(listed.policy.estimator.current_gain, stacked.policy.estimator.current_gain) < 1e-12


@pytest.mark.parametrize("observation, error, match", [
    ([], ValueError, "observation must be an Observation or a non-empty list"),
    ([np.eye(4)], TypeError, r"observation\[0\] must be a delayed_ilqr.Observation; got ndarray"),
    ([di.Observation(POS, SD_POS), di.Observation(VEL, SD_VEL, delay_steps=K)], ValueError,
     r"observation\[1\]: observation delay_steps must be below the horizon.*got delay_steps=30, horizon=30"),
    ([di.Observation(POS, SD_POS), di.Observation(lambda x: jnp.log(x[:2] - 1.0), SD_POS)], ValueError,
     r"observation\[1\]: observation output h\(x0\) must be finite"),
])
def test_the_list_is_checked_by_name(observation, error, match):
    with pytest.raises(error, match=match):
        linear_problem(observation)


@pytest.mark.parametrize("period", [0, 1.5, True])
def test_a_period_must_be_a_positive_integer(period):
    with pytest.raises(ValueError, match=f"observation period must be a positive integer; got {period!r}"):
        di.Observation(POS, SD_POS, period=period)


def test_the_delay_frame_is_refused_with_several_sensors():
    with pytest.raises(ValueError, match="delay_frame is not available with an observation"):
        point_mass(delay=0.02, horizon=K).replace(observation=sensors(), delay_frame=5)


def test_the_arms_offer_proprioception_and_vision():
    problem = arm2(horizon=K, sensory_delay=0.05, vision_delay=0.1)
    assert isinstance(problem.observation, SensorList) and problem.observation.delays == (5, 10)
    vision = problem.observation.observations[1]
    np.testing.assert_allclose(vision.measure(problem.x0), hand_position(problem.x0[:2]), rtol=1e-15)
    assert float(vision.G[0, 0]) == pytest.approx(0.0005 / math.sqrt(0.01))    # 5 mm per 10 ms sample
    assert isinstance(arm2(horizon=K, vision_delay=0.1).observation, di.Observation)


def test_signal_dependent_noise_alternates_with_several_sensors():
    """The point mass's noise proportional to the command (P1's benchmark preset) with the two
    sensors: ``solve`` returns the fused alternation of the LQG layer at its nominal (checked against
    the augmented alternation in test_fused_alternation.py), starting from iLQG's law with the
    filter of its own loop, and its exact cost is below that start's."""
    from delayed_ilqr.lqg import fused_alternate

    problem = point_mass(delay=0.02, dt=0.01, horizon=K, noise=True).replace(observation=sensors())
    sol = di.solve(problem)
    full = di.solve(problem.replace(observation=None))
    np.testing.assert_array_equal(sol.u, full.u)
    lqg = linearize(problem.replace(observation=None), full.x, full.u)
    by_hand = [DelayedObservation(np.broadcast_to(H, (K,) + H.shape), np.broadcast_to(G, (K,) + G.shape), ls, m)
               for H, G, ls, m in SENSORS]
    p = full.policy
    start = Gains(p.feedforward, p.state_feedback, p.delay_feedback)
    alt = fused_alternate(lqg, by_hand, start, tol=di.Options().tol_cost)
    assert rel_err(alt.costs[0], fused_loop(lqg, by_hand, start).expected_cost) <= 1e-12
    assert rel_err(sol.expected_cost, alt.expected_cost) <= 1e-10
    assert int(alt.alternations) >= 1 and float(alt.expected_cost) < float(alt.costs[0])
    assert rel_err(sol.policy.state_feedback, alt.gains.state_feedback) <= 1e-10
