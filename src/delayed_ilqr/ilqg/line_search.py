"""The line search: candidate step sizes scored on the nonlinear plant, the merit they minimise,
and the LQG's prediction of its change.

The candidate commands for a step size alpha are (eq. 6 applied to the nonlinear plant):

    u_k = clip(u_bar_k + alpha I_k + L_k (x_k - x_bar_k) + sum_i M_k^i (u_{k+i-l} - u_bar_{k+i-l}))

where u_{k+i-l} are the commands this rollout actually sent, so the law feeds back commands that
are already on their way but not yet acting (``candidates.nonlinear_step``). All alphas run at
once (``vmap``), scored as they run; only the best is rolled out again, so the line search stores
one trajectory.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._kernels.dense import matmul
from .._kernels.scan import packed_scan
from ..lqg.frame import SlotGains, slot_offsets
from ..lqg.model import DelayedLQG, merged_if_undelayed, stacked_dynamics
from ..problem import Problem
from .candidates import closed_loop_rollout, initial_frame, nominal_rows, nonlinear_step
from ..lqg.law import closed_loop_step
from .linearize import noise_columns, trajectory_cost

__all__ = ["candidate_scores", "noise_cost", "merit", "predicted_change", "LineSearch", "line_search", "no_step"]


def candidate_scores(problem: Problem, xs_bar, us_bar, gains: SlotGains, alphas, S):
    """`merit` of the closed-loop rollout (``candidates.closed_loop_rollout``) for every
    alpha [A], scored as the rollouts run: (cost [A], merit [A], finite [A]), finite when every
    state stayed finite. ``S``: [K+1, n, n] value Hessians of the backward pass (None without noise).

    One scan carries all A loops (the step is vmapped, not the scan) and stores no trajectory:
    each step adds its running cost (and, with noise, its term c'S c of `noise_cost`) to its
    loop's sums. Storing the candidates would hold A (n + d) numbers per step, several times the
    gains, and scoring them afterwards would copy them once more
    (docs/performance.md#candidates-scored-as-they-run-candidate_scores); the line
    search rolls the best step size out again instead (`line_search`).
    """
    noisy = problem.noise is not None
    dt = problem.dt

    def one(alpha, carry, data):
        y, running, noise, finite = carry
        row, S_next = data
        y_new, (x, u, ud, x_new) = nonlinear_step(problem, alpha, y, row)
        if noisy:       # c' S c summed over the noise columns, c = sqrt(dt) F at the nominal state
            F = problem.noise_at(row.x_bar, u, ud, row.t)                          # [n, p]
            noise = noise + dt * jnp.sum(F * matmul(S_next, F))
        return (y_new, running + problem.cost.running(x, u, row.t), noise, finite & jnp.all(jnp.isfinite(x_new)))

    step = jax.vmap(one, in_axes=(0, 0, None))
    A = alphas.shape[0]
    zero = jnp.zeros(A, us_bar.dtype)
    y0 = jnp.broadcast_to(initial_frame(problem, us_bar.dtype), (A, problem.n_states + problem.frame_steps
                                                                 * problem.n_controls))
    data = (nominal_rows(problem, xs_bar, us_bar, gains), S[1:] if noisy else None)
    (y, running, noise, finite), _ = packed_scan(lambda c, d: (step(alphas, c, d), ()),
                                                 (y0, zero, zero, jnp.ones(A, bool)), data,
                                                 pack_inputs=False)       # as in closed_loop_rollout
    cost = dt * running + jax.vmap(problem.cost.final, in_axes=(0, None))(y[:, :problem.n_states],
                                                                          problem.final_time)
    return cost, cost + noise, finite


def noise_cost(problem: Problem, xs, us, S):
    """sum_k sum_j c_{k,j}' S_{k+1} c_{k,j}: the LQG's noise cost of a nominal (S: [K+1, n, n])."""
    c = noise_columns(problem, xs, us)
    return jnp.einsum("kpn,knm,kpm->", c, S[1:], c)


def merit(problem: Problem, xs, us, S, xs_bar):
    """The quantity the line search minimises: eq. (2) on (xs, us) plus the noise cost.

    With the value Hessians S of the last backward pass fixed, this is the LQG's expected cost of
    the nominal under zero feedforward (s_tilde recursion with I = 0), so its stationary points are
    those of the noise-aware iteration (I = 0). Without noise it is the plain cost (2).

    The noise columns F(x, u, ud) are evaluated at the states ``xs_bar`` of the nominal the LQG was
    built on, not at ``xs``: the model (3) freezes F's dependence on x (it has no state-dependent
    noise term), so its feedforward descends this merit, and the first-order prediction of
    `predicted_change` is exact for it. Evaluated at the candidate's own states the merit has
    a gradient term (through dF/dx) that no step of the model accounts for; on the noisy arm the
    line search then rejected every step near the solution and the regularisation ran away
    (derivation §12).
    """
    cost = trajectory_cost(problem, xs, us)
    if problem.noise is None:
        return cost, cost
    return cost, cost + noise_cost(problem, xs_bar, us, S)


def predicted_change(lqg: DelayedLQG, gains: SlotGains, S):
    """(a, b) with merit(alpha) - merit(0) = alpha a + alpha^2 b under the LQG model.

    The linear model with du_k = alpha I_k + L_k dx_k + sum_i M_k^i du_{k+i-l} and dx_0 = 0 is
    linear in alpha: dx = alpha xi, du = alpha eta. Substituting into the quadratic cost (4) and the
    noise cost gives the exact quadratic in alpha (derivation §12). O(K (n^2 + n d + l d^2)).
    """
    l, nd, nx = lqg.frame_steps, lqg.n_controls, lqg.n_states
    lqg = merged_if_undelayed(lqg)      # with a frame and l = 0, B1 = C1 = 0: eta_d is then unused

    # The linear closed loop only (costs come after), on y = [xi, pending] in the slot frame:
    # one product for eta, one for xi_{k+1}.
    def step(y, row):
        slot, Z, gains = row

        def plant(xi, eta, eta_d):
            eta_d = jnp.zeros_like(eta) if eta_d is None else eta_d
            return matmul(Z, jnp.concatenate([xi, eta, eta_d])), eta, (xi, eta, eta_d)

        return closed_loop_step(y, slot, gains, plant, nx, delay=delay)

    K = lqg.horizon
    delay = None if lqg.delay_frame is None else lqg.delay_steps
    y, (xi, eta, eta_d) = packed_scan(step, jnp.zeros(nx + l * nd),
                                      (slot_offsets(K, l, nd), stacked_dynamics(lqg), gains))
    xiK = y[:nx]
    dc = jnp.einsum("kpnd,kd->kpn", lqg.C0, eta) + jnp.einsum("kpnd,kd->kpn", lqg.C1, eta_d)  # noise columns
    Sn = S[1:]
    a = 2 * (jnp.sum(xi * lqg.d[:-1]) + jnp.sum(eta * lqg.e)) + 2 * jnp.einsum("kpn,knm,kpm->", lqg.c, Sn, dc)
    b = (jnp.einsum("kn,knm,km->", xi, lqg.D[:-1], xi) + jnp.einsum("kd,kde,ke->", eta, lqg.E, eta)
         + 2 * jnp.einsum("kd,kdn,kn->", eta, lqg.N, xi) + jnp.einsum("kpn,knm,kpm->", dc, Sn, dc))
    return a + 2 * xiK @ lqg.d[-1], b + xiK @ lqg.D[-1] @ xiK


class LineSearch(NamedTuple):
    """Outcome of one parallel line search."""

    accepted: jax.Array          # bool
    xs: jax.Array                # best candidate
    us: jax.Array
    cost: jax.Array              # its cost (2)
    merit: jax.Array             # its merit
    alpha: jax.Array
    actual: jax.Array            # merit reduction achieved
    expected: jax.Array          # reduction predicted by the LQG model
    all_non_finite: jax.Array    # bool: every candidate rollout blew up


def no_step(xs, us, cost, merit_now) -> LineSearch:
    """The outcome of a line search that was not run (converged iteration, final pass)."""
    zero = jnp.zeros_like(merit_now)
    return LineSearch(jnp.asarray(False), xs, us, cost, merit_now, zero, zero, zero, jnp.asarray(False))


def line_search(problem: Problem, gains: SlotGains, S, xs, us, merit_now, alphas, z_min, predicted):
    """Tassa's parallel line search: all alphas at once, keep the best, accept on actual/expected > z_min.

    ``predicted``: the model's (a, b) of the backward pass (``lqg.structured.structured_slot_scan`` with
    ``predict=True``, or `predicted_change`). The candidates are scored as they run
    (`candidate_scores`) and the best one is rolled out again: the line search stores one
    trajectory, not one per alpha.
    """
    alphas = jnp.asarray(alphas)
    cand_cost, cand_merit, finite = candidate_scores(problem, xs, us, gains, alphas, S)
    finite = finite & jnp.isfinite(cand_merit)
    cand_merit = jnp.where(finite, cand_merit, jnp.inf)
    best = jnp.argmin(cand_merit)
    a, b = predicted
    alpha = alphas[best]
    expected = -(alpha * a + alpha ** 2 * b)
    actual = merit_now - cand_merit[best]
    z = jnp.where(expected > 0, actual / jnp.where(expected > 0, expected, 1.0), jnp.sign(actual))
    accepted = finite[best] & (z > z_min)
    best_xs, best_us = closed_loop_rollout(problem, xs, us, gains, alpha)
    return LineSearch(accepted, best_xs, best_us, cand_cost[best], cand_merit[best], alpha,
                      actual, expected, ~jnp.any(finite))
