"""Several delayed sensors, each with its own delay and period, fused without state augmentation.

Sensor a measures dy^a_k = H^a_k dx_{k-l_a} + G^a_k v^a_k at the steps k >= l_a with
(k - l_a) % m_a == 0 (``DelayedObservation``; the sensors' noises are independent). Indexed by the
time j of the sensed state, the rows of all sensors form one measurement z_j = Hs_j dx_j + noise
(rows of sensor a present when j % m_a == 0 and j + l_a < K), and sensor a's rows of z_j arrive at
step j + l_a. With L = max_a l_a and the window W = min(L, K) (``docs/derivation.md`` §19):

* the base filter, an ordinary Kalman filter in state time over every row of z_j, gives
  E[dx_{k-W} | z_0..z_{k-W}] at step k: every row of those measurements has arrived;
* the re-filter runs W more Kalman steps from there, over j = k-W+1..k, with the rows of z_j that
  have arrived by step k (sensor a's when l_a <= k - j): the result is x_hat_k = E[dx_k | I_k].

The covariances of both are deterministic (measurement times are known in advance), so the gains
are computed once: the base filter O(K (n^3 + M^3)), the re-filters O(K W (n^3 + M^3)) (M the
rows of all sensors), against O(K (n (L + 1))^3) for the Kalman filter on the augmented state.
Running the filter costs O(W n M) per step.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import _precision
from .law import augmented_feedback
from .estimator import _kalman_step, _process_cov
from .exact import checked_gains
from .model import DelayedLQG, Gains, Value, merged_if_undelayed
from .observation import DelayedObservation
from .output_feedback import separation_cost
from .structured import backward_pass

__all__ = ["FusionGains", "FusionCovariances", "FusedFeedback", "fused_kalman", "fused_estimates", "fused_design",
           "FusedLoop", "fused_loop", "stacked_sensors"]


class FusionGains(NamedTuple):
    """The gains of the fused filter.

    Attributes:
        base_gain: [K, n, M] the base filter's gain on z_j, indexed by the state time j (rows
            j >= K - W, never used, are zero).
        window_gain: [K, W, n, M] at step k, the re-filter's gain on z_{k-W+i+1} (i = 0..W-1);
            columns of rows not yet arrived (or not sampled) are zero.
    """

    base_gain: jax.Array
    window_gain: jax.Array


class FusionCovariances(NamedTuple):
    """Second moments of the fused filter's errors.

    Attributes:
        base: [K, n, n] Cov(dx_j | z_0..z_j), the base filter's posterior in state time j (rows
            j >= K - W, never used, may be zero).
        current: [K+1, n, n] Sigma_k = Cov(dx_k | I_k); row K is that of the terminal state given
            I_{K-1} (the same convention as ``FilterCovariances.current``).
    """

    base: jax.Array
    current: jax.Array


class Stacked:
    """The sensors in state time (``stacked_sensors``): padded by W rows in front, so that index
    p holds state time j = p - W.

    Attributes:
        H: [K + W, M, n] Hs_j, absent rows zero; R: [K + W, M, M] block-diagonal noise covariance
        (identity where absent); lags: (M,) numpy, the delay of each row; window: W (both static).
    """

    def __init__(self, H, R, lags, window: int):
        self.H, self.R, self.lags, self.window = H, R, np.asarray(lags), int(window)


jax.tree_util.register_pytree_node(
    Stacked, lambda s: ((s.H, s.R), (tuple(int(v) for v in s.lags), s.window)),
    lambda aux, data: Stacked(*data, *aux))


def _advanced(arr, by: int, fill):
    """[K, ...] -> row j holds arr[j + by] (``fill`` past the end)."""
    K = arr.shape[0]
    by = min(by, K)
    pad = jnp.broadcast_to(jnp.asarray(fill, arr.dtype), (by,) + arr.shape[1:])
    return jnp.concatenate([arr[by:], pad])


def _padded(arr, W: int, fill):
    """W rows of ``fill`` in front of arr [K, ...]."""
    pad = jnp.broadcast_to(jnp.asarray(fill, arr.dtype), (W,) + arr.shape[1:])
    return jnp.concatenate([pad, arr])


def _block_diag(blocks):
    """[K, m_a, m_a] for each a -> [K, M, M]."""
    K = blocks[0].shape[0]
    sizes = [b.shape[1] for b in blocks]
    out = jnp.zeros((K, sum(sizes), sum(sizes)), blocks[0].dtype)
    start = 0
    for b, m in zip(blocks, sizes):
        out = out.at[:, start:start + m, start:start + m].set(b)
        start += m
    return out


def window_size(sensors: Sequence[DelayedObservation]) -> int:
    """W = min(max_a l_a, K): how far back the base filter runs."""
    return min(max(s.delay_steps for s in sensors), sensors[0].horizon)


def stacked_sensors(sensors: Sequence[DelayedObservation], measurement_covs=None) -> Stacked:
    """The sensors' rows in state time j: row block a of z_j is sensor a's measurement that arrives
    at j + l_a (absent rows, and those that would arrive at or after K, are zero)."""
    W = window_size(sensors)
    covs = [s.measurement_cov for s in sensors] if measurement_covs is None else measurement_covs
    Hs, Rs, lags = [], [], []
    for s, R in zip(sensors, covs):
        ls, m = s.delay_steps, s.n_outputs
        present = _advanced(s.present, ls, False)                    # [K, m] in state time
        Hs.append(jnp.where(present[:, :, None], _advanced(s.H, ls, 0.0), 0.0))
        eye = jnp.eye(m, dtype=s.H.dtype)
        Rs.append(jnp.where(jnp.arange(s.horizon)[:, None, None] + ls < s.horizon, _advanced(R, ls, eye), eye))
        lags += [ls] * m
    H, R = jnp.concatenate(Hs, axis=1), _block_diag(Rs)
    M = H.shape[1]
    return Stacked(_padded(H, W, 0.0), _padded(R, W, jnp.eye(M, dtype=R.dtype)), np.asarray(lags), W)


def _transitions_in(arr, W: int, fill):
    """Index p -> the transition into state time j = p - W, i.e. arr[j - 1] (``fill`` for j <= 0:
    before time 0 the state stays at x0)."""
    return _padded(_padded(arr[:-1], 1, fill), W, fill)


def _window_masks(lags: np.ndarray, W: int):
    """[W, M] bool: at window position i (state time k - W + 1 + i) the rows with l <= W - 1 - i
    have arrived by step k."""
    return jnp.asarray(lags[None, :] <= (W - 1 - np.arange(W))[:, None])


def _update(P_prior, H, R):
    """The Kalman update of the covariance (Joseph form, as ``estimator._kalman_step``)."""
    n = P_prior.shape[0]
    P_next, (gain, _, P_post, _) = _kalman_step(P_prior, (H, R, jnp.eye(n, dtype=H.dtype), jnp.zeros_like(P_prior)))
    return gain, P_post


@jax.jit
def _fused_kalman(lqg: DelayedLQG, st: Stacked, Q):
    K, n, W = lqg.horizon, lqg.n_states, st.window
    dt = lqg.A.dtype
    # the base filter in state time: update with z_j, then predict with A_j
    _, (Kb, _, Pb, _) = jax.lax.scan(_kalman_step, jnp.zeros((n, n), dt), (st.H[W:], st.R[W:], lqg.A, Q))
    if W == 0:
        current = Pb
    else:
        A_in = _transitions_in(lqg.A, W, jnp.eye(n, dtype=dt))
        Q_in = _transitions_in(Q, W, 0.0)
        Pb_pad = _padded(Pb, W, 0.0)
        masks = _window_masks(st.lags, W)

        def refilter(k):
            window = lambda a: jax.lax.dynamic_slice_in_dim(a, k + 1, W)

            def step(P, data):
                A, Qk, H, R, mask = data
                return _update(A @ P @ A.T + Qk, jnp.where(mask[:, None], H, 0.0), R)[::-1]

            P, gains = jax.lax.scan(step, Pb_pad[k], (window(A_in), window(Q_in), window(st.H), window(st.R), masks))
            return gains, P

        Wg, current = jax.vmap(refilter)(jnp.arange(K))
    # base rows of state times j >= K - W are never used (step j + W is past the horizon)
    Kb = jnp.where((jnp.arange(K) < K - W)[:, None, None], Kb, 0.0)
    last = lqg.A[-1] @ current[-1] @ lqg.A[-1].T + Q[-1]
    current = jnp.concatenate([current, last[None]])
    Wg = jnp.zeros((K, 0, n, st.H.shape[1]), dt) if W == 0 else Wg
    return FusionGains(Kb, Wg), FusionCovariances(Pb, 0.5 * (current + jnp.swapaxes(current, 1, 2)))


def _checked(lqg: DelayedLQG, sensors) -> tuple:
    sensors = tuple(sensors)
    if not sensors or not all(isinstance(s, DelayedObservation) for s in sensors):
        raise ValueError(f"sensors must be a non-empty sequence of lqg.DelayedObservation; got {sensors!r}")
    for s in sensors:
        if s.horizon != lqg.horizon or s.H.shape[2] != lqg.n_states:
            raise ValueError(f"each sensor's H must have shape ({lqg.horizon}, m, {lqg.n_states}); got {s.H.shape}")
    return sensors


def fused_kalman(lqg: DelayedLQG, sensors: Sequence[DelayedObservation], process_cov=None,
                 measurement_covs=None) -> tuple[FusionGains, FusionCovariances]:
    """The optimal (Kalman) filter of ``lqg``'s plant seen through several delayed sensors.

    Args:
        lqg: the plant (A is used; B0, B1 only move the estimates).
        sensors: the sensors, each a [`DelayedObservation`][delayed_ilqr.lqg.DelayedObservation]
            with its own delay and period.
        process_cov: [K, n, n] covariance of the motor noise; default sum_j c_j c_j'.
        measurement_covs: one [K, m_a, m_a] per sensor; default G G'.

    Returns:
        ([`FusionGains`][delayed_ilqr.lqg.FusionGains], [`FusionCovariances`][delayed_ilqr.lqg.FusionCovariances]).
    """
    _precision.require_x64("lqg.fused_kalman")
    sensors = _checked(lqg, sensors)
    Q = _process_cov(lqg) if process_cov is None else jnp.asarray(process_cov)
    return _fused_kalman(lqg, stacked_sensors(sensors, measurement_covs), Q)


# -- running the filter ----------------------------------------------------------------------------

class FusionRows(NamedTuple):
    """What the fused filter moves with, in state time padded by W (index p: j = p - W): the
    transitions into j (A, B0, B1 with l = 0 merged), the sensors ``Stacked``, and the gains."""

    A: jax.Array
    B0: jax.Array
    B1: jax.Array
    H: jax.Array
    base_gain: jax.Array
    window_gain: jax.Array


def fusion_rows(A, B0, B1, H_pad, fgains: FusionGains, W: int) -> FusionRows:
    """The rows the filter moves with, from the plant's A [K, n, n], B0, B1 [K, n, d] (with B1
    already folded into B0 when l = 0), the stacked sensors H_pad [K + W, M, n] and the gains."""
    n = A.shape[1]
    return FusionRows(_transitions_in(A, W, jnp.eye(n, dtype=A.dtype)), _transitions_in(B0, W, 0.0),
                      _transitions_in(B1, W, 0.0), H_pad, _padded(fgains.base_gain, W, 0.0), fgains.window_gain)


def fusion_init(n: int, M: int, d: int, W: int, l: int, dtype):
    """The filter's memory before step 0: (base estimate, measurements of the window, commands)."""
    return jnp.zeros(n, dtype), jnp.zeros((W + 1, M), dtype), jnp.zeros((W + l + 1, d), dtype)


def fusion_update(memory, k, dy, rows: FusionRows, lags: np.ndarray, W: int, l: int):
    """Step k's estimate x_hat_k = E[dx_k | I_k] from the measurements arriving at k.

    Args:
        memory: (x_b [n] the base estimate of dx_{k-W-1}, z [W+1, M] the measurements of
            dx_{k-W}..dx_k that have arrived, sent [W+l+1, d] du_{k-W-1-l}..du_{k-1}).
        dy: [M] the rows arriving at k (row r measures dx_{k - lags[r]}; absent rows are ignored).

    Returns:
        (x_hat_k, the memory with the arrivals and the new base estimate, before du_k).
    """
    x_b, z, sent = memory
    M = dy.shape[0]
    slot = np.clip(W - lags, 0, W)
    arrives = jnp.asarray(lags <= W)
    z = z.at[slot, np.arange(M)].set(jnp.where(arrives, dy, z[slot, np.arange(M)]))
    # the base filter: predict dx_{k-W} and update it with all of z_{k-W}
    x = rows.A[k] @ x_b + rows.B0[k] @ sent[l] + rows.B1[k] @ sent[0]
    x_b = x + rows.base_gain[k] @ (z[0] - rows.H[k] @ x)
    if W == 0:
        return x_b, (x_b, z, sent)

    def step(x, data):
        i, A, B0, B1, H, gain = data
        x = A @ x + B0 @ sent[l + i] + B1 @ sent[i]
        return x + gain @ (z[i] - H @ x), None

    window = lambda a: jax.lax.dynamic_slice_in_dim(a, k + 1, W)
    x, _ = jax.lax.scan(step, x_b, (jnp.arange(1, W + 1), window(rows.A), window(rows.B0), window(rows.B1),
                                    window(rows.H), rows.window_gain[k]))
    return x, (x_b, z, sent)


def fusion_advance(memory, du):
    """After du_k is sent: the window moves one step."""
    x_b, z, sent = memory
    return x_b, jnp.concatenate([z[1:], jnp.zeros_like(z[:1])]), jnp.concatenate([sent[1:], du[None]])


@jax.jit
def _fused_estimates(lqg, st: Stacked, fgains, du, dy):
    lqg = merged_if_undelayed(lqg)
    l, W = lqg.delay_steps, st.window
    rows = fusion_rows(lqg.A, lqg.B0, lqg.B1, st.H, fgains, W)

    def step(memory, data):
        k, du_k, dy_k = data
        x_hat, memory = fusion_update(memory, k, dy_k, rows, st.lags, W, l)
        return fusion_advance(memory, du_k), x_hat

    init = fusion_init(lqg.n_states, dy.shape[1], lqg.n_controls, W, l, lqg.A.dtype)
    return jax.lax.scan(step, init, (jnp.arange(lqg.horizon), du, dy))[1]


def fused_estimates(lqg: DelayedLQG, sensors: Sequence[DelayedObservation], fgains: FusionGains, du, dys):
    """Runs the fused filter on one record: commands du [K, d] and each sensor's measurements
    dys, one [K, m_a] per sensor indexed by arrival step (absent rows are ignored). Returns x_hat [K, n] =
    E[dx_k | I_k]."""
    _precision.require_x64("lqg.fused_estimates")
    sensors = _checked(lqg, sensors)
    dy = jnp.concatenate([jnp.asarray(y) for y in dys], axis=1)
    return _fused_estimates(lqg, stacked_sensors(sensors), fgains, jnp.asarray(du), dy)


# -- the controller on the fused estimate ----------------------------------------------------------

class FusedFeedback(NamedTuple):
    """Theorem 1's law on the fused filter's estimate (``fused_design``).

    Attributes:
        gains: the law ([`Gains`][delayed_ilqr.lqg.Gains]); filter_gains: [`FusionGains`][delayed_ilqr.lqg.FusionGains];
        value: the full-state cost-to-go; covariances: [`FusionCovariances`][delayed_ilqr.lqg.FusionCovariances];
        expected_cost: [] the exact expected cost of the pair (additive noise: separation).
    """

    gains: Gains
    filter_gains: FusionGains
    value: Value
    covariances: FusionCovariances
    expected_cost: jax.Array


def fused_design(lqg: DelayedLQG, sensors: Sequence[DelayedObservation]) -> FusedFeedback:
    """The separation design with several delayed sensors: [`backward_pass`][delayed_ilqr.lqg.backward_pass]'s law on the
    fused Kalman estimate, and its expected cost J(0) + sum_k tr(L_k' H_k L_k Sigma_k)
    ([`separation_cost`][delayed_ilqr.lqg.separation_cost]), exact when the motor noise is additive (C0 = C1 = 0):
    the estimation error is then independent of everything the law sees (``docs/derivation.md`` §19)."""
    fgains, cov = fused_kalman(lqg, sensors)
    gains, value = backward_pass(lqg)
    return FusedFeedback(gains, fgains, value, cov, separation_cost(lqg, value, gains, cov))


# -- the filter for the loop's own motor noise, and the exact cost of the pair ---------------------

class FusedLoop(NamedTuple):
    """The fused filter for the motor noise of the closed loop under a given law, and the pair's
    exact expected cost (``fused_loop``).

    Attributes:
        filter_gains: [`FusionGains`][delayed_ilqr.lqg.FusionGains]; covariances: [`FusionCovariances`][delayed_ilqr.lqg.FusionCovariances];
        motor_cov: [K, n, n] E[w_k w_k'] under the loop (signal-dependent noise included);
        expected_cost: [] the exact expected cost of the law on the filter's estimate.
    """

    filter_gains: FusionGains
    covariances: FusionCovariances
    motor_cov: jax.Array
    expected_cost: jax.Array


def _moments_of(T, t0, mu, X):
    m = T @ mu
    return m + t0, T @ X @ T.T + jnp.outer(m, t0) + jnp.outer(t0, m) + jnp.outer(t0, t0)


@jax.jit
def _fused_loop(lqg: DelayedLQG, st: Stacked, I_ff, LM):
    lqg = merged_if_undelayed(lqg)
    K, n, nd, l, W = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.delay_steps, st.window
    dt = lqg.A.dtype
    Nz = n + l * nd
    A_in = _transitions_in(lqg.A, W, jnp.eye(n, dtype=dt))
    masks = _window_masks(st.lags, W) if W else None
    S_del = jnp.zeros((nd, Nz), dt)                    # u_{k-l}: the oldest pending command
    if l > 0:
        S_del = S_del.at[:, n:n + nd].set(jnp.eye(nd, dtype=dt))
    E_x = jnp.zeros((n, Nz), dt).at[:, :n].set(jnp.eye(n, dtype=dt))

    def step(carry, data):
        Pb, Qbuf, Sigma_prev, mu, X, total = carry     # Qbuf[i]: Q of state time k - W - 1 + i
        k, A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, N, I, LMk = data
        # the base filter at state time k - W, then the re-filter over the window (section 18)
        Kb, Pb = _update(A_in[k] @ Pb @ A_in[k].T + Qbuf[0], st.H[k], st.R[k])
        P, Wg = Pb, jnp.zeros((0, n, st.H.shape[1]), dt)
        if W:
            def refilter(P, data):
                i, mask = data
                p = k + i
                A_p = A_in[p]
                return _update(A_p @ P @ A_p.T + Qbuf[i], jnp.where(mask[:, None], st.H[p], 0.0), st.R[p])[::-1]
            P, Wg = jax.lax.scan(refilter, Pb, (jnp.arange(1, W + 1), masks))
        Sigma = 0.5 * (P + P.T)
        # the estimate's jump at k is uncorrelated with I_{k-1}: Cov = P_{k|k-1} - Sigma_k
        A_prev = A_in[k + W]
        jump = A_prev @ Sigma_prev @ A_prev.T + Qbuf[W] - Sigma
        X = X.at[:n, :n].add(jump)
        # the stage cost, with dx = x_hat + error (the error is orthogonal to what the law sees)
        Tu = LMk
        Eu, Euu = _moments_of(Tu, I, mu, X)
        Eux = (Tu @ X @ E_x.T) + jnp.outer(I, mu[:n])
        Ex, Exx = mu[:n], X[:n, :n] + Sigma
        total = total + d_tilde + 2 * dv @ Ex + jnp.sum(D * Exx) + 2 * e @ Eu + jnp.sum(E * Euu) + 2 * jnp.sum(N * Eux)
        # the motor noise of this step: columns c_j + C0_j u_k + C1_j u_{k-l}, affine in zeta
        g = c + C0 @ I
        Gm = jnp.einsum("pnd,dz->pnz", C0, Tu) + jnp.einsum("pnd,dz->pnz", C1, S_del)
        Gmu = jnp.einsum("pnz,z->pn", Gm, mu)
        Q = jnp.einsum("pn,pm->nm", g, g) + jnp.einsum("pn,pm->nm", Gmu, g) + jnp.einsum("pn,pm->nm", g, Gmu) \
            + jnp.einsum("pnz,zy,pmy->nm", Gm, X, Gm)
        Q = 0.5 * (Q + Q.T)
        # the time update of zeta = (x_hat, pending)
        T = jnp.zeros((Nz, Nz), dt).at[:n].set(B0 @ Tu + B1 @ S_del).at[:n, :n].add(A)
        t0 = jnp.zeros(Nz, dt).at[:n].set(B0 @ I)
        if l > 0:
            T = T.at[n:Nz - nd, n + nd:].set(jnp.eye((l - 1) * nd, dtype=dt))
            T = T.at[Nz - nd:].set(Tu)
            t0 = t0.at[Nz - nd:].set(I)
        mu, X = _moments_of(T, t0, mu, X)
        Qbuf = jnp.concatenate([Qbuf[1:], Q[None]])
        return (Pb, Qbuf, Sigma, mu, X, total), (Kb, Wg, Pb, Sigma, Q)

    data = (jnp.arange(K), lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1],
            lqg.e, lqg.E, lqg.N, I_ff, LM)
    init = (jnp.zeros((n, n), dt), jnp.zeros((W + 1, n, n), dt), jnp.zeros((n, n), dt), jnp.zeros(Nz, dt),
            jnp.zeros((Nz, Nz), dt), jnp.asarray(0.0, dt))
    (_, Qbuf, Sigma, mu, X, total), (Kb, Wg, Pb, current, Qs) = jax.lax.scan(step, init, data)
    terminal = lqg.A[-1] @ Sigma @ lqg.A[-1].T + Qbuf[-1]
    total = total + lqg.d_tilde[-1] + 2 * lqg.d[-1] @ mu[:n] + jnp.sum(lqg.D[-1] * (X[:n, :n] + terminal))
    # the base filter's rows were produced at step k for state time k - W: back to state time
    Kb = jnp.concatenate([Kb[W:], jnp.zeros((min(W, K),) + Kb.shape[1:], dt)])
    Pb = jnp.concatenate([Pb[W:], jnp.zeros((min(W, K),) + Pb.shape[1:], dt)])
    current = jnp.concatenate([current, terminal[None]])
    return FusedLoop(FusionGains(Kb, Wg), FusionCovariances(Pb, current), Qs, total)


def fused_loop(lqg: DelayedLQG, sensors: Sequence[DelayedObservation], gains) -> FusedLoop:
    """The fused Kalman filter for the motor noise the closed loop actually has when the law
    ``gains`` acts on its estimate, and the exact expected cost of that pair, in one forward scan
    (``docs/derivation.md`` §19).

    The noise of step k, E[w_k w_k'] with w_k = sum_j (c_j + C0_j du_k + C1_j du_{k-l}) xi_j, is
    uncorrelated with everything before it, so the Kalman filter for that covariance is the best
    affine estimator, its error is orthogonal to the estimate and the commands, and the loop's
    second moments need only those of (x_hat, pending commands) and Sigma_k. With additive noise
    the filter is ``fused_kalman``'s and the cost that of the separation formula. Cost
    O(K W (n^3 + M^3) + K (n + l d)^3).
    """
    _precision.require_x64("lqg.fused_loop")
    sensors = _checked(lqg, sensors)
    gains = checked_gains(lqg, gains)
    return _fused_loop(lqg, stacked_sensors(sensors), gains.feedforward, augmented_feedback(gains))
