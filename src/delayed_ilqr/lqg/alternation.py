"""Signal-dependent noise with delayed sensors: Todorov's alternation, with both delays.

With motor noise that grows with the command (C0, C1 != 0) the separation design of
`output_feedback` is not optimal: its filter assumes the noise of the nominal commands, and
its controller charges the noise its commands add at the full-state value function, as if the
controller saw it at once, while an estimator sees it l_s steps late and only through noisy
sensors. Todorov (2005) alternates between the controller for a fixed filter and the filter for a
fixed controller. Here both delays are handled without augmenting the state, and every step is
measured by the exact expected cost of the pair (the joint second moments of
[`output_feedback_cost`][delayed_ilqr.lqg.output_feedback_cost]), so the cost never increases (``docs/derivation.md`` §14):

* [`controller_sweep`][delayed_ilqr.lqg.controller_sweep]: for a fixed filter, a backward pass of the value function of the joint
  system zeta = (a, x_hat, eps, pending) (quadratic, exact under any law). The noise a command adds
  is charged at W_k, the curvature of the cost-to-go along a disturbance the loop has not seen: the
  state cost of the l_s steps before any sensor sees it, then the value function's eps block when
  it reaches the filter. Each step's law is Todorov's: the minimiser of that step's Q-function for
  each value of what the controller knows (x_hat, pending), taking a = x_hat and E[eps | x_hat,
  pending] = 0. The pass returns the new law's exact cost (its value at time 0).
* [`filter_step`][delayed_ilqr.lqg.filter_step]: the delayed Kalman filter for the motor noise the loop actually has, E[w_k w_k']
  under the current pair (Todorov's filter for a fixed controller).
* [`alternate`][delayed_ilqr.lqg.alternate]: both in turn from a starting pair (the separation design); a step is kept
  only when the exact cost does not rise, and the alternation stops when one lowers it by less
  than ``tol`` (relative).

The feedforward I_k is held (the nominal stays the solver's), and commands marked not ``free`` (at
a control limit, where iLQG gives no feedback) keep their zero feedback.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from .law import augmented_feedback
from .estimator import FilterGains, _delayed_kalman, _measured_rows, delayed_rows, transition_windows
from .exact import checked_gains
from .model import DelayedLQG, Gains, merged_if_undelayed
from .observation import DelayedObservation
from .output_feedback import JointMoments, _Blocks, _joint_moments

__all__ = ["Alternation", "controller_sweep", "filter_step", "alternate"]

def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


class Alternation(NamedTuple):
    """The pair after Todorov's alternation, and the exact expected costs along the way.

    Attributes:
        gains: the law on the estimate (feedforward as given; L, M redesigned).
        filter_gains: the delayed filter.
        expected_cost: [] the exact expected cost of the returned pair.
        error_covariance: [K+1, n, n] Cov(dx_k - x_hat_k) of its linear closed loop (exact).
        costs: [max_alternations + 1] the exact cost after each alternation (index 0: the starting
            pair); NaN after the last one run.
        alternations: [] the number of alternations run.
    """

    gains: Gains
    filter_gains: FilterGains
    expected_cost: jax.Array
    error_covariance: jax.Array
    costs: jax.Array
    alternations: jax.Array


def _unseen_state_cost(lqg: DelayedLQG, ls: int):
    """Omega_k = sum_{i=k+1}^{k+l_s} Phi(i, k+1)' D_i Phi(i, k+1) [K, n, n] (D_K the terminal
    weight): the state cost of a unit disturbance of dx_{k+1} over the l_s steps before any sensor
    has seen it. It is the covariance window of ``transition_windows`` in reversed time, with A'."""
    K, n = lqg.horizon, lqg.n_states
    A_rev = jnp.concatenate([jnp.eye(n, dtype=lqg.A.dtype)[None], jnp.swapaxes(lqg.A[:0:-1], 1, 2)])
    _, Omega_rev = transition_windows(A_rev, lqg.D[:0:-1], ls)
    return Omega_rev[K:0:-1]


def _selectors(blocks: _Blocks, nd: int, dtype):
    """S_o [n + l d, Nz], the observed part (x_hat, pending) of zeta; S_del [d, Nz], du_{k-l}."""
    n, Nz = blocks.n, blocks.size
    S_o = jnp.zeros((Nz - 2 * n, Nz), dtype).at[:n, n:2 * n].set(jnp.eye(n, dtype=dtype))
    S_o = S_o.at[n:, 3 * n:].set(jnp.eye(Nz - 3 * n, dtype=dtype))
    S_del = jnp.zeros((nd, Nz), dtype)
    if blocks.l > 0:
        S_del = S_del.at[:, 3 * n:3 * n + nd].set(jnp.eye(nd, dtype=dtype))
    return S_o, S_del


def _sweep_step(carry, data, *, blocks, sensory_delay, S_o, S_del):
    P, p, r, eps_buf = carry                 # V_{k+1} on zeta before dy_{k+1}; eps blocks of V_{k+1..k+l_s+1}
    (A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, N, I, LM, free, Kd, Kc, H, R, Phi, A_del, Omega) = data
    n, l, Nz = blocks.n, blocks.l, blocks.size
    nd = I.shape[0]
    dt = P.dtype
    # the time update zeta^- _{k+1} = Tz zeta_k + Tu du_k (the noise is charged through W below)
    move = B1 @ S_del
    Tz = jnp.zeros((Nz, Nz), dt)
    Tz = Tz.at[blocks.a()].set(move).at[blocks.a(), blocks.a()].add(A)
    Tz = Tz.at[blocks.b()].set(move).at[blocks.b(), blocks.b()].add(A)
    Tz = Tz.at[blocks.eps(), blocks.eps()].set(A_del)
    Tu = jnp.zeros((Nz, nd), dt).at[blocks.a()].set(B0).at[blocks.b()].set(B0)
    if l > 0:
        Tz = Tz.at[3 * n:Nz - nd, 3 * n + nd:].set(jnp.eye((l - 1) * nd, dtype=dt))
        Tu = Tu.at[Nz - nd:].set(jnp.eye(nd, dtype=dt))
    Tx = jnp.zeros((n, Nz), dt).at[:, blocks.a()].set(jnp.eye(n, dtype=dt)).at[:, blocks.eps()].set(Phi)
    # W_k: what a unit of motor noise of step k costs (unseen for l_s steps, then in eps)
    W = Omega + eps_buf[-1]
    C1z = jnp.einsum("pnd,dz->pnz", C1, S_del)
    # Q_k(zeta, du) = Hzz, Huz, Huu, hz, hu, h0 (stage + V_{k+1} + tr(W E[w w']))
    Huu = E + Tu.T @ P @ Tu + jnp.einsum("pnd,nm,pme->de", C0, W, C0)
    Huz = N @ Tx + Tu.T @ P @ Tz + jnp.einsum("pnd,nm,pmz->dz", C0, W, C1z)
    hu = e + Tu.T @ p + jnp.einsum("pnd,nm,pm->d", C0, W, c)
    Hzz = Tx.T @ D @ Tx + Tz.T @ P @ Tz + jnp.einsum("pnz,nm,pmy->zy", C1z, W, C1z)
    hz = Tx.T @ dv + Tz.T @ p + jnp.einsum("pnz,nm,pm->z", C1z, W, c)
    h0 = d_tilde + r + jnp.einsum("pn,nm,pm->", c, W, c)
    # Todorov's controller for a fixed filter: the minimiser of Q_k(zeta, du) over du for each value
    # of the observed part y = (x_hat, pending), with a_k = x_hat_k (the filter's prediction is its
    # estimate when Kc = Phi Kd) and E[eps_k | y] = 0 (its error is orthogonal to what it has seen).
    # Commands that are not free keep their row; the free ones see them as fixed.
    Huy = jnp.concatenate([Huz[:, blocks.a()] + Huz[:, blocks.b()], Huz[:, blocks.pending()]], axis=1)
    Huy = Huy + Huu @ jnp.where(free[:, None], 0.0, LM)
    H_free = jnp.where(free[:, None] & free[None, :], Huu, jnp.eye(nd, dtype=dt))
    LM_T = -jnp.linalg.solve(H_free, jnp.where(free[:, None], Huy, 0.0))
    LM_new = jnp.where(free[:, None], LM_T, LM)
    # V_k: Q_k under the new law, then the measurement update zeta^+ = U zeta^- + gain (G v)
    F = LM_new @ S_o
    P_plus = _sym(Hzz + F.T @ Huz + Huz.T @ F + F.T @ Huu @ F)
    p_plus = hz + F.T @ hu + Huz.T @ I + F.T @ Huu @ I
    r_plus = h0 + 2 * hu @ I + I @ Huu @ I
    gain = jnp.zeros((Nz, H.shape[0]), dt).at[blocks.a()].set(Phi @ Kd).at[blocks.b()].set(Kc).at[blocks.eps()].set(-Kd)
    U = jnp.eye(Nz, dtype=dt).at[:, blocks.eps()].add(gain @ H)
    P_new = _sym(U.T @ P_plus @ U)
    r_new = r_plus + jnp.sum((gain.T @ P_plus @ gain) * R)
    if sensory_delay > 0:
        eps_buf = jnp.concatenate([P_new[blocks.eps(), blocks.eps()][None], eps_buf[:-1]])
    else:
        eps_buf = P_new[blocks.eps(), blocks.eps()][None]
    return (P_new, U.T @ p_plus, r_new, eps_buf), LM_new


def _gains_from(LM, feedforward, n: int, l: int):
    K, nd = feedforward.shape
    M = jnp.moveaxis(LM[:, :, n:].reshape(K, nd, l, nd), 2, 1)
    return Gains(feedforward, LM[:, :, :n], M)


@jax.jit
def _controller_sweep(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains, free):
    lqg = merged_if_undelayed(lqg)
    n, nd, l, ls = lqg.n_states, lqg.n_controls, lqg.delay_steps, obs.delay_steps
    dt = lqg.A.dtype
    blocks = _Blocks(n, l, nd)
    S_o, S_del = _selectors(blocks, nd, dt)
    Phi, _ = transition_windows(lqg.A, jnp.zeros_like(lqg.A), ls)
    Kd, Kc = _measured_rows(fgains, obs)
    # V_K: the terminal cost of dx_K = a_K + Phi_K eps_K (the unseen part is charged through W)
    Tx = jnp.zeros((n, blocks.size), dt).at[:, blocks.a()].set(jnp.eye(n, dtype=dt)).at[:, blocks.eps()].set(Phi[-1])
    P_K = Tx.T @ lqg.D[-1] @ Tx
    eps_buf = jnp.zeros((ls + 1, n, n), dt).at[0].set(P_K[blocks.eps(), blocks.eps()])
    init = (P_K, Tx.T @ lqg.d[-1], lqg.d_tilde[-1], eps_buf)
    data = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E,
            lqg.N, gains.feedforward, augmented_feedback(gains), free, Kd, Kc, obs.H, obs.measurement_cov,
            Phi[:-1], delayed_rows(lqg.A, ls, jnp.eye(n)), _unseen_state_cost(lqg, ls))
    step = partial(_sweep_step, blocks=blocks, sensory_delay=ls, S_o=S_o, S_del=S_del)
    (_, _, r0, _), LM = jax.lax.scan(step, init, data, reverse=True)
    return _gains_from(LM, gains.feedforward, n, l), r0


def _all_free(gains: Gains):
    return jnp.ones(gains.feedforward.shape, bool)


def controller_sweep(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains,
                     free=None) -> tuple[Gains, jax.Array]:
    """Todorov's controller for the fixed filter ``fgains``: one backward pass (module docstring).

    Args:
        lqg: the plant.
        obs: its delayed sensors.
        gains: the current law (its feedforward is kept).
        fgains: the filter, held fixed.
        free: [K, d] bool, the commands whose feedback may change (default all); the others keep
            theirs.

    Returns:
        (the new law, its exact expected cost [] as the pass computes it: the value of the joint
        system at time 0, which equals [`output_feedback_cost`][delayed_ilqr.lqg.output_feedback_cost] of the new pair).
    """
    _precision.require_x64("lqg.controller_sweep")
    gains = checked_gains(lqg, gains)
    free = _all_free(gains) if free is None else jnp.asarray(free, bool)
    return _controller_sweep(lqg, obs, gains, fgains, free)


@jax.jit
def _filter_step(lqg: DelayedLQG, obs: DelayedObservation, moments: JointMoments) -> FilterGains:
    return _delayed_kalman(lqg, obs, _sym(moments.motor_cov), obs.measurement_cov)[0]


def filter_step(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains) -> FilterGains:
    """The delayed Kalman filter for the motor noise E[w_k w_k'] of the closed loop of the pair
    (``gains``, ``fgains``): Todorov's filter for a fixed controller."""
    _precision.require_x64("lqg.filter_step")
    return _filter_step(lqg, obs, _joint_moments(lqg, obs, checked_gains(lqg, gains), fgains))


class _Loop(NamedTuple):
    gains: Gains
    fgains: FilterGains
    moments: JointMoments
    costs: jax.Array
    i: jax.Array
    done: jax.Array


def _better(new, old, take):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(take, a, b), new, old)


def _alternation(lqg, obs, free, max_alternations: int, tol):
    """(the loop's body, the ``_Loop`` it starts from given the pair and ``run``)."""
    def body(s: _Loop):
        cost = s.moments.expected_cost
        # the filter for the noise this loop has, kept if the exact cost falls
        f_new = _filter_step(lqg, obs, s.moments)
        m_new = _joint_moments(lqg, obs, s.gains, f_new)
        take = m_new.expected_cost < cost
        fgains, moments = _better((f_new, m_new), (s.fgains, s.moments), take)
        # Todorov's controller for that filter, kept if the exact cost does not rise
        g_new, _ = _controller_sweep(lqg, obs, s.gains, fgains, free)
        m_new = _joint_moments(lqg, obs, g_new, fgains)
        take = m_new.expected_cost <= moments.expected_cost
        gains, moments = _better((g_new, m_new), (s.gains, moments), take)
        i = s.i + 1
        done = ~(moments.expected_cost < cost - tol * jnp.abs(cost)) | (i >= max_alternations)
        return _Loop(gains, fgains, moments, s.costs.at[i].set(moments.expected_cost), i, done)

    def init(gains, fgains, run):
        moments = _joint_moments(lqg, obs, gains, fgains)
        costs = jnp.full(max_alternations + 1, jnp.nan, lqg.A.dtype).at[0].set(moments.expected_cost)
        return _Loop(gains, fgains, moments, costs, jnp.asarray(0), (max_alternations == 0) | ~jnp.asarray(run))

    return body, init


def _result(s: _Loop) -> Alternation:
    return Alternation(s.gains, s.fgains, s.moments.expected_cost, s.moments.error_cov, s.costs, s.i)


@partial(jax.custom_jvp, nondiff_argnums=(5,))
def _alternate_differentiable(lqg, obs, gains, fgains, free, max_alternations: int, tol, run):
    """The alternation as a ``while_loop`` (it stops when done); its derivative is that of the same
    iterations as a ``scan`` (`_alternate_unrolled`), which reverse mode can transpose."""
    body, init = _alternation(lqg, obs, free, max_alternations, tol)
    return _result(jax.lax.while_loop(lambda s: ~s.done, body, init(gains, fgains, run)))


def _alternate_unrolled(lqg, obs, gains, fgains, free, max_alternations: int, tol, run):
    """The same alternations in a ``scan`` of ``max_alternations`` steps, those after the stop skipped."""
    body, init = _alternation(lqg, obs, free, max_alternations, tol)
    step = lambda s, _: (jax.lax.cond(s.done, lambda s: s, body, s), None)
    return _result(jax.lax.scan(step, init(gains, fgains, run), None, length=max_alternations)[0])


@_alternate_differentiable.defjvp
def _alternate_jvp(max_alternations, primals, tangents):
    unrolled = lambda lqg, obs, gains, fgains, free, tol, run: _alternate_unrolled(
        lqg, obs, gains, fgains, free, max_alternations, tol, run)
    return jax.jvp(unrolled, primals, tangents)


@partial(jax.jit, static_argnames=("max_alternations",))
def _alternate(lqg, obs, gains, fgains, free, max_alternations: int, tol, run=True):
    """``alternate``; with ``run`` false (a traced bool) the starting pair comes back as is."""
    return _alternate_differentiable(lqg, obs, gains, fgains, jnp.asarray(free), max_alternations,
                                     jnp.asarray(tol, lqg.A.dtype), jnp.asarray(run))


def alternate(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains, free=None,
              max_alternations: int = 20, tol: float = 1e-9) -> Alternation:
    """Todorov's alternation from the pair (``gains``, ``fgains``), usually the separation design.

    Each alternation runs [`filter_step`][delayed_ilqr.lqg.filter_step] (kept if the exact cost falls) and then
    [`controller_sweep`][delayed_ilqr.lqg.controller_sweep]; it stops when an alternation lowers the exact cost by less than
    ``tol`` times its value, or after ``max_alternations``. The exact cost never increases.
    ``free`` as in [`controller_sweep`][delayed_ilqr.lqg.controller_sweep].
    """
    _precision.require_x64("lqg.alternate")
    gains = checked_gains(lqg, gains)
    free = _all_free(gains) if free is None else jnp.asarray(free, bool)
    fgains = FilterGains(jnp.asarray(fgains.delayed_gain), jnp.asarray(fgains.current_gain))
    max_alternations = _validate.non_negative_int(max_alternations, "max_alternations")
    return _alternate(lqg, obs, gains, fgains, free, max_alternations, jnp.asarray(tol, lqg.A.dtype))
