"""Output feedback for the delayed LQG with delayed, noisy sensors.

The policy is Theorem 1's law acting on the delayed filter's estimate:

    du_k = I_k + L_k x_hat_k + sum_i M_k^i du_{k+i-l},      x_hat_k = E[dx_k | I_k]  (.estimator)

* [`separation_design`][delayed_ilqr.lqg.separation_design]: the law of [`backward_pass`][delayed_ilqr.lqg.backward_pass] plus [`delayed_kalman`][delayed_ilqr.lqg.delayed_kalman]. With
  additive noise this is the optimal causal policy (separation), and its expected cost is
  J(0) + sum_k tr(L_k' H_k L_k Sigma_k) ([`separation_cost`][delayed_ilqr.lqg.separation_cost]; ``docs/derivation.md`` §14).
* [`output_feedback_cost`][delayed_ilqr.lqg.output_feedback_cost]: the exact expected cost of *any* controller-estimator pair, by the
  second moments of the joint system zeta_k = (a_k, x_hat_k, eps_k, pending commands), 3n + l d
  entries, whatever l_s (§14): a_k is the filter's own prediction Phi_k x_del_k + (commands in
  flight), eps_k = dx_{k-l_s} - x_del_k, and dx_k = a_k + Phi_k eps_k + eta_k with eta_k, the noise
  of the last l_s steps, uncorrelated with zeta_k. Signal-dependent motor noise is included.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from .law import augmented_feedback
from .estimator import (FilterCovariances, FilterGains, _measured_rows, delayed_kalman, delayed_rows,
                        estimator_predict, estimator_update, transition_windows)
from .exact import checked_gains
from .model import DelayedLQG, Gains, Stage, Value, merged_if_undelayed
from .observation import DelayedObservation
from .stage import CostToGo, _action_terms
from .structured import backward_pass

__all__ = ["OutputFeedback", "OutputFeedbackRuns", "separation_design", "separation_cost", "output_feedback_cost",
           "simulate_output_feedback"]


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


class OutputFeedback(NamedTuple):
    """A controller-estimator pair and what it costs.

    Attributes:
        gains: the law (6) on the estimate ([`Gains`][delayed_ilqr.lqg.Gains]).
        filter_gains: the delayed filter ([`FilterGains`][delayed_ilqr.lqg.FilterGains]).
        value: the full-state cost-to-go of ``gains`` ([`Value`][delayed_ilqr.lqg.Value]).
        covariances: the filter's error covariances ([`FilterCovariances`][delayed_ilqr.lqg.FilterCovariances]).
        expected_cost: [] the exact expected cost of the closed loop (controller plus estimator).
    """

    gains: Gains
    filter_gains: FilterGains
    value: Value
    covariances: FilterCovariances
    expected_cost: jax.Array


def separation_design(lqg: DelayedLQG, obs: DelayedObservation) -> OutputFeedback:
    """Theorem 1's controller on the delayed Kalman filter's estimate, and its exact expected cost
    (the joint second moments, [`output_feedback_cost`][delayed_ilqr.lqg.output_feedback_cost]). Optimal among causal policies when
    the noise is additive (C0 = C1 = 0)."""
    gains, value = backward_pass(lqg)
    fgains, cov = delayed_kalman(lqg, obs)
    return OutputFeedback(gains, fgains, value, cov, output_feedback_cost(lqg, obs, gains, fgains))


@jax.jit
def _separation_cost(lqg: DelayedLQG, value: Value, gains: Gains, current):
    l = lqg.delay_steps
    stages = Stage(*(getattr(merged_if_undelayed(lqg), f) for f in Stage._fields))
    stages = stages._replace(d_tilde=stages.d_tilde[:-1], d=stages.d[:-1], D=stages.D[:-1])
    J_next = CostToGo(value.s_tilde[1:], value.s[1:], value.S[1:], value.r[1:], value.Rt[1:], value.R[1:])
    H = jax.vmap(lambda st, J: _action_terms(st, J, l)[0])(stages, J_next)
    L = gains.state_feedback
    return value.expected_cost + jnp.einsum("kan,kab,kbm,knm->", L, H, L, current[:-1])


def separation_cost(lqg: DelayedLQG, value: Value, gains: Gains, cov: FilterCovariances) -> jax.Array:
    """J(0) + sum_k tr(L_k' H_k L_k Sigma_k): the expected cost of the optimal full-state law
    (``gains``, ``value`` of [`backward_pass`][delayed_ilqr.lqg.backward_pass] without regularisation) acting on the optimal
    delayed filter's estimate, whose error covariance is ``cov.current``. Exact for additive
    noise; O(K (n^3 + l n^2 d + l^2 d^3)), against O(K (3n + l d)^3) for the joint moments."""
    return _separation_cost(lqg, value, gains, cov.current)


# -- the exact cost of any pair --------------------------------------------------------------------

class _Blocks(NamedTuple):
    """Column offsets of zeta = (a, x_hat, eps, pending) and selectors of its parts."""
    n: int
    l: int
    nd: int

    @property
    def size(self):
        return 3 * self.n + self.l * self.nd

    def a(self):
        return slice(0, self.n)

    def b(self):
        return slice(self.n, 2 * self.n)

    def eps(self):
        return slice(2 * self.n, 3 * self.n)

    def pending(self):
        return slice(3 * self.n, self.size)


def _measurement_update(mu, X, blocks, H, R, Kd, Kc, Phi):
    """zeta <- U zeta + V v with e = H eps + G v: a += Phi Kd e, x_hat += Kc e, eps -= Kd e."""
    Nz = blocks.size
    gain = jnp.zeros((Nz, H.shape[0]), mu.dtype)
    gain = gain.at[blocks.a()].set(Phi @ Kd).at[blocks.b()].set(Kc).at[blocks.eps()].set(-Kd)
    U = jnp.eye(Nz, dtype=mu.dtype).at[:, blocks.eps()].add(gain @ H)
    return U @ mu, _sym(U @ X @ U.T + gain @ R @ gain.T)


def _moments_of(T, t0, mu, X):
    """Mean and second moment of T zeta + t0."""
    m = T @ mu
    return m + t0, T @ X @ T.T + jnp.outer(m, t0) + jnp.outer(t0, m) + jnp.outer(t0, t0)


def _error_cov(blocks, Phi, mu, X, Pi):
    """Cov(dx_k - x_hat_k) [n, n], with dx_k - x_hat_k = a_k - x_hat_k + Phi_k eps_k + eta_k."""
    n = blocks.n
    eye = jnp.eye(n, dtype=mu.dtype)
    T = jnp.zeros((n, blocks.size), mu.dtype).at[:, blocks.a()].set(eye).at[:, blocks.b()].set(-eye)
    T = T.at[:, blocks.eps()].set(Phi)
    m = T @ mu
    return _sym(T @ X @ T.T - jnp.outer(m, m) + Pi)


def _joint_step(carry, data, *, blocks, sensory_delay):
    mu, X, total, Pi, qbuf = carry
    (k, A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, N, I, LM, Kd, Kc, H, R, Phi, Phi_next, A_del) = data
    n, l, ls, Nz = blocks.n, blocks.l, sensory_delay, blocks.size
    dt = mu.dtype
    mu, X = _measurement_update(mu, X, blocks, H, R, Kd, Kc, Phi)
    moments = (mu, X, _error_cov(blocks, Phi, mu, X, Pi))      # after the measurement, before the command
    # the stage cost, with dx = a + Phi eps + eta and du = I + L x_hat + M pending
    Tx = jnp.zeros((n, Nz), dt).at[:, blocks.a()].set(jnp.eye(n, dtype=dt)).at[:, blocks.eps()].set(Phi)
    Tu = jnp.zeros((I.shape[0], Nz), dt).at[:, blocks.b()].set(LM[:, :n]).at[:, blocks.pending()].set(LM[:, n:])
    Ex, Exx = _moments_of(Tx, jnp.zeros(n, dt), mu, X)
    Exx = Exx + Pi
    T_xu = jnp.concatenate([Tx, Tu])
    Exu, Exuxu = _moments_of(T_xu, jnp.concatenate([jnp.zeros(n, dt), I]), mu, X)
    Eu, Euu, Eux = Exu[n:], Exuxu[n:, n:], Exuxu[n:, :n]
    total = total + d_tilde + 2 * dv @ Ex + jnp.sum(D * Exx) + 2 * e @ Eu + jnp.sum(E * Euu) + 2 * jnp.sum(N * Eux)
    # the motor noise of this step: columns c_j + C0_j du_k + C1_j du_{k-l}, affine in zeta
    S_del = jnp.zeros((I.shape[0], Nz), dt)
    if l > 0:
        S_del = S_del.at[:, 3 * n:3 * n + I.shape[0]].set(jnp.eye(I.shape[0], dtype=dt))
    g = c + C0 @ I                                                         # [p, n]
    Gm = jnp.einsum("pnd,dz->pnz", C0, Tu) + jnp.einsum("pnd,dz->pnz", C1, S_del)
    Q_now = jnp.einsum("pn,pm->nm", g, g) + jnp.einsum("pn,pm->nm", Gm @ mu, g) \
        + jnp.einsum("pn,pm->nm", g, Gm @ mu) + jnp.einsum("pnz,zy,pmy->nm", Gm, X, Gm)
    # the noise that reaches eps: that of step k - l_s (buffered), uncorrelated with zeta_k
    if ls == 0:
        Q_eps = Q_now
    else:
        slot = k % ls
        Q_eps = qbuf[slot]
        qbuf = qbuf.at[slot].set(Q_now)
        Pi = _sym(A @ Pi @ A.T + Q_now - Phi_next @ Q_eps @ Phi_next.T)
    # the time update: a, x_hat move with the commands; eps with the delayed-time transition
    T = jnp.zeros((Nz, Nz), dt)
    move = B0 @ Tu + B1 @ S_del
    T = T.at[blocks.a()].set(move).at[blocks.a(), blocks.a()].add(A)
    T = T.at[blocks.b()].set(move).at[blocks.b(), blocks.b()].add(A)
    T = T.at[blocks.eps(), blocks.eps()].set(A_del)
    t0 = jnp.zeros(Nz, dt).at[blocks.a()].set(B0 @ I).at[blocks.b()].set(B0 @ I)
    if l > 0:
        nd = I.shape[0]
        T = T.at[3 * n:Nz - nd, 3 * n + nd:].set(jnp.eye((l - 1) * nd, dtype=dt))
        T = T.at[Nz - nd:].set(Tu)
        t0 = t0.at[Nz - nd:].set(I)
    mu, X = _moments_of(T, t0, mu, X)
    X = _sym(X.at[blocks.eps(), blocks.eps()].add(Q_eps))
    return (mu, X, total, Pi, qbuf), moments + (Q_now,)


class JointMoments(NamedTuple):
    """The closed loop of a controller-estimator pair, step by step (`joint_moments`).

    Attributes:
        mean: [K, 3n + l d] E[zeta_k] after the measurement dy_k, before du_k.
        second: [K, 3n + l d, 3n + l d] E[zeta_k zeta_k'] there (raw, not centred).
        error_cov: [K+1, n, n] Cov(dx_k - x_hat_k), the estimation error of the loop (row K: the
            terminal state against the filter's prediction from I_{K-1}); with additive noise it is
            the Kalman filter's Sigma_k (14.3) when the filter is the optimal one.
        motor_cov: [K, n, n] E[w_k w_k'], the covariance of the motor noise of step k under the loop
            (signal-dependent noise included).
        expected_cost: [] the exact expected cost, as [`output_feedback_cost`][delayed_ilqr.lqg.output_feedback_cost].
    """

    mean: jax.Array
    second: jax.Array
    error_cov: jax.Array
    motor_cov: jax.Array
    expected_cost: jax.Array


@jax.jit
def _joint_moments(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains) -> JointMoments:
    lqg = merged_if_undelayed(lqg)
    K, n, nd, l, ls = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.delay_steps, obs.delay_steps
    dt = lqg.A.dtype
    blocks = _Blocks(n, l, nd)
    Phi, _ = transition_windows(lqg.A, jnp.zeros_like(lqg.A), ls)
    Kd, Kc = _measured_rows(fgains, obs)
    data = (jnp.arange(K), lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1],
            lqg.e, lqg.E, lqg.N, gains.feedforward, augmented_feedback(gains), Kd, Kc, obs.H, obs.measurement_cov,
            Phi[:-1], Phi[1:], delayed_rows(lqg.A, ls, jnp.eye(n)))
    init = (jnp.zeros(blocks.size, dt), jnp.zeros((blocks.size,) * 2, dt), jnp.asarray(0.0, dt),
            jnp.zeros((n, n), dt), jnp.zeros((max(ls, 1), n, n), dt))
    step = partial(_joint_step, blocks=blocks, sensory_delay=ls)
    (mu, X, total, Pi, _), (mus, Xs, errs, Qs) = jax.lax.scan(step, init, data)
    Tx = jnp.zeros((n, blocks.size), dt).at[:, blocks.a()].set(jnp.eye(n, dtype=dt)).at[:, blocks.eps()].set(Phi[-1])
    Ex, Exx = _moments_of(Tx, jnp.zeros(n, dt), mu, X)
    total = total + lqg.d_tilde[-1] + 2 * lqg.d[-1] @ Ex + jnp.sum(lqg.D[-1] * (Exx + Pi))
    errs = jnp.concatenate([errs, _error_cov(blocks, Phi[-1], mu, X, Pi)[None]])
    return JointMoments(mus, Xs, errs, Qs, total)


@jax.jit
def _output_feedback_cost(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains):
    return _joint_moments(lqg, obs, gains, fgains).expected_cost


def output_feedback_cost(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains) -> jax.Array:
    """Exact E[J(0)] of the law ``gains`` acting on the estimate of the delayed filter ``fgains``.

    The second moments of zeta_k = (a_k, x_hat_k, eps_k, du_{k-l}..du_{k-1}) are propagated
    through the closed loop (``docs/derivation.md`` §14): O(K (3n + l d)^3), whatever l_s. Any
    gains are allowed (rows k < l_s of ``fgains`` are ignored: nothing has arrived), and the motor
    noise may depend on the commands (C0, C1).
    """
    _precision.require_x64("lqg.output_feedback_cost")
    fgains = FilterGains(jnp.asarray(fgains.delayed_gain), jnp.asarray(fgains.current_gain))
    return _output_feedback_cost(lqg, obs, checked_gains(lqg, gains), fgains)


# -- Monte Carlo of the closed loop ----------------------------------------------------------------

class OutputFeedbackRuns(NamedTuple):
    """Monte Carlo trials of the linear closed loop with delayed sensors and the delayed filter.

    Attributes: dx [n_trials, K+1, n]; x_hat [n_trials, K, n] the estimates E[dx_k | I_k];
    du [n_trials, K, d]; cost [n_trials] (eq. 4 summed over k = 0..K per trial).
    """

    dx: jax.Array
    x_hat: jax.Array
    du: jax.Array
    cost: jax.Array


def _trial(key, lqg, obs, gains, fgains):
    K, n, nd, p, l, ls = (lqg.horizon, lqg.n_states, lqg.n_controls, lqg.n_noise, lqg.delay_steps,
                          obs.delay_steps)
    dt = lqg.A.dtype
    key_w, key_v = jax.random.split(key)
    xi = jax.random.normal(key_w, (K, p), dt)
    v = jax.random.normal(key_v, (K, obs.G.shape[2]), dt)
    Kd, Kc = _measured_rows(fgains, obs)
    delayed = (delayed_rows(lqg.A, ls, jnp.eye(n)), delayed_rows(lqg.B0, ls, 0.0), delayed_rows(lqg.B1, ls, 0.0))

    def step(carry, data):
        dx, states, x_hat_prior, x_tilde, sent = carry       # states[0] = dx_{k-l_s}; sent: du_{k-l_s-l-1}..du_{k-1}
        (A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, N, I, LM, Kdk, Kck, H, G, xik, vk, Ad, B0d, B1d) = data
        dy = H @ states[0] + G @ vk
        x_hat, x_del = estimator_update(x_hat_prior, x_tilde, dy, H, Kdk, Kck)
        pending = sent[ls + 1:].reshape(-1)                   # du_{k-l} .. du_{k-1}
        du = I + LM @ jnp.concatenate([x_hat, pending])
        sent = jnp.concatenate([sent[1:], du[None]])          # du_{k-l_s-l} .. du_k
        du_del = sent[ls]
        cost = d_tilde + 2 * dx @ dv + dx @ D @ dx + 2 * du @ e + du @ E @ du + 2 * du @ N @ dx
        dx_new = A @ dx + B0 @ du + B1 @ du_del + xik @ (c + C0 @ du + C1 @ du_del)
        prior = estimator_predict(x_hat, x_del, sent, (A, B0, B1), (Ad, B0d, B1d), l, ls)
        states = jnp.concatenate([states[1:], dx_new[None]])
        return (dx_new, states) + prior + (sent,), (dx, x_hat, du, cost)

    data = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E,
            lqg.N, gains.feedforward, augmented_feedback(gains), Kd, Kc, obs.H, obs.G, xi, v) + delayed
    init = (jnp.zeros(n, dt), jnp.zeros((ls + 1, n), dt), jnp.zeros(n, dt), jnp.zeros(n, dt),
            jnp.zeros((ls + l + 1, nd), dt))
    (dxK, *_), (dx, x_hat, du, cost) = jax.lax.scan(step, init, data)
    final = lqg.d_tilde[-1] + 2 * dxK @ lqg.d[-1] + dxK @ lqg.D[-1] @ dxK
    return jnp.concatenate([dx, dxK[None]]), x_hat, du, jnp.sum(cost) + final


@partial(jax.jit, static_argnames=("n_trials",))
def _simulate_output_feedback(lqg, obs, gains, fgains, n_trials: int, key):
    lqg = merged_if_undelayed(lqg)
    runs = jax.vmap(lambda k: _trial(k, lqg, obs, gains, fgains))(jax.random.split(key, n_trials))
    return OutputFeedbackRuns(*runs)


def simulate_output_feedback(lqg: DelayedLQG, obs: DelayedObservation, gains: Gains, fgains: FilterGains,
                             n_trials: int, seed: int = 0) -> OutputFeedbackRuns:
    """Monte Carlo of the linear closed loop: plant (3), sensors ``obs``, the delayed filter
    ``fgains`` and the law ``gains`` on its estimate; vectorised over trials."""
    _precision.require_x64("lqg.simulate_output_feedback")
    n_trials = _validate.positive_int(n_trials, "n_trials")
    fgains = FilterGains(jnp.asarray(fgains.delayed_gain), jnp.asarray(fgains.current_gain))
    return _simulate_output_feedback(lqg, obs, checked_gains(lqg, gains), fgains, n_trials,
                                     jax.random.PRNGKey(seed))
