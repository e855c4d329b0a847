"""Delays that are not a whole number of steps, tau = (l + phi) dt (docs/derivation.md §20): two taps
per channel, u_{k-l} and u_{k-l-1}, under the zero-order hold.

References, independent of the two-tap code: a fine quadrature of the held commands over one step
(the meaning of the step), the state-augmentation pass over the same taps
(``lqg.augmented_backward_pass``, whose matrices are checked against a construction written out
tap by tap), the augmented solver (``Options(method="augmented")``), the integer-delay solver at
phi = 0 and at phi -> 1 (l + 1), and central finite differences for the derivatives in phi.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import lqg as _lqg
from delayed_ilqr import Problem, QuadraticCost
from delayed_ilqr._fractional import diffusion, drift
from delayed_ilqr.lqg import DelayedLQG
from delayed_ilqr.lqg.augmented import augment

from comparisons import WorstDifference, rel_err, solution_errors   # tests/comparisons.py
from test_lqg import random_arrays                  # tests/test_lqg.py

RTOL = 1e-9
_WORST = WorstDifference("test_fractional: worst two-tap relative difference from its reference")
_report_worst = _WORST.fixture()


# ---------------------------------------------------------------------------------------------
# The meaning of one step
# ---------------------------------------------------------------------------------------------

def _coupled(x, u, ud):
    """A drift that couples the channels' delayed commands nonlinearly (so the pieces matter)."""
    return jnp.array([jnp.sin(ud[0]) * ud[1] + x[0], ud[0] ** 2 - jnp.cos(ud[1] + u[0]), ud[1] * ud[2]])


def _coupled_noise(x, u, ud):
    return jnp.stack([ud * (1 + x[0]), jnp.tanh(ud) + u[1]], axis=1)[:3, :]


def test_the_step_is_the_held_commands_integral():
    """dt f_bar and dt F F' of the step against the midpoint quadrature of the commands held over
    the step on 120 sub-intervals (exact: every fraction is a multiple of 1/120), channel j
    switching from u_{k-l_j-1} to u_{k-l_j} at phi_j dt; equal fractions and phi = 0 included."""
    rng = np.random.default_rng(0)
    x, u = rng.standard_normal(3), rng.standard_normal(3)
    newer, older = rng.standard_normal(3), rng.standard_normal(3)
    for phi in ([0.25, 0.75, 0.5], [0.5, 0.5, 0.0], [0.0, 0.0, 0.0], [0.9, 0.1, 0.9]):
        phi = np.asarray(phi)
        grid = (np.arange(120) + 0.5) / 120
        held = [np.where(s < phi, older, newer) for s in grid]
        f_ref = np.mean([_coupled(x, u, ud) for ud in held], axis=0)
        cov_ref = np.mean([_coupled_noise(x, u, ud) @ _coupled_noise(x, u, ud).T for ud in held], axis=0)
        ud2 = jnp.concatenate([newer, older])
        F = diffusion(_coupled_noise, x, u, ud2, jnp.asarray(phi))
        assert rel_err(drift(_coupled, x, u, ud2, jnp.asarray(phi)), f_ref) <= 1e-13, phi
        assert rel_err(F @ F.T, cov_ref) <= 1e-13, phi
        assert F.shape == (3, 2 * 4)                                      # (d + 1) p columns


# ---------------------------------------------------------------------------------------------
# The LQG with two taps per channel: structured pass against augmentation
# ---------------------------------------------------------------------------------------------

# (K, n, d, p, L): the taps l_j, l_j + 1 are drawn in 0..L; the second shape has taps >= K
SHAPES = [(6, 2, 2, 2, 4), (4, 3, 1, 1, 5)]


def _two_taps(seed, K, n, d, p, whole):
    """Random LQG data whose B1, C1 have 2 d columns: tap l_j (1 - phi_j) and tap l_j + 1 (phi_j)."""
    arrays = random_arrays(seed, K, n, d, p, 0)
    rng = np.random.default_rng(seed + 1)
    phi = rng.uniform(0, 1, d)
    weight = np.concatenate([1 - phi, phi])
    arrays["B1"] = rng.standard_normal((K, n, 2 * d)) / np.sqrt(n) * weight
    arrays["C1"] = 0.3 * rng.standard_normal((K, p, n, 2 * d)) * np.sqrt(weight)
    arrays["delay_steps"] = list(whole) + [l + 1 for l in whole]
    return arrays


@settings(max_examples=8, deadline=None)
@given(shape=st.sampled_from(SHAPES), data=st.data(), seed=st.integers(0, 2 ** 31 - 1),
       reg=st.sampled_from([0.0, 0.3]))
def test_two_tap_pass_equals_augmentation(shape, data, seed, reg):
    """Random time-varying data, whole parts l_j in 0..L-1 per channel (0, 1, equal, taps >= K):
    every gain and value block of the structured pass equals the augmented pass's to round-off,
    J(0) is the exact cost of its policy, and the entries of commands older than l_j + 1 are zero."""
    K, n, d, p, L = shape
    whole = data.draw(st.lists(st.integers(0, L - 1), min_size=d, max_size=d), label="whole")
    whole[0] = L - 1                                     # the frame is max_j l_j + 1
    lqg = DelayedLQG(**_two_taps(seed, K, n, d, p, whole))
    gains, value = _lqg.backward_pass(lqg, reg)
    ref_gains, ref_value = _lqg.augmented_backward_pass(lqg, reg)
    assert bool(value.positive_definite) and bool(ref_value.positive_definite)
    errs = {f: rel_err(getattr(gains, f), getattr(ref_gains, f)) for f in gains._fields}
    errs.update({f: rel_err(getattr(value, f), getattr(ref_value, f)) for f in ("s_tilde", "s", "S", "r", "Rt", "R")})
    errs["policy_cost"] = rel_err(_lqg.policy_cost(lqg, gains), value.expected_cost)
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, K={K} n={n} d={d} p={p} whole={whole} reg={reg}")
    assert all(e <= RTOL for e in errs.values()), (whole, errs)
    M = np.asarray(gains.delay_feedback)
    for j, l_j in enumerate(whole):
        assert not np.any(M[:, :L - l_j - 1, :, j]), (j, l_j)


def test_augmentation_reads_each_tap_at_its_delay():
    """``lqg.augment`` with taps against the augmented matrices written out tap by tap: column i of
    B1, C1 on the buffer entry L - l_i, component i mod d, two taps of a channel added."""
    K, n, d, p = 3, 2, 2, 1
    whole = [0, 2]
    arrays = _two_taps(5, K, n, d, p, whole)
    aug = augment(DelayedLQG(**arrays))
    L, taps = 3, arrays["delay_steps"]
    Az = np.zeros((K, n + L * d, n + L * d))
    Az[:, :n, :n] = arrays["A"]
    Cz = np.zeros((K, p, n + L * d, n + L * d))
    B0 = np.array(arrays["B0"])
    for i, l_i in enumerate(taps):
        if l_i == 0:           # the current command: folded into B0
            B0[:, :, i % d] += arrays["B1"][:, :, i]
            continue
        col = n + (L - l_i) * d + i % d
        Az[:, :n, col] += arrays["B1"][:, :, i]
        Cz[:, :, :n, col] += arrays["C1"][:, :, :, i]
    assert np.array_equal(np.asarray(aug["Az"])[:, :n], Az[:, :n])
    assert np.allclose(np.asarray(aug["Cz"]), Cz, rtol=0, atol=1e-15)
    assert np.allclose(np.asarray(aug["Bz"])[:, :n], B0, rtol=0, atol=1e-15)


# ---------------------------------------------------------------------------------------------
# The nonlinear problem: solve, phi = 0, phi -> 1, simulate, saving, derivatives, refusals
# ---------------------------------------------------------------------------------------------

FRAME = 4       # every fractional arm problem below runs in this frame: one compiled solver


@pytest.fixture(scope="module")
def arm_solves():
    """The noisy arm (noise on the delayed command) with 34 ms (3.4 steps) per channel, and per
    channel [1.5, 2.25] steps (the other solves: phi = 0 and l + 1 - 1e-9 against l, l + 1)."""
    from delayed_ilqr import Options, solve
    from delayed_ilqr.models import arm2
    base = arm2(delay=0.03, noise=True, horizon=30)
    fractional = base.replace(delay_steps=3.4)
    mixed = base.replace(delay_steps=[1.5, 2.25], delay_frame=FRAME)
    out = dict(base=base, fractional=fractional, mixed=mixed, sol=solve(fractional), mixed_sol=solve(mixed),
               augmented=solve(mixed, options=Options(method="augmented")))
    out["phi0_problem"] = base.replace(delay_steps=np.array(3.0), delay_frame=FRAME)
    out["phi0"] = solve(out["phi0_problem"])
    for eps in (1e-6, 1e-9):
        out[eps] = solve(base.replace(delay_steps=np.array(3.0 - eps), delay_frame=FRAME))
    out["int3"] = solve(base.replace(delay_steps=[3, 3], delay_frame=FRAME))
    return out


def test_fractional_problem_runs_as_two_taps(arm_solves):
    problem = arm_solves["fractional"]
    assert problem.is_fractional and problem.delay_frame == 4 and problem.n_noise == 3 * 2
    np.testing.assert_array_equal(problem.delay_steps, [3, 3, 4, 4])
    np.testing.assert_allclose(problem.delay_in_steps, [3.4, 3.4], rtol=1e-15)
    np.testing.assert_allclose(problem.delay, [0.034, 0.034], rtol=1e-14)
    assert arm_solves["sol"].status.converged
    assert "delay_steps=[3.4, 3.4]" in repr(problem)


def test_fractional_solve_equals_the_augmented_solve(arm_solves):
    """Per-channel fractions [1.5, 2.25]: the structured and the augmented solver reach the same
    nominal, expected cost and gains to round-off."""
    sol, ref = arm_solves["mixed_sol"], arm_solves["augmented"]
    assert sol.status == ref.status and sol.status.converged and int(sol.iterations) == int(ref.iterations)
    errs = solution_errors(sol, ref)
    _WORST.record(max(errs.values()), f"arm [1.5, 2.25] structured vs augmented: {max(errs, key=errs.get)}")
    assert all(e <= RTOL for e in errs.values()), errs


def test_phi_zero_and_one_are_the_whole_delays(arm_solves):
    """phi = 0 (a float delay of 3 steps, on the two-tap path) is the integer delay 3 to round-off;
    3 - eps steps (l = 2, phi = 1 - eps) tends to it linearly in eps, eps = 1e-6 and 1e-9: the
    delay is continuous across a whole step. Against the per-channel integer solve [3, 3] in the
    same frame. (The gains move fast with phi here: the arm's effort weight is 1e-4, so H is
    small and a tap of weight eps shifts G by eps B0'S B1.)"""
    ref = arm_solves["int3"]
    sol = arm_solves["phi0"]
    assert sol.status.converged
    M = sol.policy.delay_feedback           # it spans the taps 3 and 4: the gains on u_{k-4} are zero
    assert M.shape[1] == 4 and not np.any(np.asarray(M[:, 0]))
    errs = solution_errors(sol._replace(policy=sol.policy._replace(delay_feedback=M[:, 1:])), ref)
    _WORST.record(max(errs.values()), "arm phi = 0 vs the integer delay 3")
    assert all(e <= RTOL for e in errs.values()), {k: float(v) for k, v in errs.items()}
    coarse, fine = (solution_errors(arm_solves[eps], ref) for eps in (1e-6, 1e-9))
    assert all(arm_solves[eps].status.converged for eps in (1e-6, 1e-9))
    for k in coarse:            # linear in eps, down to the solves' round-off
        assert fine[k] <= 2e-3 * coarse[k] + 1e-11, (k, float(coarse[k]), float(fine[k]))
    assert coarse["u"] > 1e-8                   # the check can fail: 1e-6 of a step moves the solve
    # and the check can fail: 3.4 steps is another controller
    assert rel_err(arm_solves["sol"].u, ref.u) > 1e-3


def test_prediction_of_a_fractional_solve(arm_solves):
    """``predict`` keeps a fractional problem's frame (the solve's policy, trimmed, is padded back):
    at phi = 0 its state covariance is the unframed integer solve's to round-off."""
    from delayed_ilqr import solve
    from delayed_ilqr.prediction import predict
    base = arm_solves["base"]
    ref = predict(base, solve(base))
    got = predict(arm_solves["phi0_problem"], arm_solves["phi0"])
    err = rel_err(got.cov, ref.cov)
    _WORST.record(err, "predicted state covariance, phi = 0 against the integer delay")
    assert err <= RTOL and float(np.max(np.asarray(ref.cov[-1]))) > 0


def test_simulate_applies_the_held_commands(arm_solves):
    """Without noise the closed loop of the solved policy retraces the solver's nominal; substeps
    are refused (they would split the step's hold)."""
    from delayed_ilqr import simulate
    problem, sol = arm_solves["mixed"], arm_solves["mixed_sol"]
    runs = simulate(problem.replace(noise=None), sol.policy, n_trials=2, seed=0)
    assert rel_err(runs.x[0], sol.x) <= 1e-12 and rel_err(runs.u[0], sol.u) <= 1e-12
    wrong = simulate(problem.replace(noise=None, delay_steps=[2.25, 1.5]), sol.policy, n_trials=2, seed=0)
    assert rel_err(wrong.x[0], sol.x) > 1e-3
    with pytest.raises(ValueError, match="substeps must be 1 for a problem whose delay is not a whole number"):
        simulate(problem, sol.policy, n_trials=2, substeps=2)


def test_fractional_policy_saves_and_loads(arm_solves, tmp_path):
    from delayed_ilqr.saving import load, load_metadata, save
    problem, sol = arm_solves["mixed"], arm_solves["mixed_sol"]
    save(tmp_path / "policy", sol.policy, problem=problem)
    loaded = load(tmp_path / "policy", problem=problem)
    np.testing.assert_array_equal(np.asarray(loaded.delay_feedback), np.asarray(sol.policy.delay_feedback))
    header = load_metadata(tmp_path / "policy")
    assert header["problem"]["delay_steps"] == [1.5, 2.25]
    np.testing.assert_allclose(header["problem"]["delay"], [0.015, 0.0225])


def _richardson(f, x, e, h):
    central = lambda s: (f(x + s * e) - f(x - s * e)) / (2 * s)
    return (4 * central(h / 2) - central(h)) / 3


def test_the_linearised_cost_is_differentiable_in_each_fraction():
    """d J(0) / d tau_j of the delayed LQG linearised at a fixed nominal (the two taps' Jacobians
    and weights, the noise's pieces, the structured pass), per channel, against Richardson
    central differences: the derivative the solver's implicit derivative is built on."""
    from delayed_ilqr.ilqg.linearize import linearize, rollout
    from delayed_ilqr.models import arm2
    base = arm2(delay=0.0, noise=True, horizon=12)
    us = 0.1 * jnp.ones((12, 2))

    def cost(tau):
        problem = base.replace(delay_steps=tau, delay_frame=4)
        return _lqg.backward_pass(linearize(problem, rollout(problem, us), us), 0.0)[1].expected_cost

    cost_jit, grad = jax.jit(cost), jax.jit(jax.jacfwd(cost))      # forward mode: the cheaper compilation
    tau = jnp.array([1.3, 2.6])
    g = grad(tau)
    for j in range(2):
        e = jnp.zeros(2).at[j].set(1.0)
        fd = _richardson(cost_jit, tau, e, 1e-3)
        err = rel_err(g[j], fd)
        _WORST.record(err, f"d J(0) / d tau_{j} of the linearised arm against finite differences")
        assert abs(float(fd)) > 1e-6 and err < 1e-7, (j, float(g[j]), float(fd))


@pytest.mark.full
def test_optimal_cost_derivative_in_each_delay_matches_finite_differences():
    """d (optimal expected cost) / d tau through the implicit derivative of the solve, one delay
    and per channel, against Richardson central differences of tight re-solves (two compilations
    of the derivative, minutes: under ``make bench``)."""
    from delayed_ilqr import solve
    from delayed_ilqr.models import point_mass
    from test_gradients import TIGHT
    base = point_mass(delay=0.0, noise=True, horizon=20)

    def cost(tau):
        return solve(base.replace(delay_steps=tau, delay_frame=5), None, TIGHT).expected_cost

    cost_jit, grad = jax.jit(cost), jax.jit(jax.grad(cost))
    for tau in (jnp.asarray(2.3), jnp.array([1.6, 3.2])):
        g = jnp.atleast_1d(grad(tau))
        for j in range(g.shape[0]):
            e = jnp.zeros_like(tau).at[j].set(1.0) if tau.ndim else jnp.asarray(1.0)
            fd = _richardson(cost_jit, tau, e, 1e-3)
            err = rel_err(g[j], fd)
            _WORST.record(err, f"d cost / d tau, tau={np.asarray(tau).tolist()}, channel {j}")
            assert abs(float(fd)) > 1e-3 and err < 1e-8, (float(g[j]), float(fd))


def _tiny_problem(**kw):
    args = dict(dynamics=lambda x, u, ud: ud, x0=jnp.zeros(1), dt=0.1, horizon=5, delay_steps=1.5,
                cost=QuadraticCost(jnp.eye(1), jnp.eye(1), jnp.eye(1), jnp.zeros(1)))
    args.update(kw)
    return Problem(**args)


@pytest.mark.parametrize("kw, match", [
    (dict(delay_steps=-0.5), r"delay_steps must be a finite, non-negative number of steps; got -0.5"),
    (dict(delay_steps=float("nan")), r"delay_steps must be a finite, non-negative number of steps; got nan"),
    (dict(delay_steps=4.5), r"below the horizon less one step when it is not whole.*got delay_steps=4.5, horizon=5"),
    (dict(delay_steps=1.5, delay_frame=1), r"delay_frame must be at least the longest channel delay.*got delay_frame=1"),
])
def test_bad_fractional_delays_are_refused(kw, match):
    with pytest.raises(ValueError, match=match):
        _tiny_problem(**kw)


def test_what_needs_whole_delays_refuses_fractional_ones():
    """Delayed sensors (the filter is exact for whole steps), a sensory delay in seconds that is not
    whole, and the parts that need a static delay say so."""
    from delayed_ilqr import Observation
    from delayed_ilqr.models import arm2
    with pytest.raises(ValueError, match="not a whole number of steps is not available with an observation"):
        _tiny_problem(observation=Observation(np.eye(1), np.eye(1), delay_steps=1))
    with pytest.raises(ValueError, match="sensory_delay must be a whole number of steps.*a fractional sensory delay"):
        arm2(sensory_delay=0.025)
    with pytest.raises(ValueError, match="needs a whole number of steps as the input delay"):
        _tiny_problem().without_frame("the test")
