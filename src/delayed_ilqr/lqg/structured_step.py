"""One step k+1 -> k of Theorem 1 (eq. 6-8) as the structured pass runs it, fused: `structured_step`.

The mathematics of one step is `stage.stage_step`, written in eq. (6)'s order of the pending
commands; the step here computes the same numbers (tests/test_stage.py) arranged for speed:

* the pending blocks r, Rt, R live in the circular slot frame of `frame`, so the command
  eliminated at step k (du_k) and the one that becomes pending (du_{k-l}) share slot k mod l and
  no block moves;
* products with the same operand are fused into one ([S, s, Rt] through Z = [A, B0, B1]; the whole
  value update in one product), since per-operation overhead, not arithmetic, dominates at the
  sizes of motor-control problems (the kernels of `delayed_ilqr._kernels`);
* R is updated by a strategy of `r_update` (dense, copied factors, deferred blocks).

With a frame (``delay_frame`` L >= l, the delay l as data; docs/derivation.md §17) the command
acting at step k, du_{k-l}, sits in slot alpha = (k - l) mod L, not in slot sigma = k mod L of the
command eliminated: the step clears slot sigma (at k it holds du_{k-L}, which has acted) and writes
du_{k-l}'s blocks into slot alpha (zero at k+1, where du_{k-l} has acted), which is the step above
when alpha = sigma (l = L) (`frame.move_acting`). R is then kept symmetric (`r_update.update_framed`).

The value update is the exact cost-to-go of the quadratic model under whatever gains the gain rule
returns (regularised, or clamped by control limits; docs/derivation.md §4), so J(0) is always the
true cost of the returned policy.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._kernels.dense import matmul, matmul_t
from . import r_update
from .frame import acting_offset, move_acting, value_blocks
from .model import Stage, fold_current, idle_stage

__all__ = ["ValueCarry", "Prediction", "StepData", "structured_step"]


class ValueCarry(NamedTuple):
    """J(k+1) as the reverse scan carries it into step k (pending blocks in slot order).

    Attributes:
        s_tilde: []; s: [n]; S: [n, n]; r: [l d]; Rt: [n, l d].
        R: [l d, l d], stored with stale columns (see `r_update`).
        R_next: [d, l d] the exact rows of the slot step k eliminates.
        ok: [] bool, every step so far had a positive definite H.
        warm: [d] the feedforward of step k+1 (the box QP's warm start).
        factors: () or (F,), the deferred R updates (see `r_update`).
    """

    s_tilde: jax.Array
    s: jax.Array
    S: jax.Array
    r: jax.Array
    Rt: jax.Array
    R: jax.Array
    R_next: jax.Array
    ok: jax.Array
    warm: jax.Array
    factors: tuple


class Prediction(NamedTuple):
    """The line search's model, accumulated by the pass (``predict=True``, derivation §12).

    The change of the model's expected cost when the feedforward is scaled by alpha is
    alpha a + alpha^2 b. (s0, r0) are s, r of the policy without feedforward (I = 0, same
    feedback), g0 the g they give, and a = sum_k 2 I'g0, b = sum_k I'H I + 2 I'(g - g0).

    Attributes: s0 [n]; r0 [l d]; a []; b [].
    """

    s0: jax.Array
    r0: jax.Array
    a: jax.Array
    b: jax.Array


class StepData(NamedTuple):
    """Per-step inputs of the reverse scan, time-major (see `structured._step_data`)."""

    k: jax.Array
    slot: jax.Array              # (k mod l) d: slot sigma in the flat pending axis
    next_slot: jax.Array         # ((k - 1) mod l) d: the slot step k - 1 eliminates
    factor_row: jax.Array        # 2 (k mod q) d: the step's rows in the deferred factors
    live: jax.Array | None       # a step of the horizon (not padding); None without padding
    row: object                  # row k of the StepModels
    bounds: object               # the gain rule's per-step data (None without limits)


class ZColumns(NamedTuple):
    """Column blocks of Z = [A, B0, B1] (and rows of Z'X): dx_k, du_k, du_{k-l}."""

    x: slice
    u: slice
    ud: slice


class Propagated(NamedTuple):
    """J(k+1) seen through the dynamics: ZX = Z'[S, s, (s0,) Rt] and ZSZ = Z'S Z."""

    ZX: jax.Array
    ZSZ: jax.Array
    Zs: jax.Array
    Zs0: jax.Array | None
    Rt_columns: slice            # where Z'Rt sits in ZX


class Noise(NamedTuple):
    """sum_j X_j'S X_j with X_j = [C0_j, C1_j, c_j]: CSC [2d, 2d], CSc [2d], cost []."""

    CSC: jax.Array
    CSc: jax.Array
    cost: jax.Array



def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


def _step_stage(model, row, live, current):
    """Step k's (Z = [A, B0, B1], `Stage`): the idle stage for padding (``live`` False), and
    B1, C1 folded into B0, C0 where ``current`` (l = 0: the delayed command is the current one;
    a Python bool for a static l, a traced one with a frame)."""
    stage = Stage(*model(row))
    if live is not None:
        stage = jax.tree_util.tree_map(lambda m, idle: jnp.where(live, m, idle), stage, idle_stage(stage))
    if current is not False:
        B0, B1, C0, C1 = fold_current((stage.B0, stage.B1, stage.C0, stage.C1), current)
        stage = stage._replace(B0=B0, B1=B1, C0=C0, C1=C1)
    return jnp.concatenate([stage.A, stage.B0, stage.B1], axis=1), stage


def _through_dynamics(Z, value: ValueCarry, s0) -> Propagated:
    """All products with S, s (s0) and Rt at once, through Z: few large products beat many tiny ones."""
    nx = Z.shape[0]
    s0_col = [s0[:, None]] if s0 is not None else []
    ZX = matmul_t(Z, jnp.concatenate([value.S, value.s[:, None]] + s0_col + [value.Rt], axis=1))
    ZSZ = matmul(ZX[:, :nx], Z)
    Zs = ZX[:, nx]
    Zs0 = ZX[:, nx + 1] if s0 is not None else None
    return Propagated(ZX, ZSZ, Zs, Zs0, slice(nx + 1 + len(s0_col), None))


def _noise_terms(stage: Stage, S, nd: int) -> Noise:
    """sum_j [C0, C1, c]_j' S [C0, C1, c]_j in two products: X with its p columns side by side,
    then (S X)'X summed over the columns."""
    p, nx = stage.c.shape
    if p == 0:
        return Noise(jnp.zeros((2 * nd, 2 * nd), S.dtype), jnp.zeros(2 * nd, S.dtype), jnp.zeros((), S.dtype))
    X = jnp.concatenate([stage.C0, stage.C1, stage.c[:, :, None]], axis=2)        # [p, n, 2d + 1]
    SX = matmul(S, jnp.moveaxis(X, 1, 0).reshape(nx, -1)).reshape(nx, p, -1)
    XSX = matmul_t(X.reshape(p * nx, -1), jnp.moveaxis(SX, 1, 0).reshape(p * nx, -1))
    return Noise(XSX[:-1, :-1], XSX[:-1, -1], XSX[-1, -1])


def _action_quadratic(stage: Stage, z: ZColumns, dyn: Propagated, noise: Noise, value: ValueCarry, r0, slot,
                      acting=None):
    """The quadratic in du_k: H [d, d], g [d] (g0 with r0), G = [G_x, G_w] [d, n + l d], and Z'Rt.

    Slot sigma's blocks of J(k+1) are those of du_k; in G_w the same slot is du_{k-l}, via B1 (with a
    frame, slot alpha = ``acting`` is, and slot sigma is cleared: see `frame.move_acting`)."""
    nd = stage.e.shape[0]
    u0, u1 = slice(0, nd), slice(nd, None)
    H = stage.E + dyn.ZSZ[z.u, z.u] + noise.CSC[u0, u0]
    g = stage.e + dyn.Zs[z.u] + noise.CSc[u0]
    g0 = stage.e + dyn.Zs0[z.u] + noise.CSc[u0] if r0 is not None else None
    Gx = dyn.ZSZ[z.u, z.x] + stage.N
    if value.r.shape[0] == 0:
        return H, g, g0, Gx, None
    ZRt = dyn.ZX[:, dyn.Rt_columns]                                   # [n + 2d, l d]
    ZRt_s = jax.lax.dynamic_slice_in_dim(ZRt, slot, nd, axis=1)       # Z' Rt^sigma
    R_ss = jax.lax.dynamic_slice_in_dim(value.R_next, slot, nd, axis=1)
    H = H + R_ss + ZRt_s[z.u] + ZRt_s[z.u].T
    g = g + jax.lax.dynamic_slice_in_dim(value.r, slot, nd)
    if r0 is not None:
        g0 = g0 + jax.lax.dynamic_slice_in_dim(r0, slot, nd)
    Gx = Gx + ZRt_s[z.x].T
    # du_k against the other pending commands; in slot sigma, against du_{k-l} (via B1_k)
    G_new = dyn.ZSZ[z.u, z.ud] + noise.CSC[u0, u1] + ZRt_s[z.ud].T
    Gw = move_acting(ZRt[z.u] + value.R_next, G_new, slot, acting, axis=1, nd=nd)
    return H, g, g0, jnp.concatenate([Gx, Gw], axis=1), ZRt


class UpdateRows(NamedTuple):
    """Rows of the value update's product; its columns are [dx | pending]."""

    S: slice                     # L'W + Wx'Kfb: the update of S and Rt
    s: int                       # Kfb'(H I + g) + G'I: of s and r
    s0: int                      # Kfb'g0: of s0 and r0 (with a prediction)
    W: slice                     # W and Kfb themselves (with RStrategy.copy_factors): the last 2d rows
    Kfb: slice


def _value_product(H, g, g0, G, I, Kfb, nx: int, copy_factors: bool):
    """One product for the whole update of S, Rt (L'W + Wx'Kfb), of s, r (Kfb'(H I + g) + G'I:
    through G rather than W = H Kfb / 2 + G, whose terms would cancel) and of s0, r0 (Kfb'g0).

    Returns (update, rows, W, HIK, HIg): the product, its `UpdateRows`, W [d, n + l d],
    HIK = H [I, Kfb] [d, 1 + n + l d] and HIg = H I + g."""
    nd = H.shape[0]
    L = Kfb[:, :nx]
    HIK = matmul(H, jnp.concatenate([I[:, None], Kfb], axis=1))
    W = 0.5 * HIK[:, 1:] + G                                        # [d, n + l d]
    Wx = W[:, :nx]
    HIg = HIK[:, 0] + g
    zeros = jnp.zeros((nd, nx), Kfb.dtype)
    columns = [jnp.concatenate([L, Wx, zeros]), jnp.concatenate([jnp.zeros_like(I), HIg, I])[:, None]]
    if g0 is not None:
        columns.append(jnp.concatenate([jnp.zeros_like(I), g0, jnp.zeros_like(I)])[:, None])
    if copy_factors:
        columns.append(jnp.eye(3 * nd, 2 * nd, dtype=Kfb.dtype))
    coef = jnp.concatenate(columns, axis=1)                        # [3d, n + 1 (+ 1) (+ 2d)]
    update = matmul_t(coef, jnp.concatenate([W, Kfb, G]))          # [n + 1 (+ 1) (+ 2d), n + l d]
    rows = UpdateRows(slice(0, nx), nx, nx + 1, slice(-2 * nd, -nd), slice(-nd, None))
    return update, rows, W, HIK, HIg


def _pending_blocks(z: ZColumns, dyn: Propagated, noise: Noise, ZRt, value: ValueCarry, update, rows: UpdateRows,
                    W, Kfb, data: StepData, acting, copy_factors: bool):
    """r, Rt and R at k, and the R update's by-products (factors, R_next): J(k+1) rewritten in
    (dx_k, pending at k), where slot sigma now holds du_{k-l}, plus the gains' terms."""
    nx, nd = rows.s, W.shape[0]
    u1 = slice(nd, None)
    # the R update's factors M, W [d, l d], slot order
    if copy_factors:
        M_p, W_p = update[rows.Kfb, nx:], update[rows.W, nx:]
    else:
        M_p, W_p = Kfb[:, nx:], W[:, nx:]
    r_pre = move_acting(value.r, dyn.Zs[z.ud] + noise.CSc[u1], data.slot, acting, axis=0, nd=nd)
    Rt_pre = move_acting(ZRt[z.x], dyn.ZSZ[z.x, z.ud], data.slot, acting, axis=1, nd=nd)
    r = r_pre + update[rows.s, nx:]
    Rt = Rt_pre + update[rows.S, nx:]
    if acting is not None:
        R, factors, R_next = r_update.update_framed(value.R, value.factors, ZRt[z.ud],
                                                    dyn.ZSZ[z.ud, z.ud] + noise.CSC[u1, u1], M_p, W_p, data.slot,
                                                    acting, data.next_slot, data.factor_row)
        return r, Rt, R, factors, R_next
    row = move_acting(ZRt[z.ud], dyn.ZSZ[z.ud, z.ud] + noise.CSC[u1, u1], data.slot, acting, axis=1, nd=nd)
    R, factors, R_next = r_update.update(value.R, value.factors, row, M_p, W_p, data.slot, data.next_slot,
                                         data.factor_row)
    return r, Rt, R, factors, R_next


def _predicted(prediction: Prediction, z: ZColumns, dyn: Propagated, noise: Noise, stage: Stage, update,
               rows: UpdateRows, HIK, I, g, g0, slot, acting):
    """The prediction at k: s0, r0 as s, r with I = 0, and the step's terms of a and b."""
    nx, nd = rows.s, I.shape[0]
    s0 = stage.d + dyn.Zs0[z.x] + update[rows.s0, :nx]
    r0 = prediction.r0
    if r0.shape[0] > 0:
        r0 = move_acting(r0, dyn.Zs0[z.ud] + noise.CSc[nd:], slot, acting, axis=0, nd=nd) + update[rows.s0, nx:]
    H_I = HIK[:, 0]
    return Prediction(s0, r0, prediction.a + 2 * I @ g0, prediction.b + I @ H_I + 2 * I @ (g - g0))


def structured_step(carry, data: StepData, *, l: int, reg, store_value: bool, store_S: bool, gains_fn, model,
                     copy_factors: bool, delay=None):
    """Step k+1 -> k of the corrected recursion (eq. 8 with the corrections of docs/derivation.md):
    the fused form of `stage.stage_step`.

    ``carry = (value, prediction)``: J(k+1) as a `ValueCarry`, and a `Prediction`
    or () without ``predict``. The command eliminated here, du_k, occupies slot sigma = k mod l at
    k+1; at k the same slot holds du_{k-l}, the command acting through B1_k. Every other block
    keeps its place. ``model`` gives the step's `Stage` from ``data.row``. ``l`` is the
    number of slots: with a frame, L, and ``delay`` the traced l, which places du_{k-l} in slot
    (k - l) mod L (computed here from the slot, not read from a per-step input: see
    `frame.acting_offset`).

    Returns the carry at k and the outputs (I, Kfb = [L, M by slot], s_tilde (, s, S) (, r, Rt, R
    in eq. 7's order)).
    """
    value, prediction = carry
    Z, stage = _step_stage(model, data.row, data.live, (l == 0) if delay is None else delay == 0)
    acting = None if delay is None or l == 0 else acting_offset(data.slot, delay, l, stage.e.shape[0])
    nx, nd = Z.shape[0], stage.e.shape[0]
    z = ZColumns(slice(0, nx), slice(nx, nx + nd), slice(nx + nd, None))
    r0 = prediction.r0 if prediction else None
    dyn = _through_dynamics(Z, value, prediction.s0 if prediction else None)
    noise = _noise_terms(stage, value.S, nd)
    H, g, g0, G, ZRt = _action_quadratic(stage, z, dyn, noise, value, r0, data.slot, acting)
    H = _sym(H)
    step_ok, I, Kfb = gains_fn(H, reg, g, G, data.bounds, value.warm)
    update, rows, W, HIK, HIg = _value_product(H, g, g0, G, I, Kfb, nx, copy_factors)
    s_tilde = stage.d_tilde + value.s_tilde + noise.cost + I @ (HIg + g)
    s = stage.d + dyn.Zs[z.x] + update[rows.s, :nx]
    S = _sym(stage.D + dyn.ZSZ[z.x, z.x] + update[rows.S, :nx])
    if l > 0:
        r, Rt, R, factors, R_next = _pending_blocks(z, dyn, noise, ZRt, value, update, rows, W, Kfb, data, acting,
                                                    copy_factors)
    else:
        r, Rt, R, factors, R_next = value.r, value.Rt, value.R, value.factors, value.R_next
    if prediction:
        prediction = _predicted(prediction, z, dyn, noise, stage, update, rows, HIK, I, g, g0, data.slot, acting)
    carry = (ValueCarry(s_tilde, s, S, r, Rt, R, R_next, value.ok & step_ok, I, factors), prediction)
    out = (I, Kfb, s_tilde) + ((s, S) if store_S else ())
    if store_value:
        exact = R if l == 0 else r_update.exact(R, factors, data.k, l, nd, stale=acting is None)
        out = out + value_blocks(r, Rt, exact, data.k, l, nd)
    return carry, out
