"""Derivatives of a converged solve with respect to the problem's arrays, by implicit differentiation
of the optimality conditions at the solution (docs/derivation.md §16).

The solver's nominal u* [K, d] is a root of the stationarity conditions ``F(u, theta) = 0``
(`stationarity`), theta being the problem's leaves (x0, the cost's arrays or ``params``, the
limits, the fields of a dynamics or noise callable registered as a pytree, e.g. the models' noise
scale ``sigma_u``). The tangent of u* solves

    dF/du du = -dF/dtheta dtheta                                                    (16.1)

by GMRES on exact products with dF/du, preconditioned by the Gauss-Newton delayed LQ solve at the
solution (`preconditioner`: the structured backward pass of Theorem 1 on the linearisation,
and the linear closed loop forward). Everything else the solve returns (x, cost, the policy's
gains, expected_cost) is a differentiable function of (u*, theta). F and these outputs are
linearised together, once (``jax.linearize`` of `_at_solution`: one rollout and one
differentiated backward pass), and that one linear map gives (16.1)'s right-hand side, its
products and the outputs' tangent. Reverse mode transposes this (the Krylov solve through
``jax.lax.custom_linear_solve``), so a gradient costs a few backward passes, not the iterations of
the solve.

Without noise, F is the gradient of the cost (2) on the free commands and dF/du is its exact,
symmetric Hessian (the dynamics' second derivatives included, which the Gauss-Newton backward pass
leaves out). With noise, the nominal is the fixed point of "minimise cost +
noise cost with the value Hessians S frozen" (derivation §12), F is the gradient of that merit
with S = S(u, theta) from the backward pass at u, and dF/du is not symmetric. Commands
at a limit with the gradient pushing outward (within the solver's margin of it, by the KKT
conditions: `fixed_commands`) are fixed there: their derivative is that of the limit.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..lqg.boxqp import free_solve
from ..lqg.frame import SlotGains, from_slots, slot_offsets
from ..lqg.gains import margin_width, unconstrained_gains
from ..lqg.model import merged_if_undelayed
from ..lqg.structured import structured_slot_scan
from ..options import Options
from ..problem import Problem
from ..solution import Policy, Solution, Status
from ..lqg.law import closed_loop_step
from .line_search import noise_cost
from .linearize import linearize, rollout, step_models, trajectory_cost

__all__ = ["stationarity", "fixed_commands", "value_at", "preconditioner", "implicit_tangent",
           "differentiable", "KRYLOV_TOL", "KRYLOV_MAXITER", "RESIDUAL_CHECK"]

# The Krylov solve of (16.1) stops at this relative (preconditioned) residual; with the
# Gauss-Newton preconditioner it takes a few iterations (docs/performance.md#krylov_tol).
KRYLOV_TOL = 1e-10
KRYLOV_MAXITER = 50
# A tangent whose residual in (16.1) exceeds this (relative, GMRES's own estimate) is NaN: the
# Krylov solve failed.
RESIDUAL_CHECK = 1e-6


# -- the optimality conditions -------------------------------------------------------------------

def _near_limits(problem: Problem, us, margin: float):
    """([K, d] bool, [K, d] bool): commands within ``margin`` (times the width of the box, or times
    1 for a half-infinite one) of a finite lower, resp. upper, limit: the candidates for being held."""
    lo, hi = problem.u_min, problem.u_max
    width = hi - lo
    eps = margin * jnp.where(jnp.isfinite(width), width, 1.0)
    near_lo = jnp.isfinite(lo) & (us - lo <= eps)
    return near_lo, jnp.isfinite(hi) & (hi - us <= eps) & ~near_lo


def _effort_curvature(problem: Problem, us):
    """[K, d] the diagonal of the running cost's Hessian in the commands, dt d^2 l / du_i^2: the scale
    that turns a command's distance to its limit into a gradient. It leaves out the dynamics' part
    of the Hessian of eq. (2); the test it serves separates gradients that differ by orders of
    magnitude, for which any positive scale of the right size will do."""
    xs = rollout(problem, us)
    hessian = jax.vmap(jax.hessian(problem.cost.running, argnums=1))(xs[:-1], us, problem.step_times(us.dtype))
    return problem.dt * jnp.diagonal(hessian, axis1=1, axis2=2)


def _held_sides(problem: Problem, us, margin: float):
    """([K, d] bool at_lo, [K, d] bool at_hi): the commands the optimality conditions (KKT) at u
    hold at their lower, resp. upper, limit. Distance alone does not decide it. A command within
    the margin is held when the gradient G of the solver's objective (`_cost_gradient`)
    pushes it outward by at least what its distance to the limit accounts for: G_out >= h dist,
    with h the effort's curvature (`_effort_curvature`). At the limit (dist = 0) that is a
    multiplier G_out >= 0. The others are free: an interior optimum (G = 0) that merely lies
    close to a limit solves (16.1) like any other free command (derivation §16: such commands
    made the six-muscle arm's tangent wrong at 50 ms while they were held)."""
    if not problem.has_limits:
        none = jnp.zeros(us.shape, bool)
        return none, none
    near_lo, near_hi = _near_limits(problem, us, margin)
    us = jax.lax.stop_gradient(us)
    G = jax.lax.stop_gradient(_cost_gradient(problem, us, margin))
    h = jax.lax.stop_gradient(_effort_curvature(problem, us))
    at_lo = near_lo & (G >= h * (us - problem.u_min))
    at_hi = near_hi & (-G >= h * (problem.u_max - us))
    return at_lo, at_hi


def _limit_values(problem: Problem, at_lo, at_hi):
    """[K, d] the limit a held command sits at (0 where free), differentiable in the limits."""
    lo = jnp.where(jnp.isfinite(problem.u_min), problem.u_min, 0.0)
    hi = jnp.where(jnp.isfinite(problem.u_max), problem.u_max, 0.0)
    return jnp.where(at_lo, lo, jnp.where(at_hi, hi, 0.0))


def fixed_commands(problem: Problem, us, margin: float):
    """([K, d] bool fixed, [K, d] bound): the commands held at a limit by the optimality conditions
    at u (`_held_sides`: within ``margin`` of the limit and pushed outward by the gradient),
    and the limit's value (0 where free). These have the derivative of the limit; the others solve
    (16.1)."""
    at_lo, at_hi = _held_sides(problem, us, margin)
    return at_lo | at_hi, _limit_values(problem, at_lo, at_hi)


def _masked_gains(free_of):
    """A gain rule (``lqg.gains``) with a given free set: du_f = -(H_ff)^{-1} (g + G y)_f, zero on
    the others; ``free_of(bounds) -> [d] bool``. At a converged nominal this is the box rule's
    outcome (``lqg.gains.boxed_gains``: I = 0, no feedback on commands at a limit), written without
    its iterative QP, so that JAX can differentiate it in reverse mode."""
    def gains(H, reg, g, G, bounds, warm=None):
        free = free_of(bounds)
        H = H + reg * jnp.eye(H.shape[0], dtype=H.dtype)
        I, Kfb = free_solve(H, free, g), free_solve(H, free, G)
        return jnp.all(jnp.isfinite(Kfb)) & jnp.all(jnp.isfinite(I)), I, Kfb
    return gains


def _solver_free(margin):
    """The solver's feedback set (``lqg.gains.boxed_gains``): farther than
    ``lqg.gains.margin_width`` from both limits."""
    def free(bounds):
        lower, upper = bounds
        eps = margin_width(margin, lower, upper)
        return (lower < -eps) & (upper > eps)
    return free


def value_at(problem: Problem, xs, us, margin: float):
    """The unregularised backward pass at the nominal (xs, us), differentiably: (gains, s_tilde
    [K], s [K, n], S [K+1, n, n]). With limits, commands at a limit get no feedback, as in the
    solver's pass at a converged nominal."""
    kw = dict(gains_fn=unconstrained_gains)
    if problem.has_limits:
        kw = dict(gains_fn=_masked_gains(_solver_free(margin)), bounds=(problem.u_min - us, problem.u_max - us))
    models = step_models(problem, xs, us)
    gains, (s_tilde, s, S), _ = structured_slot_scan(models, 0.0, store_value=False, store_S=True, **kw)
    return gains, s_tilde, s, jnp.concatenate([S, models.terminal[2][None]])


def _cost_gradient(problem: Problem, us, margin: float):
    """G(u, theta): the gradient of the cost (2) in the commands, or, with noise, of the merit
    cost + sum c' S c with S from the backward pass at u and F's state frozen at u's rollout
    (derivation §12): the fixed point of the noise-aware iteration is G = 0 on the free commands."""
    xs = rollout(problem, us)
    S = None if problem.noise is None else value_at(problem, xs, us, margin)[3]
    return _merit_gradient(problem, xs, us, S)


def _merit_gradient(problem: Problem, xs, us, S):
    """`_cost_gradient` given u's rollout xs and the value Hessians S at u (None without noise)."""
    if problem.noise is None:
        return jax.grad(lambda v: trajectory_cost(problem, rollout(problem, v), v))(us)
    merit = lambda v: trajectory_cost(problem, rollout(problem, v), v) + noise_cost(problem, xs, v, S)
    return jax.grad(merit)(us)


def stationarity(problem: Problem, us, fixed, bound, margin: float):
    """F(u, theta) [K, d], zero at the solution: G (of `_cost_gradient`) on the free commands,
    evaluated with the fixed ones at their limits, and u - limit on the fixed ones. Written so that
    dF/du is symmetric where the Hessian is: v -> [v_fixed; H_ff v_free]."""
    bound = jnp.where(fixed, bound, 0.0)
    held = jnp.where(fixed, bound, us)
    return jnp.where(fixed, us - bound, _cost_gradient(problem, held, margin))


# -- the preconditioner: the Gauss-Newton delayed LQ solve ------------------------------------------

def _linear_closed_loop(lqg, gains: SlotGains):
    """The commands du [K, d] of the delayed law run on the LQ dynamics from dx_0 = 0, nothing pending."""
    nx, nd, l = lqg.n_states, lqg.n_controls, lqg.frame_steps
    K = lqg.horizon
    delay = None if lqg.delay_frame is None else lqg.delay_steps
    lqg = merged_if_undelayed(lqg)      # for l = 0, B1 = 0 (a framed l = 0 reads a slot that has acted)

    def step(y, row):
        A, B0, B1, I, Fb, slot = row

        def plant(x, du, du_delayed):
            acting = B0 @ du if du_delayed is None else B0 @ du + B1 @ du_delayed
            return A @ x + acting, du, du

        return closed_loop_step(y, slot, SlotGains(I, Fb), plant, nx, delay=delay)

    y0 = jnp.zeros(nx + l * nd, lqg.A.dtype)
    _, du = jax.lax.scan(step, y0, (lqg.A, lqg.B0, lqg.B1, gains.feedforward, gains.feedback,
                                     slot_offsets(K, l, nd)))
    return du


def preconditioner(lqg, fixed):
    """r [K, d] -> the Gauss-Newton solve: on the free commands the open-loop minimiser of the
    delayed LQ model ``lqg`` at the nominal (`linearize`) with linear terms -r (eq. 4:
    e = -r / 2, d = 0, no noise columns c), i.e. H_GN^{-1} r over the free commands with the fixed
    ones held; r itself on the fixed ones. One structured backward pass and one linear closed loop
    per application."""
    lqg = lqg.replace(c=jnp.zeros_like(lqg.c), d=jnp.zeros_like(lqg.d), d_tilde=jnp.zeros_like(lqg.d_tilde))
    held = (jnp.where(fixed, 0.0, -jnp.inf), jnp.where(fixed, 0.0, jnp.inf))
    gains_fn = _masked_gains(lambda bounds: bounds[0] < bounds[1])

    def apply(r):
        model = lqg.replace(e=jnp.where(fixed, 0.0, -0.5 * r))
        gains, _, _ = structured_slot_scan(model, 0.0, store_value=False, store_S=False, gains_fn=gains_fn,
                                           bounds=held)
        return jnp.where(fixed, r, _linear_closed_loop(model, gains))

    return apply


# -- (16.1) ------------------------------------------------------------------------------------

def gmres(A, b, tol: float, maxiter: int):
    """(x, rho): x with |A x - b| <= tol |b|, or the best in ``maxiter`` steps, and its relative
    residual rho = |A x - b| / |b| as the Givens recurrence gives it (|g_k| / |b|, the residual itself
    up to rounding: the Arnoldi basis is orthogonal to working precision; NaN if a product was).
    GMRES from x = 0 (Arnoldi with Gram-Schmidt run twice, the least-squares problem kept
    triangular by Givens rotations).
    ``jax.scipy.sparse.linalg.gmres`` cannot serve here: it wraps itself in
    ``custom_linear_solve``, which would transpose A as a primal function (the backward pass's
    products cannot be), and its batched form runs every step of a restart whatever the residual."""
    shape, b = b.shape, b.ravel()
    m = maxiter
    beta = jnp.linalg.norm(b)
    safe = lambda v, n: v / jnp.where(n > 0, n, 1.0)
    V = jnp.zeros((m + 1, b.size), b.dtype).at[0].set(safe(b, beta))

    def rotate(i, h, cs, sn):
        hi, hj = h[i], h[i + 1]
        return h.at[i].set(cs[i] * hi + sn[i] * hj).at[i + 1].set(cs[i] * hj - sn[i] * hi)

    def step(carry):
        k, V, R, g, cs, sn = carry
        w = A(V[k].reshape(shape)).ravel()
        live = jnp.arange(m + 1) <= k
        h = jnp.where(live, V @ w, 0.0)
        w = w - h @ V
        h2 = jnp.where(live, V @ w, 0.0)
        w, h = w - h2 @ V, h + h2
        norm = jnp.linalg.norm(w)
        V = V.at[k + 1].set(safe(w, norm))
        h = jax.lax.fori_loop(0, k, lambda i, h: rotate(i, h, cs, sn), h.at[k + 1].set(norm))
        r = jnp.hypot(h[k], h[k + 1])
        c, s = jnp.where(r > 0, h[k] / jnp.where(r > 0, r, 1.0), 1.0), jnp.where(r > 0, h[k + 1] / jnp.where(r > 0, r, 1.0), 0.0)
        cs, sn = cs.at[k].set(c), sn.at[k].set(s)
        R = R.at[:, k].set(h[:m].at[k].set(r))
        g = g.at[k + 1].set(-s * g[k]).at[k].set(c * g[k])
        return k + 1, V, R, g, cs, sn

    zeros = jnp.zeros(m, b.dtype)
    init = (jnp.asarray(0), V, jnp.zeros((m, m), b.dtype), jnp.zeros(m + 1, b.dtype).at[0].set(beta), zeros, zeros)
    k, V, R, g, _, _ = jax.lax.while_loop(lambda c: (c[0] < m) & (jnp.abs(c[3][c[0]]) > tol * beta), step, init)
    used = jnp.arange(m) < k
    R = jnp.where(used[None, :] & used[:, None], R, jnp.eye(m, dtype=b.dtype))
    y = jax.scipy.linalg.solve_triangular(R, jnp.where(used, g[:m], 0.0), lower=False)
    return (y @ V[:m]).reshape(shape), jnp.abs(g[k]) / jnp.where(beta > 0, beta, 1.0)


def implicit_tangent(lqg, fixed, rhs, matvec, symmetric: bool):
    """du* [K, d] solving (16.1), dF/du du* = -rhs, with ``rhs`` = dF/dtheta dtheta [K, d] and
    ``matvec`` v -> dF/du v (linear), preconditioned by the Gauss-Newton solve of the model ``lqg``
    at the nominal (`preconditioner`), ``fixed`` [K, d] the held commands; NaN where the
    Krylov solve missed `RESIDUAL_CHECK`. Linear in ``rhs`` and transposable (reverse mode)."""
    precondition = preconditioner(lqg, fixed)

    def checked(solved):
        # GMRES's residual, not one more product A x - b: it is that residual to rounding, and a
        # product costs a differentiated backward pass (docs/performance.md#krylov_tol)
        x, residual = solved
        miss = ~(residual <= RESIDUAL_CHECK)
        return x * jnp.where(miss, jnp.nan, 1.0)

    def krylov(mv, b):
        # left-preconditioned, P A x = P b: P A is close to I, and the stopping test is in the
        # preconditioned residual (the plain residual of the Hessian's products carries rounding of
        # cond(H) eps, ~1e-8 on the arm, far above KRYLOV_TOL)
        pa = lambda v: precondition(mv(v))
        pb = precondition(b)
        return checked(gmres(pa, pb, KRYLOV_TOL, KRYLOV_MAXITER))

    def krylov_transposed(vm, b):
        # the transposed system A' w = b right-preconditioned, A' P z = b, w = P z: A' P = (P A)' is
        # the forward operator's transpose and as well conditioned, where P A' (left) is similar to
        # it only through P (cond ~ cond(H)), and a small preconditioned residual left errors of
        # 1e-4 in w (the noisy arm)
        ap = lambda z: vm(precondition(z))
        return precondition(checked(gmres(ap, b, KRYLOV_TOL, KRYLOV_MAXITER)))

    return jax.lax.custom_linear_solve(matvec, -rhs, krylov, transpose_solve=krylov_transposed, symmetric=symmetric)


# -- the differentiable solve ---------------------------------------------------------------------

def _at_solution(problem: Problem, us, at_lo, at_hi, margin: float):
    """(F [K, d], outputs) as functions of (theta, u*), linearised once for (16.1) and the outputs'
    tangent together: F of `stationarity`, and the outputs (x, cost, expected_cost, the
    Policy's gains), what the tangent of a solution is the tangent of. Without limits F's rollout
    and backward pass (S) are the outputs' (u_held = u), computed once."""
    xs = rollout(problem, us)
    gains, s_tilde, _, S = value_at(problem, xs, us, margin)
    outputs = xs, trajectory_cost(problem, xs, us), s_tilde[0], from_slots(gains, problem.n_states)
    if problem.has_limits:
        F = stationarity(problem, us, at_lo | at_hi, _limit_values(problem, at_lo, at_hi), margin)
    else:
        F = _merit_gradient(problem, xs, us, None if problem.noise is None else S)
    return F, outputs


def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, jax.dtypes.float0)


def differentiable(plain_solve):
    """``plain_solve(problem, u_init, options) -> Solution`` made differentiable in ``problem``
    (forward and reverse mode, under ``vmap`` too): the primal is ``plain_solve`` unchanged; the
    tangent is (16.1) and the outputs' recomputation at (theta, u*). Tangents of an unconverged
    solve (``status`` not converged) are NaN: its nominal is not a root of F. The options are
    an argument, not a constant of the rule: their numbers may be traced (``Options`` is a
    pytree), and the solution is not differentiated in them (their tangents are ignored)."""
    @jax.custom_jvp
    def run(problem, u_init, options: Options):
        return plain_solve(problem, u_init, options)

    @run.defjvp
    def run_jvp(primals, tangents):
        problem, u_init, options = primals
        dproblem = tangents[0]
        sol = run(problem, u_init, options)
        margin = options.limit_margin
        at_lo, at_hi = _held_sides(problem, sol.u, margin)
        # one linearisation at (theta, u*) serves the right-hand side of (16.1), its products and the
        # outputs' tangent: their transposes (reverse mode) share its residuals, those of one rollout
        # and one differentiated backward pass (docs/performance.md#krylov_tol)
        _, linear = jax.linearize(lambda p, u: _at_solution(p, u, at_lo, at_hi, margin), problem, sol.u)
        no_dproblem = jax.tree_util.tree_map(_zero_tangent, problem)
        rhs = linear(dproblem, jnp.zeros_like(sol.u))[0]
        du = implicit_tangent(linearize(problem, sol.x, sol.u), at_lo | at_hi, rhs,
                              lambda v: linear(no_dproblem, v)[0], problem.noise is None)
        dx, dcost, dexpected, dgains = linear(dproblem, du)[1]
        ok = (sol.status == Status.CONVERGED_GRADIENT) | (sol.status == Status.CONVERGED_COST)
        # a factor, not a select: the tangent must stay linear, and JAX's transpose of
        # where(ok, t, nan) would drop the constant NaN (reverse mode would report zeros)
        flag = jnp.where(ok, 1.0, jnp.nan)
        unreliable = lambda t: t * flag
        dsol = Solution(x=dx, u=du, cost=dcost, expected_cost=dexpected, status=_zero_tangent(sol.status),
                        iterations=_zero_tangent(sol.iterations),
                        policy=Policy(dx, du, *dgains),
                        trace=jax.tree_util.tree_map(_zero_tangent, sol.trace))
        dsol = dsol._replace(x=unreliable(dsol.x), u=unreliable(dsol.u), cost=unreliable(dsol.cost),
                             expected_cost=unreliable(dsol.expected_cost),
                             policy=jax.tree_util.tree_map(unreliable, dsol.policy))
        return sol, dsol

    return run
