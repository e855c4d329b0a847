"""Box-constrained quadratic programming by projected Newton, in pure JAX.

Solves:

    minimise    0.5 x' H x + g' x
    subject to  lower <= x <= upper          (elementwise; bounds may be -inf / +inf)

with the projected-Newton method of Tassa, Mansard & Todorov, "Control-limited differential
dynamic programming", ICRA 2014 (Algorithm 2; the reference implementation is their MATLAB
``boxQP.m``, whose defaults and status codes are kept here).

Algorithm (one outer iteration, starting from ``x_init`` clipped into the box):

1. Stop with status 4 if the last step improved the objective by less than
   ``min_rel_improve * |old value|``.
2. Gradient ``grad = g + H x``; clamped set ``(x == lower & grad > 0) | (x == upper & grad < 0)``,
   free set = its complement. Stop with status 6 if every dimension is clamped.
3. Cholesky factor of ``H_ff`` (the free-free block); stop with status -1 if it fails
   (``H`` not positive definite on the free subspace).
4. Stop with status 5 if ``|grad_f| < min_grad``.
5. Newton step on the free subspace with the clamped coordinates held:
   ``search_f = -H_ff^{-1} (g + H x_c)_f - x_f`` where ``x_c`` is ``x`` with its free entries
   zeroed; ``search_c = 0``. Stop with status 0 if ``search . grad >= 0`` (no descent; should
   not happen for PD ``H_ff``).
6. Projected Armijo back-tracking: ``step = 1, step_dec, step_dec^2, ...`` until
   ``(f(clip(x + step search)) - f(x)) / (step * search . grad) >= armijo``; status 2 (after
   accepting the last trial point, as ``boxQP.m`` does) if ``step < min_step``.

After ``max_iter`` accepted steps without another stop, status 1. When no bound is finite the
loop is skipped and the exact Newton point ``-H^{-1} g`` is returned with status 3 (-1 if
``H`` is not PD).

Fixed shapes: the free set is a boolean mask, never a gather. The "free Hessian" is
``where(free_i & free_j, H, I)`` -- block-diagonal (after a permutation) with the free block
and an identity on the clamped dimensions -- so its Cholesky factor always exists when
``H_ff`` is PD and solves against it are masked. Both loops are ``jax.lax.while_loop``, so
`box_qp` can be jitted, vmapped (batched while loops), and called inside ``lax.scan``.

Differences from ``boxQP.m`` (all deliberate, none affecting the minimiser):

* The returned ``free`` mask is recomputed at the returned ``x`` (``boxQP.m`` returns the mask
  of its last iteration's start, which is stale when it stops on status 1, 2 or 4).
* ``iterations`` counts accepted steps (a warm start at the solution gives 0).
* The Cholesky factor is recomputed every iteration (``boxQP.m`` re-factorises only when the
  clamped set changes; the factor is identical either way).
* Status 1 is reported only when no other stop fired (``boxQP.m`` overwrites a stop that fires
  on the last allowed iteration with 1).
* Non-finite entries of the clipped ``x_init`` are replaced by ``clip(0, lower, upper)``.

The factor itself is not returned: use `free_solve` with the returned ``free`` mask to
get ``-H_ff^{-1} rhs_f`` (e.g. the feedback gains of control-limited DDP).
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._kernels.dense import cholesky_solve

__all__ = [
    "BoxQPResult",
    "box_qp",
    "free_solve",
    "STATUS_MESSAGES",
]

#: Human-readable meaning of `BoxQPResult.status` (the codes of ``boxQP.m``).
STATUS_MESSAGES = {
    -1: "Hessian is not positive definite",
    0: "No descent direction found",
    1: "Maximum main iterations exceeded",
    2: "Maximum line-search iterations exceeded",
    3: "No bounds, returning Newton point",
    4: "Improvement smaller than tolerance",
    5: "Gradient norm smaller than tolerance",
    6: "All dimensions are clamped",
}


class BoxQPResult(NamedTuple):
    """Result of `box_qp` (batched leading axes under ``vmap``).

    Attributes:
        x: ``[d]`` the minimiser of ``0.5 x'Hx + g'x`` subject to ``lower <= x <= upper``.
        free: ``[d]`` bool, True where no bound is active at ``x`` (i.e. NOT
            ``(x == lower & grad > 0) | (x == upper & grad < 0)``); these are the feedback rows
            a control-limited DDP caller keeps (see `free_solve`).
        status: int scalar, as ``boxQP.m``: -1 Hessian not PD on the free set, 0 no descent
            direction, 1 max iterations, 2 max line-search steps, 3 no finite bounds (exact
            Newton point), 4 improvement below tolerance, 5 free gradient below tolerance,
            6 all dimensions clamped. 3-6 are successful terminations. See
            `STATUS_MESSAGES`.
        iterations: int scalar, number of accepted projected-Newton steps.
    """

    x: jax.Array
    free: jax.Array
    status: jax.Array
    iterations: jax.Array


# The box QP's factorisations are unrolled up to this d, LAPACK above: its loops refactor at every
# iteration, so its break-even is lower than the recursion's (docs/performance.md#boxqp-_unrolled_max).
_UNROLLED_MAX = 4


def _masked_solve(H: jax.Array, free: jax.Array, rhs: jax.Array):
    """(ok, solve(where(free_i & free_j, H, I), rhs)) by Cholesky; ok is False, and the result
    non-finite, when ``H_ff`` is not positive definite."""
    mask = free[:, None] & free[None, :]
    eye = jnp.eye(H.shape[-1], dtype=H.dtype)
    return cholesky_solve(jnp.where(mask, H, eye), rhs, _UNROLLED_MAX)


def _objective(H, g, x):
    return x @ g + 0.5 * x @ (H @ x)


def _clamped(x, grad, lower, upper):
    return ((x == lower) & (grad > 0)) | ((x == upper) & (grad < 0))


@jax.jit
def free_solve(H: jax.Array, free: jax.Array, rhs: jax.Array) -> jax.Array:
    """``-(H_ff)^{-1} rhs_f`` on the free rows, zeros on the clamped rows.

    Args:
        H: ``[d, d]`` symmetric matrix, positive definite on the free block.
        free: ``[d]`` bool mask (e.g. `BoxQPResult.free`).
        rhs: ``[d]`` or ``[d, m]``; its clamped rows are ignored.

    Returns:
        Array shaped like ``rhs``: ``out_f = -solve(H_ff, rhs_f)``, ``out_c = 0`` (exact zeros,
        never NaN). Uses the masked Cholesky factor of ``where(free_i & free_j, H, I)``, so the
        free rows are NaN if ``H_ff`` is not positive definite. For an all-False mask the result
        is all zeros.

    In control-limited DDP (Tassa et al. 2014, eq. 15) the feedback gain is
    ``K = free_solve(Quu, free, Qux)``: zero rows for the clamped controls.
    """
    H = jnp.asarray(H)
    free = jnp.asarray(free, dtype=bool)
    rhs = jnp.asarray(rhs)
    dtype = jnp.result_type(H, rhs, jnp.float32)
    H = H.astype(dtype)
    rhs = rhs.astype(dtype)
    fmask = free if rhs.ndim == 1 else free[:, None]
    _, sol = _masked_solve(H, free, jnp.where(fmask, rhs, 0.0))
    return jnp.where(fmask, -sol, 0.0)


class _Problem(NamedTuple):
    H: jax.Array
    g: jax.Array
    lower: jax.Array
    upper: jax.Array


class _Settings(NamedTuple):
    max_iter: jax.Array
    min_grad: jax.Array
    min_rel_improve: jax.Array
    step_dec: jax.Array
    min_step: jax.Array
    armijo: jax.Array


class _State(NamedTuple):
    """The projected Newton loop's state; ``it`` counts accepted steps."""

    it: jax.Array
    x: jax.Array
    value: jax.Array
    oldvalue: jax.Array
    status: jax.Array
    done: jax.Array


def _newton_iteration(qp: _Problem, opt: _Settings, state: _State) -> _State:
    """One iteration of the module docstring's algorithm: stop tests, then a projected Newton step."""
    H, g, lower, upper = qp
    it, x, value, oldvalue, _, _ = state

    small_improve = (it > 0) & ((oldvalue - value) < opt.min_rel_improve * jnp.abs(oldvalue))
    oldvalue = value

    grad = g + H @ x
    clamped = _clamped(x, grad, lower, upper)
    free = ~clamped
    all_clamped = jnp.all(clamped)

    gnorm = jnp.linalg.norm(jnp.where(free, grad, 0.0))
    small_grad = gnorm < opt.min_grad

    x_clamped = jnp.where(clamped, x, 0.0)
    grad_clamped = g + H @ x_clamped
    pd, newton = _masked_solve(H, free, -jnp.where(free, grad_clamped, 0.0))
    not_pd = ~pd
    search = jnp.where(free, newton - x, 0.0)
    sdotg = search @ grad
    no_descent = ~(sdotg < 0)  # also catches NaN

    # Same priority as boxQP.m: 4, then 6, then -1, then 5, then 0.
    status = jnp.select(
        [small_improve, all_clamped, not_pd, small_grad, no_descent],
        [4, 6, -1, 5, 0],
        default=-2,  # -2: keep going (internal only)
    ).astype(jnp.int32)
    go = status == -2
    xc, vc, ls_failed = _line_search(qp, opt, x, oldvalue, search, sdotg, go)

    status = jnp.where(go & ls_failed, 2, status).astype(jnp.int32)
    x = jnp.where(go, xc, x)
    value = jnp.where(go, vc, value)
    it = it + go.astype(it.dtype)
    done = ~go | ls_failed
    return _State(it, x, value, oldvalue, status, done)


def _line_search(qp: _Problem, opt: _Settings, x, oldvalue, search, sdotg, go):
    """Projected Armijo back-tracking from step 1: (x, value, failed) at the accepted (or last) step.
    Inactive lanes (``go`` False) do no work: ``go`` gates the loop."""
    H, g, lower, upper = qp
    safe_sdotg = jnp.where(go, sdotg, -1.0)

    def trial(step):
        xc = jnp.clip(x + step * search, lower, upper)
        return xc, _objective(H, g, xc)

    def ls_cond(ls):
        step, _, vc, failed = ls
        insufficient = ~((vc - oldvalue) / (step * safe_sdotg) >= opt.armijo)
        return go & (~failed) & insufficient

    def ls_body(ls):
        step, _, _, _ = ls
        step = step * opt.step_dec
        xc, vc = trial(step)
        return step, xc, vc, step < opt.min_step

    one = jnp.ones((), x.dtype)
    xc1, vc1 = trial(one)
    _, xc, vc, ls_failed = jax.lax.while_loop(ls_cond, ls_body, (one, xc1, vc1, jnp.zeros((), bool)))
    return xc, vc, ls_failed


@jax.jit
def box_qp(
    H: jax.Array,
    g: jax.Array,
    lower: jax.Array,
    upper: jax.Array,
    x_init: jax.Array,
    max_iter=100,
    min_grad=1e-8,
    min_rel_improve=1e-8,
    step_dec=0.6,
    min_step=1e-22,
    armijo=0.1,
) -> BoxQPResult:
    """Minimise ``0.5 x'Hx + g'x`` subject to ``lower <= x <= upper`` (projected Newton).

    Tassa, Mansard & Todorov, ICRA 2014, Algorithm 2 / ``boxQP.m`` (see the module docstring for
    the iteration and the small deliberate differences). Pure JAX with fixed shapes: jit-, vmap-
    and scan-compatible (already jitted; the options are traced, so changing them does not
    recompile).

    Args:
        H: ``[d, d]`` symmetric, positive definite (at least on the free subspaces visited).
        g: ``[d]`` linear term.
        lower, upper: ``[d]`` (or broadcastable) bounds, ``-inf`` / ``inf`` for none;
            ``lower <= upper`` is assumed.
        x_init: ``[d]`` warm start; clipped into the box first.
        max_iter: maximum number of accepted Newton steps (100).
        min_grad: stop when the norm of the free gradient is below this (1e-8).
        min_rel_improve: stop when a step improves the objective by less than this times its
            magnitude (1e-8).
        step_dec: line-search step decrease factor (0.6).
        min_step: line search gives up below this step (1e-22).
        armijo: fraction of the linear decrease the line search requires (0.1).

    Returns:
        `BoxQPResult` ``(x, free, status, iterations)``. With status -1 (``H`` not PD on
        the free set) ``x`` is the last iterate (finite; the clipped ``x_init`` when no bound
        is finite) and no exception is raised.
    """
    H = jnp.asarray(H)
    g = jnp.asarray(g)
    dtype = jnp.result_type(H, g, jnp.float32)
    H = H.astype(dtype)
    g = g.astype(dtype)
    d = g.shape[-1]
    lower = jnp.broadcast_to(jnp.asarray(lower, dtype), (d,))
    upper = jnp.broadcast_to(jnp.asarray(upper, dtype), (d,))
    x_init = jnp.broadcast_to(jnp.asarray(x_init, dtype), (d,))

    max_iter = jnp.asarray(max_iter, jnp.int32)
    min_grad = jnp.asarray(min_grad, dtype)
    min_rel_improve = jnp.asarray(min_rel_improve, dtype)
    step_dec = jnp.asarray(step_dec, dtype)
    min_step = jnp.asarray(min_step, dtype)
    armijo = jnp.asarray(armijo, dtype)

    x0 = jnp.clip(x_init, lower, upper)
    x0 = jnp.where(jnp.isfinite(x0), x0, jnp.clip(jnp.zeros_like(x0), lower, upper))
    value0 = _objective(H, g, x0)

    # --- no finite bound: exact Newton point (status 3), or status -1 -----------------------
    no_bounds = jnp.all(jnp.isinf(lower) & jnp.isinf(upper))
    full_pd, x_newton = cholesky_solve(H, -g, _UNROLLED_MAX)

    # --- projected Newton loop -----------------------------------------------------------------
    problem = _Problem(H, g, lower, upper)
    settings = _Settings(max_iter, min_grad, min_rel_improve, step_dec, min_step, armijo)
    cond = lambda state: (~state.done) & (state.it < max_iter)
    init = _State(jnp.zeros((), jnp.int32), x0, value0, value0, jnp.asarray(3, jnp.int32), no_bounds)
    it, x, _, _, status, done = jax.lax.while_loop(cond, partial(_newton_iteration, problem, settings), init)
    status = jnp.where(done, status, 1).astype(jnp.int32)  # loop ran out of iterations

    # no-bounds branch
    x = jnp.where(no_bounds & full_pd, x_newton, x)
    status = jnp.where(no_bounds, jnp.where(full_pd, 3, -1), status).astype(jnp.int32)

    grad = g + H @ x
    free = ~_clamped(x, grad, lower, upper)
    return BoxQPResult(x=x, free=free, status=status, iterations=it)
