"""One step of Theorem 1, J(k+1) -> J(k), written as the mathematics (docs/derivation.md §3-4).

This is the readable statement of the recursion: the pending commands in eq. (6)'s order
(w_i = du_{k+i-l}, i = 0..l-1), one block per formula, no slot frame, no fused products, no
kernels. The library runs the fused form (`structured`); tests/test_stage.py holds the two
equal, step by step, and this step equal to the augmented-state reference.

At step k the variables are dx_k, the pending commands w_0..w_{l-1} and the new command du_k. One
step later dx_{k+1} = A dx_k + B0 du_k + B1 w_0 + noise, and the pending commands are
(w_1, ..., w_{l-1}, du_k): w_i moves to position i-1 and du_k enters at l-1. Substituting this into
J(k+1) (eq. 7) and adding the stage cost (eq. 4) gives a quadratic in (y, du_k), y = [dx; w]:

    Q(y, du) = q0 + 2 y'q_y + y'Q_yy y + 2 du'(g + G y) + du'H du,      G = [G_x, G_0, ..., G_{l-1}],

with, writing sum_j X_j'S Y_j over the noise columns as <X, Y> (X, Y among c, C0, C1) and the
blocks of J(k+1) as s_tilde', s', S', r'^i, Rt'^i, R'^ij (last = l - 1):

    H   = E + B0'S'B0 + <C0, C0> + R'^{last,last} + B0'Rt'^{last} + Rt'^{last}'B0
    g   = e + B0's' + <C0, c> + r'^{last}
    G_x = B0'S'A + N + Rt'^{last}'A
    G_0 = B0'S'B1 + <C0, C1> + Rt'^{last}'B1              (w_0 acts now, through B1)
    G_i = B0'Rt'^{i-1} + R'^{last,i-1}                     (i >= 1: w_i is pending at k+1)

and the blocks of q0, q_y, Q_yy listed in `_free_quadratic`. For l = 0 there is no w, and
B1, C1 act on du_k (they are folded into B0, C0). A gain rule (`gains`) returns
du = I + Kfb y, Kfb = [L, M^0, ..., M^{l-1}]; the value J(k) is the exact cost-to-go under those
gains (derivation §4), with W = H Kfb / 2 + G:

    J(k) = Q_yy + Kfb'W + W'Kfb,   q_y + Kfb'(H I + g) + G'I,   q0 + I'H I + 2 I'g.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .gains import unconstrained_gains
from .model import Stage

__all__ = ["CostToGo", "StageGains", "stage_step"]


class CostToGo(NamedTuple):
    """The coefficients of J(k), eq. (7), at one k, the pending blocks in eq. (6)'s order.

    Attributes: s_tilde []; s [n]; S [n, n]; r [l, d]; Rt [l, n, d]; R [l, l, d, d].
    """

    s_tilde: jax.Array
    s: jax.Array
    S: jax.Array
    r: jax.Array
    Rt: jax.Array
    R: jax.Array


class StageGains(NamedTuple):
    """The law (6) at one step: I [d], L [d, n], M [l, d, d]; ok: the gain rule succeeded."""

    feedforward: jax.Array
    state_feedback: jax.Array
    delay_feedback: jax.Array
    ok: jax.Array


def _noise(S, X, Y):
    """<X, Y> = sum_j X_j' S Y_j over the p noise columns; X_j, Y_j are rows of c [p, n] or of
    C0, C1 [p, n, d]."""
    x, y = ("jna" if X.ndim == 3 else "jn"), ("jmb" if Y.ndim == 3 else "jm")
    return jnp.einsum(f"{x},nm,{y}->{x[2:]}{y[2:]}", X, S, Y)


def _blocks(X, Y):
    """[X_i' Y_j]_ij for X, Y [l, a, b] stacks of blocks: [l, l, b, b]."""
    return jnp.einsum("iab,jac->ijbc", X, Y)


def _action_terms(stage: Stage, J: CostToGo, l: int):
    """H [d, d], g [d], G_x [d, n] and G_w = [G_0, ..., G_{l-1}] [l, d, d] of the quadratic in du_k."""
    A, B0, B1, c, C0, C1 = stage.A, stage.B0, stage.B1, stage.c, stage.C0, stage.C1
    S, s = J.S, J.s
    H = stage.E + B0.T @ S @ B0 + _noise(S, C0, C0)
    g = stage.e + B0.T @ s + _noise(S, C0, c)
    G_x = B0.T @ S @ A + stage.N
    if l == 0:
        return H, g, G_x, jnp.zeros((0,) + H.shape, H.dtype)
    last = l - 1                                          # du_k's position in J(k+1)
    H = H + J.R[last, last] + B0.T @ J.Rt[last] + J.Rt[last].T @ B0
    g = g + J.r[last]
    G_x = G_x + J.Rt[last].T @ A
    G_0 = B0.T @ S @ B1 + _noise(S, C0, C1) + J.Rt[last].T @ B1
    G_i = jnp.einsum("na,inb->iab", B0, J.Rt[:last]) + J.R[last, :last]             # i = 1..l-1
    return H, g, G_x, jnp.concatenate([G_0[None], G_i])


def _free_quadratic(stage: Stage, J: CostToGo, l: int):
    """The part of the quadratic without du_k: q0 [], q_y = (q_x [n], q_w [l, d]) and
    Q_yy = (Q_xx [n, n], Q_xw [l, n, d], Q_ww [l, l, d, d])."""
    A, B1, c, C1 = stage.A, stage.B1, stage.c, stage.C1
    S, s = J.S, J.s
    q0 = stage.d_tilde + J.s_tilde + _noise(S, c, c)
    q_x = stage.d + A.T @ s
    Q_xx = stage.D + A.T @ S @ A
    # w_0 acts now (through B1 and C1); w_i, i >= 1, is pending at k+1 in position i-1
    q_w = jnp.concatenate([(B1.T @ s + _noise(S, C1, c))[None], J.r[:l - 1]])
    Q_xw = jnp.concatenate([(A.T @ S @ B1)[None], jnp.einsum("mn,imb->inb", A, J.Rt[:l - 1])])
    Q_0w = jnp.concatenate([(B1.T @ S @ B1 + _noise(S, C1, C1))[None],          # w_0 against w_j
                            jnp.einsum("na,jnb->jab", B1, J.Rt[:l - 1])])
    Q_ww = jnp.zeros((l, l) + Q_0w.shape[1:], S.dtype).at[1:, 1:].set(J.R[:l - 1, :l - 1])
    Q_ww = Q_ww.at[0].set(Q_0w).at[1:, 0].set(jnp.swapaxes(Q_0w[1:], -1, -2))
    return q0, (q_x, q_w), (Q_xx, Q_xw, Q_ww)


def stage_step(stage: Stage, J: CostToGo, reg=0.0, gains_fn=unconstrained_gains, bounds=None, warm=None):
    """Theorem 1's step k: the gains of the law (6) at k and J(k), from J(k+1) and step k's model.

    Args:
        stage: step k's model (eq. 3-4).
        J: J(k+1), with l pending blocks (l = ``J.r.shape[0]``).
        reg: the Levenberg-Marquardt shift of the gains (H + reg I).
        gains_fn, bounds, warm: the gain rule and its per-step data (see `gains`).

    Returns:
        (`StageGains`, J(k) as a `CostToGo`).
    """
    l, (n, nd) = J.r.shape[0], stage.B0.shape
    if l == 0:
        stage = stage._replace(B0=stage.B0 + stage.B1, B1=jnp.zeros_like(stage.B1),
                               C0=stage.C0 + stage.C1, C1=jnp.zeros_like(stage.C1))
    H, g, G_x, G_w = _action_terms(stage, J, l)
    H = 0.5 * (H + H.T)
    G = jnp.concatenate([G_x, jnp.moveaxis(G_w, 0, 1).reshape(nd, l * nd)], axis=1)      # [d, n + l d]
    ok, I, Kfb = gains_fn(H, reg, g, G, bounds, warm)
    L, M = Kfb[:, :n], jnp.moveaxis(Kfb[:, n:].reshape(nd, l, nd), 1, 0)              # M [l, d, d]
    W = 0.5 * H @ Kfb + G
    W_x, W_w = W[:, :n], jnp.moveaxis(W[:, n:].reshape(nd, l, nd), 1, 0)
    HIg = H @ I + g
    gains = StageGains(I, L, M, ok)
    q0, (q_x, q_w), (Q_xx, Q_xw, Q_ww) = _free_quadratic(stage, J, l) if l else _free_state_part(stage, J)
    s_tilde = q0 + I @ H @ I + 2 * I @ g
    s = q_x + L.T @ HIg + G_x.T @ I
    S = Q_xx + L.T @ W_x + W_x.T @ L
    if l == 0:
        return gains, CostToGo(s_tilde, s, S, J.r, J.Rt, J.R)
    r = q_w + jnp.einsum("iab,a->ib", M, HIg) + jnp.einsum("iab,a->ib", G_w, I)
    Rt = Q_xw + jnp.einsum("an,iab->inb", L, W_w) + jnp.einsum("an,iab->inb", W_x, M)
    R = Q_ww + _blocks(M, W_w) + _blocks(W_w, M)
    return gains, CostToGo(s_tilde, s, S, r, Rt, R)


def _free_state_part(stage: Stage, J: CostToGo):
    """`_free_quadratic` for l = 0: no pending command."""
    q0 = stage.d_tilde + J.s_tilde + _noise(J.S, stage.c, stage.c)
    return q0, (stage.d + stage.A.T @ J.s, None), (stage.D + stage.A.T @ J.S @ stage.A, None, None)
