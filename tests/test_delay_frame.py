"""One compiled solver for many delays: the frame of L pending slots with the delay l as data
(``delay_frame``, docs/derivation.md §17).

References, all independent of the framed code: the state-augmentation pass of the same LQG
without a frame (``lqg.augmented_backward_pass``), and the library's unframed solver, simulator
and prediction, each at the static delay l.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr import lqg as _lqg
from delayed_ilqr import Options, Status, simulate, solve
from delayed_ilqr.ilqg import solver
from delayed_ilqr.lqg import DelayedLQG
from delayed_ilqr.lqg import structured
from delayed_ilqr.models import arm2, pendulum, point_mass

from comparisons import WorstDifference, rel_err   # tests/comparisons.py
from test_lqg import random_arrays                  # tests/test_lqg.py

RTOL = 1e-9
_WORST = WorstDifference("test_delay_frame: worst framed-vs-unframed relative difference")
_report_worst = _WORST.fixture()

# (K, n, d, p, L): each frame shape compiles the framed pass once, whatever l; the unframed
# references compile per l. The second has L >= K: delays l >= K, where no command sent inside
# the horizon acts, are in the frame too.
FRAMES = [(6, 2, 2, 2, 4), (5, 3, 1, 1, 7)]


def _blocks(framed, unframed, L: int, l: int, axes: int):
    """(live, dead): the framed pending blocks of the l live commands, and those of the L - l
    that have acted, along the first ``axes`` pending axes after the time axis."""
    live = framed[(slice(None),) + (slice(L - l, None),) * axes]
    dead = [framed[(slice(None),) * (1 + a) + (slice(0, L - l),)] for a in range(axes)]
    return live, dead


@settings(max_examples=12)
@given(frame=st.sampled_from(FRAMES), data=st.data(), seed=st.integers(0, 2 ** 31 - 1),
       reg=st.sampled_from([0.0, 0.3]))
def test_framed_pass_equals_augmentation_for_every_delay_in_the_frame(frame, data, seed, reg):
    """Structured and augmented passes on the frame, at any l in 0..L (l = 1, l = L, l >= K):
    every gain and value block of the l live commands equals the unframed augmentation's to
    round-off, and every block of a command that has acted is exactly zero."""
    K, n, d, p, L = frame
    l = data.draw(st.integers(0, L), label="l")
    arrays = random_arrays(seed, K, n, d, p, l)
    ref_gains, ref_value = _lqg.augmented_backward_pass(DelayedLQG(**arrays), reg)
    framed = DelayedLQG(**arrays, delay_frame=L)
    for name, (gains, value) in (("structured", _lqg.backward_pass(framed, reg)),
                                 ("augmented", _lqg.augmented_backward_pass(framed, reg))):
        assert bool(value.positive_definite)
        errs = {f: rel_err(getattr(gains, f), getattr(ref_gains, f)) for f in ("feedforward", "state_feedback")}
        errs.update({f: rel_err(getattr(value, f), getattr(ref_value, f)) for f in ("s_tilde", "s", "S")})
        for field, source, ref, axes in (("M", gains.delay_feedback, ref_gains.delay_feedback, 1),
                                         ("r", value.r, ref_value.r, 1), ("Rt", value.Rt, ref_value.Rt, 1),
                                         ("R", value.R, ref_value.R, 2)):
            live, dead = _blocks(source, ref, L, l, axes)
            errs[field] = rel_err(live, ref)
            assert all(not np.any(np.asarray(block)) for block in dead), f"{name}: {field} of acted commands"
        worst = max(errs, key=errs.get)
        _WORST.record(errs[worst], f"{name} {worst}, K={K} n={n} d={d} p={p} L={L} l={l} reg={reg}")
        assert all(e <= RTOL for e in errs.values()), (name, errs)


def test_framed_pass_compiles_once_for_all_delays():
    """The delays 0..L of one frame shape run through one compiled pass."""
    K, n, d, p, L = FRAMES[0]
    before = structured._backward_pass._cache_size()
    costs = [float(_lqg.backward_pass(DelayedLQG(**random_arrays(l, K, n, d, p, l), delay_frame=L), 0.0)[1]
                   .expected_cost) for l in range(L + 1)]
    assert structured._backward_pass._cache_size() - before <= 1
    assert all(np.isfinite(costs))


def test_frame_must_hold_the_delay():
    arrays = random_arrays(0, 6, 2, 2, 1, 3)
    with pytest.raises(ValueError, match="delay_frame must be at least delay_steps.*delay_frame=2 with delay_steps=3"):
        DelayedLQG(**arrays, delay_frame=2)
    with pytest.raises(ValueError, match="delay_frame must be at least delay_steps.*delay_frame=4 with delay_steps=5"):
        arm2(delay=0.05).replace(delay_frame=4)
    with pytest.raises(ValueError, match="delay_frame must be a non-negative integer"):
        arm2(delay=0.05).replace(delay_frame=7.5)


# -- the solver ------------------------------------------------------------------------------------

# The arm at 0-150 ms (l = 0..15, dt = 10 ms) in one frame of 15 slots.
ARM_FRAME = 15


@pytest.mark.parametrize("noise", [False, True])
def test_framed_solves_equal_unframed_ones_with_one_compilation(noise):
    """Delays 0, 10 and 150 ms (l = 0, 1 and l = L) of the noisy and the deterministic arm:
    the three framed solves compile the solver at most once (once per process and problem
    structure), and each takes the unframed solve's iterations and ends on its commands, cost,
    expected cost and gains to round-off. The noisy arm's noise depends on the delayed command,
    which the frame must keep in the backward pass."""
    problems = [arm2(delay=ms / 1000, noise=noise) for ms in (0, 10, 150)]
    before = solver._solve._cache_size()
    framed = [solve(problem.replace(delay_frame=ARM_FRAME)) for problem in problems]
    assert solver._solve._cache_size() - before <= 1
    for problem, sol in zip(problems, framed):
        ref = solve(problem)
        assert sol.status == ref.status and sol.status.converged
        assert int(sol.iterations) == int(ref.iterations)
        assert sol.policy.delay_feedback.shape == ref.policy.delay_feedback.shape     # trimmed to l
        errs = dict(u=rel_err(sol.u, ref.u), cost=rel_err(sol.cost, ref.cost),
                    expected_cost=rel_err(sol.expected_cost, ref.expected_cost),
                    L=rel_err(sol.policy.state_feedback, ref.policy.state_feedback),
                    M=rel_err(sol.policy.delay_feedback, ref.policy.delay_feedback))
        worst = max(errs, key=errs.get)
        _WORST.record(errs[worst], f"{worst}, arm2 noise={noise} l={problem.delay_steps}")
        assert all(e <= RTOL for e in errs.values()), (problem.delay_steps, errs)


def test_solve_under_vmap_over_delays():
    """Problems of different delays in one frame stack into one batch: ``vmap(solve)`` gives each
    the unframed solve's result, with the policy over the whole frame (zeros on the commands that
    have acted); ``simulate`` runs a framed problem's trials as the unframed one's, to round-off."""
    problems = [arm2(delay=ms / 1000, noise="benchmark").replace(delay_frame=ARM_FRAME) for ms in (0, 30, 150)]
    batch = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *problems)
    sols = jax.vmap(solve)(batch)
    for i, problem in enumerate(problems):
        ref = solve(problem.without_frame("test"))
        l = problem.delay_steps
        assert rel_err(sols.u[i], ref.u) <= RTOL and rel_err(sols.cost[i], ref.cost) <= RTOL
        assert rel_err(sols.policy.delay_feedback[i, :, ARM_FRAME - l:], ref.policy.delay_feedback) <= RTOL
        assert not np.any(np.asarray(sols.policy.delay_feedback[i, :, :ARM_FRAME - l]))
    framed = solve(problems[1])
    runs = simulate(problems[1], framed.policy, n_trials=20, seed=3)
    ref_runs = simulate(problems[1].without_frame("test"), framed.policy, n_trials=20, seed=3)
    assert rel_err(runs.x, ref_runs.x) <= 1e-12        # round-off: the framed plant indexes by a traced l


@pytest.mark.parametrize("noise", [False, True])
def test_framed_solves_with_limits(noise):
    """With command limits that bind: the bounded step (no noise) and the box QP with the feedback
    latch (noise) give the unframed solve's result at l = 0 and l = 3."""
    for ms in (0, 30):
        problem = arm2(delay=ms / 1000, noise=noise).replace(u_min=-0.3, u_max=0.3)
        ref, sol = solve(problem), solve(problem.replace(delay_frame=ARM_FRAME))
        assert np.any(np.abs(ref.u) >= 0.3 - 1e-12)          # the limits bind
        assert sol.status == ref.status and int(sol.iterations) == int(ref.iterations)
        assert rel_err(sol.u, ref.u) <= RTOL and rel_err(sol.cost, ref.cost) <= RTOL


def test_augmented_method_in_a_frame():
    """``Options(method="augmented")`` on a framed problem: the solver's reference pass (augmentation
    over the frame, B1 and C1 on buffer entry L - l) gives the unframed solve's result."""
    options = Options(method="augmented")
    for delay in (0.0, 0.06):
        problem = pendulum(delay=delay, noise=True, limits=False)
        ref, sol = solve(problem, options=options), solve(problem.replace(delay_frame=8), options=options)
        assert sol.status == ref.status and sol.status.converged
        assert rel_err(sol.u, ref.u) <= RTOL and rel_err(sol.expected_cost, ref.expected_cost) <= RTOL
        assert rel_err(sol.policy.delay_feedback, ref.policy.delay_feedback) <= RTOL


def test_implicit_derivative_preconditioner_in_a_frame():
    """The implicit derivative's only framed code is its preconditioner (the Gauss-Newton delayed
    LQ solve, a backward pass and a linear closed loop; ilqg/implicit.py): on the noisy pendulum's
    linearisation at its solution, with some commands held, the framed preconditioner gives the
    unframed one's result at l = 0 and l = 3 in a frame of 8 (the rest of the derivative is the
    problem's own arithmetic)."""
    from delayed_ilqr.ilqg.implicit import preconditioner
    from delayed_ilqr.ilqg.linearize import linearize
    rng = np.random.default_rng(0)
    for delay in (0.0, 0.06):
        problem = pendulum(delay=delay, noise=True, limits=False)
        sol = solve(problem)
        fixed = jnp.asarray(rng.random(sol.u.shape) < 0.2)
        r = jnp.asarray(rng.standard_normal(sol.u.shape))
        ref = preconditioner(linearize(problem, sol.x, sol.u), fixed)(r)
        framed_problem = problem.replace(delay_frame=8)
        framed = preconditioner(linearize(framed_problem, sol.x, sol.u), fixed)(r)
        assert np.all(np.isfinite(ref)) and rel_err(framed, ref) <= RTOL


def test_a_traced_frame_refuses_what_needs_a_static_delay():
    problem = arm2(delay=0.05, noise="benchmark").replace(delay_frame=ARM_FRAME)
    with pytest.raises(ValueError, match="closed_loop_prediction needs a static delay"):
        jax.vmap(lambda p: p.without_frame("closed_loop_prediction").x0)(
            jax.tree_util.tree_map(lambda leaf: jnp.stack([leaf, leaf]), problem))


def test_delay_study_in_one_frame():
    """``compare_delays(..., delay_frame="auto")``: the point mass at 0 and 30 ms, both designs, in
    one frame: the same statuses and iterations as the unframed study, and costs, predictions and
    Monte Carlo statistics equal to round-off."""
    from delayed_ilqr.experiments.delay_study import compare_delays
    args = dict(n_trials=50, seed=2, controllers=("aware", "ignorant"), model_kwargs=dict(horizon=20))
    ref = compare_delays("point_mass", (0.0, 0.03), **args)
    framed = compare_delays("point_mass", (0.0, 0.03), delay_frame="auto", **args)
    for a, b in zip(framed, ref):
        assert (a.delay_steps, a.controller, a.status, a.iterations) == (b.delay_steps, b.controller, b.status,
                                                                         b.iterations)
        assert a.problem.delay_frame == 3 and b.problem.delay_frame is None
        for field in ("nominal_cost", "predicted_cost"):
            assert rel_err(getattr(a, field), getattr(b, field)) <= RTOL
        assert rel_err(a.cost.mean, b.cost.mean) <= RTOL and rel_err(a.endpoint_error.median, b.endpoint_error.median) <= RTOL


def test_shared_delay_frame_frames_only_different_delays():
    """"auto" (sweep, compare_delays) frames problems of different delays at the longest; problems
    of one delay keep their own solver, which a frame would only slow down."""
    from delayed_ilqr.problem import shared_delay_frame
    assert shared_delay_frame([arm2(delay=0.05), arm2(delay=0.0), arm2(delay=0.12)]) == 12
    assert shared_delay_frame([arm2(delay=0.05), arm2(delay=0.05)]) is None


def test_a_traced_delay_outside_the_frame_is_flagged_in_the_status():
    """A delay that is data (a frame) is checked against 0 <= l <= L when concrete; traced (under
    vmap) it cannot be refused, so a delay above the frame or a negative one ends
    INVALID_TRACED_INPUT without solving, beside valid delays in the same batch (before, l = 12 in
    a frame of 9 was solved at a wrong delay and l = -1 ended converged)."""
    problem = point_mass(delay=0.02).replace(horizon=20, delay_frame=9)
    sols = jax.vmap(lambda l: solve(problem.replace(delay_steps=l)))(jnp.array([2, 12, -1, 9]))
    statuses = [int(s) for s in sols.status]
    assert statuses[1:3] == [Status.INVALID_TRACED_INPUT] * 2, statuses
    assert Status(statuses[0]).converged and Status(statuses[3]).converged, statuses
    assert "delay_steps outside 0..delay_frame" in sols.message[1]
    assert np.all(np.asarray(sols.iterations[1:3]) == 0)
    for leaf in jax.tree_util.tree_leaves(sols.policy):
        assert np.all(np.isfinite(np.asarray(leaf)))
    ref = solve(problem.replace(delay_steps=2).without_frame("test"))
    assert rel_err(sols.u[0], ref.u) <= RTOL


@pytest.mark.parametrize("frame", [20, 10 ** 6])
def test_a_frame_beyond_the_horizon_is_refused_before_anything_is_allocated(frame):
    """A frame holds delays below the horizon K, so L >= K only costs memory (L = 10**6 asked the
    solver for 32 TB): refused by name, for a concrete and for a traced delay."""
    problem = point_mass(delay=0.02).replace(horizon=20)
    match = f"delay_frame must be below the horizon.*got delay_frame={frame}, horizon=20"
    with pytest.raises(ValueError, match=match):
        problem.replace(delay_frame=frame)
    with pytest.raises(ValueError, match=match):
        jax.vmap(lambda l: problem.replace(delay_steps=l, delay_frame=frame).x0)(jnp.array([1, 2]))
    assert problem.replace(delay_frame=19).delay_frame == 19
