"""Todorov's alternation with several delayed sensors (``lqg.fusion``): the controller for a fixed
fused filter, and the alternation of controller and filter (``docs/derivation.md`` §22).

With signal-dependent motor noise (C0, C1 != 0) the law designed for full state is not the best
law on the fused estimate. As for one sensor (``lqg.alternation``), the alternation redesigns in
turn the law for a fixed filter and the filter for a fixed law, measuring every pair by its exact
expected cost, so the cost never rises:

* [`fused_controller_sweep`][delayed_ilqr.lqg.fused_controller_sweep]: for the fused Kalman filter
  of a given process covariance Q_k, one backward pass of the value function of the joint system
  zeta_k = (x_hat_k, pending, e_k), where e_k = [dx_k - x_hat_{k|k}, ..., dx_{k-W} - x_hat_{k-W|k}]
  are the errors of the filter's estimates of the window's states given I_k (W = min(max_a l_a, K)).
  The errors move on their own (e^-_{k+1} = [A e_0 + w_k; e_0; ...; e_{W-1}]) and each arrival
  corrects them and the estimate (x_hat += Kz_0 nu, e -= Kz nu, nu = Hz e^- + v). A command's noise
  is charged at the value's curvature along e_0 (a disturbance no sensor has seen yet), and each
  step's law is Todorov's: the minimiser of the step's Q-function at e = 0 for each value of what
  the law sees, (x_hat_k, pending). The pass's value at zeta = 0 is the new law's exact cost with
  that filter. Per step O((n (W + 2) + l d)^3): the controller half costs what augmentation costs,
  since the errors of the window's states are what a slower sensor will still correct.
* the filter for a fixed law is ``fusion.fused_loop``'s: the fused filter for the motor noise of
  that law's closed loop, with the pair's exact cost.
* [`fused_alternate`][delayed_ilqr.lqg.fused_alternate]: both in turn; an alternation is kept when
  the pair's exact cost falls, and it stops when it falls by less than ``tol`` (relative).

The feedforward is held, and commands marked not ``free`` keep their feedback rows.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from .exact import checked_gains
from .fusion import FusedLoop, FusionCovariances, FusionGains, _checked, _fused_loop, stacked_sensors, window_size
from .law import augmented_feedback
from .model import DelayedLQG, Gains, merged_if_undelayed
from .observation import DelayedObservation

__all__ = ["FusedAlternation", "ErrorSensors", "error_sensors", "error_kalman", "fused_controller_sweep",
           "fused_alternate"]


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


class ErrorSensors(NamedTuple):
    """The sensors as measurements of the window's errors e_k (``error_sensors``).

    Attributes:
        H: [K, M, n (W+1)] the rows arriving at k: sensor a's on block l_a (dx_{k-l_a}), zero where
            absent. R: [K, M, M] their noise covariance (block-diagonal; identity on absent rows,
            whose gain columns are zero).
    """

    H: jax.Array
    R: jax.Array


def error_sensors(sensors: Sequence[DelayedObservation], W: int) -> ErrorSensors:
    """The rows of every sensor, by arrival step, on the window's error blocks 0..W."""
    K, n = sensors[0].horizon, sensors[0].H.shape[2]
    Hs, covs, present = [], [], []
    for s in sensors:
        block = min(s.delay_steps, W)          # l_a > W only when l_a >= K: never present
        H = jnp.zeros((K, s.n_outputs, n * (W + 1)), s.H.dtype)
        Hs.append(H.at[:, :, block * n:(block + 1) * n].set(jnp.where(s.present[:, :, None], s.H, 0.0)))
        covs.append(s.measurement_cov)
        present.append(s.present)
    M = sum(s.n_outputs for s in sensors)
    R = jnp.zeros((K, M, M), Hs[0].dtype)
    start = 0
    for cov in covs:
        m = cov.shape[1]
        R = R.at[:, start:start + m, start:start + m].set(cov)
        start += m
    both = jnp.concatenate(present, axis=1)
    both = both[:, :, None] & both[:, None, :]
    return ErrorSensors(jnp.concatenate(Hs, axis=1), jnp.where(both, R, jnp.eye(M, dtype=R.dtype)))


def _error_transition(A, W: int):
    """e^-_{k+1} = Ae e_k (+ w_k on block 0): A on block 0, the other blocks shift by one."""
    n = A.shape[0]
    Ae = jnp.zeros((n * (W + 1), n * (W + 1)), A.dtype).at[:n, :n].set(A)
    return Ae.at[n:, :n * W].set(jnp.eye(n * W, dtype=A.dtype)) if W else Ae


@partial(jax.jit, static_argnames=("W",))
def _error_kalman(A, es: ErrorSensors, Q, W: int):
    n = A.shape[1]
    Ne = n * (W + 1)

    def step(P, data):
        A_k, H, R, Q_k = data
        S = H @ P @ H.T + R
        gain = jnp.linalg.solve(S, H @ P).T
        I_KH = jnp.eye(Ne, dtype=P.dtype) - gain @ H
        post = _sym(I_KH @ P @ I_KH.T + gain @ R @ gain.T)
        Ae = _error_transition(A_k, W)
        return _sym(Ae @ post @ Ae.T).at[:n, :n].add(Q_k), (gain, post[:n, :n])

    return jax.lax.scan(step, jnp.zeros((Ne, Ne), A.dtype), (A, es.H, es.R, Q))[1]


def error_kalman(lqg: DelayedLQG, sensors: Sequence[DelayedObservation], process_cov):
    """The Kalman filter of the window's errors for the motor-noise covariance Q_k [K, n, n]: the
    gains Kz [K, n (W+1), M] of each arrival on the estimates of dx_k..dx_{k-W}, and Sigma_k [K, n, n]
    (the same filter as ``fused_kalman``'s for that Q: the same information, the same estimate)."""
    _precision.require_x64("lqg.error_kalman")
    sensors = _checked(lqg, sensors)
    W = window_size(sensors)
    return _error_kalman(lqg.A, error_sensors(sensors, W), jnp.asarray(process_cov), W)


class _Joint(NamedTuple):
    """Offsets of zeta = (x_hat, pending, e): sizes n, l d, n (W + 1)."""
    n: int
    l: int
    nd: int
    W: int

    @property
    def ny(self):
        return self.n + self.l * self.nd

    @property
    def size(self):
        return self.ny + self.n * (self.W + 1)


def _sweep_step(carry, data, *, z: _Joint):
    P, p, r = carry                          # V_{k+1} on zeta before the arrivals of step k+1
    (A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, N, I, LM, free, H, R, gain_e) = data
    n, l, nd, ny, Nz = z.n, z.l, z.nd, z.ny, z.size
    dt = P.dtype
    e0 = slice(ny, ny + n)
    # the time update zeta^-_{k+1} = Tz zeta_k + Tu du_k + (w_k on e_0)
    S_del = jnp.zeros((nd, Nz), dt)
    if l > 0:
        S_del = S_del.at[:, n:n + nd].set(jnp.eye(nd, dtype=dt))
    Tz = jnp.zeros((Nz, Nz), dt).at[:n].set(B1 @ S_del).at[:n, :n].add(A).at[e0, e0].set(A)
    if z.W:
        Tz = Tz.at[ny + n:, ny:Nz - n].set(jnp.eye(n * z.W, dtype=dt))
    Tu = jnp.zeros((Nz, nd), dt).at[:n].set(B0)
    if l > 0:
        Tz = Tz.at[n:ny - nd, n + nd:ny].set(jnp.eye((l - 1) * nd, dtype=dt))
        Tu = Tu.at[ny - nd:ny].set(jnp.eye(nd, dtype=dt))
    Tx = jnp.zeros((n, Nz), dt).at[:, :n].set(jnp.eye(n, dtype=dt)).at[:, e0].set(jnp.eye(n, dtype=dt))
    # a unit of motor noise of step k is an error no sensor has seen: charged at V's e_0 block
    Wk = P[e0, e0]
    C1z = jnp.einsum("pnd,dz->pnz", C1, S_del)
    Huu = E + Tu.T @ P @ Tu + jnp.einsum("pnd,nm,pme->de", C0, Wk, C0)
    Huz = N @ Tx + Tu.T @ P @ Tz + jnp.einsum("pnd,nm,pmz->dz", C0, Wk, C1z)
    hu = e + Tu.T @ p + jnp.einsum("pnd,nm,pm->d", C0, Wk, c)
    Hzz = Tx.T @ D @ Tx + Tz.T @ P @ Tz + jnp.einsum("pnz,nm,pmy->zy", C1z, Wk, C1z)
    hz = Tx.T @ dv + Tz.T @ p + jnp.einsum("pnz,nm,pm->z", C1z, Wk, c)
    h0 = d_tilde + r + jnp.einsum("pn,nm,pm->", c, Wk, c)
    # Todorov's law: the minimiser at e = 0 for each (x_hat, pending); rows not free are kept
    Huy = Huz[:, :ny] + Huu @ jnp.where(free[:, None], 0.0, LM)
    H_free = jnp.where(free[:, None] & free[None, :], Huu, jnp.eye(nd, dtype=dt))
    LM_new = jnp.where(free[:, None], -jnp.linalg.solve(H_free, jnp.where(free[:, None], Huy, 0.0)), LM)
    # V_k: Q_k under the new law, then the arrivals of step k (x_hat += Kz_0 nu, e -= Kz nu)
    F = jnp.zeros((nd, Nz), dt).at[:, :ny].set(LM_new)
    P_plus = _sym(Hzz + F.T @ Huz + Huz.T @ F + F.T @ Huu @ F)
    p_plus = hz + F.T @ hu + Huz.T @ I + F.T @ Huu @ I
    r_plus = h0 + 2 * hu @ I + I @ Huu @ I
    gain = jnp.zeros((Nz, H.shape[0]), dt).at[:n].set(gain_e[:n]).at[ny:].set(-gain_e)
    U = jnp.eye(Nz, dtype=dt).at[:, ny:].add(gain @ H)
    return (_sym(U.T @ P_plus @ U), U.T @ p_plus, r_plus + jnp.sum((gain.T @ P_plus @ gain) * R)), LM_new


def _gains_from(LM, feedforward, n: int, l: int):
    K, nd = feedforward.shape
    return Gains(feedforward, LM[:, :, :n], jnp.moveaxis(LM[:, :, n:].reshape(K, nd, l, nd), 2, 1))


@partial(jax.jit, static_argnames=("W",))
def _fused_sweep(lqg: DelayedLQG, es: ErrorSensors, gains: Gains, Q, free, W: int):
    lqg = merged_if_undelayed(lqg)
    n, nd, l = lqg.n_states, lqg.n_controls, lqg.delay_steps
    z = _Joint(n, l, nd, W)
    dt = lqg.A.dtype
    gain_e, _ = _error_kalman(lqg.A, es, Q, W)
    Tx = jnp.zeros((n, z.size), dt).at[:, :n].set(jnp.eye(n, dtype=dt)).at[:, z.ny:z.ny + n].set(jnp.eye(n, dtype=dt))
    init = (Tx.T @ lqg.D[-1] @ Tx, Tx.T @ lqg.d[-1], lqg.d_tilde[-1])
    data = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E,
            lqg.N, gains.feedforward, augmented_feedback(gains), free, es.H, es.R, gain_e)
    (_, _, r0), LM = jax.lax.scan(partial(_sweep_step, z=z), init, data, reverse=True)
    return _gains_from(LM, gains.feedforward, n, l), r0


def _all_free(gains: Gains):
    return jnp.ones(gains.feedforward.shape, bool)


def fused_controller_sweep(lqg: DelayedLQG, sensors: Sequence[DelayedObservation], gains: Gains, process_cov,
                           free=None) -> tuple[Gains, jax.Array]:
    """Todorov's controller for the fused Kalman filter of the motor-noise covariance ``process_cov``
    (Q_k [K, n, n], e.g. ``fused_loop(...).motor_cov``): one backward pass (module docstring).

    Args:
        lqg: the plant; sensors: its delayed sensors (``fusion``'s list).
        gains: the current law (its feedforward is kept).
        process_cov: [K, n, n] the Q_k the filter is designed for.
        free: [K, d] bool, the commands whose feedback may change (default all).

    Returns:
        (the new law, its exact expected cost [] with that filter: the pass's value at time 0).
    """
    _precision.require_x64("lqg.fused_controller_sweep")
    sensors = _checked(lqg, sensors)
    gains = checked_gains(lqg, gains)
    free = _all_free(gains) if free is None else jnp.asarray(free, bool)
    W = window_size(sensors)
    return _fused_sweep(lqg, error_sensors(sensors, W), gains, jnp.asarray(process_cov), free, W)


class FusedAlternation(NamedTuple):
    """The pair after the alternation with several sensors.

    Attributes:
        gains: the law on the fused estimate (feedforward as given; L, M redesigned).
        filter_gains: [`FusionGains`][delayed_ilqr.lqg.FusionGains], the fused filter for the motor
            noise of this law's own loop.
        covariances: its [`FusionCovariances`][delayed_ilqr.lqg.FusionCovariances]; ``current`` is
            the estimation error's exact covariance (the filter is Kalman for the loop's noise).
        motor_cov: [K, n, n] E[w_k w_k'] of the loop.
        expected_cost: [] the pair's exact expected cost.
        costs: [max_alternations + 1] the exact cost after each alternation (index 0: the starting
            law with its loop's filter); NaN after the last one run.
        alternations: [] the number of alternations run.
    """

    gains: Gains
    filter_gains: FusionGains
    covariances: FusionCovariances
    motor_cov: jax.Array
    expected_cost: jax.Array
    costs: jax.Array
    alternations: jax.Array


class _Loop(NamedTuple):
    gains: Gains
    loop: FusedLoop
    costs: jax.Array
    i: jax.Array
    done: jax.Array


def _alternation(lqg, st, es, free, max_alternations: int, tol):
    W = st.window
    loop_of = lambda g: _fused_loop(lqg, st, g.feedforward, augmented_feedback(g))

    def body(s: _Loop):
        cost = s.loop.expected_cost
        g_new, _ = _fused_sweep(lqg, es, s.gains, s.loop.motor_cov, free, W)
        new = loop_of(g_new)
        take = new.expected_cost < cost
        gains, loop = jax.tree_util.tree_map(lambda a, b: jnp.where(take, a, b), (g_new, new), (s.gains, s.loop))
        i = s.i + 1
        done = ~(loop.expected_cost < cost - tol * jnp.abs(cost)) | (i >= max_alternations)
        return _Loop(gains, loop, s.costs.at[i].set(loop.expected_cost), i, done)

    def init(gains, run):
        loop = loop_of(gains)
        costs = jnp.full(max_alternations + 1, jnp.nan, lqg.A.dtype).at[0].set(loop.expected_cost)
        return _Loop(gains, loop, costs, jnp.asarray(0), (max_alternations == 0) | ~jnp.asarray(run))

    return body, init


def _result(s: _Loop) -> FusedAlternation:
    loop = s.loop
    return FusedAlternation(s.gains, loop.filter_gains, loop.covariances, loop.motor_cov, loop.expected_cost,
                            s.costs, s.i)


@partial(jax.custom_jvp, nondiff_argnums=(5,))
def _alternate_differentiable(lqg, st, es, gains, free, max_alternations: int, tol, run):
    """The alternation as a ``while_loop``; its derivative is that of the same iterations as a
    ``scan`` (`_alternate_unrolled`), which reverse mode can transpose."""
    body, init = _alternation(lqg, st, es, free, max_alternations, tol)
    return _result(jax.lax.while_loop(lambda s: ~s.done, body, init(gains, run)))


def _alternate_unrolled(lqg, st, es, gains, free, max_alternations: int, tol, run):
    body, init = _alternation(lqg, st, es, free, max_alternations, tol)
    step = lambda s, _: (jax.lax.cond(s.done, lambda s: s, body, s), None)
    return _result(jax.lax.scan(step, init(gains, run), None, length=max_alternations)[0])


@_alternate_differentiable.defjvp
def _alternate_jvp(max_alternations, primals, tangents):
    unrolled = lambda lqg, st, es, gains, free, tol, run: _alternate_unrolled(
        lqg, st, es, gains, free, max_alternations, tol, run)
    return jax.jvp(unrolled, primals, tangents)


@partial(jax.jit, static_argnames=("max_alternations",))
def _fused_alternate(lqg, sensors, gains, free, max_alternations: int, tol, run=True):
    """``fused_alternate`` on checked input; with ``run`` false (a traced bool) the starting law
    comes back with the filter of its own loop."""
    st = stacked_sensors(sensors)
    es = error_sensors(sensors, st.window)
    return _alternate_differentiable(lqg, st, es, gains, jnp.asarray(free), max_alternations,
                                     jnp.asarray(tol, lqg.A.dtype), jnp.asarray(run))


def fused_alternate(lqg: DelayedLQG, sensors: Sequence[DelayedObservation], gains: Gains, free=None,
                    max_alternations: int = 20, tol: float = 1e-9) -> FusedAlternation:
    """Todorov's alternation with several delayed sensors, from the law ``gains`` with the fused
    filter for its own loop's motor noise (``fused_loop``).

    Each alternation runs [`fused_controller_sweep`][delayed_ilqr.lqg.fused_controller_sweep] for the
    current filter, then the filter for the new law's loop; the new pair is kept when its exact cost
    is lower. It stops when an alternation lowers the cost by less than ``tol`` times its value, or
    after ``max_alternations``. ``free`` as in the sweep.
    """
    _precision.require_x64("lqg.fused_alternate")
    sensors = _checked(lqg, sensors)
    gains = checked_gains(lqg, gains)
    free = _all_free(gains) if free is None else jnp.asarray(free, bool)
    max_alternations = _validate.non_negative_int(max_alternations, "max_alternations")
    return _fused_alternate(lqg, sensors, gains, free, max_alternations, jnp.asarray(tol, lqg.A.dtype))
