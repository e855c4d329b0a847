"""Small dense linear algebra written for XLA on CPU: the products of one time step (``matmul``,
``matmul_t``, ``add_symmetric_product``) and its d x d Cholesky solve (``cholesky_solve``).

Products. On CPU, XLA runs a ``dot`` as a call into its matrix library, one thunk per product and
per step of a loop, which costs more than the arithmetic for the small operands of motor-control
problems. The same product as a broadcast multiply and a sum is plain elementwise work that XLA
fuses with the operations around it; past a few thousand multiply-adds the library wins, so larger
products stay dots (see docs/performance.md#fused_max).

Cholesky. For d <= ``UNROLLED_CHOLESKY_MAX`` the factorisation and the two triangular solves are
unrolled into elementwise operations that XLA fuses, instead of a LAPACK call per time step (and
per iteration of the box QP).

Switch back to library calls: the three thresholds below are read when a function is traced, so
setting ``FUSED_MAX = 0`` (every product a library dot) and ``UNROLLED_CHOLESKY_MAX = 0`` (every
Cholesky LAPACK's) before tracing gives the same mathematics without the kernels, for comparisons.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.linalg import cho_solve

__all__ = ["add_symmetric_product", "cholesky_solve", "matmul", "matmul_t", "small_matvec"]

# Products with at most this many multiply-adds, and this many columns, are fused: one library call
# against elementwise work that XLA fuses but recomputes in each consumer (docs/performance.md#fused_max).
FUSED_MAX = 4096
FUSED_MAX_COLUMNS = 128


def _fused(m: int, k: int, n: int) -> bool:
    return m * k * n <= FUSED_MAX and n <= FUSED_MAX_COLUMNS


def matmul(a, b):
    """a @ b for a [m, k] and b [k, n] or [k]."""
    m, k = a.shape
    n = b.shape[1] if b.ndim == 2 else 1
    if b.ndim == 1:
        return (_fused_matvec if _fused(m, k, n) else _dot_matvec)(a, b)
    return (_fused_matmat if _fused(m, k, n) else _dot_matmat)(a, b)


def matmul_t(a, b):
    """a' @ b for a [k, m] and b [k, n]. As a dot, a' is written to memory first: the barrier keeps
    XLA from folding the transpose into the product, whose transposed-operand form is several
    times slower on CPU for the small matrices of a step. Fused, the transpose is only indexing."""
    k, m = a.shape
    return (_fused_matmul_t if _fused(m, k, b.shape[1]) else _dot_matmul_t)(a, b)


def small_matvec(a, x):
    """a @ x over leading axes, for a [..., m, k] and x [..., k] with m, k a handful (the models'
    2 x 2 and 2 x 6 products): always fused, never a library dot, so that a model's dynamics stay
    elementwise work that XLA fuses with the rest of the step."""
    return _sum_matvec(a, x)


# The fused forms broadcast over leading batch axes, so they serve unbatched and batched operands.
def _sum_matvec(a, b):
    return jnp.sum(a * b[..., None, :], axis=-1)


def _sum_matmat(a, b):
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _sum_matmul_t(a, b):
    return jnp.sum(a[..., :, :, None] * b[..., :, None, :], axis=-3)


def _dot_matvec(a, b):
    return jnp.einsum("...mk,...k->...m", a, b)


def _dot_matmat(a, b):
    return jnp.einsum("...mk,...kn->...mn", a, b)


def _dot_matmul_t(a, b):
    # a' written to memory first, as for an unbatched dot (see matmul_t)
    return _dot_matmat(jax.lax.optimization_barrier(jnp.swapaxes(a, -1, -2)), b)


def _batchable(fused, dot):
    """``fused`` as a function whose vmap stays fused while the whole batch is small (the line
    search's 11 step sizes) and becomes one batched ``dot`` above ``FUSED_MAX`` multiply-adds: a
    batched dot is one library call for the whole batch, where the fused form would be one large
    elementwise loop (docs/performance.md#the-cpu-batching-rule). Nested vmaps (64 problems of 11
    step sizes each) count every batch axis: the batched product is again such a function, with
    the batch axis leading both operands."""
    @jax.custom_batching.custom_vmap
    def product(a, b):
        return fused(a, b)

    @product.def_vmap
    def rule(axis_size, in_batched, a, b):
        a, b = (x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape) for x, batched in zip((a, b), in_batched))
        multiply_adds = math.prod(a.shape) * (b.shape[-1] if b.ndim == a.ndim else 1)
        return (dot if multiply_adds > FUSED_MAX else product)(a, b), True

    # JAX cannot linearise a custom_vmap (reverse mode fails), so the product carries its own
    # derivative: bilinear, its tangent is two products in plain operations, which JAX transposes
    # and batches by itself (derivatives through the backward pass, ilqg/implicit.py)
    @jax.custom_jvp
    def differentiable(a, b):
        return product(a, b)

    @differentiable.defjvp
    def _tangent(primals, tangents):
        (a, b), (da, db) = primals, tangents
        return product(a, b), fused(da, b) + fused(a, db)

    return differentiable


_fused_matvec = _batchable(_sum_matvec, _dot_matvec)
_fused_matmat = _batchable(_sum_matmat, _dot_matmat)
_fused_matmul_t = _batchable(_sum_matmul_t, _dot_matmul_t)


def add_symmetric_product(R, M, W):
    """R + M'W + W'M for R [m, m] and M, W [d, m], as d rank-one updates: elementwise work that XLA
    fuses into one loop over R, run in place (a dot would write a second [m, m] array)."""
    for a in range(M.shape[0]):
        R = R + M[a][:, None] * W[a][None, :] + W[a][:, None] * M[a][None, :]
    return R


# Up to this d the factorisation is unrolled: a LAPACK call per step against fused elementwise work
# (docs/performance.md#unrolled_cholesky_max).
UNROLLED_CHOLESKY_MAX = 8


def cholesky_solve(H, rhs, unrolled_max: int | None = None):
    """(ok, H^{-1} rhs) for symmetric H [d, d] and rhs [d] or [d, m] by Cholesky; ok is False (and
    the result non-finite) when H is not numerically positive definite. Unrolled for d <=
    ``unrolled_max`` (default ``UNROLLED_CHOLESKY_MAX``)."""
    nd = H.shape[0]
    if nd > (UNROLLED_CHOLESKY_MAX if unrolled_max is None else unrolled_max):
        chol = jnp.linalg.cholesky(H)
        return jnp.all(jnp.isfinite(chol)), cho_solve((chol, True), rhs)
    low = [[None] * nd for _ in range(nd)]
    for j in range(nd):
        pivot = H[j, j] - sum(low[j][i] ** 2 for i in range(j))
        ok_j = pivot > 0.0
        low[j][j] = jnp.sqrt(jnp.where(ok_j, pivot, jnp.nan))
        ok = ok_j if j == 0 else ok & ok_j
        for i in range(j + 1, nd):
            low[i][j] = (H[i, j] - sum(low[i][m] * low[j][m] for m in range(j))) / low[j][j]
    y = []
    for i in range(nd):                                  # L y = rhs
        y.append((rhs[i] - sum(low[i][m] * y[m] for m in range(i))) / low[i][i])
    x = [None] * nd
    for i in reversed(range(nd)):                        # L' x = y
        x[i] = (y[i] - sum(low[m][i] * x[m] for m in range(i + 1, nd))) / low[i][i]
    return ok, jnp.stack(x)
