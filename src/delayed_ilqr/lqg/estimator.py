"""The delayed Kalman filter, structured like the controller: no state augmentation.

The information for du_k is dy_{l_s..k} (measurements of dx_0..dx_{k-l_s}), the commands already
sent and dx_0 = 0. So the filter is an ordinary Kalman filter *in delayed time* j = k - l_s, whose
estimate E[dx_{k-l_s} | I_k] is carried forward l_s steps with the linearised dynamics and the
commands already sent (``docs/derivation.md`` §14):

    x_tilde_k = A_{k-l_s-1} x_del_{k-1} + B0 du_{k-l_s-1} + B1 du_{k-l_s-1-l}    predicted dx_{k-l_s}
    e_k       = dy_k - H_k x_tilde_k                                             innovation
    x_del_k   = x_tilde_k + Kd_k e_k                                             E[dx_{k-l_s} | I_k]
    x_hat_k   = A_{k-1} x_hat_{k-1} + B0 du_{k-1} + B1 du_{k-1-l} + Kc_k e_k     E[dx_k | I_k]

with Kd_k the delayed-time Kalman gain and Kc_k = Phi_k Kd_k its transport to the present,
Phi_k = A_{k-1} ... A_{k-l_s}. Per step the gains cost O(n^3 + m^3 + n^2 m) and the transports
Phi_k (and the covariance Pi_k of the noise that entered after k - l_s) O(n^3 log l_s), by doubling;
the augmented filter on [dx_k, ..., dx_{k-l_s}] costs O((n (l_s + 1))^3) per step.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import _precision
from .model import DelayedLQG, merged_if_undelayed
from .observation import DelayedObservation

__all__ = ["FilterGains", "FilterCovariances", "transition_windows", "delayed_kalman", "delayed_rows",
           "estimator_update", "estimator_predict", "filter_estimates"]


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


class FilterGains(NamedTuple):
    """The gains of the delayed filter (rows k < l_s, and columns of rows between two samples, are
    zero: no measurement has arrived).

    Attributes:
        delayed_gain: [K, n, m] Kd_k, the innovation's gain on the estimate of dx_{k-l_s}.
        current_gain: [K, n, m] Kc_k, its gain on the estimate of dx_k (Phi_k Kd_k when optimal).
    """

    delayed_gain: jax.Array
    current_gain: jax.Array


class FilterCovariances(NamedTuple):
    """Second moments of the optimal delayed filter's errors.

    Attributes:
        prior: [K, n, n] Cov(dx_{k-l_s} | I_{k-1}), before dy_k.
        posterior: [K, n, n] Cov(dx_{k-l_s} | I_k).
        innovation: [K, m, m] S_k = H P_prior H' + G G', the covariance of e_k (rows k < l_s: G G').
        current: [K+1, n, n] Sigma_k = Cov(dx_k | I_k) = Phi_k P_posterior Phi_k' + Pi_k; row K is
            that of the terminal state given I_{K-1}.
        transport: [K+1, n, n] Phi_k = Phi(k, k - l_s).
        fresh: [K+1, n, n] Pi_k, the covariance of the noise that entered dx_{k-l_s+1}..dx_k.
    """

    prior: jax.Array
    posterior: jax.Array
    innovation: jax.Array
    current: jax.Array
    transport: jax.Array
    fresh: jax.Array


def _compose(later, earlier):
    """Two consecutive stretches of transitions (Phi, Pi) -> the stretch that covers both."""
    Pl, Ql = later
    Pe, Qe = earlier
    return Pl @ Pe, Pl @ Qe @ jnp.swapaxes(Pl, -1, -2) + Ql


def _shifted(chunks, by):
    """chunks[p - by] at index p; the empty stretch (I, 0) where p < by."""
    P, Q = chunks
    n = P.shape[1]
    eye = jnp.broadcast_to(jnp.eye(n, dtype=P.dtype), (by, n, n))
    return (jnp.concatenate([eye, P[:-by]]), jnp.concatenate([jnp.zeros_like(eye), Q[:-by]]))


def transition_windows(A, Q, window: int):
    """Phi_k = A_{k-1} ... A_{k-w} and Pi_k = sum_{j=k-w}^{k-1} Phi(k, j+1) Q_j Phi(k, j+1)' for k = 0..K.

    Transitions before time 0 are (I, 0): the state stays at x0. Computed by doubling: stretches of
    2^b transitions are composed from two of 2^{b-1}, so the cost is O(K n^3 log w), not O(K n^3 w).

    Args:
        A: [K, n, n] transitions; Q: [K, n, n] covariances of the noise they add; window: w >= 0.

    Returns:
        (Phi [K+1, n, n], Pi [K+1, n, n]).
    """
    K, n = A.shape[0], A.shape[1]
    w = min(window, K)                  # before time 0 nothing moves: Phi(k, k - w) = Phi(k, 0) for w >= k
    eye = jnp.broadcast_to(jnp.eye(n, dtype=A.dtype), (w + 1, n, n))
    # stretch of one transition ending at padded position p (time p - w): transition p - 1
    chunk = (jnp.concatenate([eye, A]), jnp.concatenate([jnp.zeros_like(eye), Q]))
    result = (jnp.broadcast_to(jnp.eye(n, dtype=A.dtype), (K + w + 1, n, n)), jnp.zeros((K + w + 1, n, n), A.dtype))
    covered, size = 0, 1
    while size <= w:
        if w & size:                    # the stretch before the part covered so far
            result = _compose(result, _shifted(chunk, covered) if covered else chunk)
            covered += size
        if 2 * size <= w:
            chunk = _compose(chunk, _shifted(chunk, size))
        size *= 2
    return result[0][w:], result[1][w:]


def delayed_rows(arr, delay: int, fill):
    """[K, ...] -> row k holds arr[k - delay] (``fill`` before time 0), for the delayed-time model."""
    K = arr.shape[0]
    delay = min(delay, K)
    pad = jnp.broadcast_to(fill, (delay,) + arr.shape[1:]).astype(arr.dtype)
    return jnp.concatenate([pad, arr[:K - delay]])


def _process_cov(lqg: DelayedLQG):
    """sum_j c_j c_j' [K, n, n]: the additive motor noise of eq. (3)."""
    return jnp.einsum("kpn,kpm->knm", lqg.c, lqg.c)


def _kalman_step(P_prior, data):
    H, R, A_del, Q_del = data
    S = _sym(H @ P_prior @ H.T + R)
    chol = jax.scipy.linalg.cho_factor(S, lower=True)
    gain = jax.scipy.linalg.cho_solve(chol, H @ P_prior).T               # P H' S^{-1}  [n, m]
    J = jnp.eye(P_prior.shape[0], dtype=P_prior.dtype) - gain @ H
    P_post = _sym(J @ P_prior @ J.T + gain @ R @ gain.T)                 # Joseph form: stays PSD
    return _sym(A_del @ P_post @ A_del.T + Q_del), (gain, P_prior, P_post, S)


@jax.jit
def _delayed_kalman(lqg: DelayedLQG, obs: DelayedObservation, Q, R):
    ls, n = obs.delay_steps, lqg.n_states
    # the delayed-time filter at step k predicts dx_{k-l_s+1} with the transition of time k - l_s
    A_del = delayed_rows(lqg.A, ls, jnp.eye(n))
    Q_del = delayed_rows(Q, ls, 0.0)
    # an absent row (before l_s, or between two samples) has H = 0: R is block diagonal across
    # sensors, so its gain column P H' S^{-1} is exactly zero and the update ignores it
    H = jnp.where(obs.present[:, :, None], obs.H, 0.0)
    P_last, (Kd, P_prior, P_post, S) = jax.lax.scan(
        _kalman_step, jnp.zeros((n, n), lqg.A.dtype), (H, R, A_del, Q_del))
    Phi, Pi = transition_windows(lqg.A, Q, ls)
    Kc = Phi[:-1] @ Kd
    P_end = jnp.concatenate([P_post, P_last[None]])
    current = _sym(Phi @ P_end @ jnp.swapaxes(Phi, 1, 2) + Pi)
    return FilterGains(Kd, Kc), FilterCovariances(P_prior, P_post, S, current, Phi, Pi)


def delayed_kalman(lqg: DelayedLQG, obs: DelayedObservation, process_cov=None,
                   measurement_cov=None) -> tuple[FilterGains, FilterCovariances]:
    """The optimal (Kalman) delayed filter of ``lqg``'s plant seen through ``obs``.

    Args:
        lqg: the plant (A is used; B0, B1 only move the estimates, not the gains).
        obs: the delayed observation.
        process_cov: [K, n, n] covariance of the motor noise; default sum_j c_j c_j' (the additive
            part of eq. 3; signal-dependent noise needs the closed loop's moments, §14).
        measurement_cov: [K, m, m] covariance of the sensory noise; default G G'.

    Returns:
        ([`FilterGains`][delayed_ilqr.lqg.FilterGains], [`FilterCovariances`][delayed_ilqr.lqg.FilterCovariances]).
    """
    _precision.require_x64("lqg.delayed_kalman")
    Q = _process_cov(lqg) if process_cov is None else jnp.asarray(process_cov)
    R = obs.measurement_cov if measurement_cov is None else jnp.asarray(measurement_cov)
    return _delayed_kalman(lqg, obs, Q, R)


# -- running the filter ----------------------------------------------------------------------------

def estimator_update(x_hat_prior, x_tilde, dy, H, delayed_gain, current_gain):
    """The measurement update at step k: returns (x_hat_k, x_del_k), the estimates of dx_k and
    dx_{k-l_s} given I_k. For k < l_s pass zero gains (nothing has arrived)."""
    e = dy - H @ x_tilde
    return x_hat_prior + current_gain @ e, x_tilde + delayed_gain @ e


def estimator_predict(x_hat, x_del, sent, rows, rows_delayed, delay_steps: int, sensory_delay: int):
    """The time update k -> k+1 with the commands already sent.

    Args:
        x_hat, x_del: [n] E[dx_k | I_k], E[dx_{k-l_s} | I_k].
        sent: [l_s + l + 1, d] du_{k-l_s-l} .. du_k in time order (zeros before time 0).
        rows: (A_k, B0_k, B1_k); rows_delayed: the same at time k - l_s (I, 0, 0 before time 0), with
            B1 folded into B0 when l = 0 (``merged_if_undelayed``).

    Returns:
        (x_hat_prior_{k+1}, x_tilde_{k+1}).
    """
    l, ls = delay_steps, sensory_delay
    A, B0, B1 = rows
    Ad, B0d, B1d = rows_delayed
    return (A @ x_hat + B0 @ sent[ls + l] + B1 @ sent[ls],
            Ad @ x_del + B0d @ sent[l] + B1d @ sent[0])


@jax.jit
def _filter_estimates(lqg, obs, fgains, du, dy):
    lqg = merged_if_undelayed(lqg)
    l, ls, n = lqg.delay_steps, obs.delay_steps, lqg.n_states
    dt = lqg.A.dtype
    delayed = (delayed_rows(lqg.A, ls, jnp.eye(n)), delayed_rows(lqg.B0, ls, 0.0), delayed_rows(lqg.B1, ls, 0.0))

    def step(carry, data):
        x_hat_prior, x_tilde, sent = carry
        H, Kd, Kc, dy_k, du_k, A, B0, B1, Ad, B0d, B1d = data
        x_hat, x_del = estimator_update(x_hat_prior, x_tilde, dy_k, H, Kd, Kc)
        sent = jnp.concatenate([sent[1:], du_k[None]])
        prior = estimator_predict(x_hat, x_del, sent, (A, B0, B1), (Ad, B0d, B1d), l, ls)
        return prior + (sent,), (x_hat, x_del)

    Kd, Kc = _measured_rows(fgains, obs)
    init = (jnp.zeros(n, dt), jnp.zeros(n, dt), jnp.zeros((ls + l + 1, lqg.n_controls), dt))
    _, out = jax.lax.scan(step, init, (obs.H, Kd, Kc, dy, du, lqg.A, lqg.B0, lqg.B1) + delayed)
    return out


def _measured_rows(fgains: FilterGains, obs: DelayedObservation):
    """The gains with the columns of absent rows set to zero: no measurement arrives before step
    l_s, nor between two samples of a sensor (``DelayedObservation.present``)."""
    mask = obs.present[:, None, :]
    return jnp.where(mask, fgains.delayed_gain, 0.0), jnp.where(mask, fgains.current_gain, 0.0)


def filter_estimates(lqg: DelayedLQG, obs: DelayedObservation, fgains: FilterGains, du, dy):
    """Runs the delayed filter on one record: commands du [K, d], measurements dy [K, m] (rows
    k < l_s are ignored). Returns (x_hat [K, n] = E[dx_k | I_k], x_del [K, n] = E[dx_{k-l_s} | I_k])."""
    _precision.require_x64("lqg.filter_estimates")
    return _filter_estimates(lqg, obs, fgains, jnp.asarray(du), jnp.asarray(dy))
