"""Monte Carlo of the nonlinear plant under the delayed feedback law (``delayed_ilqr.simulate``),
against independent references: the nominal rollout, a plain-Python loop of the law, the exact
expected cost of the linear noisy point mass, and the delay-aware vs delay-ignorant study."""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.experiments import delay_study as study
from delayed_ilqr.experiments.designs import design as design_problem
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.lqg import Gains, policy_cost
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.statistics import sample_stats


@pytest.fixture(scope="module")
def arm_solution():
    problem = arm2(delay=0.03)
    return problem, di.solve(problem)


@pytest.fixture(scope="module")
def noisy_point_mass():
    problem = point_mass(delay=0.03, noise=True)
    return problem, di.solve(problem)


def random_policy(problem, l_p, seed, scale=0.3):
    """A policy with arbitrary gains and nominal (the law need not be a good controller to be tested)."""
    rng = np.random.default_rng(seed)
    K, n, d = problem.horizon, problem.n_states, problem.n_controls
    u_nom = 0.5 * rng.standard_normal((K, d))
    x_nom = np.cumsum(0.01 * rng.standard_normal((K + 1, n)), axis=0)
    return di.Policy(x_nominal=x_nom, u_nominal=u_nom, feedforward=rng.standard_normal((K, d)),
                     state_feedback=-scale * rng.standard_normal((K, d, n)),
                     delay_feedback=0.2 * rng.standard_normal((K, l_p, d, d)))


def reference_closed_loop(problem, policy, xi=None, substeps=1):
    """The delayed feedback law written out step by step in NumPy (an independent implementation).

    u_k = clip(u_nom_k + L_k (x_k - x_nom_k) + sum_i M_k^i (u_{k+i-l_p} - u_nom_{k+i-l_p})),
    ud_k = u_{k-l}, zero before t = 0; Euler-Maruyama with ``substeps`` sub-steps and noise xi [K, substeps, p].
    """
    K, l = problem.horizon, problem.delay_steps
    x_nom, u_nom = np.asarray(policy.x_nominal), np.asarray(policy.u_nominal)
    L, M = np.asarray(policy.state_feedback), np.asarray(policy.delay_feedback)
    l_p = M.shape[1]
    lo, hi = np.asarray(problem.u_min), np.asarray(problem.u_max)
    sent = {}
    nominal = {k: u_nom[k] for k in range(K)}
    zero = np.zeros(problem.n_controls)
    x = np.asarray(problem.x0, dtype=float)
    xs, us = [x], []
    f = jax.jit(problem.dynamics)                      # one step at a time, compiled once
    F = jax.jit(problem.noise) if problem.noise is not None else None
    h = problem.dt / substeps
    for k in range(K):
        u = u_nom[k] + L[k] @ (x - x_nom[k])
        for i in range(l_p):
            j = k + i - l_p
            u = u + M[k, i] @ (sent.get(j, zero) - nominal.get(j, zero))
        u = np.clip(u, lo, hi)
        sent[k] = u
        ud = sent.get(k - l, zero)
        for s in range(substeps):
            dx = h * np.asarray(f(x, u, ud))
            if xi is not None:
                dx = dx + math.sqrt(h) * np.asarray(F(x, u, ud)) @ xi[k, s]
            x = x + dx
        xs.append(x)
        us.append(u)
    return np.array(xs), np.array(us)


# ------------------------------------------------------------------------------------------------
# deterministic agreement
# ------------------------------------------------------------------------------------------------

def test_zero_noise_reproduces_the_nominal_rollout(arm_solution):
    problem, sol = arm_solution
    assert sol.converged, sol.message
    runs = di.simulate(problem, sol.policy, n_trials=3, seed=0, substeps=1)
    assert runs.x.shape == (3, problem.horizon + 1, 4) and runs.u.shape == (3, problem.horizon, 2)
    assert runs.cost.shape == (3,)
    for j in range(3):
        np.testing.assert_allclose(np.asarray(runs.x[j]), np.asarray(sol.x), rtol=1e-12, atol=1e-13)
        np.testing.assert_allclose(np.asarray(runs.u[j]), np.asarray(sol.u), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(np.asarray(runs.cost), float(sol.cost), rtol=1e-10)
    summary = runs.summary()
    assert summary.std_cost < 1e-12 * float(sol.cost)
    # same absolute floor as the per-trial check: final velocities are ~1e-6, where averaging
    # identical trials rounds at ~1e-16
    np.testing.assert_allclose(summary.final_state_mean, np.asarray(sol.x[-1]), rtol=1e-12, atol=1e-13)


def test_substeps_refine_the_integration_at_first_order(arm_solution):
    """Without noise, m sub-steps integrate the same closed loop more finely: Euler's error against
    a 32-sub-step reference halves each time m doubles (measured ratios 2.1, 2.2)."""
    problem, sol = arm_solution
    reference = np.asarray(di.simulate(problem, sol.policy, 1, substeps=32).x[0])
    errors = [np.max(np.abs(np.asarray(di.simulate(problem, sol.policy, 1, substeps=m).x[0]) - reference))
              for m in (1, 2, 4)]
    assert errors[0] > 1e-3                       # the coarse nominal's Euler error is visible
    for coarse, fine in zip(errors, errors[1:]):
        assert 1.6 < coarse / fine < 2.6


@pytest.mark.parametrize("plant_delay, policy_delay", [(3, 0), (3, 5), (0, 2)],
                         ids=["ignorant-on-delayed", "longer-policy-delay", "delayed-policy-on-undelayed"])
def test_policy_delay_may_differ_from_the_plant_delay(plant_delay, policy_delay):
    """The law feeds back the commands actually sent, over the policy's own delay l_p; the plant
    acts on the command sent l steps earlier. Compared with a step-by-step NumPy loop."""
    problem = point_mass(delay=0.01 * plant_delay, horizon=20)
    policy = random_policy(problem, policy_delay, seed=plant_delay + 10 * policy_delay)
    runs = di.simulate(problem, policy, n_trials=2, seed=0)
    xs, us = reference_closed_loop(problem, policy)
    np.testing.assert_allclose(np.asarray(runs.x[1]), xs, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(runs.u[1]), us, rtol=1e-12, atol=1e-12)


def test_noise_and_substeps_follow_the_documented_euler_maruyama_scheme():
    """Trial j uses xi = normal(split(PRNGKey(seed), N)[j], (K, substeps, p)) and increments sqrt(h) F xi."""
    problem = point_mass(delay=0.02, noise=True, horizon=15)
    policy = random_policy(problem, 2, seed=7)
    seed, n, m = 5, 3, 3
    runs = di.simulate(problem, policy, n_trials=n, seed=seed, substeps=m)
    key = jax.random.split(jax.random.PRNGKey(seed), n)[2]
    xi = np.asarray(jax.random.normal(key, (problem.horizon, m, problem.n_noise)))
    xs, us = reference_closed_loop(problem, policy, xi=xi, substeps=m)
    np.testing.assert_allclose(np.asarray(runs.x[2]), xs, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(np.asarray(runs.u[2]), us, rtol=1e-11, atol=1e-12)


def test_commands_are_clipped_to_the_limits():
    problem = point_mass(delay=0.02, horizon=15).replace(u_min=[-0.1, -0.2], u_max=[0.1, 0.3])
    policy = random_policy(problem, 2, seed=3, scale=5.0)
    runs = di.simulate(problem, policy, 1)
    u = np.asarray(runs.u[0])
    assert np.all(u >= [-0.1, -0.2]) and np.all(u <= [0.1, 0.3])
    assert np.any(u == 0.1) or np.any(u == -0.1)          # the limits are active in this test
    xs, us = reference_closed_loop(problem, policy)
    np.testing.assert_allclose(u, us, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------------

def test_monte_carlo_mean_agrees_with_the_exact_expected_cost_on_the_linear_point_mass(noisy_point_mass):
    """The point mass is linear with noise linear in the commands, so the LQG around the nominal is
    exact and policy_cost is the true E[J] of the policy (feedforward not applied)."""
    problem, sol = noisy_point_mass
    assert sol.converged, sol.message
    policy = sol.policy
    gains = Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)
    exact = float(policy_cost(linearize(problem, policy.x_nominal, policy.u_nominal), gains))
    np.testing.assert_allclose(exact, float(sol.expected_cost), rtol=1e-8)
    summary = di.simulate(problem, policy, n_trials=4000, seed=1).summary()
    assert summary.n_trials == 4000 and summary.n_diverged == 0
    assert abs(summary.mean_cost - exact) < 4 * summary.standard_error, (summary.mean_cost, exact)
    # the noise matters: the deterministic cost lies many standard errors away
    assert abs(summary.mean_cost - float(sol.cost)) > 5 * summary.standard_error     # measured 9.3
    # the bootstrap interval of a well-behaved sample is the normal one (half widths within 10 %)
    lo, hi = summary.ci95
    assert lo < summary.mean_cost < hi
    np.testing.assert_allclose([summary.mean_cost - lo, hi - summary.mean_cost],
                               1.959964 * summary.standard_error, rtol=0.1)


def test_same_seed_same_trials_different_seed_different(noisy_point_mass):
    problem, sol = noisy_point_mass
    a = di.simulate(problem, sol.policy, 16, seed=3)
    b = di.simulate(problem, sol.policy, 16, seed=3)
    c = di.simulate(problem, sol.policy, 16, seed=4)
    np.testing.assert_array_equal(np.asarray(a.x), np.asarray(b.x))
    np.testing.assert_array_equal(np.asarray(a.cost), np.asarray(b.cost))
    assert not np.any(np.asarray(a.cost) == np.asarray(c.cost))
    assert len(np.unique(np.asarray(a.cost))) == 16                  # the trials are independent draws


def test_sample_stats_counts_diverged_trials_and_keeps_a_robust_median():
    values = np.concatenate([np.arange(1.0, 100.0), [np.nan, np.inf]])
    s = sample_stats(values)
    assert s.n == 101 and s.n_diverged == 2
    assert s.mean == 50.0                                         # over the 99 trials that did not diverge
    assert s.ci95[0] < 50.0 < s.ci95[1]
    assert s.median == 51.0                                       # NaN ranks last, like inf
    assert s.median_ci95[0] <= s.median <= s.median_ci95[1]
    finite = sample_stats(np.arange(10.0))
    assert finite.n_diverged == 0 and finite.mean == 4.5
    np.testing.assert_allclose(finite.standard_error, np.std(np.arange(10.0), ddof=1) / math.sqrt(10))
    assert finite.to_dict()["ci95"][0] < 4.5
    everything = sample_stats([np.inf, np.nan])
    assert everything.n_diverged == 2 and everything.to_dict()["mean"] is None     # strict JSON: no inf, NaN


@pytest.fixture(scope="module")
def arm_study():
    return study.compare_delays("arm2", [0.05, 0.1], n_trials=300, seed=0, noise="benchmark")


def test_delay_aware_beats_delay_ignorant_on_the_noisy_delayed_arm(arm_study):
    """Measured (300 trials, seed 0): aware median cost 19.6 and 76.5 at 50 and 100 ms; ignorant
    3.6e4 and 7.8e4 (its closed loop is nearly unstable, some trials diverge); the aware cost is
    lower in every paired trial. Stated margins, far below the measured ~1e-3 ratio:
    the aware median's 95 % upper bound < 0.02 x the ignorant median's 95 % lower bound, the aware
    mean's upper bound < 0.02 x the ignorant mean, and P(aware < ignorant) > 0.9 with 95 % confidence."""
    assert [(r.delay, r.controller) for r in arm_study] == [(0.05, "aware"), (0.05, "ignorant"),
                                                            (0.1, "aware"), (0.1, "ignorant")]
    for aware, ignorant in (arm_study[0:2], arm_study[2:4]):
        assert aware.converged, aware.message
        assert aware.cost.n_diverged == 0
        assert aware.cost.median_ci95[1] < 0.02 * ignorant.cost.median_ci95[0]
        assert aware.cost.ci95[1] < 0.02 * ignorant.cost.mean
        ca = np.asarray(aware.runs.cost)
        ci = np.where(np.isfinite(np.asarray(ignorant.runs.cost)), np.asarray(ignorant.runs.cost), np.inf)
        n, wins = ca.size, np.count_nonzero(ca < ci)
        p, z = wins / n, 1.959964
        wilson_low = (p + z * z / (2 * n) - z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))) / (1 + z * z / n)
        assert wilson_low > 0.9
        # the hand ends closer to the target too
        assert aware.endpoint_error.median_ci95[1] < ignorant.endpoint_error.median_ci95[0]


def test_study_results_are_the_direct_api_results(arm_study):
    aware, ignorant = arm_study[0:2]
    problem = arm2(delay=0.05, noise="benchmark")
    design, options = design_problem(problem, "aware")              # the options the study designs with
    sol = di.solve(design, options=options)
    runs = di.simulate(problem, sol.policy, 300, seed=0)
    np.testing.assert_array_equal(np.asarray(aware.runs.cost), np.asarray(runs.cost))
    assert aware.cost == sample_stats(runs.cost)
    assert aware.predicted_cost == float(sol.expected_cost) and aware.iterations == int(sol.iterations)
    # the ignorant controller: designed without delay, so its policy has no delay feedback
    assert ignorant.solution.policy.delay_feedback.shape[1] == 0 and ignorant.delay_steps == 5
    hand = np.asarray(di.models.hand_position(jnp.asarray(np.asarray(runs.x[:, -1, :2]))))
    target = np.asarray(di.models.hand_position(jnp.asarray(problem.cost.x_target[:2])))
    np.testing.assert_allclose(np.median(np.linalg.norm(hand - target, axis=1)), aware.endpoint_error.median)
    record = aware.to_dict()
    assert record["cost"]["median"] == aware.cost.median and "runs" not in record and "solution" not in record


# ------------------------------------------------------------------------------------------------
# validation
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kwargs, error, message", [
    (dict(n_trials=0), ValueError, r"n_trials must be a positive integer; got 0"),
    (dict(n_trials=-5), ValueError, r"n_trials must be a positive integer; got -5"),
    (dict(n_trials=2.5), ValueError, r"n_trials must be a positive integer; got 2.5"),
    (dict(substeps=0), ValueError, r"substeps must be a positive integer; got 0"),
    (dict(seed=1.5), TypeError, r"seed must be a non-negative integer; got 1.5"),
    (dict(seed=-1), ValueError, r"seed must be a non-negative integer below 2\*\*63; got -1"),
])
def test_argument_validation(noisy_point_mass, kwargs, error, message):
    problem, sol = noisy_point_mass
    args = dict(n_trials=4, seed=0)
    args.update(kwargs)
    with pytest.raises(error, match=message):
        di.simulate(problem, sol.policy, **args)


def test_policy_must_match_the_problem(noisy_point_mass):
    problem, sol = noisy_point_mass
    with pytest.raises(ValueError, match=r"policy.x_nominal must have shape \(41, 4\); got shape \(61, 4\)"):
        di.simulate(problem.replace(horizon=40), sol.policy, 2)
    bad = sol.policy._replace(state_feedback=sol.policy.state_feedback[:, :, :3])
    with pytest.raises(ValueError, match=r"policy.state_feedback must have shape \(60, 2, 4\); got shape \(60, 2, 3\)"):
        di.simulate(problem, bad, 2)
    bad = sol.policy._replace(delay_feedback=sol.policy.delay_feedback[..., 0])
    with pytest.raises(ValueError, match=r"policy.delay_feedback must have shape \(60, \*, 2, 2\)"):
        di.simulate(problem, bad, 2)
    with pytest.raises(TypeError, match=r"policy must be a delayed_ilqr.Policy"):
        di.simulate(problem, sol, 2)
    with pytest.raises(TypeError, match=r"problem must be a delayed_ilqr.Problem; got dict"):
        di.simulate({}, sol.policy, 2)


def _probe(*args, timeout=300):
    """tests/memory_probe.py in a child process: its JSON line."""
    import json
    import os
    import pathlib
    import subprocess
    import sys
    here = pathlib.Path(__file__).parent
    # the child imports the library this process imported
    source = str(pathlib.Path(di.__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [source, os.environ.get("PYTHONPATH")])))
    out = subprocess.run([sys.executable, str(here / "memory_probe.py"), *map(str, args)], capture_output=True,
                         text=True, timeout=timeout, env=env, cwd=here)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("substeps", [1, 4])
def test_memory_estimate_bounds_the_measured_peak(substeps):
    """memory_estimate is an upper bound of what simulate holds: the growth of the process's peak
    resident memory over 50000 trials of the arm (measured 9161 bytes per trial at one sub-step,
    13561 at four, against an estimate of 3240 and 5640 before), and not more than three times it."""
    N = 50_000
    measured = _probe("peak", N, substeps)
    assert measured["peak"] <= measured["estimate"] <= 3 * measured["peak"], measured


@pytest.mark.parametrize("model, substeps", [("arm2", 1), ("arm2", 4), ("sensed point mass", 1),
                                             ("sensed point mass", 3)])
def test_memory_estimate_bounds_xlas_own_plan(model, substeps):
    """... and XLA's plan of the compiled simulator (temporaries, outputs and arguments), with and
    without sensors, for any number of sub-steps."""
    from delayed_ilqr.simulate import _simulate, _simulate_observed, memory_estimate
    problem = arm2(delay=0.05, noise=True) if model == "arm2" else point_mass(noise=True, sensory_delay=0.02)
    policy = di.solve(problem).policy
    N, key = 1000, jax.random.PRNGKey(0)
    lowered = _simulate.lower(problem, policy, N, substeps, key) if problem.observation is None else \
        _simulate_observed.lower(problem, policy, N, substeps, key, jnp.zeros((problem.horizon, problem.n_states)))
    plan = lowered.compile().memory_analysis()
    planned = plan.temp_size_in_bytes + plan.output_size_in_bytes + plan.argument_size_in_bytes
    assert planned <= memory_estimate(problem, N, substeps) <= 3 * planned


def test_an_address_space_limit_is_respected_and_an_allocation_failure_is_an_error():
    """Under ``ulimit -v`` (RLIMIT_AS) the check counts the address space left, not the physical
    memory: 1500000 trials of the arm (about 14 GB at their peak) under a 6 GB limit are refused up
    front (before, accepted, and XLA's allocation failed in the run with an internal error); run
    anyway, the failed allocation ends in a MemoryError that says what to do, not an XLA internal
    error or a hang."""
    result = _probe("limit", 6 * 10 ** 9, 1_500_000)
    assert result["checked"].startswith("ValueError: n_trials=1500000 trials would hold about"), result
    assert "address-space limit (ulimit -v)" in result["checked"], result
    assert result["unchecked"].startswith("MemoryError: simulate ran out of memory with n_trials=1500000"), result
    assert "fewer trials per call" in result["unchecked"], result
