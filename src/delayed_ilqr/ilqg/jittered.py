"""iLQG for a plant whose input delay jitters (``Problem(..., delay_jitter=DelayJitter(...))``,
docs/derivation.md §21): the delay of the command acting at step k, l_k, is drawn independently
at every step from a known distribution p over 0..L.

The nominal is certainty-equivalent in the delay: it runs the plant under the mean acting command

    x_{k+1} = x_k + dt f(x_k, u_k, u_bar_k),      u_bar_k = sum_l p_l u_{k-l}      (u_k = 0 for k < 0)

(for dynamics affine in the acting command, the expected dynamics). Linearised there (eq. 3 with
ud = u_bar_k), the plant under the delay l is the LQG of ``lqg.jitter`` with B1 = dt f_ud and the
offsets delta_{k,l} = u_{k-l} - u_bar_k: the nominal command that acts when the delay is l departs
from the mean by delta, a disturbance that the nominal's own commands make. The backward pass is
``lqg.jitter``'s (the law over the L commands in flight, expectation over l_k inside the step);
its J(0) is the exact expected cost of the law on that linearisation.

One iteration: linearise at the nominal, the jittered backward pass with H + lambda I, roll out the
law with its feedforward scaled by every alpha of ``Options.alphas`` (clipped to the limits), keep
the candidate of least merit (`jittered_merit`: the jittered LQG's expected cost of the nominal
under zero feedforward, which the feedforward descends); accept when it decreases (lambda falls),
else lambda rises by ``reg_factor``. The iteration stops when the best step changes the merit by
less than ``tol_cost`` (relative, up or down: at the optimum no step decreases it), the feedforward is
below ``tol_grad`` (Tassa's measure, lambda < 1e-5), at ``max_iterations`` or when lambda passes
``reg_max``. The solve runs under ``jit`` and ``vmap``; it has no implicit derivative (the fixed-
delay solver's, ``ilqg.implicit``), so ``jax.grad`` through it is not supported. ``Options.method``
is not read: the pass is the structured one (its augmented reference is
``lqg.jittered_augmented_pass``), and ``max_alternations`` does not apply (no sensors). Limits are
enforced by clipping the commands in the rollouts (the gains are not box-constrained).
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..lqg.gains import boxed_gains, unconstrained_gains, unregularized_feedback
from ..lqg.jitter import jittered_scan
from ..lqg.law import augmented_feedback, delayed_law
from ..lqg.model import DelayedLQG
from ..options import Options
from ..problem import Problem
from ..solution import Policy, Solution, Status, Trace
from .linearize import _step, _terminal, trajectory_cost

__all__ = ["mean_acting", "jittered_rollout", "jittered_linearize", "jittered_merit", "solve_jittered"]

_RUNNING = -1
NEWTON_REG = 1e-5          # lambda below which a small feedforward certifies convergence (as the solver's)


def _probabilities(problem: Problem):
    return jnp.asarray(problem.delay_jitter.by_delay(), jnp.float64)


def mean_acting(problem: Problem, us):
    """u_bar_k = sum_l p_l u_{k-l} for k = 0..K-1 (zeros before t = 0): [K, d]."""
    p = _probabilities(problem)
    L, K = p.shape[0] - 1, us.shape[0]
    padded = jnp.concatenate([jnp.zeros((L,) + us.shape[1:], us.dtype), us])
    return sum(p[l] * padded[L - l:L - l + K] for l in range(L + 1))


def jittered_rollout(problem: Problem, us):
    """The nominal: the noise-free Euler rollout under the mean acting command, xs [K+1, n]."""
    def step(x, row):
        u, ud, t = row
        x_new = x + problem.dt * problem.dynamics_at(x, u, ud, t)
        return x_new, x_new

    _, xs = jax.lax.scan(step, problem.x0, (us, mean_acting(problem, us), problem.step_times(us.dtype)))
    return jnp.concatenate([problem.x0[None], xs])


def jittered_linearize(problem: Problem, xs, us):
    """(DelayedLQG at delay L, offsets [K, L+1, d]): eq. (3)-(4) at (x_k, u_k, u_bar_k), and
    delta_{k,l} = u_{k-l} - u_bar_k."""
    L, K = problem.delay_jitter.longest, us.shape[0]
    u_bar = mean_acting(problem, us)
    A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, N = jax.vmap(partial(_step, problem))(
        (xs[:-1], us, u_bar, problem.step_times(us.dtype)))
    final = _terminal(problem, xs[-1])
    lqg = DelayedLQG.from_traced(
        A=A, B0=B0, B1=B1, c=c, C0=C0, C1=C1, d_tilde=jnp.concatenate([d_tilde, final[0][None]]),
        d=jnp.concatenate([d, final[1][None]]), D=jnp.concatenate([D, final[2][None]]), e=e, E=E, N=N,
        delay_steps=L, delay_frame=None)
    padded = jnp.concatenate([jnp.zeros((L,) + us.shape[1:], us.dtype), us])
    past = jnp.stack([padded[L - l:L - l + K] for l in range(L + 1)], axis=1)          # [K, L+1, d] u_{k-l}
    return lqg, past - u_bar[:, None, :]


def _closed_loop(problem: Problem, xs, us, I, LM, alpha):
    """The nominal plant (mean acting command) under the law with its feedforward scaled by alpha,
    the commands clipped: (xs, us) of the new nominal."""
    L = problem.delay_jitter.longest
    p = _probabilities(problem)
    nd = problem.n_controls

    def step(carry, data):
        x, sent, nominal = carry                          # sent[i] = u_{k-L+i}, nominal[i] = u_bar_{k-L+i}
        x_bar, u_bar, Ik, LMk, t = data
        du = delayed_law(alpha * Ik, LMk, jnp.concatenate([x - x_bar, (sent - nominal).reshape(-1)]))
        u = jnp.clip(u_bar + du, problem.u_min, problem.u_max)
        acting = p[0] * u + (p[1:][::-1] @ sent if L > 0 else 0.0)
        x_new = x + problem.dt * problem.dynamics_at(x, u, acting, t)
        if L > 0:
            sent = jnp.concatenate([sent[1:], u[None]])
            nominal = jnp.concatenate([nominal[1:], u_bar[None]])
        return (x_new, sent, nominal), (x_new, u)

    zeros = jnp.zeros((L, nd), us.dtype)
    _, (x_new, u_new) = jax.lax.scan(step, (problem.x0, zeros, zeros),
                                     (xs[:-1], us, I, LM, problem.step_times(us.dtype)))
    return jnp.concatenate([problem.x0[None], x_new]), u_new


def jittered_merit(problem: Problem, xs, us, S, Phi, xs_bar):
    """(cost (2), merit) of a nominal: the merit is the jittered LQG's expected cost of the nominal
    under zero feedforward, the s_tilde recursion of §21 with I = 0 (derivation §12 for noise):

        merit = J(xs, us) + sum_k [ sum_j c_kj' S_{k+1} c_kj + sum_l p_l delta_kl' Phi_k delta_kl ]

    with delta_kl = u_{k-l} - u_bar_k the candidate's offsets, c_k = sqrt(dt) F(x_bar_k, u_k,
    u_bar_k)' (F at the states ``xs_bar`` of the linearisation, §12) and S [K+1, n, n], Phi
    [K, d, d] = B1' S_{k+1} B1 + sum_j C1_j' S_{k+1} C1_j held from the last backward pass."""
    cost = trajectory_cost(problem, xs, us)
    L, K = problem.delay_jitter.longest, us.shape[0]
    u_bar = mean_acting(problem, us)
    padded = jnp.concatenate([jnp.zeros((L,) + us.shape[1:], us.dtype), us])
    delta = jnp.stack([padded[L - l:L - l + K] for l in range(L + 1)], axis=1) - u_bar[:, None, :]
    extra = jnp.einsum("l,kla,kab,klb->", _probabilities(problem), delta, Phi, delta)
    if problem.noise is not None:
        F = jax.vmap(problem.noise_at)(xs_bar[:-1], us, u_bar, problem.step_times(us.dtype))      # [K, n, p]
        extra = extra + problem.dt * jnp.einsum("knp,knm,kmp->", F, S[1:], F)
    return cost, cost + extra


def _acting_curvature(lqg: DelayedLQG, S):
    """Phi_k = B1' S_{k+1} B1 + sum_j C1_j' S_{k+1} C1_j: [K, d, d] (the acting command's)."""
    return jnp.einsum("kna,knm,kmb->kab", lqg.B1, S[1:], lqg.B1) \
        + jnp.einsum("kpna,knm,kpmb->kab", lqg.C1, S[1:], lqg.C1)


class _State(NamedTuple):
    us: jax.Array
    xs: jax.Array
    cost: jax.Array
    reg: jax.Array
    iteration: jax.Array
    status: jax.Array
    trace: Trace


def _pass(problem: Problem, o: Options, xs, us, reg):
    """The jittered backward pass at the nominal with the fixed-delay solver's gain rules
    (``ilqg.backward``): with limits the feedforward solves each step's box QP and clamped commands
    get no feedback; with noise lambda regularises the feedforward only."""
    lqg, offsets = jittered_linearize(problem, xs, us)
    gains_fn, bounds = unconstrained_gains, None
    if problem.has_limits:
        gains_fn, bounds = partial(boxed_gains, margin=o.limit_margin), (problem.u_min - us, problem.u_max - us)
    if problem.noise is not None:
        gains_fn = unregularized_feedback(gains_fn)
    gains, value = jittered_scan(lqg, _probabilities(problem), offsets, reg, gains_fn, bounds)
    return gains, value, _acting_curvature(lqg, value.S)


def _iteration(problem: Problem, o: Options, aware: bool, st: _State) -> _State:
    gains, value, Phi = _pass(problem, o, st.xs, st.us, st.reg)
    pd = value.positive_definite & jnp.all(jnp.isfinite(gains.feedforward))
    LM = augmented_feedback(gains)
    alphas = jnp.asarray(o.alphas)
    xs_all, us_all = jax.vmap(lambda a: _closed_loop(problem, st.xs, st.us, gains.feedforward, LM, a))(alphas)
    if aware:
        score = partial(jittered_merit, problem, S=value.S, Phi=Phi, xs_bar=st.xs)
        costs, merits = jax.vmap(score)(xs_all, us_all)
        current = score(st.xs, st.us)[1]
    else:
        costs = merits = jax.vmap(partial(trajectory_cost, problem))(xs_all, us_all)
        current = st.cost
    merits = jnp.where(jnp.isfinite(merits) & pd, merits, jnp.inf)
    best = jnp.argmin(merits)
    accept = merits[best] < current
    gnorm = jnp.mean(jnp.max(jnp.abs(gains.feedforward) / (jnp.abs(st.us) + 1.0), axis=1))
    it = st.iteration + 1
    # converged: the best step changes the merit by less than tol_cost (relative), up or down
    converged_cost = pd & (jnp.abs(merits[best] - current) < o.tol_cost * jnp.abs(current))
    converged_grad = pd & (gnorm < o.tol_grad) & (st.reg < NEWTON_REG)
    reg = jnp.where(accept, jnp.where(st.reg / o.reg_factor < o.reg_min, 0.0, st.reg / o.reg_factor),
                    jnp.maximum(st.reg * o.reg_factor, o.reg_min))
    status = jnp.select([converged_grad, converged_cost, reg > o.reg_max, it >= o.max_iterations],
                        [Status.CONVERGED_GRADIENT, Status.CONVERGED_COST, Status.REGULARIZATION_LIMIT,
                         Status.MAX_ITERATIONS], _RUNNING).astype(jnp.int32)
    keep = accept & ~converged_grad
    us, xs = jnp.where(keep, us_all[best], st.us), jnp.where(keep, xs_all[best], st.xs)
    cost = jnp.where(keep, costs[best], st.cost)
    t = st.trace
    trace = Trace(cost=t.cost.at[it].set(cost), merit=t.merit.at[it].set(jnp.where(keep, merits[best], current)),
                  expected_reduction=t.expected_reduction.at[it].set(jnp.nan),
                  step_size=t.step_size.at[it].set(jnp.where(accept, alphas[best], 0.0)),
                  reg=t.reg.at[it].set(st.reg), grad_norm=t.grad_norm.at[it].set(gnorm))
    return _State(us, xs, cost, reg, it, status, trace)


@partial(jax.jit, static_argnames=("aware",))
def _solve_jittered(problem: Problem, u_init, options: Options, aware: bool = True) -> Solution:
    """The solve; ``aware=False`` scores the candidates by their nominal cost (2) alone, the
    comparison of benchmarks/jitter_merit.py."""
    us = jnp.clip(jnp.asarray(u_init, jnp.float64), problem.u_min, problem.u_max)
    xs = jittered_rollout(problem, us)
    cost = trajectory_cost(problem, xs, us)
    ok = jnp.isfinite(cost) & jnp.all(jnp.isfinite(xs))
    nan = jnp.full(options.max_iterations + 1, jnp.nan)
    trace = Trace(cost=nan.at[0].set(cost), merit=nan.at[0].set(cost), expected_reduction=nan, step_size=nan,
                  reg=nan, grad_norm=nan)
    init = _State(us, xs, cost, jnp.asarray(options.reg_init, jnp.float64), jnp.asarray(0, jnp.int32),
                  jnp.where(ok, _RUNNING, Status.NON_FINITE_INITIAL).astype(jnp.int32), trace)
    st = jax.lax.while_loop(lambda s: s.status == _RUNNING, partial(_iteration, problem, options, aware), init)
    gains, value, _ = _pass(problem, options, st.xs, st.us, 0.0)
    finite = value.positive_definite & jnp.all(jnp.isfinite(gains.state_feedback)) \
        & jnp.all(jnp.isfinite(gains.delay_feedback))
    status = jnp.where(finite | (st.status == Status.NON_FINITE_INITIAL), st.status, Status.NON_FINITE_GAINS)
    gains = jax.tree_util.tree_map(lambda g: jnp.where(finite, g, 0.0), gains)
    policy = Policy(st.xs, st.us, *gains)
    return Solution(x=st.xs, u=st.us, cost=st.cost, expected_cost=jnp.where(finite, value.expected_cost, jnp.nan),
                    status=status.astype(jnp.int32), iterations=st.iteration, policy=policy, trace=st.trace)


def solve_jittered(problem: Problem, u_init, options: Options) -> Solution:
    """The solve of a problem with ``delay_jitter`` (called by [`solve`][delayed_ilqr.solve], which
    checks the arguments). ``expected_cost`` is the exact expected cost of the returned law on the
    linearisation at the returned nominal, the jitter and the nominal's offsets included (a
    linearised prediction: `simulate` measures the plant's)."""
    return _solve_jittered(problem, u_init, options)
