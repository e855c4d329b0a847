"""``_kernels.dense``: ``matmul`` / ``matmul_t`` equal the matrix product on both of their paths (fused
broadcast-and-sum for small products, a library dot for large ones), and ``cholesky_solve`` the
solution of the system on both of its paths (unrolled, LAPACK): against NumPy."""
import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from delayed_ilqr._kernels.dense import FUSED_MAX, FUSED_MAX_COLUMNS, _fused, cholesky_solve, matmul, matmul_t

dims = st.integers(min_value=1, max_value=40)


@settings(deadline=None)
@given(m=dims, k=dims, n=st.one_of(st.integers(1, 40), st.integers(100, 300)), vector=st.booleans(),
       seed=st.integers(0, 2 ** 32 - 1))
def test_products_match_numpy(m, k, n, vector, seed):
    rng = np.random.default_rng(seed)
    a, at = rng.normal(size=(m, k)), rng.normal(size=(k, m))
    b = rng.normal(size=(k,)) if vector else rng.normal(size=(k, n))
    tol = dict(rtol=1e-13, atol=1e-13 * np.sqrt(k))
    np.testing.assert_allclose(jax.jit(matmul)(a, b), a @ b, **tol)
    if not vector:
        np.testing.assert_allclose(jax.jit(matmul_t)(at, b), at.T @ b, **tol)


def test_both_paths_are_taken():
    """The threshold splits the shapes the tests above draw: some are fused, some are dots."""
    assert _fused(8, 4, 25) and _fused(2, 24, 1)
    assert not _fused(8, 8, 105)                          # too many multiply-adds
    assert not _fused(1, 1, FUSED_MAX_COLUMNS + 1)        # too many columns
    assert _fused(1, FUSED_MAX // 100, 100) and not _fused(2, FUSED_MAX // 100, 100)


def test_fused_products_are_fused():
    """A small product compiles to no dot (so that XLA fuses it), a large one to a dot."""
    small = jax.jit(matmul).lower(np.ones((8, 4)), np.ones((4, 25))).compile().as_text()
    large = jax.jit(matmul).lower(np.ones((40, 40)), np.ones((40, 40))).compile().as_text()
    assert " dot(" not in small and "dot(" in large


@settings(deadline=None)
@given(d=st.integers(1, 10), m=st.integers(0, 5), vector=st.booleans(), definite=st.booleans(),
       seed=st.integers(0, 2 ** 32 - 1))
def test_cholesky_solve_matches_numpy(d, m, vector, definite, seed):
    """Unrolled (d <= 8) and LAPACK (d > 8) paths: the solution for a positive definite H, and
    ok = False with a non-finite result for an indefinite one."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(d, d))
    H = X @ X.T + 0.1 * np.eye(d)
    if not definite:
        H = H - (np.linalg.eigvalsh(H)[0] + 1.0) * np.eye(d)        # smallest eigenvalue -1
    rhs = rng.normal(size=(d,)) if vector else rng.normal(size=(d, m))
    ok, sol = jax.jit(cholesky_solve)(H, rhs)
    if definite:
        assert bool(ok)
        want = np.linalg.solve(H, rhs)
        np.testing.assert_allclose(sol, want, rtol=1e-9, atol=1e-9 * np.abs(want).max(initial=1.0))
    else:
        assert not bool(ok)
        assert sol.size == 0 or not np.all(np.isfinite(sol))


@pytest.mark.parametrize("batch", [5, 200])
def test_products_under_vmap(batch):
    """Batched, each operand batched or not, against NumPy: a small batch keeps the fused form, a
    large one (200 x 72 multiply-adds > FUSED_MAX) goes to batched dots."""
    rng = np.random.default_rng(1)
    a, b, v = rng.normal(size=(batch, 3, 4)), rng.normal(size=(batch, 4, 6)), rng.normal(size=(batch, 4))
    at = rng.normal(size=(batch, 4, 3))
    for a_axis, b_axis in ((0, 0), (0, None), (None, 0)):
        for fn, x, y in ((matmul, a, b), (matmul, a, v), (matmul_t, at, b)):
            got = jax.jit(jax.vmap(fn, in_axes=(a_axis, b_axis)))(x if a_axis == 0 else x[0], y if b_axis == 0 else y[0])
            for i in range(batch):
                xi, yi = x[i if a_axis == 0 else 0], y[i if b_axis == 0 else 0]
                want = (xi.T if fn is matmul_t else xi) @ yi
                np.testing.assert_allclose(got[i], want, rtol=1e-13, atol=1e-13)


def test_switch_back_to_library_calls(monkeypatch):
    """FUSED_MAX = 0 and UNROLLED_CHOLESKY_MAX = 0, read at trace time, give library calls with the
    same results: the kernels' switch for comparisons."""
    from delayed_ilqr._kernels import dense
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(8, 4)), rng.normal(size=(4, 25))
    X = rng.normal(size=(3, 3))
    H, rhs = X @ X.T + np.eye(3), rng.normal(size=(3, 2))
    monkeypatch.setattr(dense, "FUSED_MAX", 0)
    monkeypatch.setattr(dense, "UNROLLED_CHOLESKY_MAX", 0)
    product = jax.jit(lambda x, y: matmul(x, y))           # new functions: jit caches traces per function
    solve = jax.jit(lambda x, y: cholesky_solve(x, y))
    assert "dot_general" in product.lower(a, b).as_text()
    np.testing.assert_allclose(product(a, b), a @ b, rtol=1e-13, atol=1e-13)
    assert "cholesky" in solve.lower(H, rhs).as_text().lower()
    np.testing.assert_allclose(solve(H, rhs)[1], np.linalg.solve(H, rhs), rtol=1e-10)
