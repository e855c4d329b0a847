"""A jittered input delay (``DelayJitter``, docs/derivation.md §21): the delay of the acting command
drawn at every step from a known distribution.

References, independent of the structured pass (``lqg.jittered_backward_pass``): the Riccati
recursion on the augmented state with the expectation over the delay (``jittered_augmented_pass``,
built from the library's augmentation at each delay); the exact second moments of the closed
loop (``jittered_policy_cost``, no recursion on the value); the library's delayed pass for a
point mass (no jitter); and Monte Carlo with the delay drawn per step (``simulate_jittered_lqg``).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import DelayJitter
from delayed_ilqr import lqg as _lqg
from delayed_ilqr.lqg import DelayedLQG

from comparisons import WorstDifference, rel_err   # tests/comparisons.py
from test_lqg import random_arrays                  # tests/test_lqg.py

RTOL = 1e-9
_WORST = WorstDifference("test_jitter: worst jittered structured-vs-reference relative difference")
_report_worst = _WORST.fixture()

# (K, n, d, p, L): each shape compiles each pass once (the distribution over 0..L is data). The
# second has L >= K: commands that may act after the horizon.
SHAPES = [(6, 2, 2, 2, 3), (3, 3, 1, 1, 4)]
VALUE_FIELDS = ("s_tilde", "s", "S", "r", "Rt", "R")


def _distribution(data, L: int) -> DelayJitter:
    """A random distribution over a random subset of 0..L that contains L (a point mass among them)."""
    steps = sorted(set(data.draw(st.lists(st.integers(0, L - 1), max_size=L), label="steps")) | {L})
    weights = np.asarray(data.draw(st.lists(st.floats(0.05, 1.0), min_size=len(steps), max_size=len(steps)),
                                   label="weights"))
    return DelayJitter(steps, weights / weights.sum())


def _errors(gains, value, ref_gains, ref_value):
    errs = {f: rel_err(getattr(gains, f), getattr(ref_gains, f)) for f in gains._fields}
    errs.update({f: rel_err(getattr(value, f), getattr(ref_value, f)) for f in VALUE_FIELDS})
    return errs


@settings(max_examples=8, deadline=None)
@given(shape=st.sampled_from(SHAPES), data=st.data(), seed=st.integers(0, 2 ** 31 - 1),
       reg=st.sampled_from([0.0, 0.3]), offsets=st.booleans())
def test_jittered_pass_equals_augmentation(shape, data, seed, reg, offsets):
    """Random time-varying data, random delay distributions (with 0, 1, L >= K, point masses) and
    offsets: every gain and value block of the structured pass equals the augmented reference's
    to round-off, J(0) is the exact expected cost of the returned law (second moments), and no
    higher than that of the law designed for the fixed delay L under the same jitter."""
    K, n, d, p, L = shape
    jitter = _distribution(data, L)
    lqg = DelayedLQG(**random_arrays(seed, K, n, d, p, L))
    delta = np.random.default_rng(seed).standard_normal((K, L + 1, d)) if offsets else None
    gains, value = _lqg.jittered_backward_pass(lqg, jitter, reg, delta)
    ref_gains, ref_value = _lqg.jittered_augmented_pass(lqg, jitter, reg, delta)
    assert bool(value.positive_definite) and bool(ref_value.positive_definite)
    errs = _errors(gains, value, ref_gains, ref_value)
    errs["J0 vs moments"] = rel_err(value.expected_cost, _lqg.jittered_policy_cost(lqg, jitter, gains, delta))
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, {jitter}, {shape}, reg={reg}")
    assert errs[worst] < RTOL, (worst, errs[worst], jitter)
    if reg == 0.0:      # optimal: no better than the law designed for the fixed delay L, under the jitter
        fixed_law = _lqg.backward_pass(lqg)[0]
        assert float(value.expected_cost) <= float(_lqg.jittered_policy_cost(lqg, jitter, fixed_law, delta)) \
            * (1 + RTOL)


@pytest.mark.parametrize("shape", SHAPES)
def test_point_mass_equals_the_delayed_pass(shape):
    """No jitter (a point mass at l = L; the second shape has l >= K): the jittered pass is the
    library's delayed pass at delay l (Theorem 1), gain by gain and block by block, and its exact
    cost the second-moment cost of the delayed system (``policy_cost``). (The shapes of the
    property test: one compilation of the jittered pass serves both.)"""
    K, n, d, p, l = shape
    lqg = DelayedLQG(**random_arrays(11 + l, K, n, d, p, l))
    gains, value = _lqg.jittered_backward_pass(lqg, DelayJitter.fixed(l))
    ref_gains, ref_value = _lqg.backward_pass(lqg)
    errs = _errors(gains, value, ref_gains, ref_value)
    errs["cost"] = rel_err(_lqg.jittered_policy_cost(lqg, DelayJitter.fixed(l), gains), _lqg.policy_cost(lqg, gains))
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, point mass at {l}")
    assert errs[worst] < RTOL, (worst, errs[worst])


@pytest.mark.parametrize("offsets", [False, True])
def test_monte_carlo_agrees_with_the_exact_cost(offsets):
    """The exact expected cost (J(0) of the pass, = the second moments) lies in the Monte Carlo's
    99.9 % interval: 4000 trials, the delay drawn per step and trial, signal-dependent noise; the
    same seed gives the same trials."""
    K, n, d, p, L = SHAPES[0]
    jitter = DelayJitter([1, 2, 3], [0.3, 0.3, 0.4])
    lqg = DelayedLQG(**random_arrays(5, K, n, d, p, L))
    delta = np.random.default_rng(5).standard_normal((K, L + 1, d)) if offsets else None
    gains, value = _lqg.jittered_backward_pass(lqg, jitter, 0.0, delta)
    cost = np.asarray(_lqg.simulate_jittered_lqg(lqg, jitter, gains, 4000, seed=3, offsets=delta).cost)
    mean, se = cost.mean(), cost.std(ddof=1) / np.sqrt(cost.size)
    assert abs(mean - float(value.expected_cost)) < 3.3 * se, (mean, se, float(value.expected_cost))
    again = _lqg.simulate_jittered_lqg(lqg, jitter, gains, 4000, seed=3, offsets=delta).cost      # reproducible
    np.testing.assert_array_equal(np.asarray(again), cost)


def test_point_mass_monte_carlo_is_the_delayed_one():
    """Without jitter the Monte Carlo is the delayed system's (``simulate_lqg``, same noise from the
    same seed): trial by trial, to round-off."""
    K, n, d, p, L = SHAPES[0]
    lqg = DelayedLQG(**random_arrays(6, K, n, d, p, L))
    gains, _ = _lqg.backward_pass(lqg)
    runs = _lqg.simulate_jittered_lqg(lqg, DelayJitter.fixed(L), gains, 50, seed=4)
    ref = _lqg.simulate_lqg(lqg, gains, 50, seed=4)
    assert rel_err(runs.dx, ref.dx) < RTOL and rel_err(runs.cost, ref.cost) < RTOL


def test_clamped_jittered_pass_equals_its_augmented_version():
    """With limits (the box QP's gain rule, the nonlinear solver's with limits) the jittered pass
    agrees with its augmented version, and its J(0) is the exact cost of its law."""
    import jax.numpy as jnp
    from delayed_ilqr.lqg.gains import boxed_gains
    from delayed_ilqr.lqg.jitter import jittered_augmented_scan, jittered_scan
    K, n, d, p, L = SHAPES[0]
    jitter = DelayJitter([0, 2, 3], [0.3, 0.3, 0.4])
    lqg = DelayedLQG(**random_arrays(8, K, n, d, p, L))
    delta = jnp.asarray(np.random.default_rng(8).standard_normal((K, L + 1, d)))
    probs = jnp.asarray(jitter.by_delay())
    half = 0.5 * float(jnp.max(jnp.abs(_lqg.jittered_backward_pass(lqg, jitter, 0.0, delta)[0].feedforward)))
    bounds = (jnp.full((K, d), -half), jnp.full((K, d), half))
    gains, value = jittered_scan(lqg, probs, delta, 0.0, boxed_gains, bounds)
    ref_gains, ref_value = jittered_augmented_scan(lqg, probs, delta, 0.0, boxed_gains, bounds)
    assert bool(value.positive_definite) and np.any(np.abs(np.asarray(gains.feedforward)) >= half * (1 - 1e-12))
    errs = _errors(gains, value, ref_gains, ref_value)
    errs["J0 vs moments"] = rel_err(value.expected_cost, _lqg.jittered_policy_cost(lqg, jitter, gains, delta))
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"clamped, {worst}")
    assert errs[worst] < RTOL, (worst, errs[worst])


def test_the_delays_drawn_follow_the_distribution():
    """``DelayJitter.sample`` draws from p (a chi-square bound on 20000 draws), from the key alone."""
    import jax
    jitter = DelayJitter([0, 2, 3], [0.5, 0.2, 0.3])
    draws = np.asarray(jitter.sample(jax.random.PRNGKey(0), (20000,)))
    np.testing.assert_array_equal(draws, np.asarray(jitter.sample(jax.random.PRNGKey(0), (20000,))))
    counts = np.array([(draws == s).sum() for s in jitter.steps])
    expected = 20000 * np.asarray(jitter.probabilities)
    assert set(np.unique(draws)) <= set(jitter.steps)
    assert np.sum((counts - expected) ** 2 / expected) < 13.8      # chi-square, 2 dof, p = 0.001


@pytest.mark.parametrize("steps, probabilities, match", [
    ([1, 2], [0.5, 0.6], "must sum to 1"),
    ([1, 2], [1.2, -0.2], "non-negative"),
    ([1, 2], [0.5, np.nan], "finite"),
    ([1, -2], [0.5, 0.5], r"steps\[1\] must be a non-negative integer"),
    ([1, 2.5], [0.5, 0.5], r"steps\[1\] must be a non-negative integer"),
    ([2, 2], [0.5, 0.5], "must not repeat"),
    ([1, 2, 3], [0.5, 0.5], "one probability per delay"),
    ([], [], "at least one delay"),
])
def test_bad_distributions_are_refused(steps, probabilities, match):
    with pytest.raises(ValueError, match=match):
        DelayJitter(steps, probabilities)


def test_the_model_must_hold_the_commands_in_flight():
    """The LQG's delay_steps is the longest delay (the commands in flight), named in the error."""
    lqg = DelayedLQG(**random_arrays(0, 4, 2, 1, 1, 2))
    with pytest.raises(ValueError, match="longest delay L = 3"):
        _lqg.jittered_backward_pass(lqg, DelayJitter([1, 3], [0.5, 0.5]))
    with pytest.raises(TypeError, match="DelayJitter"):
        _lqg.jittered_backward_pass(lqg, [0.5, 0.5])
    with pytest.raises(ValueError, match="offsets"):
        _lqg.jittered_backward_pass(lqg, DelayJitter([1, 2], [0.5, 0.5]), offsets=np.zeros((4, 2, 1)))


# ---------------------------------------------------------------------------------------------
# The nonlinear layer: Problem(delay_jitter=...), solve and simulate
# ---------------------------------------------------------------------------------------------

JITTER = DelayJitter([1, 2, 3], [0.3, 0.3, 0.4])


@pytest.fixture(scope="module")
def point_mass_solves():
    """P1 (linear plant, quadratic cost, noise linear in the acting force: its LQG is exact) on a
    short horizon, solved for the jitter, for a point mass at 2 and for delay 2."""
    from delayed_ilqr import solve
    from delayed_ilqr.models import point_mass
    noisy = point_mass(noise=True, horizon=20)
    jittered = noisy.replace(delay_steps=JITTER.longest, delay_jitter=JITTER)
    point = noisy.replace(delay_steps=2, delay_jitter=DelayJitter.fixed(2))
    return dict(noisy=noisy, jittered=jittered, solve=solve(jittered), point=solve(point),
                delayed=solve(noisy.replace(delay_steps=2)))


def test_jittered_solve_predicts_its_monte_carlo(point_mass_solves):
    """On a plant whose linearisation is exact, the solve's expected cost (the jittered LQG's J(0),
    the nominal's offsets included) lies in the 99.9 % interval of ``simulate`` under the same
    jitter (the delay drawn per step and trial)."""
    from delayed_ilqr import simulate
    sol, problem = point_mass_solves["solve"], point_mass_solves["jittered"]
    assert sol.converged, sol.status
    cost = np.asarray(simulate(problem, sol.policy, 4000, seed=1).cost)
    mean, se = cost.mean(), cost.std(ddof=1) / np.sqrt(cost.size)
    assert abs(mean - float(sol.expected_cost)) < 3.3 * se, (mean, se, float(sol.expected_cost))


def test_point_mass_jitter_is_the_delayed_problem(point_mass_solves):
    """No jitter (a point mass at l = 2): the jittered solver reaches the delayed solver's optimum
    (nominal and gains; with noise linear in the command, so the two line searches' merits must
    be the same function of the nominal, derivation §12), and ``simulate`` under the point mass is the delayed plant's, trial by
    trial (same seed: same motor noise)."""
    from delayed_ilqr import simulate
    sol, ref = point_mass_solves["point"], point_mass_solves["delayed"]
    assert sol.converged and ref.converged
    for name in ("u", "x"):
        assert rel_err(getattr(sol, name), getattr(ref, name)) < 1e-6, name
    for name in ("state_feedback", "delay_feedback"):
        assert rel_err(getattr(sol.policy, name), getattr(ref.policy, name)) < 1e-6, name
    assert rel_err(sol.expected_cost, ref.expected_cost) < 1e-6
    noisy = point_mass_solves["noisy"].replace(delay_steps=2)
    runs = simulate(noisy.replace(delay_jitter=DelayJitter.fixed(2)), ref.policy, 20, seed=2)
    np.testing.assert_array_equal(np.asarray(runs.x), np.asarray(simulate(noisy, ref.policy, 20, seed=2).x))


def test_the_merit_is_the_expected_cost_under_zero_feedforward(point_mass_solves):
    """The line search's merit of a nominal (off the optimum), with S and Phi of its backward
    pass, equals the exact second-moment cost (``jittered_policy_cost``) of that pass's law with
    its feedforward set to zero, on the linearisation with the nominal's offsets."""
    import jax
    from delayed_ilqr import Options
    from delayed_ilqr.ilqg.jittered import _pass, jittered_linearize, jittered_merit, jittered_rollout
    problem = point_mass_solves["jittered"]
    us = point_mass_solves["solve"].u + 0.3 * np.random.default_rng(0).standard_normal((20, 2))

    @jax.jit
    def both(us):
        xs = jittered_rollout(problem, us)
        lqg, offsets = jittered_linearize(problem, xs, us)
        gains, value, Phi = _pass(problem, Options(), xs, us, 0.0)
        zero = gains._replace(feedforward=0 * gains.feedforward)
        from delayed_ilqr.lqg.jitter import jittered_moments_and_cost
        return (jittered_merit(problem, xs, us, value.S, Phi, xs)[1],
                jittered_moments_and_cost(lqg, problem.delay_jitter.by_delay(), offsets, zero)[2])

    merit, exact = both(us)
    assert rel_err(merit, exact) < 1e-10, (float(merit), float(exact))


def test_problem_refuses_a_jitter_it_cannot_take(point_mass_solves):
    """The delay_steps of a jittered problem is its longest delay; no frame; a DelayJitter; the
    support within the horizon (delay_steps < K); the receding-horizon controller refuses it."""
    noisy = point_mass_solves["noisy"]
    with pytest.raises(ValueError, match="longest delay"):
        noisy.replace(delay_steps=2, delay_jitter=JITTER)
    with pytest.raises(TypeError, match="DelayJitter"):
        noisy.replace(delay_steps=3, delay_jitter={1: 0.5, 3: 0.5})
    with pytest.raises(ValueError, match="below the horizon"):
        noisy.replace(delay_steps=25, delay_jitter=DelayJitter([1, 25], [0.5, 0.5]))
    with pytest.raises(ValueError, match="not available with delay_frame"):
        noisy.replace(delay_steps=3, delay_frame=4, delay_jitter=JITTER)
    from delayed_ilqr import mpc
    with pytest.raises(ValueError, match="fixed input delay"):        # the receding horizon refuses it
        mpc.MPC(noisy.replace(delay_steps=3, delay_jitter=JITTER))


def test_distributions_are_data_one_compilation_and_vmap(point_mass_solves):
    """The probabilities are a leaf of the problem (the support static): a second distribution on
    the same support reuses the compiled solver, and ``jax.vmap`` over a stack of the two gives
    each separate solve (nominal, gains, expected cost) to round-off."""
    import jax
    import jax.numpy as jnp
    from delayed_ilqr import solve
    from delayed_ilqr.ilqg.jittered import _solve_jittered
    first, jittered = point_mass_solves["solve"], point_mass_solves["jittered"]
    other = jittered.replace(delay_jitter=DelayJitter([1, 2, 3], [0.6, 0.0, 0.4]))
    compiled = _solve_jittered._cache_size()
    second = solve(other)
    assert _solve_jittered._cache_size() == compiled           # no new compilation
    assert second.converged and rel_err(second.expected_cost, first.expected_cost) > 1e-3   # another design
    both = jax.vmap(solve)(jax.tree_util.tree_map(lambda *a: jnp.stack(a), jittered, other))
    for i, ref in enumerate((first, second)):
        for name in ("x", "u", "expected_cost", "status"):
            assert rel_err(getattr(both, name)[i], getattr(ref, name)) < 1e-9, (i, name)
        for name in ("state_feedback", "delay_feedback"):
            assert rel_err(getattr(both.policy, name)[i], getattr(ref.policy, name)) < 1e-9, (i, name)


def test_a_saved_jittered_solution_loads_back_with_its_jitter(point_mass_solves, tmp_path):
    """The header records the plant's jitter: the file loads back bitwise with its DelayJitter,
    ``load(problem=)`` refuses a plant of another jitter (or none), and a header whose jitter is
    invalid or contradicts its delay is one FileFormatError."""
    import re
    from delayed_ilqr import load, load_metadata, saving
    from test_saving import _rewrite, assert_same_record
    sol, jittered, noisy = point_mass_solves["solve"], point_mass_solves["jittered"], point_mass_solves["noisy"]
    path = tmp_path / "jittered.npz"
    sol.save(path, jittered)
    assert_same_record(sol, load(path, problem=jittered))
    assert saving.load_delay_jitter(path) == JITTER
    assert load_metadata(path)["problem"]["delay_jitter"] == dict(steps=[1, 2, 3], probabilities=[0.3, 0.3, 0.4])
    for plant, said in ((noisy.replace(delay_steps=3), "None"),
                        (jittered.replace(delay_jitter=DelayJitter([1, 3], [0.5, 0.5])), r"\[1, 3\]")):
        with pytest.raises(ValueError, match=f"saved for a plant with delay_jitter=DelayJitter.* but the problem "
                                             f"has delay_jitter=.*{said}"):
            load(path, problem=plant)
    sol.save(tmp_path / "fixed.npz", noisy.replace(delay_steps=3))        # no jitter: recorded as None
    assert saving.load_delay_jitter(tmp_path / "fixed.npz") is None
    sol.save(tmp_path / "bare.npz")
    with pytest.raises(saving.FileFormatError, match="records no delay jitter"):
        saving.load_delay_jitter(tmp_path / "bare.npz")
    problem = load_metadata(path)["problem"]
    for i, (record, match) in enumerate([(dict(steps=[1, 2, 3], probabilities=[0.3, 0.3, 0.3]), "must sum to 1"),
                                         (dict(steps=[1, 2], probabilities=[0.5, 0.5]), "contradicts its problem"),
                                         ([1, 2, 3], "keys 'steps' and 'probabilities'")]):
        bad = tmp_path / f"bad{i}.npz"
        _rewrite(path, bad, dict(problem=dict(problem, delay_jitter=record)))
        with pytest.raises(saving.FileFormatError, match=f"^{re.escape(str(bad))}: .*problem.delay_jitter .*{match}"):
            load(bad)


@pytest.mark.full
def test_designing_for_the_jitter_beats_the_mean_delay_on_the_arm():
    """The study's key result (docs/results/jitter.md, benchmarks/jitter_study.py), small: on the
    arm with a delay of 40-60 ms, the design for the jitter costs less than the design for the
    mean delay on the same 300 jittered trials (the paired difference's 95 % interval above 0)."""
    from delayed_ilqr import simulate, solve
    from delayed_ilqr.models import arm2
    jitter = DelayJitter([4, 5, 6], [0.25, 0.5, 0.25])
    base = arm2(noise=True)
    plant = base.replace(delay_steps=jitter.longest, delay_jitter=jitter)
    aware, mean = solve(plant), solve(base.replace(delay_steps=5))
    d = np.asarray(simulate(plant, mean.policy, 300, seed=0).cost) - np.asarray(simulate(plant, aware.policy, 300,
                                                                                           seed=0).cost)
    d = d[np.isfinite(d)]
    assert d.mean() - 1.96 * d.std(ddof=1) / np.sqrt(d.size) > 0, (d.mean(), d.std())
