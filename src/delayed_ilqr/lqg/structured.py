"""Theorem 1 (eq. 6-8) as the library runs it: the structured reverse scan, one fused step per k.

Per step it costs O(l^2 d^3 + l n^2 d + n^3), against (n + l d)^3 for augmentation. The mathematics
of one step is `stage.stage_step`, written in eq. (6)'s order of the pending commands; the step
here computes the same numbers (tests/test_stage.py) arranged for speed:

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
when alpha = sigma (l = L). R is then kept whole and symmetric (`r_update.update_framed`).

The value update is the exact cost-to-go of the quadratic model under whatever gains the gain rule
returns (regularised, or clamped by control limits; docs/derivation.md §4), so J(0) is always the
true cost of the returned policy.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from .._kernels.dense import matmul, matmul_t
from .._kernels.scan import Blocks, packed_scan
from . import r_update
from .frame import SlotGains, acting_offset, add_acting, from_slots, slot_offsets, value_blocks
from .gains import unconstrained_gains
from .model import (DelayedLQG, Gains, Stage, StepModels, Value, checked_entry, fold_current, idle_stage,
                    stored_models)

__all__ = ["ValueCarry", "Prediction", "structured_scan", "structured_slot_scan", "backward_pass"]


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
    """Per-step inputs of the reverse scan, time-major (see `_step_data`)."""

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


def _step_data(models: StepModels, bounds, steps: int, block: int) -> StepData:
    """`StepData` for k = 0..steps-1 (the horizon and any padding, see `_padded_rows`);
    the offsets are computed here, once, rather than in every step."""
    k = jnp.arange(steps)
    frame, nd = models.frame_steps, models.n_controls
    rows, bounds = _padded_rows(models.rows, bounds, steps - models.horizon)
    live = k < models.horizon if steps > models.horizon else None
    return StepData(k, slot_offsets(steps, frame, nd), ((k - 1) % max(frame, 1)) * nd, (k % block) * 2 * nd, live,
                    rows, bounds)


def _padded_rows(rows, bounds, steps: int):
    """``rows`` and ``bounds`` with ``steps`` rows appended, copies of the last (any row will do:
    the recursion replaces the model of these steps by `model.idle_stage`, and their bounds
    are +-1), so that blocked passes can run on a horizon that is a multiple of their block."""
    if steps == 0:
        return rows, bounds
    grow = lambda x, fill=None: jnp.concatenate([x, jnp.repeat(x[-1:], steps, axis=0) if fill is None
                                                 else jnp.full((steps,) + x.shape[1:], fill, x.dtype)])
    rows = jax.tree_util.tree_map(grow, rows)
    if bounds is not None:
        bounds = (grow(bounds[0], -1.0), grow(bounds[1], 1.0), *(grow(b, False) for b in bounds[2:]))
    return rows, bounds


def _sym(M):
    return 0.5 * (M + jnp.swapaxes(M, -1, -2))


# ---------------------------------------------------------------------------------------------
# The phases of one step k+1 -> k
# ---------------------------------------------------------------------------------------------

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


def _moved(blocks, new, slot, acting, axis: int, nd: int):
    """``blocks`` with the acting command's ``new`` blocks written at its slot, along ``axis``.

    Without a frame (``acting`` None) they replace slot sigma's, where du_{k-l} follows du_k. With
    one, slot sigma (``nd`` wide) is cleared first (du_{k-L} has acted) and slot alpha = ``acting``
    receives them; alpha = sigma where l = L. With one delay per channel ``acting`` holds the
    [d] indices of the channels' acting components, and column j of ``new`` goes to index j; with
    taps (a fractional delay), [t d] indices, and the blocks are added (`frame.add_acting`: a
    command read by the later tap is still pending at k+1)."""
    start = lambda offset: (offset,) if blocks.ndim == 1 else ((0, offset) if axis == 1 else (offset, 0))
    if acting is not None:
        axis = axis if blocks.ndim > 1 else 0
        blocks = jax.lax.dynamic_update_slice(blocks, jnp.zeros(new.shape[:axis] + (nd,) + new.shape[axis + 1:],
                                                                new.dtype), start(slot))
        return add_acting(blocks, new, acting, axis)
    return jax.lax.dynamic_update_slice(blocks, new, start(slot))


def _action_quadratic(stage: Stage, z: ZColumns, dyn: Propagated, noise: Noise, value: ValueCarry, r0, slot,
                      acting=None):
    """The quadratic in du_k: H [d, d], g [d] (g0 with r0), G = [G_x, G_w] [d, n + l d], and Z'Rt.

    Slot sigma's blocks of J(k+1) are those of du_k; in G_w the same slot is du_{k-l}, via B1 (with a
    frame, slot alpha = ``acting`` is, and slot sigma is cleared: see `_moved`)."""
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
    Gw = _moved(ZRt[z.u] + value.R_next, G_new, slot, acting, axis=1, nd=nd)
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
    r_pre = _moved(value.r, dyn.Zs[z.ud] + noise.CSc[u1], data.slot, acting, axis=0, nd=nd)
    Rt_pre = _moved(ZRt[z.x], dyn.ZSZ[z.x, z.ud], data.slot, acting, axis=1, nd=nd)
    r = r_pre + update[rows.s, nx:]
    Rt = Rt_pre + update[rows.S, nx:]
    if acting is not None:
        R, factors, R_next = r_update.update_framed(value.R, value.factors, ZRt[z.ud],
                                                    dyn.ZSZ[z.ud, z.ud] + noise.CSC[u1, u1], M_p, W_p, data.slot,
                                                    acting, data.next_slot, data.factor_row)
        return r, Rt, R, factors, R_next
    row = _moved(ZRt[z.ud], dyn.ZSZ[z.ud, z.ud] + noise.CSC[u1, u1], data.slot, acting, axis=1, nd=nd)
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
        r0 = _moved(r0, dyn.Zs0[z.ud] + noise.CSc[nd:], slot, acting, axis=0, nd=nd) + update[rows.s0, nx:]
    H_I = HIK[:, 0]
    return Prediction(s0, r0, prediction.a + 2 * I @ g0, prediction.b + I @ H_I + 2 * I @ (g - g0))


def _structured_step(carry, data: StepData, *, l: int, reg, store_value: bool, store_S: bool, gains_fn, model,
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


# ---------------------------------------------------------------------------------------------
# The reverse scan
# ---------------------------------------------------------------------------------------------

def _terminal(models: StepModels, strategy: r_update.RStrategy) -> ValueCarry:
    """J(K): the final cost, no pending blocks (no command acts after K)."""
    l, nd, nx = models.frame_steps, models.n_controls, models.n_states
    d_tilde, d, D = models.terminal
    dt = D.dtype
    factors = strategy.initial_factors(nd, l * nd, dt)
    return ValueCarry(d_tilde, d, D, jnp.zeros(l * nd, dt), jnp.zeros((nx, l * nd), dt),
                      jnp.zeros((l * nd, l * nd), dt), jnp.zeros((nd, l * nd), dt), jnp.asarray(True),
                      jnp.zeros(nd, dt), factors)


def _flush(carry):
    """End of a block of the deferred strategy (see `r_update.flush`)."""
    value, prediction = carry
    R, factors = r_update.flush(value.R, value.factors, value.R_next.shape[0])
    return value._replace(R=R, factors=factors), prediction


def structured_scan(lqg: DelayedLQG, reg=0.0, store_value: bool = True, gains_fn=unconstrained_gains,
                    bounds=None, block: int | None = None):
    """Runs Theorem 1 backwards with ``lax.scan``; returns (Gains, outputs, positive_definite).

    ``outputs`` are s_tilde [K], s [K, n], S [K, n, n] (and, with ``store_value``, r, Rt, R).

    Args:
        store_value: False keeps only s_tilde, s, S per step (memory O(K (n^2 + l d^2)) instead of
            O(K l^2 d^2)); the solver uses it.
        gains_fn: the gain rule ``(H, reg, g, G, bounds_k, warm) -> (ok, I, Kfb)`` (see
            `gains`; default: unconstrained, Cholesky of H + reg I). The control-limited
            solver passes a box-QP version; ``warm`` is the feedforward of the step after.
        bounds: per-step data for ``gains_fn``, time-major (e.g. [K, 2, d] limits on du_k).
        block: q > 1 defers the O((l d)^2) part of each step to one matrix product per block of q
            steps (see `r_update`); the horizon is padded to a multiple of q with steps
            that change nothing. Default: ``r_update.DEFER_BLOCK`` from l d >= ``DEFER_MIN_LD``,
            else 1 (no deferral).
    """
    gains, out, ok = structured_slot_scan(lqg, reg, store_value, gains_fn, bounds, block)
    return from_slots(gains, lqg.n_states), out, ok


def structured_slot_scan(lqg: DelayedLQG | StepModels, reg=0.0, store_value: bool = True, gains_fn=unconstrained_gains,
                         bounds=None, block: int | None = None, predict: bool = False, store_S: bool = True):
    """`structured_scan` with the gains as `frame.SlotGains`, as the recursion makes
    them, on a stored [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG] or on `StepModels` (the solver's, linearised in
    the pass).

    ``store_S=False`` leaves s and S out of the outputs (s_tilde only, with ``store_value=False``):
    the solver needs S only with noise, and at l = 1 they are more numbers per step than the gains.

    ``predict=True`` also returns (a, b) of `Prediction`: under the LQG, the expected cost
    of the returned policy with its feedforward scaled by alpha, minus that at alpha = 0, is
    alpha a + alpha^2 b. That is the line search's model, which ``ilqg.line_search.predicted_change``
    computes by a forward pass; here it costs two columns in products the step makes anyway.
    """
    models = stored_models(lqg) if isinstance(lqg, DelayedLQG) else lqg
    K, l, nd = models.horizon, models.frame_steps, models.n_controls
    strategy = r_update.RStrategy.choose(l, nd, None if block is None else _validate.positive_int(block, "block"))
    if store_value and not store_S:
        raise ValueError("store_S=False needs store_value=False: the value blocks include S")
    steps = K + (-K % strategy.block)
    step = partial(_structured_step, l=l, reg=reg, store_value=store_value, store_S=store_S, gains_fn=gains_fn,
                   model=models.model, copy_factors=strategy.copy_factors,
                   delay=None if models.delay_frame is None else models.delay_steps)
    d_K = models.terminal[1]
    zero = jnp.zeros((), d_K.dtype)
    prediction = Prediction(d_K, jnp.zeros(l * nd, d_K.dtype), zero, zero) if predict else ()
    # the outputs unpacked (docs/performance.md#pack_inputs-and-pack_outputs)
    (value, prediction), out = packed_scan(step, (_terminal(models, strategy), prediction),
                                           _step_data(models, bounds, steps, strategy.block), reverse=True,
                                           blocks=Blocks(strategy.block, _flush), pack_outputs=False)
    out = tuple(o[:K] for o in out)
    if predict:
        return SlotGains(*out[:2]), out[2:], value.ok, (prediction.a, prediction.b)
    return SlotGains(*out[:2]), out[2:], value.ok


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
    return _backward_pass(lqg, checked_entry(lqg, reg, "lqg.backward_pass"))


@jax.jit
def _backward_pass(lqg: DelayedLQG, reg):
    _precision.require_x64("lqg.backward_pass")   # at tracing, which float32 always causes
    gains, out, ok = structured_scan(lqg, reg, store_value=True)
    # out = (s_tilde, s, S, r, Rt, R) for k = 0..K-1; J(K) is the final cost, with no pending blocks
    final = stored_models(lqg).terminal + tuple(jnp.zeros_like(o[0]) for o in out[3:])
    value = Value(*(jnp.concatenate([o, f[None]]) for o, f in zip(out, final)), positive_definite=ok)
    return gains, value
