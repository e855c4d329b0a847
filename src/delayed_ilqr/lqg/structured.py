"""Theorem 1 (eq. 6-8) as the library runs it: the structured reverse scan, one fused step per k
(`structured_step`), and [`backward_pass`][delayed_ilqr.lqg.backward_pass].

Per step it costs O(l^2 d^3 + l n^2 d + n^3), against (n + l d)^3 for augmentation. This module
lays out the per-step inputs (the slot offsets, padding to a multiple of the deferred strategy's
block), picks the R update's strategy (`r_update.RStrategy`), starts from J(K) and runs the scan.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from .. import _precision, _validate
from .._kernels.scan import Blocks, packed_scan
from . import r_update
from .frame import SlotGains, from_slots, slot_offsets
from .gains import unconstrained_gains
from .model import DelayedLQG, Gains, StepModels, Value, checked_entry, stored_models
from .structured_step import Prediction, StepData, ValueCarry, structured_step

__all__ = ["structured_scan", "structured_slot_scan", "backward_pass"]


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
    step = partial(structured_step, l=l, reg=reg, store_value=store_value, store_S=store_S, gains_fn=gains_fn,
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
