"""Gain rules: how one step of a backward pass turns its quadratic in du into the law's gains.

Every backward pass (structured, augmented, the readable `stage`) minimises, at each step,

    du'H du + 2 du'(g + G y)        over du,   y = the step's other variables ([dx; pending])

and asks a gain rule ``(H, reg, g, G, bounds, warm) -> (ok, I, Kfb)`` for the affine minimiser
du = I + Kfb y, with H replaced by H + reg I (the Levenberg-Marquardt shift). ``bounds`` are the
step's limits on du (or None) and ``warm`` the feedforward of the step after (a warm start); ``ok``
is False where the rule failed (H + reg I not positive definite), and the gains are then non-finite.
The value update that follows is exact for whatever gains the rule returns (docs/derivation.md §4).
"""
from __future__ import annotations

import jax.numpy as jnp

from .._kernels.dense import cholesky_solve
from .boxqp import box_qp, free_solve

__all__ = ["unconstrained_gains", "boxed_gains", "clamped_gains", "unregularized_feedback"]


def unconstrained_gains(H, reg, g, G, bounds=None, warm=None):
    """Minimiser of du'H du + 2 du'(g + G y) with H replaced by H + reg I: (ok, I, Kfb = [d, m])."""
    nd = H.shape[0]
    ok, sol = cholesky_solve(H + reg * jnp.eye(nd, dtype=H.dtype), jnp.concatenate([g[:, None], G], axis=1))
    return ok, -sol[:, 0], -sol[:, 1:]


def margin_width(margin, lower, upper):
    """The width of the epsilon-active set: ``margin`` times the box's width upper - lower (the
    range u_max - u_min of each command), or ``margin`` itself (in the command's unit) for a
    command bounded on one side only, whose range is infinite (an infinite width would take the
    feedback of every such command, however far from its bound)."""
    width = upper - lower
    return margin * jnp.where(jnp.isfinite(width), width, 1.0)


def boxed_gains(H, reg, g, G, bounds, warm, margin=0.0):
    """Control-limited step (Tassa, Mansard & Todorov 2014): the feedforward solves the box QP
    min du'(H + reg I) du + 2 du'g over lower <= du <= upper (warm-started from the next step's),
    and the feedback acts only in the free directions: rows of L and of every M^i are zero for
    clamped commands.

    Commands whose nominal lies at a bound, or within ``margin * (upper - lower)`` of one (lower or
    upper within that distance of du = 0; `margin_width`), get no feedback either, even when the QP frees them to
    move inward (an epsilon-active set, as in Bertsekas' projected Newton method). Their feedback would
    push them outside as often as inside, the forward pass clips it, and the steps upstream, which
    were planned on that feedback, then miss: the first-order prediction fails for every step
    size and the solve crawls. The feedforward still moves them inward, and at the solution
    (I = 0) the stationarity conditions do not depend on the gains (derivation §13).

    ``bounds`` is (lower, upper) or (lower, upper, held): ``held`` [d] bool marks commands that
    get no feedback whatever their nominal (the noisy solver's feedback latch, derivation §12).
    """
    lower, upper = bounds[:2]
    H_reg = H + reg * jnp.eye(H.shape[0], dtype=H.dtype)
    # The QP's stopping tests are absolute (|grad| < 1e-8): scaled as given (H ~ dt Q ~ 1e-6 in
    # motor tasks) it stops far from the optimum, with a wrong active set. The same QP divided by
    # the largest diagonal entry has the same minimiser and tests that are relative.
    scale = jnp.max(jnp.abs(jnp.diag(H_reg)))
    scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
    qp = box_qp(H_reg / scale, g / scale, lower, upper, warm)
    # once the active set is known, the free part is one exact Newton solve
    clamped = jnp.where(qp.free, 0.0, qp.x)
    I = jnp.clip(clamped + free_solve(H_reg, qp.free, g + H_reg @ clamped), lower, upper)
    eps = margin_width(margin, lower, upper)
    feedback = qp.free & (lower < -eps) & (upper > eps)
    if len(bounds) > 2:
        feedback = feedback & ~bounds[2]
    Kfb = free_solve(H_reg, feedback, G)
    ok = (qp.status != -1) & jnp.all(jnp.isfinite(Kfb)) & jnp.all(jnp.isfinite(I))
    return ok, I, Kfb


def clamped_gains(H, reg, g, G, bounds, warm=None):
    """The minimiser with some commands held fixed: ``bounds = (lower, upper)`` [d] marks command i
    as fixed at du_i = lower_i where lower_i == upper_i, and free where they differ (the free
    commands are not bounded). The free part is the Newton solve of the reduced quadratic,
    I_f = -(H_ff + reg I)^{-1} (g + H du_c)_f, and only free commands get feedback (rows of L and of
    every M^i are zero for the fixed ones). ``warm`` is unused. The bounded solver's projected
    Newton method (``ilqg.bounded``) passes its active set this way.
    """
    lower, upper = bounds
    fixed = lower == upper
    H_reg = H + reg * jnp.eye(H.shape[0], dtype=H.dtype)
    held = jnp.where(fixed, lower, 0.0)
    I = held + free_solve(H_reg, ~fixed, g + H_reg @ held)
    Kfb = free_solve(H_reg, ~fixed, G)
    return jnp.all(jnp.isfinite(Kfb)) & jnp.all(jnp.isfinite(I)), I, Kfb


def unregularized_feedback(gains_fn):
    """``gains_fn`` with the feedback of its unregularised step (reg = 0) wherever that step exists.

    The feedforward keeps ``reg``: lambda only shortens the step. With control-dependent noise the
    value Hessians S depend on the feedback (the noise cost c'S c is part of the recursion), so
    regularised feedback would make the merit of one nominal (cost + sum c'S c, derivation §12)
    change with lambda, and the acceptance test would compare different objectives from one
    iteration to the next: on the noisy six-muscle arm 0 of the 24 center-out reaches converged
    without this and 23 with it (derivation §12). Where H is not positive definite the
    regularised feedback is kept. ``gains_fn`` runs twice even at reg = 0, without a ``lax.cond``
    (docs/performance.md#unregularized_feedback).
    """
    def gains(H, reg, g, G, bounds=None, warm=None):
        ok, I, Kfb = gains_fn(H, reg, g, G, bounds, warm)
        ok_0, _, Kfb_0 = gains_fn(H, 0.0, g, G, bounds, warm)
        return ok, I, jnp.where(ok_0, Kfb_0, Kfb)

    return gains
