"""The delayed LQG problem of eq. (3)-(5) and its exact solutions.

The system, in deviations from a nominal trajectory (time-major arrays, k = 0..K-1)::

    dx_{k+1} = A_k dx_k + B0_k du_k + B1_k du_{k-l} + sum_j xi_{k,j} (c_{k,j} + C0_{k,j} du_k + C1_{k,j} du_{k-l})
    cost_k   = d_tilde_k + 2 dx_k'd_k + dx_k'D_k dx_k + 2 du_k'e_k + du_k'E_k du_k          (eq. 4)
               + 2 du_k'N_k dx_k                           (cross term, zero in eq. 4)
    cost_K   = d_tilde_K + 2 dx_K'd_K + dx_K'D_K dx_K

with dx_0 = 0, du_k = 0 for k < 0 and xi_{k,j} ~ N(0, 1) independent. For l = 0 the "delayed"
command is the current one: B1 and C1 act on du_k like B0 and C0.

Three solutions of the same problem live here:

* :func:`backward_pass`: Theorem 1 (eq. 6-8), the structured recursion on the value function (7),
  with the corrections of ``docs/derivation.md``. Per step it costs O(l^2 d^3 + l n^2 d + n^3).
* :func:`augmented_backward_pass`: the independent reference, a plain Riccati recursion on the
  augmented state z_k = [dx_k, du_{k-l}, ..., du_{k-1}]; per step O((n + l d)^3).
* :func:`policy_cost`: the exact expected cost of *any* affine delayed policy, by propagating the
  mean and second moment of z_k (no sampling); :func:`simulate_lqg` estimates it by Monte Carlo.

Both backward passes accept a Levenberg-Marquardt shift ``reg`` (the solver's lambda): the gains
use H + reg I, and the value function is the exact cost-to-go of the quadratic model under those
gains (see ``docs/derivation.md`` §4), so that J(0) is always the true cost of the returned policy.
"""
from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _precision, _validate
from ._dense import cholesky_solve, matmul, matmul_t
from ._scan import packed_scan

__all__ = [
    "DelayedLQG",
    "Gains",
    "SlotGains",
    "StepModels",
    "stored_models",
    "to_slots",
    "from_slots",
    "Value",
    "LQGRuns",
    "backward_pass",
    "augmented_backward_pass",
    "policy_cost",
    "simulate_lqg",
]

_ARRAY_FIELDS = ("A", "B0", "B1", "c", "C0", "C1", "d_tilde", "d", "D", "e", "E", "N")


class DelayedLQG:
    """The discrete delayed LQG approximation of eq. (3)-(4).

    Args:
        A: [K, n, n] state transition.
        B0: [K, n, d] effect of the command sent now, du_k.
        B1: [K, n, d] effect of the command sent l steps ago, du_{k-l}.
        c: [K, p, n] noise columns (j-th column of the diffusion, already times sqrt(dt)).
        C0: [K, p, n, d] control-dependent part of noise column j on du_k.
        C1: [K, p, n, d] control-dependent part of noise column j on du_{k-l}.
        d_tilde: [K+1] constant cost terms.
        d: [K+1, n] linear state cost (factor-2 convention of eq. 4).
        D: [K+1, n, n] quadratic state cost, symmetric.
        e: [K, d] linear control cost.
        E: [K, d, d] quadratic control cost, symmetric.
        delay_steps: l >= 0, the input delay in steps.
        N: optional [K, d, n] cross cost 2 du_k'N_k dx_k (absent from eq. 4, which is N = 0; a
            general running cost l(x, u) has one).

    ``p = 0`` (no noise) is allowed: pass arrays with a zero-length second axis, or ``None`` for
    c, C0 and C1 together. Instances are JAX pytrees whose only static field is ``delay_steps``.
    """

    def __init__(self, A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, delay_steps, N=None):
        _precision.require_x64("lqg.DelayedLQG")
        self.delay_steps = _validate.delay_steps(delay_steps)
        A = _validate.array(A, "A", (None, None, None))
        K, n = A.shape[0], A.shape[1]
        if K < 1:
            raise ValueError(f"A must hold at least one time step (K >= 1); got shape {A.shape}")
        A = _validate.array(A, "A", (K, n, n))
        B0 = _validate.array(B0, "B0", (K, n, None))
        nd = B0.shape[2]
        B1 = _validate.array(B1, "B1", (K, n, nd))
        if c is None and C0 is None and C1 is None:
            c, C0, C1 = np.zeros((K, 0, n)), np.zeros((K, 0, n, nd)), np.zeros((K, 0, n, nd))
        c = _validate.array(c, "c", (K, None, n))
        p = c.shape[1]
        C0 = _validate.array(C0, "C0", (K, p, n, nd))
        C1 = _validate.array(C1, "C1", (K, p, n, nd))
        d_tilde = _validate.array(d_tilde, "d_tilde", (K + 1,))
        d = _validate.array(d, "d", (K + 1, n))
        D = _check_symmetric(_validate.array(D, "D", (K + 1, n, n)), "D")
        e = _validate.array(e, "e", (K, nd))
        E = _check_symmetric(_validate.array(E, "E", (K, nd, nd)), "E")
        N = np.zeros((K, nd, n)) if N is None else _validate.array(N, "N", (K, nd, n))
        for name, value in zip(_ARRAY_FIELDS, (A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, N)):
            setattr(self, name, jnp.asarray(value))

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def horizon(self) -> int:
        """K, the number of control steps."""
        return self.A.shape[0]

    @property
    def n_states(self) -> int:
        return self.A.shape[1]

    @property
    def n_controls(self) -> int:
        return self.B0.shape[2]

    @property
    def n_noise(self) -> int:
        return self.c.shape[1]

    @classmethod
    def from_traced(cls, *, delay_steps: int, **arrays) -> "DelayedLQG":
        """Builds an instance from (possibly traced) arrays without validation: for use inside jit,
        where the arrays come from the library's own linearisation."""
        return _unflatten(delay_steps, tuple(arrays[name] for name in _ARRAY_FIELDS))

    def replace(self, **changes) -> "DelayedLQG":
        """A copy with some arrays replaced (no validation: for internal use on traced data)."""
        new = object.__new__(DelayedLQG)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def __repr__(self) -> str:
        return (f"DelayedLQG(K={self.horizon}, n={self.n_states}, d={self.n_controls}, "
                f"p={self.n_noise}, delay_steps={self.delay_steps})")


def _check_symmetric(mat: np.ndarray, name: str) -> np.ndarray:
    asym = np.max(np.abs(mat - np.swapaxes(mat, -1, -2)), initial=0.0)
    if asym > 1e-9 * max(1.0, float(np.max(np.abs(mat), initial=0.0))):
        raise ValueError(f"{name} must be symmetric in its last two axes; got an asymmetry of {asym:.3g}")
    return mat


def _flatten(lqg: DelayedLQG):
    return tuple(getattr(lqg, f) for f in _ARRAY_FIELDS), lqg.delay_steps


def _unflatten(delay_steps, arrays):
    new = object.__new__(DelayedLQG)
    new.delay_steps = delay_steps
    for name, value in zip(_ARRAY_FIELDS, arrays):
        setattr(new, name, value)
    return new


jax.tree_util.register_pytree_node(DelayedLQG, _flatten, _unflatten)


class Gains(NamedTuple):
    """An affine delayed feedback law, eq. (6): du_k = I_k + L_k dx_k + sum_i M_k^i du_{k+i-l}.

    Attributes:
        feedforward: [K, d] I_k.
        state_feedback: [K, d, n] L_k.
        delay_feedback: [K, l, d, d] M_k^i; index i multiplies du_{k+i-l}, so i = 0 is the command
            acting now (sent l steps ago) and i = l-1 the one sent at the previous step.
    """

    feedforward: jax.Array
    state_feedback: jax.Array
    delay_feedback: jax.Array


class SlotGains(NamedTuple):
    """The law (6) in the backward recursion's circular frame, as the solver's loop uses it.

    du_k = I_k + F_k [dx_k; pending_k], where pending_k is the flat [l d] vector with du_j in slot
    j mod l (components (j mod l) d ... + d), so a rollout writes one slot per step instead of
    shifting a buffer. :func:`to_slots` and :func:`from_slots` convert to and from :class:`Gains`.

    Attributes:
        feedforward: [K, d] I_k.
        feedback: [K, d, n + l d] F_k = [L_k, M_k by slot].
    """

    feedforward: jax.Array
    feedback: jax.Array


def slot_offsets(K: int, l: int, nd: int):
    """(k mod l) d for k = 0..K-1: where du_k sits in the flat pending vector (0 when l = 0)."""
    return (jnp.arange(K) % max(l, 1)) * nd


def to_slots(gains: Gains) -> SlotGains:
    """:class:`Gains` -> :class:`SlotGains`: M_k^i multiplies du_{k+i-l}, which is in slot (k+i) mod l."""
    I, L, M = gains
    K, l, nd = M.shape[:3]
    i_of_slot = (jnp.arange(l)[None, :] - jnp.arange(K)[:, None]) % l           # [K, l]
    by_slot = jnp.take_along_axis(M, i_of_slot[:, :, None, None], axis=1)       # [K, slot, d, d]
    return SlotGains(I, jnp.concatenate([L, jnp.swapaxes(by_slot, 1, 2).reshape(K, nd, l * nd)], axis=2))


def from_slots(gains: SlotGains, n_states: int) -> Gains:
    """:class:`SlotGains` -> :class:`Gains` (one gather over all steps)."""
    I, F = gains
    K, nd = I.shape
    l = (F.shape[2] - n_states) // nd
    if l == 0:
        return Gains(I, F[:, :, :n_states], jnp.zeros((K, 0, nd, nd), F.dtype))
    slot_of_i = (jnp.arange(K)[:, None] + jnp.arange(l)[None, :]) % l          # [K, l]
    by_slot = F[:, :, n_states:].reshape(K, nd, l, nd)
    M = jnp.moveaxis(jnp.take_along_axis(by_slot, slot_of_i[:, None, :, None], axis=2), 2, 1)
    return Gains(I, F[:, :, :n_states], M)


class Value(NamedTuple):
    """Coefficients of the cost-to-go (7), for k = 0..K (index K is the terminal cost).

    J(k) = s_tilde + 2 dx's + dx'S dx + 2 sum_i du_i'r^i + 2 dx' sum_i Rt^i du_i + sum_ij du_i'R^ij du_j,
    with du_i = du_{k+i-l}. Blocks for commands that no longer act (k + i >= K) are zero.

    Attributes:
        s_tilde: [K+1]; s: [K+1, n]; S: [K+1, n, n]; r: [K+1, l, d]; Rt: [K+1, l, n, d];
        R: [K+1, l, l, d, d].
        positive_definite: [] bool, every (regularised) H_k was positive definite. When False the
            gains are not a minimiser and contain NaN at the failing steps.
    """

    s_tilde: jax.Array
    s: jax.Array
    S: jax.Array
    r: jax.Array
    Rt: jax.Array
    R: jax.Array
    positive_definite: jax.Array

    @property
    def expected_cost(self) -> jax.Array:
        """J(0) = s_tilde_0: the optimal expected cost of the LQG problem (dx_0 = 0)."""
        return self.s_tilde[0]


# ---------------------------------------------------------------------------------------------
# Theorem 1: the structured recursion
# ---------------------------------------------------------------------------------------------

def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def merged_if_undelayed(lqg: DelayedLQG):
    """For l = 0 the delayed command is the current one: fold B1, C1 into B0, C0."""
    if lqg.delay_steps > 0:
        return lqg
    return lqg.replace(B0=lqg.B0 + lqg.B1, B1=jnp.zeros_like(lqg.B1),
                       C0=lqg.C0 + lqg.C1, C1=jnp.zeros_like(lqg.C1))


def stacked_dynamics(lqg: DelayedLQG):
    """Z = [A, B0, B1] [K, n, n + 2d]: x_{k+1} = Z_k [dx_k, du_k, du_{k-l}] in one product."""
    return jnp.concatenate([lqg.A, lqg.B0, lqg.B1], axis=2)


class StepModels(NamedTuple):
    """The delayed LQG given step by step, for the structured pass to build as it goes.

    ``model(row)`` returns step k's arrays (A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, N), shaped
    as one time step of :class:`DelayedLQG`, from row k of ``rows`` (a time-major pytree of K
    rows); ``terminal`` is (d_tilde_K, d_K, D_K). :func:`stored_models` makes one from a
    :class:`DelayedLQG` (its rows are the model's arrays); ``linearize.step_models`` makes one
    whose rows are the nominal (x_k, u_k, u_{k-l}), linearised inside the pass, so that the solver
    never stores the model: 67 numbers per step for the point mass, 4.8 times its gains at l = 1.
    """

    model: Any
    rows: Any
    terminal: tuple
    delay_steps: int
    n_controls: int

    @property
    def horizon(self) -> int:
        return jax.tree_util.tree_leaves(self.rows)[0].shape[0]

    @property
    def n_states(self) -> int:
        return self.terminal[1].shape[0]


def stored_models(lqg: DelayedLQG) -> StepModels:
    """:class:`StepModels` of a stored :class:`DelayedLQG`."""
    rows = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E,
            lqg.N)
    return StepModels(lambda row: row, rows, (lqg.d_tilde[-1], lqg.d[-1], lqg.D[-1]), lqg.delay_steps,
                      lqg.n_controls)


def _stage_data(models: StepModels, bounds, steps: int, block: int):
    """Per-step inputs of the backward recursion, time-major, k = 0..steps-1 (the horizon and any
    padding, see :func:`_padded_rows`): the step k, the offsets (k mod l) d and ((k - 1) mod l) d
    of its slot and of the next step's in the flattened pending axis, 2 (k mod block) d, its rows
    in the deferred factors of :func:`_r_update` (computed here, once, rather than in every step),
    whether it is a step of the horizon (None without padding), then the row of ``models`` and
    the bounds."""
    k = jnp.arange(steps)
    l, nd = max(models.delay_steps, 1), models.n_controls
    rows, bounds = _padded_rows(models.rows, bounds, steps - models.horizon)
    live = k < models.horizon if steps > models.horizon else None
    return (k, slot_offsets(steps, models.delay_steps, nd), ((k - 1) % l) * nd, (k % block) * 2 * nd, live, rows,
            bounds)


def _padded_rows(rows, bounds, steps: int):
    """``rows`` and ``bounds`` with ``steps`` rows appended, copies of the last (any row will do:
    the recursion replaces the model of these steps by :func:`_idle_step`'s, and their bounds are
    +-1), so that blocked passes can run on a horizon that is a multiple of their block."""
    if steps == 0:
        return rows, bounds
    grow = lambda x, fill=None: jnp.concatenate([x, jnp.repeat(x[-1:], steps, axis=0) if fill is None
                                                 else jnp.full((steps,) + x.shape[1:], fill, x.dtype)])
    rows = jax.tree_util.tree_map(grow, rows)
    if bounds is not None:
        bounds = (grow(bounds[0], -1.0), grow(bounds[1], 1.0))
    return rows, bounds


def _idle_step(model):
    """A step that leaves every value exactly as it is (A = I, E = I, everything else zero): the
    backward pass crosses it with J unchanged and gains zero."""
    A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, Nxu = (jnp.zeros_like(x) for x in model)
    return (jnp.eye(A.shape[0], dtype=A.dtype), B0, B1, c, C0, C1, d_tilde, dv, D, e,
            jnp.eye(E.shape[0], dtype=E.dtype), Nxu)


def unconstrained_gains(H, reg, g, G, bounds=None, warm=None):
    """Minimiser of du'H du + 2 du'(g + G y) with H replaced by H + reg I: (ok, I, K = [d, m])."""
    nd = H.shape[0]
    ok, sol = cholesky_solve(H + reg * jnp.eye(nd, dtype=H.dtype), jnp.concatenate([g[:, None], G], axis=1))
    return ok, -sol[:, 0], -sol[:, 1:]


def boxed_gains(H, reg, g, G, bounds, warm, margin=0.0):
    """Control-limited step (Tassa, Mansard & Todorov 2014): the feedforward solves the box QP
    min du'(H + reg I) du + 2 du'g over lower <= du <= upper (warm-started from the next step's),
    and the feedback acts only in the free directions: rows of L and of every M^i are zero for
    clamped commands.

    Commands whose nominal lies at a bound, or within ``margin * (upper - lower)`` of one (lower or
    upper within that distance of du = 0), get no feedback either, even when the QP frees them to
    move inward (an epsilon-active set, as in Bertsekas' projected Newton method). Their feedback would
    push them outside as often as inside, the forward pass clips it, and the steps upstream, which
    were planned on that feedback, then miss: the first-order prediction fails for every step
    size and the solve crawls. The feedforward still moves them inward, and at the solution
    (I = 0) the stationarity conditions do not depend on the gains (derivation §13).
    """
    from .boxqp import box_qp, free_solve       # local import: the unconstrained path never needs it

    lower, upper = bounds
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
    eps = margin * (upper - lower)
    K = free_solve(H_reg, qp.free & (lower < -eps) & (upper > eps), G)
    ok = (qp.status != -1) & jnp.all(jnp.isfinite(K)) & jnp.all(jnp.isfinite(I))
    return ok, I, K


def unregularized_feedback(gains_fn):
    """``gains_fn`` with the feedback of its unregularised step (reg = 0) wherever that step exists.

    The feedforward keeps ``reg``: lambda only shortens the step. With control-dependent noise the
    value Hessians S depend on the feedback (the noise cost c'S c is part of the recursion), so
    regularised feedback would make the merit of one nominal (cost + sum c'S c, derivation §12)
    change with lambda, and the acceptance test would compare different objectives from one
    iteration to the next: on the noisy six-muscle arm 0 of the 24 center-out reaches converged
    without this and 23 with it (derivation §12). Where H is not positive definite the
    regularised feedback is kept. ``gains_fn`` runs twice even at reg = 0: skipping the second
    call under a ``lax.cond`` was measured slower on P2-noisy (the cond costs more per step than a
    2 x 2 Cholesky) and under ``vmap``, where both branches run.
    """
    def gains(H, reg, g, G, bounds=None, warm=None):
        ok, I, K = gains_fn(H, reg, g, G, bounds, warm)
        ok_0, _, K_0 = gains_fn(H, 0.0, g, G, bounds, warm)
        return ok, I, jnp.where(ok_0, K_0, K)

    return gains


def _pending_order(k, l: int, nd: int):
    """Positions in the slot-ordered pending axis of du_{k-l}, ..., du_{k-1} (eq. 6's order i = 0..l-1).

    The recursion stores the pending commands in a circular frame: du_j lives in slot j mod l, so
    the command eliminated at step k (du_k) and the one that becomes pending (du_{k-l}) share a slot
    and no block ever moves. Returns [l d] indices into the flattened (slot, component) axis.
    """
    slots = (k + jnp.arange(l)) % l
    return (slots[:, None] * nd + jnp.arange(nd)).reshape(-1)


def _step_model(model, row, live, l: int):
    """Step k's model for the recursion: Z = [A, B0, B1] and the rest of ``model(row)``, with B1
    and C1 folded into B0 and C0 for l = 0 (the delayed command is the current one), and the
    idle step's for padding (``live`` False; None: no padding)."""
    A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, Nxu = model = model(row)
    if live is not None:
        model = jax.tree_util.tree_map(lambda m, idle: jnp.where(live, m, idle), model, _idle_step(model))
        A, B0, B1, c, C0, C1, d_tilde, dv, D, e, E, Nxu = model
    if l == 0:
        B0, B1, C0, C1 = B0 + B1, jnp.zeros_like(B1), C0 + C1, jnp.zeros_like(C1)
    return jnp.concatenate([A, B0, B1], axis=1), c, C0, C1, d_tilde, dv, D, e, E, Nxu


def _structured_step(carry, data, *, l: int, reg, store_value: bool, store_S: bool, gains_fn, model):
    """Step k+1 -> k of the corrected recursion (eq. 8 with the errata of docs/derivation.md).

    ``carry`` holds J(k+1)'s coefficients with the pending commands in slot order (see
    :func:`_pending_order`): r [l d], Rt [n, l d], R [l d, l d]; ``data`` the model at k. The
    command eliminated here, du_k, occupies slot sigma = k mod l at k+1; at k the same slot holds
    du_{k-l}, the command acting through B1_k. Every other block keeps its place.

    The value update is the exact cost-to-go of the quadratic model under whatever gains
    ``gains_fn`` returns (regularised, or clamped by control limits): with the quadratic
    q0 + 2 y'q_y + y'Q_yy y + 2 du'(g + G y) + du'H du and du = I + K y it is
    Q_yy + K'W + W'K with W = H K / 2 + G, q_y + K'(H I + g) + G'I and q0 + I'H I + 2 I'g
    (derivation §4). For the unregularised optimum it reduces to the paper's "- K'H K" form.

    ``model`` gives the step's LQG from its row of ``data`` (see :class:`StepModels`).

    ``carry = (value, predicted)``. ``predicted`` is () or (s0, r0, a, b), which predicts the
    change of the model's cost when the feedforward is scaled by alpha, alpha a + alpha^2 b
    (derivation §12):
    (s0, r0) are s, r of the policy without feedforward (I = 0, same K), g0 the g they give, and
    a = sum_k 2 I'g0, b = sum_k I'H I + 2 I'(g - g0).
    """
    (s_tilde, s, S, r, Rt, R, R_s, ok, warm, F), predicted = carry
    k, j0, j_next, jq, live, model_row, bounds = data
    Z, c, C0, C1, d_tilde, dv, D, e, E, Nxu = _step_model(model, model_row, live, l)
    nx, nd = Z.shape[0], e.shape[0]
    # All products with S, s and Rt at once, through Z = [A, B0, B1] (few large products beat many
    # tiny ones: per-operation overhead dominates at the sizes of motor-control problems).
    a_, b0, b1 = slice(0, nx), slice(nx, nx + nd), slice(nx + nd, nx + 2 * nd)
    s0_col = [predicted[0][:, None]] if predicted else []
    ZX = matmul_t(Z, jnp.concatenate([S, s[:, None]] + s0_col + [Rt], axis=1))   # Z'[S, s, (s0,) Rt]
    ZSZ = matmul(ZX[:, :nx], Z)
    Zs = ZX[:, nx]
    Zs0 = ZX[:, nx + 1] if predicted else None                         # Z's0
    w0 = nx + 1 + len(s0_col)                                      # where Z'Rt starts
    if c.shape[0] > 0:
        # The noise terms, sum_j of [C0, C1, c]_j' S [C0, C1, c]_j, in two products: X = [C0, C1, c]
        # with its p noise columns side by side, then (S X)'X summed over the columns
        p = c.shape[0]
        X = jnp.concatenate([C0, C1, c[:, :, None]], axis=2)        # [p, n, 2d + 1]
        SX = matmul(S, jnp.moveaxis(X, 1, 0).reshape(nx, -1)).reshape(nx, p, -1)
        XSX = matmul_t(X.reshape(p * nx, -1), jnp.moveaxis(SX, 1, 0).reshape(p * nx, -1))
        CSC, CSc, noise_cost = XSX[:-1, :-1], XSX[:-1, -1], XSX[-1, -1]
    else:
        CSC, CSc = jnp.zeros((2 * nd, 2 * nd), Z.dtype), jnp.zeros(2 * nd, Z.dtype)
        noise_cost = jnp.zeros((), Z.dtype)
    u0, u1 = slice(0, nd), slice(nd, 2 * nd)

    # Coefficients of the quadratic in du_k: H (d x d), g (d), G = [G_x (d x n), G_w (d x l d)].
    H = E + ZSZ[b0, b0] + CSC[u0, u0]
    g = e + Zs[b0] + CSc[u0]
    g0 = e + Zs0[b0] + CSc[u0] if predicted else None
    Gx = ZSZ[b0, a_] + Nxu
    if l > 0:                                               # j0: slot sigma in the flattened pending axis
        ZRt = ZX[:, w0:]                                             # [n + 2d, l d]
        ZRt_s = jax.lax.dynamic_slice_in_dim(ZRt, j0, nd, axis=1)    # Z' Rt^sigma
        R_ss = jax.lax.dynamic_slice_in_dim(R_s, j0, nd, axis=1)
        H = H + R_ss + ZRt_s[b0] + ZRt_s[b0].T
        g = g + jax.lax.dynamic_slice_in_dim(r, j0, nd)
        if predicted:
            g0 = g0 + jax.lax.dynamic_slice_in_dim(predicted[1], j0, nd)
        Gx = Gx + ZRt_s[a_].T
        # du_k against the other pending commands; in slot sigma, against du_{k-l} (via B1_k)
        G_new = ZSZ[b0, b1] + CSC[u0, u1] + ZRt_s[b1].T
        Gw = jax.lax.dynamic_update_slice(ZRt[b0] + R_s, G_new, (0, j0))
        G = jnp.concatenate([Gx, Gw], axis=1)
    else:
        G = Gx
    H = _sym(H)
    step_ok, I, K = gains_fn(H, reg, g, G, bounds, warm)
    L = K[:, :nx]
    HIK = matmul(H, jnp.concatenate([I[:, None], K], axis=1))
    W = 0.5 * HIK[:, 1:] + G                                        # [d, n + l d]
    Wx = W[:, :nx]
    HIg = HIK[:, 0] + g
    # One product for the whole update of S, Rt (rows :n: L'W + Wx'K) and of s, r (row n:
    # K'(H I + g) + G'I; through G rather than W = H K / 2 + G, whose terms would cancel)
    # (and of s0, r0, row n + 1: K'g0)
    zeros = jnp.zeros((nd, nx), Z.dtype)
    columns = [jnp.concatenate([L, Wx, zeros]), jnp.concatenate([jnp.zeros_like(I), HIg, I])[:, None]]
    if predicted:
        columns.append(jnp.concatenate([jnp.zeros_like(I), g0, jnp.zeros_like(I)])[:, None])
    copied = l * nd >= _COPIED_FACTORS_MIN_LD
    if copied:                     # the product's last 2d rows: W and K themselves (see _COPIED_FACTORS_MIN_LD)
        columns.append(jnp.eye(3 * nd, 2 * nd, dtype=Z.dtype))
    coef = jnp.concatenate(columns, axis=1)                        # [3d, n + 1 (+ 1) (+ 2d)]
    update = matmul_t(coef, jnp.concatenate([W, K, G]))            # [n + 1 (+ 1) (+ 2d), n + l d]
    s_tilde_new = d_tilde + s_tilde + noise_cost + I @ (HIg + g)
    s_new = dv + Zs[a_] + update[nx, :nx]
    S_new = _sym(D + ZSZ[a_, a_] + update[:nx, :nx])
    if l > 0:
        # the R update's factors [d, l d], slot order
        Mw, Ww = (update[-nd:, nx:], update[-2 * nd:-nd, nx:]) if copied else (K[:, nx:], W[:, nx:])
        # J(k+1) rewritten in (dx_k, pending at k): slot sigma now holds du_{k-l}
        r_pre = jax.lax.dynamic_update_slice(r, Zs[b1] + CSc[u1], (j0,))
        Rt_pre = jax.lax.dynamic_update_slice(ZRt[a_], ZSZ[a_, b1], (0, j0))
        row = jax.lax.dynamic_update_slice(ZRt[b1], ZSZ[b1, b1] + CSC[u1, u1], (0, j0))   # [d, l d]
        r_new = r_pre + update[nx, nx:]
        Rt_new = Rt_pre + update[:nx, nx:]
        R_new, F, R_s = _r_update(R, F, row, Mw, Ww, j0, j_next, jq)     # R_s: for step k-1
    else:
        r_new, Rt_new, R_new = r, Rt, R
    if predicted:
        s0, r0, a, b = predicted
        s0_new = dv + Zs0[a_] + update[nx + 1, :nx]
        r0_new = r0
        if l > 0:
            r0_new = jax.lax.dynamic_update_slice(r0, Zs0[b1] + CSc[u1], (j0,)) + update[nx + 1, nx:]
        IH = HIK[:, 0]                                              # H I
        predicted = (s0_new, r0_new, a + 2 * I @ g0, b + I @ IH + 2 * I @ (g - g0))
    carry = ((s_tilde_new, s_new, S_new, r_new, Rt_new, R_new, R_s, ok & step_ok, I, F), predicted)
    out = (I, K, s_tilde_new) + ((s_new, S_new) if store_S else ())     # K = [L, M by slot]: see SlotGains
    if store_value:
        out = out + _value_blocks(r_new, Rt_new, _exact_r(R_new, F, k, l, nd) if l > 0 else R_new, k, l, nd)
    return carry, out


# From this l d on, the value update's product also copies out W and K (exactly: unit columns),
# and the R update reads its factors M = K, W from that buffer. Otherwise XLA fuses their cheap
# producers (K = -H^-1 G from the Cholesky solve, W = H K / 2 + G) into the loop over R's
# (l d)^2 elements, and that loop's speed then depended on where the heap put its buffers: P3's
# pass took 2.57 to 2.93 ms over five heap offsets, against 2.50 to 2.61 ms with the copy.
# Solves in separate processes, alternately (2-core machine): P3 32.0-32.7 -> 29.9-31.4 ms,
# P4 l d = 200 38.5-39.9 -> 30.1-32.1 ms, l d = 100 16.0-16.8 -> 15.3-15.6 ms; P4's pass at
# l d = 80 about 5 % faster, at 60 and 64 equal (whether the product is fused or a library dot);
# at l d <= 20 (P1, P2, P4 l = 1) the extra product rows cost 0-5 %.
_COPIED_FACTORS_MIN_LD = 64


def _r_update(R, F, row, Mw, Ww, j0, j_next, jq):
    """R at k from R at k+1 (the hot spot: [l d, l d] per step, everything else is O(l d^2)).

    Returns (R, F, R_s): the stored R and deferred factors at k, and the exact rows [d, l d] of
    the slot that step k-1 eliminates.

    Exactly, slot sigma's rows become ``row`` (du_{k-l} against the pending commands), its
    columns row', and M'W + W'M is added. Only the rows are written: R is stored with each slot's
    row block exact as of the step that last replaced it, and its column block stale. Slots are
    replaced in cyclic order, so the slot read next (k - 1 mod l) is the one replaced longest ago,
    and its exact values are in its *columns*, which every newer row wrote (see :func:`_exact_r`).

    ``F = ()``: M'W + W'M is added at once, one loop over R that XLA fuses and runs in place (per
    step it reads and writes R: memory-bound for large l d). ``F = (F,)``, [2 q d, l d]: the
    factors M_p, W_p of the steps p of the block so far are kept instead, the exact R being
    R + sum_p M_p'W_p + W_p'M_p, and :func:`_flush` adds them with one matrix product per block.
    A step then only corrects the rows it writes and the column block it reads by products with the
    factors, O(q d^2 l d) instead of O((l d)^2).
    """
    nd, ld = row.shape
    if not F:
        for a in range(nd):
            R = R + Mw[a][:, None] * Ww[a][None, :] + Ww[a][:, None] * Mw[a][None, :]
        MWs = jnp.concatenate([jax.lax.dynamic_slice_in_dim(X, j0, nd, axis=1) for X in (Mw, Ww)])
        R = jax.lax.dynamic_update_slice(R, row + matmul_t(MWs, jnp.concatenate([Ww, Mw])), (j0, 0))
        return R, F, jax.lax.dynamic_slice_in_dim(R, j_next, nd, axis=1).T
    (F,) = F                                 # [2 q d, l d]: step p of the block at rows 2 p d: M_p, W_p
    # X'F with X = F, its M and W rows swapped, at some columns is (sum_p M_p'W_p + W_p'M_p) at
    # those rows: one product gives the factors' part of slot sigma's rows (written now) and of
    # the next slot's (read next).
    cols = jnp.concatenate([jax.lax.dynamic_slice_in_dim(F, j, nd, axis=1) for j in (j0, j_next)], axis=1)
    part = matmul_t(_swap_factors(cols, nd), F)                               # [2d, l d]
    # stored rows = exact rows - the factors' part (this step's own part cancels: added to both)
    R = jax.lax.dynamic_update_slice(R, row - part[:nd], (j0, 0))
    F = jax.lax.dynamic_update_slice_in_dim(F, jnp.concatenate([Mw, Ww]), jq, axis=0)
    own = jnp.concatenate([jax.lax.dynamic_slice_in_dim(X, j_next, nd, axis=1) for X in (Ww, Mw)])
    R_s = jax.lax.dynamic_slice_in_dim(R, j_next, nd, axis=1).T + part[nd:] + matmul_t(own, jnp.concatenate([Mw, Ww]))
    return R, (F,), R_s


def _swap_factors(F, nd: int):
    """[2 q d, m] factors with M_p, W_p at rows 2 p d: the same with W_p, M_p."""
    return F.reshape(-1, 2, nd, F.shape[1])[:, ::-1].reshape(F.shape)


def _flush(carry):
    """End of a block of the blocked pass: R += sum_p M_p'W_p + W_p'M_p, factors reset (see
    :func:`_r_update`)."""
    *head, R, R_s, ok, warm, (F,) = carry
    R = R + F.T @ _swap_factors(F, R_s.shape[0])
    return (*head, R, R_s, ok, warm, (jnp.zeros_like(F),))


def _exact_r(R, F, k, l: int, nd: int):
    """The exact (symmetric) R from its stored form (see :func:`_r_update`), after step k.

    The pass runs down in k, so slot s was last replaced at step k + ((s - k) mod l), that many
    steps ago; entry (i, j) is exact in the row of whichever of the two slots was replaced more
    recently (for slots never replaced, both copies hold the same sum of updates).
    """
    if F:
        (F,) = F
        R = R + F.T @ _swap_factors(F, nd)
    age = (jnp.arange(l) - k) % l                           # steps since slot s was replaced
    age = jnp.repeat(age, nd)
    return jnp.where(age[:, None] <= age[None, :], R, R.T)


def _value_blocks(r, Rt, R, k, l: int, nd: int):
    """J(k)'s pending blocks from slot order to eq. 7's order: r [l, d], Rt [l, n, d], R [l, l, d, d]."""
    if l == 0:
        nx = Rt.shape[0]
        return (jnp.zeros((0, nd)), jnp.zeros((0, nx, nd)), jnp.zeros((0, 0, nd, nd)))
    order = _pending_order(k, l, nd)
    nx = Rt.shape[0]
    return (r[order].reshape(l, nd),
            jnp.moveaxis(Rt[:, order].reshape(nx, l, nd), 1, 0),
            jnp.moveaxis(R[order][:, order].reshape(l, nd, l, nd), 2, 1))


def _terminal(models: StepModels, block: int = 1):
    l, nd, nx = models.delay_steps, models.n_controls, models.n_states
    d_tilde, dv, D = models.terminal
    dt = D.dtype
    F = (jnp.zeros((2 * block * nd, l * nd), dt),) if block > 1 else ()
    return (d_tilde, dv, D, jnp.zeros(l * nd, dt), jnp.zeros((nx, l * nd), dt),
            jnp.zeros((l * nd, l * nd), dt), jnp.zeros((nd, l * nd), dt), jnp.asarray(True), jnp.zeros(nd, dt), F)


# Deferring the R update pays once the per-step loop over R is bound by memory: on the 2-core CI
# machine, P4's pass (K = 600, d = 2) with q = 16 against none took 15.4 / 12.8 ms at l d = 200,
# 25.0 / 27.7 ms at 300, 35.8 / 53.7 ms at 400 and 60.6 / 89.7 ms at 600 (q = 8 was slower).
_DEFER_MIN_LD = 300
_DEFER_BLOCK = 16


def _default_block(lqg: DelayedLQG | StepModels) -> int:
    return _DEFER_BLOCK if lqg.delay_steps * lqg.n_controls >= _DEFER_MIN_LD else 1


def structured_scan(lqg: DelayedLQG, reg=0.0, store_value: bool = True, gains_fn=unconstrained_gains,
                    bounds=None, block: int | None = None):
    """Runs Theorem 1 backwards with ``lax.scan``; returns (Gains, outputs, positive_definite).

    ``outputs`` are s_tilde [K], s [K, n], S [K, n, n] (and, with ``store_value``, r, Rt, R).

    Args:
        store_value: False keeps only s_tilde, s, S per step (memory O(K (n^2 + l d^2)) instead of
            O(K l^2 d^2)); the solver uses it.
        gains_fn: ``(H, reg, g, G, bounds_k, warm) -> (ok, I, K)``, the minimiser of the step's
            quadratic in du (default: unconstrained, Cholesky of H + reg I). The control-limited
            solver passes a box-QP version; ``warm`` is the feedforward of the step after.
        bounds: per-step data for ``gains_fn``, time-major (e.g. [K, 2, d] limits on du_k).
        block: q > 1 defers the O((l d)^2) part of each step to one matrix product per block of q
            steps (see :func:`_r_update`); the horizon is padded to a multiple of q with steps
            that change nothing. Default: 16 when l d >= 300, else 1 (no deferral).
    """
    gains, out, ok = structured_slot_scan(lqg, reg, store_value, gains_fn, bounds, block)
    return from_slots(gains, lqg.n_states), out, ok


def structured_slot_scan(lqg: DelayedLQG | StepModels, reg=0.0, store_value: bool = True, gains_fn=unconstrained_gains,
                         bounds=None, block: int | None = None, predict: bool = False, store_S: bool = True):
    """:func:`structured_scan` with the gains as :class:`SlotGains`, as the recursion makes them,
    on a stored :class:`DelayedLQG` or on :class:`StepModels` (the solver's, linearised in the pass).

    ``store_S=False`` leaves s and S out of the outputs (s_tilde only, with ``store_value=False``):
    the solver needs S only with noise, and at l = 1 they are more numbers per step than the gains.

    ``predict=True`` also returns (a, b): under the LQG, the expected cost of the returned policy
    with its feedforward scaled by alpha, minus that at alpha = 0, is alpha a + alpha^2 b. That is
    the line search's model, which ``forward.predicted_change`` computes by a forward pass; here it
    costs two columns in products the step makes anyway (P3: one scan of 250 steps less per
    iteration).
    """
    models = stored_models(lqg) if isinstance(lqg, DelayedLQG) else lqg
    K, l = models.horizon, models.delay_steps
    block = _default_block(models) if block is None else _validate.positive_int(block, "block")
    block = block if l > 0 else 1
    if store_value and not store_S:
        raise ValueError("store_S=False needs store_value=False: the value blocks include S")
    steps = K + (-K % block)
    step = partial(_structured_step, l=l, reg=reg, store_value=store_value, store_S=store_S, gains_fn=gains_fn,
                   model=models.model)
    d_K = models.terminal[1]
    zero = jnp.zeros((), d_K.dtype)
    predicted = (d_K, jnp.zeros(l * models.n_controls, d_K.dtype), zero, zero) if predict else ()
    # the outputs unpacked: packing I, K and s_tilde into one row per step, then slicing them out,
    # held both copies (P4 at l = 1: 58 kB more, 0.9 times the gains)
    (carry, predicted), out = packed_scan(step, (_terminal(models, block), predicted),
                                          _stage_data(models, bounds, steps, block), reverse=True, block=block,
                                          flush=lambda c: (_flush(c[0]), c[1]), pack_outputs=False)
    out = tuple(o[:K] for o in out)
    if predict:
        return SlotGains(*out[:2]), out[2:], carry[7], predicted[2:]
    return SlotGains(*out[:2]), out[2:], carry[7]


def _append_terminal(per_step, terminal):
    return jnp.concatenate([per_step, terminal[None]])


@jax.jit
def backward_pass(lqg: DelayedLQG, reg=0.0) -> tuple[Gains, Value]:
    """Theorem 1: the optimal delayed policy (6) and the value function (7), structured.

    Args:
        lqg: the problem.
        reg: Levenberg-Marquardt shift lambda >= 0 added to H for the gains (0 gives the exact
            LQG optimum).

    Returns:
        (gains, value). ``value.expected_cost`` is J(0). If some H_k + reg I is not positive
        definite, ``value.positive_definite`` is False and the gains hold NaN from that step back.
    """
    _precision.require_x64("lqg.backward_pass")   # at tracing, which float32 always causes
    gains, out, ok = structured_scan(lqg, reg, store_value=True)
    # out = (s_tilde, s, S, r, Rt, R) for k = 0..K-1; the terminal J(K) has no pending blocks
    term = _terminal(stored_models(lqg))
    term = term[:3] + tuple(jnp.zeros_like(o[0]) for o in out[3:])
    value = Value(*(_append_terminal(o, t) for o, t in zip(out, term)), positive_definite=ok)
    return gains, value


# ---------------------------------------------------------------------------------------------
# Reference: ordinary Riccati recursion on the augmented state z = [dx, du_{k-l}, ..., du_{k-1}]
# ---------------------------------------------------------------------------------------------

def augment(lqg: DelayedLQG):
    """The augmented (undelayed) system, time-major.

    Returns a dict with Az [K, N, N], Bz [K, N, d], cz [K, p, N], Cz [K, p, N, N], Cu [K, p, N, d],
    dz [K+1, N], Dz [K+1, N, N], Nz [K, d, N] where N = n + l d; the buffer holds du_{k-l} .. du_{k-1}.
    """
    lqg = merged_if_undelayed(lqg)
    K, nx, nd, p, l = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.n_noise, lqg.delay_steps
    N = nx + l * nd
    dt = lqg.A.dtype
    Az = jnp.zeros((K, N, N), dt).at[:, :nx, :nx].set(lqg.A)
    Bz = jnp.zeros((K, N, nd), dt).at[:, :nx, :].set(lqg.B0)
    Cz = jnp.zeros((K, p, N, N), dt)
    Cu = jnp.zeros((K, p, N, nd), dt).at[:, :, :nx, :].set(lqg.C0)
    Nz = jnp.zeros((K, nd, N), dt).at[:, :, :nx].set(lqg.N)
    if l > 0:
        Az = Az.at[:, :nx, nx:nx + nd].set(lqg.B1)                          # du_{k-l} acts now
        Az = Az.at[:, nx:N - nd, nx + nd:].set(jnp.eye((l - 1) * nd, dtype=dt))  # buffer shifts
        Bz = Bz.at[:, N - nd:, :].set(jnp.eye(nd, dtype=dt))                # du_k enters last
        Cz = Cz.at[:, :, :nx, nx:nx + nd].set(lqg.C1)
    cz = jnp.zeros((K, p, N), dt).at[:, :, :nx].set(lqg.c)
    dz = jnp.zeros((K + 1, N), dt).at[:, :nx].set(lqg.d)
    Dz = jnp.zeros((K + 1, N, N), dt).at[:, :nx, :nx].set(lqg.D)
    return dict(Az=Az, Bz=Bz, cz=cz, Cz=Cz, Cu=Cu, dz=dz, Dz=Dz, Nz=Nz)


def _augmented_step(carry, data, *, reg, gains_fn):
    v0, v, V, ok, warm = carry
    Az, Bz, cz, Cz, Cu, d_tilde, dz, Dz, e, E, Nz, bounds = data
    Vc = cz @ V                                                  # [p, N]
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


@jax.jit
def augmented_backward_pass(lqg: DelayedLQG, reg=0.0) -> tuple[Gains, Value]:
    """The state-augmentation reference: same problem, same return types as :func:`backward_pass`."""
    _precision.require_x64("lqg.augmented_backward_pass")   # at tracing, which float32 always causes
    return augmented_scan(lqg, reg)


def augmented_scan(lqg: DelayedLQG, reg=0.0, gains_fn=unconstrained_gains, bounds=None):
    """Riccati recursion on z = [dx, du_{k-l}, ..., du_{k-1}]; ``gains_fn``/``bounds`` as in
    :func:`structured_scan`."""
    nx, nd, l = lqg.n_states, lqg.n_controls, lqg.delay_steps
    aug = augment(lqg)
    data = (aug["Az"], aug["Bz"], aug["cz"], aug["Cz"], aug["Cu"], lqg.d_tilde[:-1], aug["dz"][:-1],
            aug["Dz"][:-1], lqg.e, lqg.E, aug["Nz"], bounds)
    init = (lqg.d_tilde[-1], aug["dz"][-1], aug["Dz"][-1], jnp.asarray(True), jnp.zeros(nd, lqg.A.dtype))
    carry, (I, Kz, v0, v, V) = jax.lax.scan(partial(_augmented_step, reg=reg, gains_fn=gains_fn), init, data,
                                            reverse=True)
    v0 = _append_terminal(v0, init[0])
    v = _append_terminal(v, init[1])
    V = _append_terminal(V, init[2])
    K1 = v.shape[0]                                                   # K + 1
    gains = Gains(I, Kz[:, :, :nx], jnp.moveaxis(Kz[:, :, nx:].reshape(K1 - 1, nd, l, nd), 2, 1))
    value = Value(
        s_tilde=v0, s=v[:, :nx], S=V[:, :nx, :nx],
        r=v[:, nx:].reshape(K1, l, nd),
        Rt=jnp.moveaxis(V[:, :nx, nx:].reshape(K1, nx, l, nd), 2, 1),
        R=jnp.moveaxis(V[:, nx:, nx:].reshape(K1, l, nd, l, nd), 3, 2),
        positive_definite=carry[3])
    return gains, value


# ---------------------------------------------------------------------------------------------
# Exact expected cost of any affine delayed policy, and Monte Carlo of the linear system
# ---------------------------------------------------------------------------------------------

def _check_gains(lqg: DelayedLQG, gains: Gains) -> Gains:
    K, nx, nd, l = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.delay_steps
    return Gains(
        jnp.asarray(_validate.array(gains.feedforward, "gains.feedforward", (K, nd))),
        jnp.asarray(_validate.array(gains.state_feedback, "gains.state_feedback", (K, nd, nx))),
        jnp.asarray(_validate.array(gains.delay_feedback, "gains.delay_feedback", (K, l, nd, nd))))


@jax.jit
def _policy_cost(lqg: DelayedLQG, gains: Gains):
    aug = augment(lqg)
    Kz = jnp.concatenate([gains.state_feedback,
                          jnp.moveaxis(gains.delay_feedback, 1, 2).reshape(lqg.horizon, lqg.n_controls, -1)],
                         axis=2)                                      # [K, d, N]
    N = Kz.shape[2]

    def step(carry, data):
        mu, X, total = carry
        Az, Bz, cz, Cz, Cu, I, Kk, d_tilde, dz, Dz, e, E, Nz = data
        Eu = I + Kk @ mu                                              # E[du]
        Euu = jnp.outer(I, I) + Kk @ jnp.outer(mu, I) + jnp.outer(I, mu) @ Kk.T + Kk @ X @ Kk.T
        Ezu = jnp.outer(mu, I) + X @ Kk.T                              # E[z du']
        total = total + d_tilde + 2 * dz @ mu + jnp.sum(Dz * X) + 2 * e @ Eu + jnp.sum(E * Euu) \
            + 2 * jnp.sum(Nz.T * Ezu)
        F, f = Az + Bz @ Kk, Bz @ I
        gcol = cz + Cu @ I                                            # [p, N]
        Gcol = Cz + Cu @ Kk                                           # [p, N, N]
        mu_new = F @ mu + f
        Fm = F @ mu
        X_new = F @ X @ F.T + jnp.outer(Fm, f) + jnp.outer(f, Fm) + jnp.outer(f, f)
        Gm = jnp.einsum("pnk,k->pn", Gcol, mu)
        X_new = X_new + jnp.einsum("pnk,kl,pml->nm", Gcol, X, Gcol) + jnp.einsum("pn,pm->nm", Gm, gcol) \
            + jnp.einsum("pn,pm->nm", gcol, Gm) + jnp.einsum("pn,pm->nm", gcol, gcol)
        return (mu_new, _sym(X_new), total), None

    dt = lqg.A.dtype
    init = (jnp.zeros(N, dt), jnp.zeros((N, N), dt), jnp.asarray(0.0, dt))
    data = (aug["Az"], aug["Bz"], aug["cz"], aug["Cz"], aug["Cu"], gains.feedforward, Kz,
            lqg.d_tilde[:-1], aug["dz"][:-1], aug["Dz"][:-1], lqg.e, lqg.E, aug["Nz"])
    (mu, X, total), _ = jax.lax.scan(step, init, data)
    return total + lqg.d_tilde[-1] + 2 * aug["dz"][-1] @ mu + jnp.sum(aug["Dz"][-1] * X)


def policy_cost(lqg: DelayedLQG, gains: Gains) -> jax.Array:
    """Exact E[J(0)] of the affine delayed policy ``gains`` on ``lqg`` (no sampling).

    Propagates the mean mu_k and second moment X_k = E[z_k z_k'] of the augmented state z_k
    through the closed loop, including the control-dependent noise, and sums the expected costs.
    Cost O(K (n + l d)^3): a reference, not a hot path.
    """
    _precision.require_x64("lqg.policy_cost")
    return _policy_cost(lqg, _check_gains(lqg, gains))


class LQGRuns(NamedTuple):
    """Monte Carlo trials of the linear delayed system.

    Attributes: dx [N, K+1, n], du [N, K, d], cost [N] (eq. 4 summed over k = 0..K per trial).
    """

    dx: jax.Array
    du: jax.Array
    cost: jax.Array


@partial(jax.jit, static_argnames=("n_trials",))
def _simulate_lqg(lqg: DelayedLQG, gains: Gains, n_trials: int, key):
    lqg = merged_if_undelayed(lqg)
    K, nx, nd, p, l = lqg.horizon, lqg.n_states, lqg.n_controls, lqg.n_noise, lqg.delay_steps
    dt = lqg.A.dtype

    def trial(trial_key):
        xi = jax.random.normal(trial_key, (K, p), dt)

        def step(carry, data):
            dx, pending = carry                                       # pending[i] = du_{k+i-l}
            A, B0, B1, c, C0, C1, I, L, M, xik, d_tilde, dv, D, e, E, Nxu = data
            du = I + L @ dx + jnp.einsum("ide,ie->d", M, pending)
            du_delayed = pending[0] if l > 0 else jnp.zeros(nd, dt)
            noise = xik @ (c + C0 @ du + C1 @ du_delayed)
            dx_new = A @ dx + B0 @ du + B1 @ du_delayed + noise
            cost = d_tilde + 2 * dx @ dv + dx @ D @ dx + 2 * du @ e + du @ E @ du + 2 * du @ Nxu @ dx
            pending = jnp.concatenate([pending[1:], du[None]]) if l > 0 else pending
            return (dx_new, pending), (dx, du, cost)

        data = (lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, *gains, xi,
                lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e, lqg.E, lqg.N)
        (dxK, _), (dx, du, cost) = jax.lax.scan(step, (jnp.zeros(nx, dt), jnp.zeros((l, nd), dt)), data)
        final = lqg.d_tilde[-1] + 2 * dxK @ lqg.d[-1] + dxK @ lqg.D[-1] @ dxK
        return jnp.concatenate([dx, dxK[None]]), du, jnp.sum(cost) + final

    return LQGRuns(*jax.vmap(trial)(jax.random.split(key, n_trials)))


def simulate_lqg(lqg: DelayedLQG, gains: Gains, n_trials: int, seed: int = 0) -> LQGRuns:
    """Monte Carlo of the linear delayed system (3) under ``gains``, vectorised over trials."""
    _precision.require_x64("lqg.simulate_lqg")
    n_trials = _validate.positive_int(n_trials, "n_trials")
    return _simulate_lqg(lqg, _check_gains(lqg, gains), n_trials, jax.random.PRNGKey(seed))
