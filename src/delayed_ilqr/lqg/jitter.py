"""The delayed LQG with a jittered input delay (docs/derivation.md §21): the structured backward
pass, the augmented reference, the exact expected cost of any law and its Monte Carlo.

At step k the command acting is du_{k-l_k}, with l_k drawn independently at every step from p over
0..L (``DelayJitter``; L = l_max), and ``lqg.B1``, ``lqg.C1`` are its matrices:

    dx_{k+1} = A dx_k + B0 du_k + B1 (du_{k-l_k} + delta_{k,l_k})
               + sum_j xi_{k,j} (c_j + C0_j du_k + C1_j (du_{k-l_k} + delta_{k,l_k}))

``delta`` [K, L+1, d] ("offsets", zero by default) is known per step and per delay: about a
nominal whose acting command is the mean u_bar_k = sum_l p_l u_{k-l}, the nominal command that
acts when the delay is l departs from it by delta_{k,l} = u_{k-l} - u_bar_k (the nonlinear
solver's linearisation, ``ilqg.jittered``). The controller does not see l_k; it keeps the L
commands du_{k-L}, ..., du_{k-1} that may still act, so the problem is an LQG on
z_k = [dx_k, du_{k-L}, ..., du_{k-1}] whose coefficients are random and independent from step
to step (multiplicative noise): its optimal law is affine in z_k, eq. (6) over the L commands in
flight, and its expected cost follows from exact second moments.

The ``lqg`` argument is a [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG] with ``delay_steps`` = L (no frame);
a point mass at l (``DelayJitter.fixed(l)``) is the delayed LQG at delay l in a frame of L slots.

* [`jittered_backward_pass`][delayed_ilqr.lqg.jittered_backward_pass]: Theorem 1 with the expectation over
  l_k taken inside the step, in eq. (6)'s order; per step O(L^2 d^3 + L n^2 d + n^3).
* [`jittered_augmented_pass`][delayed_ilqr.lqg.jittered_augmented_pass]: the Riccati recursion on z with
  the expectation over the L + 1 augmented systems (``lqg.augment`` at each delay): the reference.
* [`jittered_policy_cost`][delayed_ilqr.lqg.jittered_policy_cost]: the exact E[J] of any affine law,
  by propagating the mean and second moment of z (the mixture over l_k).
* [`simulate_jittered_lqg`][delayed_ilqr.lqg.simulate_jittered_lqg]: Monte Carlo, l_k drawn per step
  and trial.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from ..delay_jitter import DelayJitter
from .augmented import augment
from .exact import LQGRuns, checked_gains
from .gains import unconstrained_gains
from .law import augmented_feedback, closed_loop_affine, delayed_law
from .model import DelayedLQG, Gains, Stage, Value, checked_entry
from .stage import CostToGo, _noise

__all__ = ["jittered_backward_pass", "jittered_augmented_pass", "jittered_policy_cost", "simulate_jittered_lqg",
           "checked_jitter"]


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def checked_jitter(lqg: DelayedLQG, jitter, offsets, where: str):
    """(p [L+1], offsets [K, L+1, d]) after checking ``jitter`` against ``lqg`` (whose delay_steps
    must be the jitter's longest delay L, without a frame) and the offsets' shape."""
    if not isinstance(jitter, DelayJitter):
        raise TypeError(f"{where}: jitter must be a delayed_ilqr.DelayJitter; got {type(jitter).__name__}")
    if lqg.delay_frame is not None or not isinstance(lqg.delay_steps, int) or lqg.delay_steps != jitter.longest:
        raise ValueError(f"{where}: lqg.delay_steps must be the jitter's longest delay L = {jitter.longest} (the "
                         f"commands in flight), without a delay_frame; got delay_steps={lqg.delay_steps!r}, "
                         f"delay_frame={lqg.delay_frame!r}")
    K, L, nd = lqg.horizon, jitter.longest, lqg.n_controls
    if offsets is None:
        offsets = jnp.zeros((K, L + 1, nd), lqg.A.dtype)
    else:
        offsets = jnp.asarray(_validate.array(offsets, "offsets", (K, L + 1, nd)))
    return jnp.asarray(jitter.by_delay(), lqg.A.dtype), offsets


# ---------------------------------------------------------------------------------------------
# The structured pass
# ---------------------------------------------------------------------------------------------

def _jittered_step(stage: Stage, J: CostToGo, p, delta, reg, gains_fn=unconstrained_gains, bounds=None, warm=None):
    """Step k of §21: the law's gains at k and J(k) from J(k+1), the delay averaged over p.

    The pending commands are w_q = du_{k+q-L}, q = 0..L-1 (eq. 6's order); w_q acts at step k
    with probability p[L - q], du_k itself with p[0]. At k+1 the pending commands are
    (w_1, ..., w_{L-1}, du_k). The quadratic in (dx, w, du) is the one of `stage.stage_step`
    without any acting command, plus the acting command's terms, added with its probability at
    each place it can act (derivation §21, (21.3)).

    Args:
        stage: step k's model (B1, C1: the acting command's matrices); J: J(k+1) with L blocks.
        p: [L+1] P(l_k = l); delta: [L+1, d] the offsets delta_{k,l}.

    Returns:
        ((ok, I [d], L [d, n], M [L, d, d]), J(k)).
    """
    A, B0, B1, c, C0, C1 = stage.A, stage.B0, stage.B1, stage.c, stage.C0, stage.C1
    S, s = J.S, J.s
    L, n, nd = J.r.shape[0], A.shape[0], B0.shape[1]
    # the acting command a (+ delta) through the dynamics and the noise, against everything else
    Phi = B1.T @ S @ B1 + _noise(S, C1, C1)                       # a' Phi a
    psi = B1.T @ s + _noise(S, C1, c)                              # 2 a' psi
    Gam_x = B1.T @ S @ A                                           # 2 a' Gam_x dx
    Gam_u = B1.T @ S @ B0 + _noise(S, C1, C0)                      # 2 a' Gam_u du
    Lam = jnp.einsum("na,inb->iab", B1, J.Rt)                      # 2 a' Lam^i (pending i at k+1)
    p0, pw = p[0], p[1:][::-1]                                     # pw[q] = p[L - q]: w_q acts
    mean_delta = p @ delta
    dPhi = delta @ Phi.T                                           # [L+1, d] Phi delta_l
    # the quadratic without an acting command (stage.stage_step with B1 = C1 = 0)
    H = stage.E + B0.T @ S @ B0 + _noise(S, C0, C0)
    g = stage.e + B0.T @ s + _noise(S, C0, c)
    G_x = B0.T @ S @ A + stage.N
    q0 = stage.d_tilde + J.s_tilde + _noise(S, c, c)
    q_x = stage.d + A.T @ s
    Q_xx = stage.D + A.T @ S @ A
    if L > 0:
        last = L - 1
        H = H + J.R[last, last] + B0.T @ J.Rt[last] + J.Rt[last].T @ B0
        g = g + J.r[last]
        G_x = G_x + J.Rt[last].T @ A
        shift = lambda X: jnp.concatenate([jnp.zeros_like(X[:1]), X[:last]])   # block i from J(k+1)'s i - 1
        G_w = shift(jnp.einsum("na,inb->iab", B0, J.Rt) + J.R[last])
        q_w = shift(J.r)
        Q_xw = shift(jnp.einsum("mn,imb->inb", A, J.Rt))
        Q_ww = jnp.zeros((L, L, nd, nd), S.dtype).at[1:, 1:].set(J.R[:last, :last])
    # du_k acts (p0), including through the pending command it becomes at k+1 (Lam^{L-1})
    H = H + p0 * (Phi + Gam_u + Gam_u.T)
    g = g + p0 * (psi + dPhi[0]) + Gam_u.T @ mean_delta
    G_x = G_x + p0 * Gam_x
    q0 = q0 + p @ jnp.einsum("la,la->l", delta, dPhi) + 2 * mean_delta @ psi
    q_x = q_x + Gam_x.T @ mean_delta
    if L > 0:
        H = H + p0 * (Lam[last] + Lam[last].T)
        g = g + Lam[last].T @ mean_delta
        Lam_w = shift(Lam)                                         # Lam^{i-1}: a against w_i at k+1
        G_w = G_w + p0 * Lam_w
        q_w = q_w + jnp.einsum("iab,a->ib", Lam_w, mean_delta)
        # w_q acts (pw[q])
        q_w = q_w + pw[:, None] * (psi + dPhi[1:][::-1])
        Q_xw = Q_xw + pw[:, None, None] * Gam_x.T
        G_w = G_w + pw[:, None, None] * jnp.swapaxes(Gam_u + Lam[last], 0, 1)[None]
        cross = pw[:, None, None, None] * Lam_w[None]              # [q, i]: w_q against w_i
        Q_ww = Q_ww + cross + jnp.swapaxes(jnp.swapaxes(cross, 0, 1), 2, 3)
        Q_ww = Q_ww + jnp.einsum("q,qr,ab->qrab", pw, jnp.eye(L, dtype=S.dtype), Phi)
    else:
        G_w = jnp.zeros((0, nd, nd), S.dtype)
    H = _sym(H)
    G = jnp.concatenate([G_x, jnp.moveaxis(G_w, 0, 1).reshape(nd, L * nd)], axis=1)         # [d, n + L d]
    ok, I, Kfb = gains_fn(H, reg, g, G, bounds, warm)
    Lx, M = Kfb[:, :n], jnp.moveaxis(Kfb[:, n:].reshape(nd, L, nd), 1, 0)
    W = 0.5 * H @ Kfb + G
    W_x, W_w = W[:, :n], jnp.moveaxis(W[:, n:].reshape(nd, L, nd), 1, 0)
    HIg = H @ I + g
    s_tilde = q0 + I @ H @ I + 2 * I @ g
    s_new = q_x + Lx.T @ HIg + G_x.T @ I
    S_new = _sym(Q_xx + Lx.T @ W_x + W_x.T @ Lx)
    if L == 0:
        return (ok, I, Lx, M), CostToGo(s_tilde, s_new, S_new, J.r, J.Rt, J.R)
    r = q_w + jnp.einsum("iab,a->ib", M, HIg) + jnp.einsum("iab,a->ib", G_w, I)
    Rt = Q_xw + jnp.einsum("an,iab->inb", Lx, W_w) + jnp.einsum("an,iab->inb", W_x, M)
    R = Q_ww + jnp.einsum("iab,jac->ijbc", M, W_w) + jnp.einsum("iab,jac->ijbc", W_w, M)
    return (ok, I, Lx, M), CostToGo(s_tilde, s_new, S_new, r, Rt, R)


def jittered_scan(lqg: DelayedLQG, p, offsets, reg=0.0, gains_fn=unconstrained_gains, bounds=None):
    """The reverse scan of `_jittered_step` over a stored ``lqg``: (Gains, Value) (traced data, no checks)."""
    n, nd, L = lqg.n_states, lqg.n_controls, lqg.delay_steps
    dt = lqg.A.dtype
    rows = Stage(lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e,
                 lqg.E, lqg.N)
    final = CostToGo(lqg.d_tilde[-1], lqg.d[-1], lqg.D[-1], jnp.zeros((L, nd), dt), jnp.zeros((L, n, nd), dt),
                     jnp.zeros((L, L, nd, nd), dt))

    def step(carry, data):
        J, ok, warm = carry
        stage, delta, bound = data
        (step_ok, I, Lx, M), J = _jittered_step(stage, J, p, delta, reg, gains_fn, bound, warm)
        return (J, ok & step_ok, I), ((I, Lx, M), J)

    (_, ok, _), ((I, Lx, M), values) = jax.lax.scan(step, (final, jnp.asarray(True), jnp.zeros(nd, dt)),
                                                    (rows, offsets, bounds), reverse=True)
    value = Value(*(jnp.concatenate([v, f[None]]) for v, f in zip(values, final)), positive_definite=ok)
    return Gains(I, Lx, M), value


def jittered_backward_pass(lqg: DelayedLQG, jitter: DelayJitter, reg=0.0, offsets=None) -> tuple[Gains, Value]:
    """The optimal law (6) over the L commands in flight and its value (7) under the jittered delay
    ``jitter`` (derivation §21): structured, no augmentation.

    Args:
        lqg: the model, ``delay_steps`` = ``jitter.longest`` (B1, C1: the acting command's matrices).
        jitter: the distribution of the delay, drawn independently at every step.
        reg: the Levenberg-Marquardt shift of the gains (the value is the exact cost-to-go of the
            returned law, as in [`backward_pass`][delayed_ilqr.lqg.backward_pass]).
        offsets: optional [K, L+1, d] delta_{k,l} (module docstring); None: zero.

    Returns:
        (gains, value) shaped as [`backward_pass`][delayed_ilqr.lqg.backward_pass]'s at delay L;
        ``value.expected_cost`` is the exact E[J(0)] of the returned law.
    """
    reg = checked_entry(lqg, reg, "lqg.jittered_backward_pass")
    p, offsets = checked_jitter(lqg, jitter, offsets, "lqg.jittered_backward_pass")
    return _jittered_backward_pass(lqg, p, offsets, reg)


@jax.jit
def _jittered_backward_pass(lqg, p, offsets, reg):
    _precision.require_x64("lqg.jittered_backward_pass")
    return jittered_scan(lqg, p, offsets, reg)


# ---------------------------------------------------------------------------------------------
# The augmented reference and the exact cost
# ---------------------------------------------------------------------------------------------

def _modes(lqg: DelayedLQG, offsets):
    """The augmented system at every delay l = 0..L over the frame [du_{k-L}, ..., du_{k-1}]
    (``lqg.augment``, B1 and C1 reading entry L - l), with the offsets as constants:
    Az, Bz [L+1, K, ...], bz = [B1 delta_l; 0] [L+1, K, m], cz = [c + C1 delta_l; 0] [L+1, K, p, m],
    Cz, Cu; and the mode-free Nz, dz, Dz."""
    L = lqg.delay_steps
    systems = [augment(lqg.replace(delay_steps=l, delay_frame=L)) for l in range(L + 1)]
    stack = lambda name: jnp.stack([a[name] for a in systems])
    nx, m = lqg.n_states, systems[0]["Az"].shape[-1]
    delta = jnp.moveaxis(offsets, 1, 0)                                       # [L+1, K, d]
    bz = jnp.zeros(delta.shape[:2] + (m,), lqg.A.dtype).at[..., :nx].set(jnp.einsum("knd,lkd->lkn", lqg.B1, delta))
    cz = stack("cz").at[..., :nx].add(jnp.einsum("kpnd,lkd->lkpn", lqg.C1, delta))
    return dict(Az=stack("Az"), Bz=stack("Bz"), bz=bz, cz=cz, Cz=stack("Cz"), Cu=stack("Cu"),
                Nz=systems[0]["Nz"], dz=systems[0]["dz"], Dz=systems[0]["Dz"])


def _mode_quadratic(v, V, Az, Bz, bz, cz, Cz, Cu):
    """E over the noise of [J(k+1) at z' = Az z + Bz u + bz + noise] for one delay, as
    (Quu, Quz, Qzz, qu, qz, q0) of the quadratic in (z, u) (stage cost excluded)."""
    Vc = cz @ V
    VCz = jnp.einsum("mn,pnk->pmk", V, Cz)
    VCu = jnp.einsum("mn,pnd->pmd", V, Cu)
    vb = v + V @ bz
    return (Bz.T @ V @ Bz + jnp.einsum("pnd,pne->de", Cu, VCu),
            Bz.T @ V @ Az + jnp.einsum("pnd,pnk->dk", Cu, VCz),
            Az.T @ V @ Az + jnp.einsum("pnk,pnm->km", Cz, VCz),
            Bz.T @ vb + jnp.einsum("pnd,pn->d", Cu, Vc),
            Az.T @ vb + jnp.einsum("pnk,pn->k", Cz, Vc),
            2 * bz @ v + bz @ V @ bz + jnp.sum(cz * Vc))


def jittered_augmented_scan(lqg: DelayedLQG, p, offsets, reg=0.0, gains_fn=unconstrained_gains, bounds=None):
    """The Riccati recursion on z with E over l_k: each term of the quadratic in (z, u) is the
    p-weighted sum of those of the L + 1 augmented systems; ``gains_fn``/``bounds`` as in
    `jittered_scan`. (Gains, Value) (traced, no checks)."""
    nx, nd, L = lqg.n_states, lqg.n_controls, lqg.delay_steps
    modes = _modes(lqg, offsets)
    per_step = {name: jnp.moveaxis(modes[name], 0, 1) for name in ("Az", "Bz", "bz", "cz", "Cz", "Cu")}

    def step(carry, data):
        v0, v, V, ok, warm = carry
        Az, Bz, bz, cz, Cz, Cu, d_tilde, dz, Dz, e, E, Nz, bound = data
        terms = jax.vmap(_mode_quadratic, in_axes=(None, None, 0, 0, 0, 0, 0, 0))(v, V, Az, Bz, bz, cz, Cz, Cu)
        Quu, Quz, Qzz, qu, qz, q0 = (jnp.tensordot(p, t, axes=1) for t in terms)
        Quu, Quz, Qzz = _sym(E + Quu), Quz + Nz, Dz + Qzz
        qu, qz, q0 = e + qu, dz + qz, d_tilde + v0 + q0
        step_ok, I, Kz = gains_fn(Quu, reg, qu, Quz, bound, warm)
        W = 0.5 * Quu @ Kz + Quz
        carry = (q0 + I @ (Quu @ I + 2.0 * qu), qz + Kz.T @ (Quu @ I + qu) + Quz.T @ I,
                 _sym(Qzz + Kz.T @ W + W.T @ Kz), ok & step_ok, I)
        return carry, (I, Kz) + carry[:3]

    data = tuple(per_step[name] for name in ("Az", "Bz", "bz", "cz", "Cz", "Cu")) + (
        lqg.d_tilde[:-1], modes["dz"][:-1], modes["Dz"][:-1], lqg.e, lqg.E, modes["Nz"], bounds)
    init = (lqg.d_tilde[-1], modes["dz"][-1], modes["Dz"][-1], jnp.asarray(True), jnp.zeros(nd, lqg.A.dtype))
    carry, (I, Kz, v0, v, V) = jax.lax.scan(step, init, data, reverse=True)
    v0, v, V = (jnp.concatenate([x, f[None]]) for x, f in zip((v0, v, V), init[:3]))
    K1 = v.shape[0]
    gains = Gains(I, Kz[:, :, :nx], jnp.moveaxis(Kz[:, :, nx:].reshape(K1 - 1, nd, L, nd), 2, 1))
    value = Value(s_tilde=v0, s=v[:, :nx], S=V[:, :nx, :nx], r=v[:, nx:].reshape(K1, L, nd),
                  Rt=jnp.moveaxis(V[:, :nx, nx:].reshape(K1, nx, L, nd), 2, 1),
                  R=jnp.moveaxis(V[:, nx:, nx:].reshape(K1, L, nd, L, nd), 3, 2), positive_definite=carry[3])
    return gains, value


def jittered_augmented_pass(lqg: DelayedLQG, jitter: DelayJitter, reg=0.0, offsets=None) -> tuple[Gains, Value]:
    """The reference for [`jittered_backward_pass`][delayed_ilqr.lqg.jittered_backward_pass]: same arguments,
    same results, by the Riccati recursion on the augmented state; per step O(L (n + L d)^3)."""
    reg = checked_entry(lqg, reg, "lqg.jittered_augmented_pass")
    p, offsets = checked_jitter(lqg, jitter, offsets, "lqg.jittered_augmented_pass")
    return _jittered_augmented_pass(lqg, p, offsets, reg)


@jax.jit
def _jittered_augmented_pass(lqg, p, offsets, reg):
    _precision.require_x64("lqg.jittered_augmented_pass")
    return jittered_augmented_scan(lqg, p, offsets, reg)


def _mode_moments(mu, X, Acl, bcl, Gcol, gcol):
    """(E[z'], E[z' z'']) for one delay: z' = Acl z + bcl + sum_j xi_j (Gcol_j z + gcol_j)."""
    Am = Acl @ mu
    X_new = Acl @ X @ Acl.T + jnp.outer(Am, bcl) + jnp.outer(bcl, Am) + jnp.outer(bcl, bcl)
    Gm = jnp.einsum("pnk,k->pn", Gcol, mu)
    X_new = X_new + jnp.einsum("pnk,kl,pml->nm", Gcol, X, Gcol) + jnp.einsum("pn,pm->nm", Gm, gcol) \
        + jnp.einsum("pn,pm->nm", gcol, Gm) + jnp.einsum("pn,pm->nm", gcol, gcol)
    return Am + bcl, X_new


def jittered_moments_and_cost(lqg: DelayedLQG, p, offsets, gains: Gains):
    """(mean [K+1, m], second moment [K+1, m, m] of z, E[J]) of the affine law ``gains`` under the
    jittered delay: the moments of z_{k+1} are the p-weighted sums over l_k of those of each
    augmented system (l_k is independent of z_k), the stage cost does not depend on l_k."""
    modes = _modes(lqg, offsets)
    Kz = augmented_feedback(gains)
    nz = Kz.shape[2]

    def step(carry, data):
        mu, X, total = carry
        Az, Bz, bz, cz, Cz, Cu, I, Kk, d_tilde, dz, Dz, e, E, Nz = data
        Eu = delayed_law(I, Kk, mu)
        Euu = jnp.outer(I, I) + Kk @ jnp.outer(mu, I) + jnp.outer(I, mu) @ Kk.T + Kk @ X @ Kk.T
        Ezu = jnp.outer(mu, I) + X @ Kk.T
        total = total + d_tilde + 2 * dz @ mu + jnp.sum(Dz * X) + 2 * e @ Eu + jnp.sum(E * Euu) \
            + 2 * jnp.sum(Nz.T * Ezu)

        def one(Az, Bz, bz, cz, Cz, Cu):
            Acl, bcl = closed_loop_affine(Az, Bz, I, Kk)
            Gcol, CuI = closed_loop_affine(Cz, Cu, I, Kk)
            return _mode_moments(mu, X, Acl, bcl + bz, Gcol, cz + CuI)

        mus, Xs = jax.vmap(one)(Az, Bz, bz, cz, Cz, Cu)
        mu_new, X_new = p @ mus, _sym(jnp.tensordot(p, Xs, axes=1))
        return (mu_new, X_new, total), (mu_new, X_new)

    dt = lqg.A.dtype
    init = (jnp.zeros(nz, dt), jnp.zeros((nz, nz), dt), jnp.asarray(0.0, dt))
    per_step = tuple(jnp.moveaxis(modes[name], 0, 1) for name in ("Az", "Bz", "bz", "cz", "Cz", "Cu"))
    data = per_step + (gains.feedforward, Kz, lqg.d_tilde[:-1], modes["dz"][:-1], modes["Dz"][:-1], lqg.e, lqg.E,
                       modes["Nz"])
    (mu, X, total), (mus, Xs) = jax.lax.scan(step, init, data)
    total = total + lqg.d_tilde[-1] + 2 * modes["dz"][-1] @ mu + jnp.sum(modes["Dz"][-1] * X)
    return jnp.concatenate([init[0][None], mus]), jnp.concatenate([init[1][None], Xs]), total


def jittered_policy_cost(lqg: DelayedLQG, jitter: DelayJitter, gains: Gains, offsets=None) -> jax.Array:
    """Exact E[J(0)] of the affine law ``gains`` (eq. 6 over the L commands in flight) under the
    jittered delay, by propagating the mean and second moment of z (no sampling, no recursion on
    the value); per step O(L (n + L d)^3)."""
    checked_entry(lqg, 0.0, "lqg.jittered_policy_cost")
    p, offsets = checked_jitter(lqg, jitter, offsets, "lqg.jittered_policy_cost")
    return _jittered_policy_cost(lqg, p, offsets, checked_gains(lqg, gains))


@jax.jit
def _jittered_policy_cost(lqg, p, offsets, gains):
    _precision.require_x64("lqg.jittered_policy_cost")
    return jittered_moments_and_cost(lqg, p, offsets, gains)[2]


@partial(jax.jit, static_argnames=("n_trials",))
def _simulate_jittered(lqg: DelayedLQG, gains: Gains, offsets, jitter: DelayJitter, n_trials: int, key):
    K, nx, nd, p, L = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.n_noise, lqg.delay_steps
    dt = lqg.A.dtype

    def trial(trial_key):
        xi = jax.random.normal(trial_key, (K, p), dt)
        delays = jitter.sample(jax.random.fold_in(trial_key, 2), (K,))

        def step(carry, data):
            dx, pending = carry                                   # pending[i] = du_{k-L+i}
            A, B0, B1, c, C0, C1, I, LM, xik, lk, delta, d_tilde, dv, D, e, E, Nxu = data
            du = delayed_law(I, LM, jnp.concatenate([dx, pending.reshape(-1)]))
            acting = du if L == 0 else jnp.where(lk == 0, du, pending[jnp.clip(L - lk, 0, L - 1)])
            acting = acting + delta[lk]
            dx_new = A @ dx + B0 @ du + B1 @ acting + xik @ (c + C0 @ du + C1 @ acting)
            cost = d_tilde + 2 * dx @ dv + dx @ D @ dx + 2 * du @ e + du @ E @ du + 2 * du @ Nxu @ dx
            pending = jnp.concatenate([pending[1:], du[None]]) if L > 0 else pending
            return (dx_new, pending), (dx, du, cost)

        data = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, gains.feedforward, augmented_feedback(gains), xi,
                delays, offsets, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E, lqg.N)
        (dxK, _), (dx, du, cost) = jax.lax.scan(step, (jnp.zeros(nx, dt), jnp.zeros((L, nd), dt)), data)
        final = lqg.d_tilde[-1] + 2 * dxK @ lqg.d[-1] + dxK @ lqg.D[-1] @ dxK
        return jnp.concatenate([dx, dxK[None]]), du, jnp.sum(cost) + final

    return LQGRuns(*jax.vmap(trial)(jax.random.split(key, n_trials)))


def simulate_jittered_lqg(lqg: DelayedLQG, jitter: DelayJitter, gains: Gains, n_trials: int, seed: int = 0,
                          offsets=None) -> LQGRuns:
    """Monte Carlo of the jittered linear system under ``gains``: in each trial the delay l_k is
    drawn at every step from ``jitter`` (key ``fold_in(trial_key, 2)``), the noise from the
    trial's key as in [`simulate_lqg`][delayed_ilqr.lqg.simulate_lqg]; reproducible from ``seed``."""
    _precision.require_x64("lqg.simulate_jittered_lqg")
    checked_entry(lqg, 0.0, "lqg.simulate_jittered_lqg")
    _, offsets = checked_jitter(lqg, jitter, offsets, "lqg.simulate_jittered_lqg")
    n_trials = _validate.positive_int(n_trials, "n_trials")
    seed = _validate.seed(seed)
    return _simulate_jittered(lqg, checked_gains(lqg, gains), offsets, jitter, n_trials, jax.random.PRNGKey(seed))
