"""Tests for :mod:`delayed_ilqr.lqg.boxqp` (projected-Newton box QP, Tassa et al. 2014).

Independent references:

* exact active-set enumeration (every coordinate at its lower bound, its upper bound, or
  free: 3^d equality-constrained QPs solved with numpy; the minimiser of a strictly convex QP
  over a box is the best primal-feasible one of these stationary points);
* ``scipy.optimize.minimize(method="L-BFGS-B")`` for larger problems;
* ``numpy.linalg.solve`` for the Newton point and for ``free_solve``.

Problems are padded to a few fixed sizes (identity Hessian, zero gradient, infinite bounds in
the padding: the padded coordinates stay at 0 and free and do not change the solution) to keep
the number of compilations low.
"""
import itertools

import jax
import numpy as np
import pytest
import scipy.optimize
from hypothesis import given, settings
from hypothesis import strategies as st

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

from delayed_ilqr.lqg.boxqp import STATUS_MESSAGES, BoxQPResult, box_qp, free_solve  # noqa: E402

SETTINGS = settings(deadline=None, max_examples=30, derandomize=True)
PAD = 8  # enumeration tests
PAD_LARGE = 16  # L-BFGS-B tests
SUCCESS = (3, 4, 5, 6)


# --------------------------------------------------------------------------------------------
# problem generation and references
# --------------------------------------------------------------------------------------------
def random_problem(seed, d, cond=1e2, g_scale=3.0):
    """Random SPD H (eigenvalues log-uniform in [1, cond] / 3), g, mixed boxes, x_init.

    Per coordinate the box is unbounded, lower-only, upper-only, two-sided or (rarely) a
    point; bounds lie near the origin while the unconstrained minimiser is typically far out,
    so several bounds are active.
    """
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    eig = np.exp(rng.uniform(0.0, np.log(cond), size=d)) / 3.0
    H = (Q * eig) @ Q.T
    H = 0.5 * (H + H.T)
    g = g_scale * rng.normal(size=d)
    kind = rng.choice(5, size=d, p=[0.2, 0.15, 0.15, 0.45, 0.05])
    c = rng.normal(size=d)
    lo = c - rng.uniform(0.05, 1.5, size=d)
    hi = c + rng.uniform(0.05, 1.5, size=d)
    lower = np.where((kind == 1) | (kind == 3), lo, -np.inf)
    upper = np.where((kind == 2) | (kind == 3), hi, np.inf)
    lower = np.where(kind == 4, c, lower)
    upper = np.where(kind == 4, c, upper)
    x_init = 2.0 * rng.normal(size=d)
    return H, g, lower, upper, x_init


def pad(H, g, lower, upper, x_init, size):
    d = g.shape[0]
    Hp = np.eye(size)
    Hp[:d, :d] = H
    gp = np.zeros(size)
    gp[:d] = g
    lp = np.full(size, -np.inf)
    lp[:d] = lower
    up = np.full(size, np.inf)
    up[:d] = upper
    xp = np.zeros(size)
    xp[:d] = x_init
    return Hp, gp, lp, up, xp


def solve_padded(H, g, lower, upper, x_init, size=PAD, **kw):
    d = g.shape[0]
    r = box_qp(*pad(H, g, lower, upper, x_init, size), **kw)
    x = np.asarray(r.x)
    free = np.asarray(r.free)
    assert np.all(x[d:] == 0.0) and np.all(free[d:])
    return x[:d], free[:d], int(r.status), int(r.iterations)


def objective(H, g, x):
    return float(0.5 * x @ H @ x + g @ x)


def enumerate_active_sets(H, g, lower, upper):
    """Exact minimiser: best primal-feasible stationary point over all 3^d faces of the box.

    Returns ``(x, at_bound)`` with ``at_bound[i]`` True when coordinate i is fixed at a bound
    in the winning face.
    """
    d = g.shape[0]
    best = (np.inf, None, None)
    choices = []
    for i in range(d):
        c = [0]  # free
        if np.isfinite(lower[i]):
            c.append(-1)
        if np.isfinite(upper[i]) and upper[i] != lower[i]:
            c.append(1)
        choices.append(c)
    finite_bounds = np.concatenate([lower[np.isfinite(lower)], upper[np.isfinite(upper)], [0.0]])
    scale = 1.0 + np.max(np.abs(finite_bounds))
    for combo in itertools.product(*choices):
        combo = np.array(combo)
        fixed = combo != 0
        x = np.where(combo == -1, lower, np.where(combo == 1, upper, 0.0))
        F = ~fixed
        if F.any():
            rhs = -(g[F] + H[np.ix_(F, fixed)] @ x[fixed])
            x[F] = np.linalg.solve(H[np.ix_(F, F)], rhs)
        tol = 1e-12 * scale
        if np.any(x < lower - tol) or np.any(x > upper + tol):
            continue
        x = np.clip(x, lower, upper)
        f = objective(H, g, x)
        if f < best[0]:
            best = (f, x, fixed)
    return best[1], best[2]


# --------------------------------------------------------------------------------------------
# random problems against the exact enumeration
# --------------------------------------------------------------------------------------------
@SETTINGS
@given(d=st.integers(1, PAD), seed=st.integers(0, 2**32 - 1))
def test_matches_exact_active_set_enumeration(d, seed):
    H, g, lower, upper, x_init = random_problem(seed, d)
    x_ref, fixed_ref = enumerate_active_sets(H, g, lower, upper)
    x, free, status, _ = solve_padded(H, g, lower, upper, x_init)

    assert status in SUCCESS, STATUS_MESSAGES[status]
    # feasibility (clipping is exact)
    assert np.all(x >= lower) and np.all(x <= upper)
    # objective and minimiser
    f, f_ref = objective(H, g, x), objective(H, g, x_ref)
    assert abs(f - f_ref) <= 1e-10 * max(1.0, abs(f_ref))
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-7 * max(1.0, np.max(np.abs(x_ref))))

    # KKT at the returned point
    grad = g + H @ x
    gscale = 1e-7 * (1.0 + np.max(np.abs(g)))
    at_lo, at_hi = x == lower, x == upper
    assert np.all(np.abs(grad[free]) <= gscale)
    assert np.all(at_lo[~free] | at_hi[~free])
    assert np.all(grad[~free & at_lo & ~at_hi] >= 0)
    assert np.all(grad[~free & at_hi & ~at_lo] <= 0)

    # one step of the projected Armijo line search never increases the objective
    x1, _, _, _ = solve_padded(H, g, lower, upper, x_init, max_iter=1)
    assert objective(H, g, x1) <= objective(H, g, np.clip(x_init, lower, upper))

    # free mask = complement of the strictly active set of the exact solution
    grad_ref = g + H @ x_ref
    strictly_active = fixed_ref & (np.abs(grad_ref) > 1e-6 * (1.0 + np.max(np.abs(g))))
    interior = (x_ref > lower + 1e-6) & (x_ref < upper - 1e-6)
    assert not np.any(free & strictly_active)
    assert np.all(free[interior])


@SETTINGS
@given(d=st.integers(PAD + 1, PAD_LARGE), seed=st.integers(0, 2**32 - 1))
def test_matches_lbfgsb_larger(d, seed):
    H, g, lower, upper, x_init = random_problem(seed, d, cond=10.0)
    x, free, status, _ = solve_padded(H, g, lower, upper, x_init, size=PAD_LARGE)
    assert status in SUCCESS, STATUS_MESSAGES[status]

    bounds = [
        (None if np.isinf(lo) else lo, None if np.isinf(hi) else hi) for lo, hi in zip(lower, upper)
    ]
    ref = scipy.optimize.minimize(
        lambda z: objective(H, g, z),
        np.clip(x_init, lower, upper),
        jac=lambda z: H @ z + g,
        method="L-BFGS-B",
        bounds=bounds,
        options=dict(ftol=1e-15, gtol=1e-12, maxiter=10000),
    )
    f, f_ref = objective(H, g, x), objective(H, g, ref.x)
    # the exact solver must be at least as good as the iterative reference, and close to it
    assert f <= f_ref + 1e-12 * max(1.0, abs(f_ref))
    assert f_ref - f <= 1e-8 * max(1.0, abs(f_ref))
    np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-4)
    grad = g + H @ x
    assert np.all(np.abs(grad[free]) <= 1e-7 * (1.0 + np.max(np.abs(g))))


# --------------------------------------------------------------------------------------------
# special cases and status codes
# --------------------------------------------------------------------------------------------
@SETTINGS
@given(d=st.integers(1, PAD), seed=st.integers(0, 2**32 - 1))
def test_no_bounds_returns_newton_point(d, seed):
    H, g, _, _, x_init = random_problem(seed, d)
    inf = np.full(d, np.inf)
    x, free, status, iterations = solve_padded(H, g, -inf, inf, x_init)
    assert status == 3 and iterations == 0
    assert np.all(free)
    np.testing.assert_allclose(x, np.linalg.solve(H, -g), rtol=1e-12, atol=1e-12)


def test_one_sided_infinite_bounds_are_not_no_bounds():
    H = np.eye(2)
    g = np.array([1.0, -1.0])
    r = box_qp(H, g, np.array([-np.inf, -np.inf]), np.array([np.inf, 0.5]), np.zeros(2))
    assert int(r.status) in (4, 5)
    np.testing.assert_allclose(r.x, [-1.0, 0.5], atol=1e-14)
    np.testing.assert_array_equal(r.free, [True, False])


def test_all_clamped_status_6():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3))
    H = A @ A.T + 3 * np.eye(3)
    # minimiser far outside the unit box in the direction where every bound is active
    x_far = np.array([50.0, -50.0, 50.0])
    g = -H @ x_far
    lower, upper = -np.ones(3), np.ones(3)
    r = box_qp(H, g, lower, upper, np.zeros(3))
    assert int(r.status) == 6
    np.testing.assert_array_equal(r.x, [1.0, -1.0, 1.0])
    assert not np.any(r.free)
    grad = g + H @ np.asarray(r.x)
    assert np.all(grad * np.sign(r.x) < 0)
    # warm start at the corner: immediately all clamped, no step
    r2 = box_qp(H, g, lower, upper, np.asarray(r.x))
    assert int(r2.status) == 6 and int(r2.iterations) == 0


@SETTINGS
@given(d=st.integers(1, PAD), seed=st.integers(0, 2**32 - 1))
def test_warm_start_at_solution_returns_immediately(d, seed):
    H, g, lower, upper, x_init = random_problem(seed, d)
    x, free, status, _ = solve_padded(H, g, lower, upper, x_init)
    x2, free2, status2, iterations2 = solve_padded(H, g, lower, upper, x)
    assert iterations2 == 0
    assert status2 in (5, 6, 3)
    np.testing.assert_array_equal(x2, x)
    np.testing.assert_array_equal(free2, free)


def test_x_init_outside_box_and_nonfinite_is_clipped():
    H = np.diag([1.0, 2.0, 3.0])
    g = np.zeros(3)
    lower, upper = np.array([1.0, -2.0, 0.5]), np.array([2.0, -1.0, np.inf])
    r = box_qp(H, g, lower, upper, np.array([100.0, np.nan, -np.inf]))
    np.testing.assert_allclose(r.x, [1.0, -1.0, 0.5], atol=0)
    assert int(r.status) == 6


def test_max_iter_status_1():
    H, g, lower, upper, x_init = random_problem(11, 6)
    _, _, status, iterations = solve_padded(H, g, lower, upper, x_init)
    assert iterations >= 2
    x1, _, status1, it1 = solve_padded(H, g, lower, upper, x_init, max_iter=1)
    assert status1 == 1 and it1 == 1
    x0, _, status0, it0 = solve_padded(H, g, lower, upper, x_init, max_iter=0)
    assert status0 == 1 and it0 == 0
    np.testing.assert_array_equal(x0, np.clip(x_init, lower, upper))


def test_tolerance_options_are_honoured():
    H, g, lower, upper, x_init = random_problem(11, 6)
    x0 = np.clip(x_init, lower, upper)
    x, _, status, iterations = solve_padded(H, g, lower, upper, x_init, min_grad=np.inf)
    assert status == 5 and iterations == 0
    np.testing.assert_array_equal(x, x0)
    # any improvement is "too small": stop right after the first step
    _, _, status, iterations = solve_padded(H, g, lower, upper, x_init, min_rel_improve=np.inf)
    assert status == 4 and iterations == 1
    # the line search may not shrink the step at all: status 2 unless the full step is accepted
    _, _, status, iterations = solve_padded(
        H, g, lower, upper, x_init, min_step=1.0, armijo=1.0 - 1e-12
    )
    assert status == 2 and iterations == 1


def test_not_positive_definite_status_minus_1():
    H = np.array([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3, -1
    g = np.array([0.3, -0.2])
    inf = np.full(2, np.inf)
    for lower, upper in [(-inf, inf), (-np.ones(2), np.ones(2))]:
        r = box_qp(H, g, lower, upper, np.zeros(2))
        assert int(r.status) == -1
        assert np.all(np.isfinite(r.x))
    # negative curvature only on a dimension clamped from the start: not detected (as boxQP.m,
    # which factorises H_ff only), converges to the KKT point of the free subproblem
    H = np.diag([-1.0, 2.0])
    g = np.array([1.0, -1.0])
    r = box_qp(H, g, np.array([0.0, -5.0]), np.array([5.0, 5.0]), np.zeros(2))
    assert int(r.status) == 5
    np.testing.assert_allclose(r.x, [0.0, 0.5], atol=1e-15)
    np.testing.assert_array_equal(r.free, [False, True])


# --------------------------------------------------------------------------------------------
# transformations: jit, vmap, scan
# --------------------------------------------------------------------------------------------
def _batch(n, size=PAD, first_seed=100):
    probs = []
    for k in range(n):
        d = 1 + k % size
        probs.append(pad(*random_problem(first_seed + k, d), size))
    return tuple(np.stack(a) for a in zip(*probs))


def _assert_same(batched: BoxQPResult, singles):
    for k, r in enumerate(singles):
        np.testing.assert_allclose(batched.x[k], r.x, rtol=1e-12, atol=1e-13)
        np.testing.assert_array_equal(batched.free[k], r.free)
        assert int(batched.status[k]) == int(r.status)
        assert int(batched.iterations[k]) == int(r.iterations)


def test_vmap_scan_jit_match_unbatched():
    H, g, lower, upper, x_init = batch = _batch(16)
    # add a no-bounds problem and a non-PD problem to the batch
    H[1] = -H[1]
    lower[2], upper[2] = -np.inf, np.inf
    singles = [box_qp(*(a[k] for a in batch)) for k in range(H.shape[0])]
    assert int(singles[1].status) == -1 and int(singles[2].status) == 3
    assert len({int(r.iterations) for r in singles}) > 1  # lanes really do differ

    _assert_same(jax.vmap(box_qp)(*batch), singles)

    def step(carry, prob):
        r = box_qp(*prob)
        return carry + r.iterations, r

    total, scanned = jax.lax.scan(step, jnp.zeros((), jnp.int32), batch)
    _assert_same(scanned, singles)
    assert int(total) == sum(int(r.iterations) for r in singles)

    @jax.jit
    def jitted(H, g, lower, upper, x_init):
        return box_qp(H, g, lower, upper, x_init, max_iter=50, armijo=0.1)

    _assert_same(jax.vmap(jitted)(*batch), singles)


# --------------------------------------------------------------------------------------------
# free_solve
# --------------------------------------------------------------------------------------------
@SETTINGS
@given(
    d=st.integers(1, PAD),
    seed=st.integers(0, 2**32 - 1),
    m=st.sampled_from([0, 3]),
)
def test_free_solve_matches_numpy_on_free_block(d, seed, m):
    rng = np.random.default_rng(seed)
    H, _, _, _, _ = random_problem(seed, d)
    free = rng.random(d) < 0.6
    # make the clamped part indefinite: it must be ignored entirely
    H[~free, ~free] = -5.0
    rhs = rng.normal(size=(d,) if m == 0 else (d, m))
    Hp = np.eye(PAD)
    Hp[:d, :d] = H
    freep = np.zeros(PAD, bool)
    freep[:d] = free
    rhsp = np.zeros((PAD,) + rhs.shape[1:])
    rhsp[:d] = rhs
    out = np.asarray(free_solve(Hp, freep, rhsp))
    assert out.shape == rhsp.shape
    assert np.all(np.isfinite(out))
    assert np.all(out[~freep] == 0.0)
    if free.any():
        expect = -np.linalg.solve(H[np.ix_(free, free)], rhs[free])
        np.testing.assert_allclose(out[:d][free], expect, rtol=1e-10, atol=1e-12)


def test_free_solve_gains_from_box_qp():
    """The intended use: gains K = free_solve(H, result.free, B) are zero on clamped rows."""
    H, g, lower, upper, x_init = pad(*random_problem(7, 5), PAD)
    r = box_qp(H, g, lower, upper, x_init)
    B = np.arange(PAD * 2, dtype=float).reshape(PAD, 2)
    K = np.asarray(free_solve(H, r.free, B))
    free = np.asarray(r.free)
    assert (~free).any() and free.any()
    np.testing.assert_array_equal(K[~free], 0.0)
    expect = -np.linalg.solve(H[np.ix_(free, free)], B[free])
    np.testing.assert_allclose(K[free], expect, rtol=1e-10)


@pytest.mark.parametrize("code", sorted(STATUS_MESSAGES))
def test_status_messages_cover_codes(code):
    assert isinstance(STATUS_MESSAGES[code], str)
