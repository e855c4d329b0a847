"""Delayed, noisy sensors in the nonlinear API: ``Observation``, ``Problem(observation=)``,
``solve`` (controller + delayed filter) and ``simulate`` (the filter on the nonlinear plant).

References, all independent of the code under test:
* on a LINEAR plant with additive noise, ``solve`` equals the LQG layer on the linearisation at its
  nominal: the filter of ``lqg.delayed_kalman`` on a ``DelayedObservation`` built here by hand, and
  the expected cost of ``lqg.separation_design`` (its own backward pass); ``simulate``'s Monte Carlo
  cost lies within its CI of it and the estimation errors have the filter's covariance Sigma_k;
* a NumPy loop of the closed loop on the nonlinear arm (plant, sensors, the filter written as
  (14.2): x_hat_k = Phi_k x_del_k + the commands in flight) gives ``simulate``'s trajectories;
* with perfect-ish undelayed sensors the observed design tends to the full-state one;
* perturbations: the first command that differs from the unperturbed run is u_{kp+1+l_s}.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from comparisons import rel_err

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.lqg import DelayedObservation, Gains, delayed_kalman, output_feedback_cost, separation_design
from delayed_ilqr.models import arm2, point_mass

SENSOR_SD = np.array([0.004, 0.004, 0.03, 0.03])      # position (m) and velocity (m/s) per sample


@dataclass(frozen=True)
class AdditiveForceNoise:
    """Additive force noise on the point mass: the plant stays linear-Gaussian (separation is exact)."""

    sigma: float = 0.5

    def __call__(self, x, u, ud):
        return jnp.concatenate([jnp.zeros((2, 2), x.dtype), self.sigma * jnp.eye(2, dtype=x.dtype)])


def linear_problem(sensory_delay, motor_delay):
    """The point mass (linear) with additive noise, sensing position and velocity l_s steps late."""
    obs = di.Observation(np.eye(4), np.diag(SENSOR_SD), delay_steps=sensory_delay)
    return point_mass(delay=0.01 * motor_delay, dt=0.01, horizon=40).replace(
        noise=AdditiveForceNoise(), observation=obs)


@cache
def linear_solution(sensory_delay, motor_delay):
    problem = linear_problem(sensory_delay, motor_delay)
    return problem, di.solve(problem)


def gains_of(policy):
    return Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback)


DELAYS = [(0, 0), (1, 3), (5, 0), (5, 3)]       # (l_s, l_m)
N_TRIALS = 2000             # one compiled Monte Carlo per problem serves the tests below


@pytest.mark.parametrize("ls,lm", [d if d in ((0, 0), (5, 3)) else pytest.param(*d, marks=pytest.mark.full) for d in DELAYS])
def test_linear_plant_equals_the_lqg_layer(ls, lm):
    problem, sol = linear_solution(ls, lm)
    assert sol.converged, sol.message
    est = sol.policy.estimator
    assert est.sensory_delay == ls
    lqg = linearize(problem.replace(observation=None), sol.x, sol.u)
    K = problem.horizon
    obs = DelayedObservation(np.broadcast_to(np.eye(4), (K, 4, 4)), np.broadcast_to(np.diag(SENSOR_SD), (K, 4, 4)), ls)
    fgains, cov = delayed_kalman(lqg, obs)
    assert rel_err(est.delayed_gain[ls:], fgains.delayed_gain[ls:]) < 1e-12
    assert rel_err(est.current_gain[ls:], fgains.current_gain[ls:]) < 1e-12
    assert rel_err(est.error_covariance, cov.current) < 1e-12
    # the controller of the solve is the LQG layer's optimum: the separation design's cost
    design = separation_design(lqg, obs)
    assert rel_err(sol.expected_cost, design.expected_cost) < 1e-9
    assert rel_err(output_feedback_cost(lqg, obs, gains_of(sol.policy), fgains), sol.expected_cost) < 1e-12
    # seeing less costs: later sensors, higher cost than the full-state design
    full = di.solve(problem.replace(observation=None))
    assert float(sol.expected_cost) > float(full.expected_cost)


@pytest.mark.parametrize("ls,lm", [(0, 0), (5, 3)])
def test_monte_carlo_matches_the_expected_cost_and_the_filter_covariance(ls, lm):
    problem, sol = linear_solution(ls, lm)
    runs = di.simulate(problem, sol.policy, n_trials=N_TRIALS, seed=7)
    s = runs.summary()
    assert abs(s.mean_cost - float(sol.expected_cost)) < 4 * s.standard_error, (s.mean_cost, float(sol.expected_cost))
    # the estimation error x_k - x_hat_k has mean 0 and covariance Sigma_k (14.3)
    err = np.asarray(runs.x[:, :-1] - runs.x_hat)
    Sigma = np.asarray(sol.policy.estimator.error_covariance)
    for k in (ls + 1, 20, 39):
        sd = np.sqrt(np.diag(Sigma[k]))
        assert np.all(np.abs(err[:, k].mean(0)) <= 4 * sd / math.sqrt(err.shape[0]) + 1e-12)
        sample = np.cov(err[:, k].T)
        # the variance of a sample variance is 2 sigma^4 / (N - 1) for Gaussian errors
        assert np.all(np.abs(np.diag(sample) - sd ** 2) <= 4 * sd ** 2 * math.sqrt(2 / (err.shape[0] - 1)) + 1e-15)


def test_nearly_perfect_undelayed_sensors_give_the_full_state_design():
    """H = I, G = 1e-7 I, l_s = 0: the filter returns the state, so the expected cost is the
    full-state J(0) and each trial the full-state trial with the same motor noise (same seed)."""
    base = point_mass(delay=0.03, noise=True)         # the shape test_simulate and test_cli compile
    problem = base.replace(observation=di.Observation(np.eye(4), 1e-7 * np.eye(4)))
    sol, full = di.solve(problem), di.solve(base)
    assert rel_err(sol.expected_cost, full.expected_cost) < 1e-8
    runs, runs_full = di.simulate(problem, sol.policy, 20, seed=3), di.simulate(base, full.policy, 20, seed=3)
    assert runs_full.x_hat is None
    np.testing.assert_allclose(np.asarray(runs.u), np.asarray(runs_full.u), atol=1e-4)
    np.testing.assert_allclose(np.asarray(runs.x_hat), np.asarray(runs.x[:, :-1]), atol=1e-6)


# ------------------------------------------------------------------------------------------------
# the closed loop on a nonlinear plant, against a NumPy loop
# ------------------------------------------------------------------------------------------------

def reference_observed_loop(problem, policy, xi, v, disturbance=None):
    """Plant, sensors, filter and law step by step in NumPy. The filter's present estimate is
    (14.2): Phi_k x_del_k plus the commands in flight, not the recursion with Kc of the library."""
    K, l, n = problem.horizon, problem.delay_steps, problem.n_states
    est, obs = policy.estimator, problem.observation
    ls = est.sensory_delay
    x_nom, u_nom = np.asarray(policy.x_nominal), np.asarray(policy.u_nominal)
    L, M = np.asarray(policy.state_feedback), np.asarray(policy.delay_feedback)
    A, B0, B1 = (np.asarray(a) for a in (est.A, est.B0, est.B1))
    if l == 0:
        B0, B1 = B0 + B1, 0 * B1
    H, ybar, Kd = np.asarray(est.H), np.asarray(est.y_nominal), np.asarray(est.delayed_gain)
    f, F = jax.jit(problem.dynamics), jax.jit(problem.noise)
    h, G = jax.jit(obs.measure), jax.jit(obs.noise_matrix)
    zero_u, eye = np.zeros(problem.n_controls), np.eye(n)
    du = {}                                              # command deviations sent, by time
    get = lambda j: du.get(j, zero_u)
    rows = lambda j: (A[j], B0[j], B1[j]) if j >= 0 else (eye, 0 * B0[0], 0 * B1[0])
    x = np.asarray(problem.x0, float)
    xs, us, x_hats = [x], [], []
    x_tilde = np.zeros(n)
    for k in range(K):
        sensed = xs[max(k - ls, 0)]
        dy = np.asarray(h(sensed)) + np.asarray(G(sensed)) @ v[k] - ybar[k]
        x_del = x_tilde + (Kd[k] @ (dy - H[k] @ x_tilde) if k >= ls else 0)
        Phi, flight = eye, np.zeros(n)
        for j in range(k - ls, k):                        # (14.2), oldest step first
            Aj, B0j, B1j = rows(j)
            Phi, flight = Aj @ Phi, Aj @ flight + B0j @ get(j) + B1j @ get(j - l)
        x_hat = Phi @ x_del + flight
        u = u_nom[k] + L[k] @ x_hat + sum(M[k, i] @ get(k + i - l) for i in range(l))
        u = np.clip(u, np.asarray(problem.u_min), np.asarray(problem.u_max))
        du[k] = u - u_nom[k]
        ud = u if l == 0 else (du[k - l] + u_nom[k - l] if k >= l else zero_u)
        x = x + problem.dt * np.asarray(f(x, u, ud)) + math.sqrt(problem.dt) * np.asarray(F(x, u, ud)) @ xi[k]
        if disturbance is not None:
            x = x + disturbance[k]
        Aj, B0j, B1j = rows(k - ls)
        x_tilde = Aj @ x_del + B0j @ get(k - ls) + B1j @ get(k - ls - l)
        xs.append(x)
        us.append(u)
        x_hats.append(x_nom[k] + x_hat)
    return np.array(xs), np.array(us), np.array(x_hats)


def test_simulate_on_the_nonlinear_arm_equals_a_numpy_loop():
    # nonlinear outputs and state-dependent sensory noise (velocity noise growing with speed)
    obs = di.Observation(lambda x: jnp.concatenate([x[:2], 0.5 * x[2:] ** 2 + x[2:]]),
                         lambda x: 0.01 * jnp.diag(jnp.concatenate([jnp.ones(2), 1 + x[2:4] ** 2])), delay_steps=3)
    problem = arm2(delay=0.02, noise="benchmark", dt=0.01, horizon=25).replace(observation=obs)
    sol = di.solve(problem)
    W = np.zeros((25, 4))
    W[8, 2:] = [0.3, -0.2]
    runs = di.simulate(problem, sol.policy, n_trials=2, seed=5, disturbance=W)
    for trial, key in enumerate(jax.random.split(jax.random.PRNGKey(5), 2)):
        xi = np.asarray(jax.random.normal(key, (25, 1, problem.n_noise)))[:, 0]
        v = np.asarray(jax.random.normal(jax.random.fold_in(key, 1), (25, 4)))
        xs, us, x_hats = reference_observed_loop(problem, sol.policy, xi, v, W)
        np.testing.assert_allclose(np.asarray(runs.x[trial]), xs, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(np.asarray(runs.u[trial]), us, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(np.asarray(runs.x_hat[trial]), x_hats, rtol=1e-9, atol=1e-11)


# ------------------------------------------------------------------------------------------------
# perturbations
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("ls,lm", [(0, 0), (1, 3), (5, 3)])
def test_first_response_to_a_disturbance_is_u_at_kp_plus_1_plus_ls(ls, lm):
    problem, sol = linear_solution(ls, lm)
    kp = 10
    W = np.zeros((problem.horizon, 4))
    W[kp, 2] = 0.05                                      # a velocity kick entering x_{kp+1}
    base = di.simulate(problem, sol.policy, n_trials=N_TRIALS, seed=2)
    pert = di.simulate(problem, sol.policy, n_trials=N_TRIALS, seed=2, disturbance=W)
    changed = np.any(np.asarray(pert.u) != np.asarray(base.u), axis=(0, 2))
    assert not changed[:kp + 1 + ls].any()
    assert changed[kp + 1 + ls]
    # the plant: the disturbance alone (commands of the unperturbed run) up to x_{kp+1+ls+lm}; the
    # command u_{kp+1+ls} acts at kp+1+ls+lm and first changes x_{kp+2+ls+lm}
    open_loop = np.asarray(base.x).copy()
    A = np.asarray(sol.policy.estimator.A)          # linear plant: deviations propagate with A
    delta = np.zeros((N_TRIALS, 4))
    for k in range(kp + 1, problem.horizon + 1):
        delta = delta @ A[k - 1].T if k > kp + 1 else np.tile(W[kp], (N_TRIALS, 1))
        open_loop[:, k] += delta
    same = np.all(np.abs(np.asarray(pert.x) - open_loop) < 1e-12, axis=(0, 2))
    assert same[:kp + 2 + ls + lm].all()
    assert not same[kp + 2 + ls + lm]


def test_disturbance_without_observation_is_seen_at_the_next_step():
    problem = point_mass(delay=0.03, noise=True)
    sol = di.solve(problem)
    W = np.zeros((60, 4))
    W[10, 3] = 0.05
    base = di.simulate(problem, sol.policy, 3, seed=1)
    pert = di.simulate(problem, sol.policy, 3, seed=1, disturbance=W)
    changed = np.any(np.asarray(pert.u) != np.asarray(base.u), axis=(0, 2))
    assert not changed[:11].any() and changed[11]
    np.testing.assert_array_equal(np.asarray(pert.x[:, :11]), np.asarray(base.x[:, :11]))
    np.testing.assert_allclose(np.asarray(pert.x[:, 11] - base.x[:, 11]), np.tile(W[10], (3, 1)), atol=1e-15)


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("args,match", [
    ((np.eye(4)[:2], np.eye(3)), "noise must have shape"),
    ((np.eye(4)[:2], np.zeros((2, 2))), "positive definite"),
    ((np.full((2, 4), np.nan), np.eye(2)), "output must be finite"),
    ((np.ones(4), np.eye(2)), "output must have shape"),
    ((np.eye(4)[:2], np.eye(2), -1), "delay_steps must be a non-negative integer"),
    ((np.eye(4)[:2], np.eye(2), 1.5), "delay_steps must be a non-negative integer"),
])
def test_observation_refuses_bad_arguments(args, match):
    with pytest.raises(ValueError, match=match):
        di.Observation(*args)


@pytest.mark.parametrize("obs,match", [
    (lambda: di.Observation(np.eye(3), np.eye(3)), r"output must have shape \(m, 4\)"),
    (lambda: di.Observation(np.eye(4), np.eye(4), delay_steps=60), "below the horizon"),
    (lambda: di.Observation(lambda x: x[:2], np.eye(3)), r"noise must have shape \(2, q\)"),
    (lambda: di.Observation(lambda x: x[:2], lambda x: jnp.zeros((2, 2))), "positive definite"),
    (lambda: di.Observation(lambda x: x[:2], lambda x: jnp.eye(3)), r"must return shape \(2, q\)"),
    (lambda: di.Observation(lambda x: x[:2, None], np.eye(2)), r"must return shape \(m,\)"),
])
def test_problem_checks_the_observation_against_the_state(obs, match):
    with pytest.raises(ValueError, match=match):
        point_mass().replace(observation=obs())


@pytest.mark.parametrize("output,match", [
    (lambda x: jnp.full(2, jnp.nan) * x[0], r"observation output h\(x0\) must be finite; got a non-finite value "
                                            r"at index \(0,\)"),
    (lambda x: jnp.sqrt(x[:2] - 1.0), r"observation output h\(x0\) must be finite"),
    (lambda x: x[jnp.array([7, 8])], r"observation output h\(x\) indexes past its argument at x0 of shape \(4,\)"
                                     r".*index 7 is out of bounds for axis 0 with size 4"),
    (lambda x: jnp.take(x, jnp.array([1, 9])), r"observation output h\(x\) indexes past.*index 9 is out of bounds"),
    (lambda x: x[7:9], r"observation output h\(x\) must return shape \(m,\) with m >= 1; got \(0,\)"),
])
def test_problem_evaluates_the_observation_at_x0(output, match):
    """An output that is NaN at x0 or reads past the state (JAX clamps such an index, or fills
    NaN) is refused when the problem is built; before, the solve ended CONVERGED_GRADIENT with a
    NaN expected cost and NaN filter gains."""
    with pytest.raises(ValueError, match=match):
        point_mass().replace(observation=di.Observation(output, np.eye(2) * 1e-3))


def test_a_filter_that_is_not_finite_at_the_nominal_is_reported():
    """Sensors finite at x0 but NaN along the nominal (a pole of h on the way): the status says
    the filter failed, and the policy carries no NaN: the full-state feedback and a filter without
    measurement updates."""
    pole = lambda x: x[:2] * jnp.where(x[0] > 0.05, jnp.nan, 1.0)
    problem = point_mass(noise=True).replace(observation=di.Observation(pole, np.eye(2) * 1e-3, 1))
    sol = di.solve(problem)
    assert sol.status == di.Status.NON_FINITE_FILTER, sol.status
    assert "filter" in sol.message and "observation" in sol.message
    for leaf in jax.tree_util.tree_leaves(sol.policy):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.all(np.asarray(sol.policy.estimator.delayed_gain) == 0)
    assert np.all(np.asarray(sol.policy.estimator.current_gain) == 0)
    full_state = di.solve(point_mass(noise=True))
    np.testing.assert_array_equal(sol.policy.state_feedback, full_state.policy.state_feedback)


def test_problem_refuses_a_non_observation():
    with pytest.raises(TypeError, match="observation must be None or a delayed_ilqr.Observation"):
        point_mass().replace(observation=np.eye(4))


def test_simulate_refuses_mismatched_policy_and_sensors():
    problem, sol = linear_solution(0, 0)
    with pytest.raises(ValueError, match="policy.estimator is set but the problem has no observation"):
        di.simulate(problem.replace(observation=None), sol.policy, 2)
    with pytest.raises(ValueError, match="policy.estimator must be a delayed_ilqr.Estimator"):
        di.simulate(problem, sol.policy._replace(estimator=None), 2)
    with pytest.raises(ValueError, match="disturbance must have shape"):
        di.simulate(problem, sol.policy, 2, disturbance=np.zeros((3, 4)))
    bad = sol.policy._replace(estimator=sol.policy.estimator.replace(H=np.zeros((40, 2, 4))))
    with pytest.raises(ValueError, match=r"policy.estimator.H must have shape \(40, 4, 4\)"):
        di.simulate(problem, bad, 2)


# ------------------------------------------------------------------------------------------------
# the models' default sensors
# ------------------------------------------------------------------------------------------------

def test_models_attach_their_default_sensors():
    from delayed_ilqr.models import arm2_muscle6, sensors
    assert point_mass().observation is None and arm2().observation is None
    obs = point_mass(sensory_delay=0.05, dt=0.01).observation
    assert obs.delay_steps == 5
    np.testing.assert_allclose(np.diag(obs.G), [0.005, 0.005, 0.05, 0.05], rtol=1e-12)   # the documented SDs at 10 ms
    # a density: halving dt multiplies the per-sample SD by sqrt 2
    fine = arm2(sensory_delay=0.05, dt=0.005).observation
    assert fine.delay_steps == 10
    np.testing.assert_allclose(np.diag(fine.G), math.sqrt(2) * np.array([0.02, 0.02, 0.2, 0.2]), rtol=1e-12)
    muscle = arm2_muscle6(sensory_delay=0.0).observation
    np.testing.assert_array_equal(muscle.H, np.eye(10)[:4])           # joint angles and velocities
    assert sensors.JOINT_ANGLE_DENSITY / math.sqrt(0.01) == pytest.approx(0.02)
    with pytest.raises(ValueError, match="sensory_delay must be a whole number of steps"):
        arm2(sensory_delay=0.025)


@pytest.mark.full
def test_sensing_study_runs_both_filters_on_the_delayed_sensors():
    """l_s = 5: both designs share the controller and nominal; the aware one has an exact expected
    cost, the ignorant one (its filter made for l_s = 0, run on sensors 5 steps late: the plant's
    and the filter's sensory delays differ in simulate) none; both first correct the kick
    (1 + l_s) dt after it (no limits on the point mass: nothing is clipped)."""
    from delayed_ilqr.experiments.sensing_study import sensory_delay_study, study_rows
    results = sensory_delay_study([0.05], delay=0.03, model="point_mass", trials=50, seed=4, kick=0.2,
                                  pulse_time=0.2, model_kwargs=dict(noise=True))
    aware, ignorant = results
    assert aware.solution.policy.estimator.sensory_delay == 5 and ignorant.solution.policy.estimator.sensory_delay == 0
    np.testing.assert_array_equal(np.asarray(aware.solution.x), np.asarray(ignorant.solution.x))
    rows = {r["design"]: r for r in study_rows(results)}
    assert ignorant.expected_cost is None and rows["ignorant"]["local prediction E[J] (linearised)"] is None
    assert rows["aware"]["local prediction E[J] (linearised)"] == pytest.approx(float(aware.solution.expected_cost))
    assert rows["aware"]["first response [ms]"] == pytest.approx(60.0)
    assert rows["ignorant"]["first response [ms]"] == pytest.approx(60.0)
    # the filters differ, so the trials do (same seed: same noise)
    assert np.any(np.asarray(aware.runs.u) != np.asarray(ignorant.runs.u))


def test_a_noise_free_design_gets_the_filter_of_the_plants_noise():
    """experiments.designs.filter_on_plant: iLQR's design problem has no motor noise, so its own
    filter trusts the model (zero gain) and its controller would run open loop on the sensed plant.
    With the plant's filter (its motor and sensory noise, at iLQR's nominal, separation) the same
    feedback corrects the noise: the endpoint scatter on the noisy plant falls."""
    from delayed_ilqr.experiments import designs
    from delayed_ilqr.models.point_mass import PointMassNoise

    # a tenth of P1-noisy's signal-dependent noise: at 0.5 iLQR's high-gain feedback diverges in
    # mean square on this plant even with the state (endpoint spread of tens of metres)
    plant = point_mass(delay=0.03, noise=True, sensory_delay=0.03).replace(noise=PointMassNoise(sigma_u=0.05))
    problem, options = designs.design(plant, "deterministic")
    sol = di.solve(problem, None, options)
    assert float(jnp.max(jnp.abs(sol.policy.estimator.delayed_gain))) == 0.0
    filtered = designs.filter_on_plant(plant, sol)
    assert float(jnp.max(jnp.abs(filtered.policy.estimator.delayed_gain))) > 0.0
    # the design itself is unchanged: nominal, feedback, its own (noise-free) prediction and status
    for a, b in ((filtered.u, sol.u), (filtered.policy.state_feedback, sol.policy.state_feedback),
                 (filtered.expected_cost, sol.expected_cost), (filtered.status, sol.status)):
        np.testing.assert_array_equal(a, b)

    def spread(policy):
        ends = np.asarray(di.simulate(plant, policy, 400, seed=2).x[:, -1, :2])
        return float(np.sqrt(np.linalg.eigvalsh(np.cov(ends, rowvar=False))[-1]))

    open_loop, closed = spread(sol.policy), spread(filtered.policy)
    print(f"\nendpoint spread: zero-gain filter {1e3 * open_loop:.2f} mm, the plant's filter {1e3 * closed:.2f} mm")
    assert closed < 0.5 * open_loop
