"""The independent reference: an ordinary Riccati recursion on the augmented (undelayed) state
z_k = [dx_k, du_{k-l}, ..., du_{k-1}], per step O((n + l d)^3).

Same problem and same return types as [`structured.backward_pass`][delayed_ilqr.lqg.backward_pass]; the tests hold the two
equal, and ``Options(method="augmented")`` solves with it. With a frame (``delay_frame`` L, the
delay l as data) the buffer holds du_{k-L}, ..., du_{k-1} and B1, C1 read its entry L - l.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from .. import _precision
from .gains import unconstrained_gains
from .model import DelayedLQG, Gains, Value, checked_entry, fold_taps, merged_if_undelayed

__all__ = ["augment", "augmented_scan", "augmented_backward_pass"]


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def _with_final(per_step, final):
    return jnp.concatenate([per_step, final[None]])


def augment(lqg: DelayedLQG):
    """The augmented (undelayed) system, time-major.

    Returns a dict with Az [K, m, m], Bz [K, m, d], cz [K, p, m], Cz [K, p, m, m], Cu [K, p, m, d],
    dz [K+1, m], Dz [K+1, m, m], Nz [K, d, m] where m = n + l d; the buffer holds du_{k-l} .. du_{k-1}
    (with a frame, m = n + L d and du_{k-L} .. du_{k-1}).
    """
    lqg = merged_if_undelayed(lqg)
    K, nx, nd, p, l = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.n_noise, lqg.frame_steps
    m = nx + l * nd
    dt = lqg.A.dtype
    Az = jnp.zeros((K, m, m), dt).at[:, :nx, :nx].set(lqg.A)
    Bz = jnp.zeros((K, m, nd), dt).at[:, :nx, :].set(lqg.B0)
    Cz = jnp.zeros((K, p, m, m), dt)
    Cu = jnp.zeros((K, p, m, nd), dt).at[:, :, :nx, :].set(lqg.C0)
    Nz = jnp.zeros((K, nd, m), dt).at[:, :, :nx].set(lqg.N)
    if l > 0:
        # du_{k-l} acts now: entry 0 of the buffer, or entry L - l of a frame (none for l = 0, where
        # merged_if_undelayed folded B1, C1 into B0, C0)
        # (here l is the buffer's length: the delay, or the frame L)
        # (per-channel delays: column j of B1, C1 reads entry L - l_j, channel j's component;
        # taps: column i reads entry L - l_i, channel i mod d's component, taps of a channel summed)
        entry = jnp.zeros((l, 1), dt).at[0].set(1.0) if lqg.delay_frame is None else \
            (jnp.arange(l)[:, None] == lqg.frame_steps - jnp.asarray(lqg.delay_steps)).astype(dt)
        at = lambda X: fold_taps(X[..., None, :] * entry, nd).reshape(X.shape[:-1] + (l * nd,))
        Az = Az.at[:, :nx, nx:].set(at(lqg.B1))
        Az = Az.at[:, nx:m - nd, nx + nd:].set(jnp.eye((l - 1) * nd, dtype=dt))  # buffer shifts
        Bz = Bz.at[:, m - nd:, :].set(jnp.eye(nd, dtype=dt))                # du_k enters last
        Cz = Cz.at[:, :, :nx, nx:].set(at(lqg.C1))
    cz = jnp.zeros((K, p, m), dt).at[:, :, :nx].set(lqg.c)
    dz = jnp.zeros((K + 1, m), dt).at[:, :nx].set(lqg.d)
    Dz = jnp.zeros((K + 1, m, m), dt).at[:, :nx, :nx].set(lqg.D)
    return dict(Az=Az, Bz=Bz, cz=cz, Cz=Cz, Cu=Cu, dz=dz, Dz=Dz, Nz=Nz)


def _augmented_step(carry, data, *, reg, gains_fn):
    v0, v, V, ok, warm = carry
    Az, Bz, cz, Cz, Cu, d_tilde, dz, Dz, e, E, Nz, bounds = data
    Vc = cz @ V                                                  # [p, m]
    VCz = jnp.einsum("mn,pnk->pmk", V, Cz)
    VCu = jnp.einsum("mn,pnd->pmd", V, Cu)
    Quu = _sym(E + Bz.T @ V @ Bz + jnp.einsum("pnd,pne->de", Cu, VCu))
    Quz = Bz.T @ V @ Az + jnp.einsum("pnd,pnk->dk", Cu, VCz) + Nz
    Qzz = Dz + Az.T @ V @ Az + jnp.einsum("pnk,pnm->km", Cz, VCz)
    qu = e + Bz.T @ v + jnp.einsum("pnd,pn->d", Cu, Vc)
    qz = dz + Az.T @ v + jnp.einsum("pnk,pn->k", Cz, Vc)
    q0 = d_tilde + v0 + jnp.sum(cz * Vc)
    step_ok, I, Kz = gains_fn(Quu, reg, qu, Quz, bounds, warm)
    # exact cost-to-go of the quadratic under the gains (equal to the Riccati update when reg = 0)
    W = 0.5 * Quu @ Kz + Quz
    carry = (q0 + I @ (Quu @ I + 2.0 * qu), qz + Kz.T @ (Quu @ I + qu) + Quz.T @ I,
             _sym(Qzz + Kz.T @ W + W.T @ Kz), ok & step_ok, I)
    return carry, (I, Kz) + carry[:3]


def augmented_backward_pass(lqg: DelayedLQG, reg=0.0) -> tuple[Gains, Value]:
    """The state-augmentation reference: same problem, same return types as [`backward_pass`][delayed_ilqr.lqg.backward_pass]."""
    return _augmented_backward_pass(lqg, checked_entry(lqg, reg, "lqg.augmented_backward_pass"))


@jax.jit
def _augmented_backward_pass(lqg: DelayedLQG, reg):
    _precision.require_x64("lqg.augmented_backward_pass")   # at tracing, which float32 always causes
    return augmented_scan(lqg, reg)


def augmented_scan(lqg: DelayedLQG, reg=0.0, gains_fn=unconstrained_gains, bounds=None):
    """Riccati recursion on z = [dx, du_{k-l}, ..., du_{k-1}]; ``gains_fn``/``bounds`` as in
    `structured.structured_scan`."""
    nx, nd, l = lqg.n_states, lqg.n_controls, lqg.frame_steps
    aug = augment(lqg)
    data = (aug["Az"], aug["Bz"], aug["cz"], aug["Cz"], aug["Cu"], lqg.d_tilde[:-1], aug["dz"][:-1],
            aug["Dz"][:-1], lqg.e, lqg.E, aug["Nz"], bounds)
    init = (lqg.d_tilde[-1], aug["dz"][-1], aug["Dz"][-1], jnp.asarray(True), jnp.zeros(nd, lqg.A.dtype))
    carry, (I, Kz, v0, v, V) = jax.lax.scan(partial(_augmented_step, reg=reg, gains_fn=gains_fn), init, data,
                                            reverse=True)
    v0 = _with_final(v0, init[0])
    v = _with_final(v, init[1])
    V = _with_final(V, init[2])
    K1 = v.shape[0]                                                   # K + 1
    gains = Gains(I, Kz[:, :, :nx], jnp.moveaxis(Kz[:, :, nx:].reshape(K1 - 1, nd, l, nd), 2, 1))
    value = Value(
        s_tilde=v0, s=v[:, :nx], S=V[:, :nx, :nx],
        r=v[:, nx:].reshape(K1, l, nd),
        Rt=jnp.moveaxis(V[:, :nx, nx:].reshape(K1, nx, l, nd), 2, 1),
        R=jnp.moveaxis(V[:, nx:, nx:].reshape(K1, l, nd, l, nd), 3, 2),
        positive_definite=carry[3])
    return gains, value
