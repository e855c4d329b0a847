"""One input delay per command channel (``delay_steps=[l_1, ..., l_d]``, docs/derivation.md §18):
channel j's column of B1, C1 acts with du_{k-l_j}.

References, independent of the structured pass: the state-augmentation pass over the same
channels (``lqg.augmented_backward_pass``), whose augmented matrices are checked here against a
construction written out channel by channel; the library's single-delay pass where every channel
has the same delay; and the exact second moments of the closed loop (``lqg.policy_cost``).
"""
from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import lqg as _lqg
from delayed_ilqr.lqg import DelayedLQG
from delayed_ilqr.lqg.augmented import augment
from delayed_ilqr.lqg.structured import structured_scan

from comparisons import WorstDifference, rel_err, solution_errors   # tests/comparisons.py
from test_lqg import random_arrays                  # tests/test_lqg.py

RTOL = 1e-9
_WORST = WorstDifference("test_channels: worst per-channel structured-vs-reference relative difference")
_report_worst = _WORST.fixture()

# (K, n, d, p, L): per-channel delays 0..L are drawn; each shape compiles each pass once (the
# delays are data). The second has L >= K: channels whose commands never act in the horizon.
SHAPES = [(6, 2, 3, 2, 4), (4, 3, 2, 1, 5)]


def _channel_delays(data, d: int, L: int):
    """Delays 0..L per channel, the longest equal to L (the frame is max_j l_j)."""
    delays = data.draw(st.lists(st.integers(0, L), min_size=d, max_size=d), label="delays")
    delays[data.draw(st.integers(0, d - 1), label="longest")] = L
    return delays


# the pass with its R update deferred to blocks of 3 steps (by default from L d >= 300 on)
_blocked_scan = jax.jit(lambda q, reg: structured_scan(q, reg, store_value=True, block=3))


def _errors(gains, value, ref_gains, ref_value):
    errs = {f: rel_err(getattr(gains, f), getattr(ref_gains, f))
            for f in ("feedforward", "state_feedback", "delay_feedback")}
    errs.update({f: rel_err(getattr(value, f), getattr(ref_value, f)) for f in ("s_tilde", "s", "S", "r", "Rt", "R")})
    return errs


@settings(max_examples=8, deadline=None)
@given(shape=st.sampled_from(SHAPES), data=st.data(), seed=st.integers(0, 2 ** 31 - 1),
       reg=st.sampled_from([0.0, 0.3]))
def test_per_channel_pass_equals_augmentation(shape, data, seed, reg):
    """Random time-varying data and random channel delays (0, 1, equal, l >= K among them): every
    gain and value block of the structured pass, with its R update deferred to blocks or not,
    equals the augmented pass's to round-off, and J(0) is the exact expected cost of the returned
    policy."""
    K, n, d, p, L = shape
    delays = _channel_delays(data, d, L)
    lqg = DelayedLQG(**random_arrays(seed, K, n, d, p, delays))
    gains, value = _lqg.backward_pass(lqg, reg)
    ref_gains, ref_value = _lqg.augmented_backward_pass(lqg, reg)
    assert bool(value.positive_definite) and bool(ref_value.positive_definite)
    errs = _errors(gains, value, ref_gains, ref_value)
    errs["policy_cost"] = rel_err(_lqg.policy_cost(lqg, gains), value.expected_cost)
    blocked_gains, blocked_value, _ = _blocked_scan(lqg, reg)
    errs.update({f"blocked {f}": rel_err(got, getattr(ref_gains, f)) for f, got in zip(gains._fields, blocked_gains)})
    errs.update({f"blocked {f}": rel_err(got, getattr(ref_value, f)[:-1])
                 for f, got in zip(("s_tilde", "s", "S", "r", "Rt", "R"), blocked_value)})
    worst = max(errs, key=errs.get)
    _WORST.record(errs[worst], f"{worst}, K={K} n={n} d={d} p={p} delays={delays} reg={reg}")
    assert all(e <= RTOL for e in errs.values()), (delays, errs)
    # a channel's entries older than its delay belong to commands that have acted: exactly zero
    M = np.asarray(gains.delay_feedback)
    for j, l_j in enumerate(delays):
        assert not np.any(M[:, :L - l_j, :, j]), (j, l_j)


def test_per_channel_pass_compiles_as_one_function():
    """The framed pass writes the acting components by slices, not scatters, so that XLA compiles
    its loop as one function (with configure_cpu's flags, set by conftest.py); with scatters each
    operation of a step ran as a thunk (docs/performance.md#per-channel-delays)."""
    lqg = DelayedLQG(**random_arrays(5, 6, 2, 3, 2, [1, 4, 0]))
    hlo = jax.jit(lambda q: structured_scan(q, 0.0, store_value=False)[1][0]).lower(lqg).compile().as_text()
    assert 'xla_cpu_small_call="true"' in hlo


@pytest.mark.parametrize("l", [0, 1, 4])
def test_equal_channel_delays_are_the_single_delay(l):
    """Every channel delayed by l, in the frame of 4 slots of the first shape above (its compiled
    pass): the live blocks equal the single-delay pass's gains and value to round-off, and the
    frame's 4 - l older slots are exactly zero."""
    K, n, d, p, L = SHAPES[0]
    arrays = random_arrays(11 + l, K, n, d, p, l)
    single = _lqg.backward_pass(DelayedLQG(**arrays), 0.0)
    gains, value = _lqg.backward_pass(DelayedLQG(**{**arrays, "delay_steps": [l] * d}, delay_frame=L), 0.0)
    live = lambda x, axes: x[(slice(None),) + (slice(L - l, None),) * axes]
    dead = lambda x, axes: [x[(slice(None),) * (1 + a) + (slice(0, L - l),)] for a in range(axes)]
    errs = _errors(gains._replace(delay_feedback=live(gains.delay_feedback, 1)),
                   value._replace(r=live(value.r, 1), Rt=live(value.Rt, 1), R=live(value.R, 2)), *single)
    _WORST.record(max(errs.values()), f"equal delays l={l}")
    assert all(e <= RTOL for e in errs.values()), errs
    for x, axes in ((gains.delay_feedback, 1), (value.r, 1), (value.Rt, 1), (value.R, 2)):
        assert not any(np.any(np.asarray(block)) for block in dead(x, axes))


def _augmented_by_channel(arrays, delays):
    """The augmented system written out entry by entry: z_k = [dx_k, du_{k-L}, ..., du_{k-1}],
    channel j of B1, C1 reading the buffer's entry L - l_j (du_k itself for l_j = 0)."""
    A, B0, B1, C0, C1 = (np.asarray(arrays[f]) for f in ("A", "B0", "B1", "C0", "C1"))
    K, n, d = B0.shape
    p, L = C0.shape[1], max(delays)
    m = n + L * d
    Az, Bz = np.zeros((K, m, m)), np.zeros((K, m, d))
    Cz, Cu = np.zeros((K, p, m, m)), np.zeros((K, p, m, d))
    Az[:, :n, :n], Bz[:, :n], Cu[:, :, :n] = A, B0, C0
    for j, l_j in enumerate(delays):
        if l_j == 0:
            Bz[:, :n, j] += B1[:, :, j]
            Cu[:, :, :n, j] += C1[:, :, :, j]
        else:
            column = n + (L - l_j) * d + j
            Az[:, :n, column] = B1[:, :, j]
            Cz[:, :, :n, column] = C1[:, :, :, j]
    for i in range(L - 1):                   # the buffer moves up one entry
        Az[:, n + i * d:n + (i + 1) * d, n + (i + 1) * d:n + (i + 2) * d] = np.eye(d)
    if L:
        Bz[:, m - d:] = np.eye(d)            # du_k enters last
    return Az, Bz, Cz, Cu


@pytest.mark.parametrize("delays", [[0, 3, 1], [3, 3, 0], [1, 0, 3]])
def test_augmentation_reads_each_channel_at_its_delay(delays):
    """The reference's augmented matrices equal the construction written out channel by channel."""
    arrays = random_arrays(5, 4, 2, 3, 2, delays)
    aug = jax.jit(augment)(DelayedLQG(**arrays))
    for name, ref in zip(("Az", "Bz", "Cz", "Cu"), _augmented_by_channel(arrays, delays)):
        np.testing.assert_array_equal(np.asarray(aug[name]), ref, err_msg=name)


# ---------------------------------------------------------------------------------------------
# The nonlinear problem: solve, limits, noise, simulate, saving, gradients, refusals
# ---------------------------------------------------------------------------------------------

FRAME = 4       # every per-channel arm problem below runs in this frame: one compiled solver


@pytest.fixture(scope="module")
def arm_solves():
    """The noisy arm (noise on the delayed command, so its Jacobians per channel matter) at 10 ms
    (l = 1) and per channel: [1, 1] and [0, 4] (a channel without delay), in one frame."""
    from delayed_ilqr import Options, solve
    from delayed_ilqr.ilqg import solver
    from delayed_ilqr.models import arm2
    base = arm2(delay=0.01, noise=True)
    equal_problem = base.replace(delay_steps=[1, 1], delay_frame=FRAME)
    mixed_problem = base.replace(delay_steps=[0, 4])
    before = solver._solve._cache_size()
    equal, mixed = solve(equal_problem), solve(mixed_problem)
    compiled = solver._solve._cache_size() - before
    return dict(base=base, single=solve(base), equal_problem=equal_problem, equal=equal, mixed_problem=mixed_problem,
                mixed=mixed, augmented=solve(mixed_problem, options=Options(method="augmented")), compiled=compiled)


def test_equal_channel_delays_solve_as_the_single_delay(arm_solves):
    """delay_steps=[1, 1] in a frame of 4 (trimmed to 1 by solve) against delay_steps=1: the same
    iterations, commands, costs and gains to round-off."""
    sol, ref = arm_solves["equal"], arm_solves["single"]
    assert sol.status == ref.status and sol.status.converged and int(sol.iterations) == int(ref.iterations)
    assert sol.policy.delay_feedback.shape == ref.policy.delay_feedback.shape
    errs = solution_errors(sol, ref)
    _WORST.record(max(errs.values()), f"arm [1, 1] vs 1: {max(errs, key=errs.get)}")
    assert all(e <= RTOL for e in errs.values()), errs


def test_per_channel_solve_equals_the_augmented_solve(arm_solves):
    """delay_steps=[0, 4] (one channel undelayed, noise on the delayed command): the structured
    solver and the solver on the augmented state (``Options(method="augmented")``) reach the same
    nominal, expected cost and gains to round-off; the two per-channel solves in one frame compiled
    the solver at most once."""
    sol, ref = arm_solves["mixed"], arm_solves["augmented"]
    assert sol.status == ref.status and sol.status.converged and int(sol.iterations) == int(ref.iterations)
    errs = solution_errors(sol, ref)
    _WORST.record(max(errs.values()), f"arm [0, 4] structured vs augmented: {max(errs, key=errs.get)}")
    assert all(e <= RTOL for e in errs.values()), errs
    assert arm_solves["compiled"] <= 1
    # channel 0 acts at once: no gain on its commands in flight; channel 1's four are live
    M = np.asarray(sol.policy.delay_feedback)
    assert not np.any(M[:, :, :, 0]) and np.all(np.any(M[:-4, :, :, 1] != 0, axis=(0, 2)))


@pytest.mark.full
def test_per_channel_solve_with_binding_limits():
    """Limits that bind, without noise (the bounded step) and with it (the box QP): the structured
    and augmented solvers agree at delay_steps=[1, 4] (four compilations of the solver: under
    ``make bench``; the suite checks the same steps on the LQG in
    ``test_per_channel_limits_on_the_lqg``)."""
    from delayed_ilqr import Options, solve
    from delayed_ilqr.models import arm2
    for noise in (False, True):
        problem = arm2(delay=0.03, noise=noise).replace(u_min=-0.3, u_max=0.3).replace(delay_steps=[1, 4])
        sol, ref = solve(problem), solve(problem, options=Options(method="augmented"))
        assert np.any(np.abs(np.asarray(sol.u)) >= 0.3 - 1e-12)          # the limits bind
        assert sol.status == ref.status and int(sol.iterations) == int(ref.iterations)
        errs = dict(u=rel_err(sol.u, ref.u), cost=rel_err(sol.cost, ref.cost))
        _WORST.record(max(errs.values()), f"arm [1, 4] limits noise={noise}")
        assert all(e <= RTOL for e in errs.values()), (noise, errs)


@pytest.mark.parametrize("delays", [[0, 3], [2, 3]])
def test_per_channel_limits_on_the_lqg(delays):
    """With per-channel delays, the clamped recursion (the box QP's gain rule, with limits) agrees
    with its augmented version, and its value is the exact cost of its law (``policy_cost``)."""
    import jax.numpy as jnp
    from delayed_ilqr.lqg.augmented import augmented_scan
    from delayed_ilqr.lqg.gains import boxed_gains
    K, n, d = 10, 3, 2
    lqg = DelayedLQG(**random_arrays(21, K, n, d, 1, delays))
    half = 0.5 * float(jnp.max(jnp.abs(structured_scan(lqg, store_value=False)[0].feedforward)))
    bounds = (jnp.full((K, d), -half), jnp.full((K, d), half))
    gains, (s_tilde, _, _), ok = structured_scan(lqg, store_value=False, gains_fn=boxed_gains, bounds=bounds)
    ref_gains, ref_value = augmented_scan(lqg, gains_fn=boxed_gains, bounds=bounds)
    assert bool(ok) and np.any(np.abs(np.asarray(gains.feedforward)) >= half * (1 - 1e-12))   # the box binds
    errs = {f: rel_err(getattr(gains, f), getattr(ref_gains, f)) for f in gains._fields}
    errs["J0"] = rel_err(s_tilde[0], ref_value.s_tilde[0])
    errs["policy_cost"] = rel_err(_lqg.policy_cost(lqg, gains), s_tilde[0])
    _WORST.record(max(errs.values()), f"clamped recursion, delays={delays}: {max(errs, key=errs.get)}")
    assert all(e <= RTOL for e in errs.values()), errs


@pytest.mark.full
@pytest.mark.parametrize("delays", [[0, 3], [2, 3]])
def test_per_channel_bounded_step_on_the_lqg(delays):
    """The bounded step (projected Newton over the box, no noise) with per-channel delays: the
    structured and augmented versions give the same law, whose cost is the exact one
    (``policy_cost``). Two compilations of the step: under ``make bench``."""
    import jax.numpy as jnp
    from delayed_ilqr.ilqg.bounded import bounded_step
    from delayed_ilqr.lqg.frame import from_slots
    K, n, d = 10, 3, 2
    lqg = DelayedLQG(**random_arrays(22, K, n, d, 0, delays))
    step = jax.jit(bounded_step, static_argnames="method")
    box = (jnp.full((K, d), -0.3), jnp.full((K, d), 0.3))
    (gains, cost, ok, _), (ref_gains, ref_cost, ref_ok, _) = (
        step(lqg, 0.0, *box, jnp.full(d, 1e-9), method=m) for m in ("structured", "augmented"))
    assert bool(ok) and bool(ref_ok)
    assert np.any(np.abs(np.asarray(gains.feedforward)) >= 0.3 - 1e-12)
    errs = dict(feedforward=rel_err(gains.feedforward, ref_gains.feedforward), cost=rel_err(cost, ref_cost),
                policy_cost=rel_err(_lqg.policy_cost(lqg, from_slots(gains, n)), cost))
    assert all(e <= RTOL for e in errs.values()), errs


def test_simulate_applies_each_channel_at_its_delay(arm_solves):
    """Without noise the closed loop of the solved policy retraces the solver's nominal (its
    rollout shifts each channel by its delay; simulate reads its buffer of sent commands); with
    noise, equal channel delays give the single-delay plant's trials to round-off."""
    from delayed_ilqr import simulate
    problem, sol = arm_solves["mixed_problem"], arm_solves["mixed"]
    runs = simulate(problem.replace(noise=None), sol.policy, n_trials=2, seed=0)
    assert rel_err(runs.x[0], sol.x) <= 1e-12 and rel_err(runs.u[0], sol.u) <= 1e-12
    wrong = simulate(problem.replace(noise=None, delay_steps=[4, 0]), sol.policy, n_trials=2, seed=0)
    assert rel_err(wrong.x[0], sol.x) > 1e-3          # the check can fail: swapped delays move the arm
    policy = arm_solves["single"].policy
    noisy = simulate(arm_solves["equal_problem"], policy, n_trials=4, seed=1)
    ref = simulate(arm_solves["base"], policy, n_trials=4, seed=1)
    assert rel_err(noisy.x, ref.x) <= 1e-12


def test_per_channel_policy_saves_and_loads(arm_solves, tmp_path):
    """The policy round-trips bitwise, and the header records the delays per channel (in steps and s)."""
    from delayed_ilqr.saving import load, load_metadata, save
    problem, sol = arm_solves["mixed_problem"], arm_solves["mixed"]
    save(tmp_path / "policy", sol.policy, problem=problem)
    loaded = load(tmp_path / "policy", problem=problem)
    for field in ("feedforward", "state_feedback", "delay_feedback"):
        np.testing.assert_array_equal(np.asarray(getattr(loaded, field)), np.asarray(getattr(sol.policy, field)))
    header = load_metadata(tmp_path / "policy")
    assert header["problem"]["delay_steps"] == [0, 4] and header["delay_steps"] == 4
    np.testing.assert_allclose(header["problem"]["delay"], [0.0, 0.04])


def test_per_channel_value_gradient_matches_finite_differences():
    """Reverse mode through the per-channel structured pass (its gathers and scatters): d J(0) along
    a random direction of B1, C1 and A against Richardson-extrapolated central differences."""
    import jax.numpy as jnp
    from test_gradients import richardson
    lqg = DelayedLQG(**random_arrays(31, 6, 2, 3, 2, [0, 4, 2]))
    rng = np.random.default_rng(4)
    dB1, dC1, dA = (0.1 * rng.standard_normal(np.shape(x)) for x in (lqg.B1, lqg.C1, lqg.A))
    moved = lambda t: lqg.replace(B1=lqg.B1 + t * dB1, C1=lqg.C1 + t * dC1, A=lqg.A + t * dA)
    cost = jax.jit(lambda t: _lqg.backward_pass(moved(t), 0.0)[1].expected_cost)
    fd = richardson(lambda t: dict(J=cost(jnp.asarray(t))), 1e-3)["J"]
    grad = jax.jit(jax.grad(cost))(0.0)
    err = rel_err(grad, fd)
    _WORST.record(err, "d J(0) through the per-channel pass against finite differences")
    assert abs(float(fd)) > 1e-3 and err < 1e-7, (float(grad), float(fd))


@pytest.mark.full
def test_per_channel_cost_derivative_matches_finite_differences():
    """d cost / d x0 along a random direction through the implicit derivative of the per-channel
    solve, against Richardson-extrapolated central differences of re-solves (one compilation of the
    derivative, about a minute: under ``make bench``)."""
    import jax
    from delayed_ilqr import solve
    from delayed_ilqr.models import point_mass
    from test_gradients import TIGHT, _only_x0, along, richardson
    problem = point_mass(delay=0.0, noise=True, horizon=20).replace(delay_steps=[0, 3])
    tangent = _only_x0(problem, np.random.default_rng(3).standard_normal(problem.n_states) * 0.05)
    # one compilation: the primal of the same jvp gives the re-solves of the finite differences
    cost_and_derivative = jax.jit(lambda t: jax.jvp(lambda s: solve(along(problem, tangent, s), None, TIGHT).cost,
                                                    (t,), (1.0,)))
    fd = richardson(lambda t: dict(cost=cost_and_derivative(t)[0]), 1e-2)["cost"]
    forward = cost_and_derivative(0.0)[1]
    err = rel_err(forward, fd)
    _WORST.record(err, "point mass [0, 3] d cost / d x0 against finite differences")
    assert abs(float(fd)) > 1e-6 and err < 1e-6, (float(forward), float(fd))


@pytest.mark.parametrize("delays, frame, match", [
    ([1, 2, 3], None, r"one delay per command channel \(d = 2\); got 3"),
    ([1, -2], None, r"delay_steps\[1\] must be a non-negative integer number of steps; got -2"),
    ([1, -2.5], None, r"delay_steps\[1\] must be a finite, non-negative number of steps; got -2.5"),
    ([True, 2], None, r"delay_steps\[0\] must be a non-negative integer"),
    ([[1, 2]], None, r"got an array of shape \(1, 2\)"),
    ([1, 60], None, r"delay_steps\[1\] must be below the horizon.*got delay_steps=\[1, 60\], horizon=60"),
    ([1, 4], 3, r"delay_frame must be at least the longest channel delay.*got delay_frame=3"),
])
def test_bad_channel_delays_are_refused(delays, frame, match):
    from delayed_ilqr.models import point_mass
    problem = point_mass()
    with pytest.raises(ValueError, match=match):
        problem.replace(delay_steps=delays, delay_frame=frame)


def test_delayed_sensors_refuse_per_channel_delays():
    """Delayed sensors (the filter takes one input delay) say so (the receding-horizon controller
    takes per-channel delays: tests/test_mpc.py)."""
    from delayed_ilqr.models import point_mass
    with pytest.raises(ValueError, match=r"per-channel delay_steps are not available with an observation"):
        point_mass(sensory_delay=0.05).replace(delay_steps=[1, 2])


def test_every_channel_undelayed_is_the_undelayed_problem():
    """delay_steps=[0, 0] (a frame of no slots) solves and simulates as delay_steps=0."""
    from delayed_ilqr import simulate, solve
    from delayed_ilqr.models import point_mass

    problem = point_mass(noise=True, horizon=20)
    one, channels = solve(problem), solve(problem.replace(delay_steps=[0, 0]))
    assert channels.status == one.status
    np.testing.assert_allclose([float(channels.cost), float(channels.expected_cost)],
                               [float(one.cost), float(one.expected_cost)], rtol=1e-12)
    np.testing.assert_allclose(simulate(problem.replace(delay_steps=[0, 0]), channels.policy, 4, seed=1).cost,
                               simulate(problem, one.policy, 4, seed=1).cost, rtol=1e-12)
