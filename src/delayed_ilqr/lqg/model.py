"""The delayed LQG problem of eq. (3)-(4), as a whole ([`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG]) and step by step
(`Stage`, `StepModels`), and the two results of solving it ([`Gains`][delayed_ilqr.lqg.Gains],
[`Value`][delayed_ilqr.lqg.Value]).

The system, in deviations from a nominal trajectory (time-major arrays, k = 0..K-1):

    dx_{k+1} = A_k dx_k + B0_k du_k + B1_k du_{k-l} + sum_j xi_{k,j} (c_{k,j} + C0_{k,j} du_k + C1_{k,j} du_{k-l})
    cost_k   = d_tilde_k + 2 dx_k'd_k + dx_k'D_k dx_k + 2 du_k'e_k + du_k'E_k du_k          (eq. 4)
               + 2 du_k'N_k dx_k                           (cross term, zero in eq. 4)
    cost_K   = d_tilde_K + 2 dx_K'd_K + dx_K'D_K dx_K

with dx_0 = 0, du_k = 0 for k < 0 and xi_{k,j} ~ N(0, 1) independent. For l = 0 the "delayed"
command is the current one: B1 and C1 act on du_k like B0 and C0.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _delays, _precision, _validate

__all__ = ["DelayedLQG", "Stage", "StepModels", "Gains", "Value", "stored_models", "merged_if_undelayed", "checked_entry",
           "stacked_dynamics", "idle_stage", "fold_current", "fold_taps", "frame_delay_leaf"]


class Stage(NamedTuple):
    """One step k < K of the delayed LQG, eq. (3)-(4): the fields of [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG] at row k.

    Attributes:
        A: [n, n]; B0, B1: [n, d]; c: [p, n]; C0, C1: [p, n, d]; d_tilde: []; d: [n]; D: [n, n];
        e: [d]; E: [d, d]; N: [d, n] (the cross cost 2 du'N dx).
    """

    A: jax.Array
    B0: jax.Array
    B1: jax.Array
    c: jax.Array
    C0: jax.Array
    C1: jax.Array
    d_tilde: jax.Array
    d: jax.Array
    D: jax.Array
    e: jax.Array
    E: jax.Array
    N: jax.Array


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
        delay_steps: l >= 0, the input delay in steps; or a list [l_1, ..., l_d], one per command
            channel: column j of B1, C1 then acts with du_{k-l_j}, channel j's command sent l_j steps
            ago (docs/derivation.md §18). Per-channel delays always run in a frame of L >= max_j l_j
            slots (``delay_frame``, default max_j l_j). A list of t d entries gives taps: B1, C1 then
            have t d columns, and column i acts with du_{k-l_i} of channel i mod d (a fractional
            delay is two taps per channel, docs/derivation.md §20).
        N: optional [K, d, n] cross cost 2 du_k'N_k dx_k (absent from eq. 4, which is N = 0; a
            general running cost l(x, u) has one).
        delay_frame: optional L >= l: keep the pending commands in a frame of L slots, with the
            delay l as data (docs/derivation.md §17). Problems that differ only in l <= L then
            share one compiled pass; the value's and the gains' pending blocks span the frame,
            [du_{k-L}, ..., du_{k-1}], and those of the L - l commands that have acted are zero.

    ``p = 0`` (no noise) is allowed: pass arrays with a zero-length second axis, or ``None`` for
    c, C0 and C1 together. Instances are JAX pytrees whose static fields are ``delay_steps`` and
    ``delay_frame``; with a frame, ``delay_steps`` is a leaf (an int32 scalar) instead.
    """

    def __init__(self, A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, delay_steps, N=None, delay_frame=None):
        _precision.require_x64("lqg.DelayedLQG")
        A = _validate.array(A, "A", (None, None, None))
        K, n = A.shape[0], A.shape[1]
        if K < 1:
            raise ValueError(f"A must hold at least one time step (K >= 1); got shape {A.shape}")
        A = _validate.array(A, "A", (K, n, n))
        B0 = _validate.array(B0, "B0", (K, n, None))
        nd = B0.shape[2]
        self.delay_steps = _delays.checked(delay_steps, nd, taps=True)
        self.delay_frame = _delays.checked_frame(delay_frame, self.delay_steps)
        m = nd if not _delays.is_per_channel(self.delay_steps) else len(self.delay_steps)
        B1 = _validate.array(B1, "B1", (K, n, m))
        if c is None and C0 is None and C1 is None:
            c, C0, C1 = np.zeros((K, 0, n)), np.zeros((K, 0, n, nd)), np.zeros((K, 0, n, m))
        c = _validate.array(c, "c", (K, None, n))
        p = c.shape[1]
        C0 = _validate.array(C0, "C0", (K, p, n, nd))
        C1 = _validate.array(C1, "C1", (K, p, n, m))
        d_tilde = _validate.array(d_tilde, "d_tilde", (K + 1,))
        d = _validate.array(d, "d", (K + 1, n))
        D = _check_symmetric(_validate.array(D, "D", (K + 1, n, n)), "D")
        e = _validate.array(e, "e", (K, nd))
        E = _check_symmetric(_validate.array(E, "E", (K, nd, nd)), "E")
        N = np.zeros((K, nd, n)) if N is None else _validate.array(N, "N", (K, nd, n))
        for name, value in zip(Stage._fields, (A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, N)):
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

    @property
    def frame_steps(self) -> int:
        """The number of pending slots (static): ``delay_frame``, or l without a frame."""
        return self.delay_steps if self.delay_frame is None else self.delay_frame

    @classmethod
    def from_traced(cls, *, delay_steps, delay_frame=None, **arrays) -> "DelayedLQG":
        """Builds an instance from (possibly traced) arrays without validation: for use inside jit,
        where the arrays come from the library's own linearisation."""
        return _unflatten((delay_steps, delay_frame), tuple(arrays[name] for name in Stage._fields))

    def replace(self, **changes) -> "DelayedLQG":
        """A copy with some arrays replaced (no validation: for internal use on traced data)."""
        new = object.__new__(DelayedLQG)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def __repr__(self) -> str:
        frame = "" if self.delay_frame is None else f", delay_frame={self.delay_frame}"
        return (f"DelayedLQG(K={self.horizon}, n={self.n_states}, d={self.n_controls}, "
                f"p={self.n_noise}, delay_steps={self.delay_steps}{frame})")


def _check_symmetric(mat: np.ndarray, name: str) -> np.ndarray:
    asym = np.max(np.abs(mat - np.swapaxes(mat, -1, -2)), initial=0.0)
    if asym > 1e-9 * max(1.0, float(np.max(np.abs(mat), initial=0.0))):
        raise ValueError(f"{name} must be symmetric in its last two axes; got an asymmetry of {asym:.3g}")
    return mat


def _flatten(lqg: DelayedLQG):
    arrays = tuple(getattr(lqg, f) for f in Stage._fields)
    if lqg.delay_frame is None:
        return arrays, (lqg.delay_steps, None)
    return arrays + (frame_delay_leaf(lqg.delay_steps),), (None, lqg.delay_frame)


def _unflatten(aux, arrays):
    new = object.__new__(DelayedLQG)
    new.delay_steps, new.delay_frame = aux
    if new.delay_frame is not None and len(arrays) > len(Stage._fields):
        new.delay_steps, arrays = arrays[-1], arrays[:-1]
    for name, value in zip(Stage._fields, arrays):
        setattr(new, name, value)
    return new


def frame_delay_leaf(delay_steps):
    """The delay l as the leaf of a framed pytree: an int32 scalar, or an int32 [d] array of per-channel
    delays (a traced one as it is)."""
    if isinstance(delay_steps, (int, np.integer)) or (isinstance(delay_steps, np.ndarray)
                                                      and np.issubdtype(delay_steps.dtype, np.integer)):
        return np.asarray(delay_steps, np.int32)
    return delay_steps


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


def merged_if_undelayed(lqg: DelayedLQG):
    """For l = 0 the delayed command is the current one: fold B1, C1 into B0, C0 (with a frame,
    where the traced l is 0)."""
    if lqg.delay_frame is None and lqg.delay_steps > 0:
        return lqg
    current = True if lqg.delay_frame is None else lqg.delay_steps == 0
    folded = fold_current((lqg.B0, lqg.B1, lqg.C0, lqg.C1), current)
    return lqg.replace(**dict(zip(("B0", "B1", "C0", "C1"), folded)))


def fold_current(blocks, current):
    """(B0, B1, C0, C1) with the delayed command's columns folded into the current command's where
    ``current`` (l = 0: the command acting is the one sent now): (B0 + B1, 0, C0 + C1, 0).
    ``current`` is a Python bool (a static l) or a traced bool (a framed l), per column of B1 with
    per-channel delays or taps (a tap column i folds into channel i mod d)."""
    B0, B1, C0, C1 = blocks
    if current is True:
        return B0 + B1, jnp.zeros_like(B1), C0 + C1, jnp.zeros_like(C1)
    keep = jnp.logical_not(current)
    nd = B0.shape[-1]
    return (B0 + fold_taps(jnp.where(keep, 0.0, B1), nd), jnp.where(keep, B1, 0.0),
            C0 + fold_taps(jnp.where(keep, 0.0, C1), nd), jnp.where(keep, C1, 0.0))


def fold_taps(X, nd: int):
    """[..., t d] -> [..., d]: each channel's taps summed (X itself for one tap per channel)."""
    if X.shape[-1] == nd:
        return X
    return X.reshape(X.shape[:-1] + (X.shape[-1] // nd, nd)).sum(axis=-2)


def stacked_dynamics(lqg: DelayedLQG):
    """Z = [A, B0, B1] [K, n, n + 2d]: x_{k+1} = Z_k [dx_k, du_k, du_{k-l}] in one product."""
    return jnp.concatenate([lqg.A, lqg.B0, lqg.B1], axis=2)


class StepModels(NamedTuple):
    """The delayed LQG given step by step, for the structured pass to build as it goes.

    ``model(row)`` returns step k's `Stage` (or the same twelve arrays as a plain tuple),
    from row k of ``rows`` (a time-major pytree of K rows); ``terminal`` is (d_tilde_K, d_K, D_K).
    `stored_models` makes one from a [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG] (its rows are the model's arrays);
    ``ilqg.linearize.step_models`` makes one whose rows are the nominal (x_k, u_k, u_{k-l}), linearised
    inside the pass, so that the solver never stores the model (docs/performance.md#stepmodels).
    """

    model: Callable[[Any], Stage]
    rows: Any
    terminal: tuple
    delay_steps: Any             # l: an int, or a traced int32 with a frame
    n_controls: int
    delay_frame: int | None = None

    @property
    def frame_steps(self) -> int:
        """The number of pending slots (static): ``delay_frame``, or l without a frame."""
        return self.delay_steps if self.delay_frame is None else self.delay_frame

    @property
    def horizon(self) -> int:
        return jax.tree_util.tree_leaves(self.rows)[0].shape[0]

    @property
    def n_states(self) -> int:
        return self.terminal[1].shape[0]


def stored_models(lqg: DelayedLQG) -> StepModels:
    """`StepModels` of a stored [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG]: row k is its `Stage` k."""
    rows = Stage(lqg.A, lqg.B0, lqg.B1, lqg.c, lqg.C0, lqg.C1, lqg.d_tilde[:-1], lqg.d[:-1], lqg.D[:-1], lqg.e,
                 lqg.E, lqg.N)
    return StepModels(lambda row: row, rows, (lqg.d_tilde[-1], lqg.d[-1], lqg.D[-1]), lqg.delay_steps,
                      lqg.n_controls, lqg.delay_frame)


def idle_stage(stage: Stage) -> Stage:
    """A step that leaves every value exactly as it is (A = I, E = I, everything else zero): the
    backward pass crosses it with J unchanged and gains zero."""
    zero = Stage(*(jnp.zeros_like(x) for x in stage))
    return zero._replace(A=jnp.eye(stage.A.shape[0], dtype=stage.A.dtype),
                         E=jnp.eye(stage.E.shape[0], dtype=stage.E.dtype))


def checked_entry(lqg, reg, where: str):
    """The checks of the public LQG entry points: ``lqg`` a [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG], ``reg`` a finite
    lambda >= 0 (a traced one passes as it is); returns ``reg``."""
    if not isinstance(lqg, DelayedLQG):
        raise TypeError(f"{where}: lqg must be a delayed_ilqr.lqg.DelayedLQG; got {type(lqg).__name__}")
    return _validate.reg(reg)
