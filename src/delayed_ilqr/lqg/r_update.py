"""The update of R, the [l d, l d] block of the value (7) that couples the pending commands: the hot
spot of the structured pass (everything else in a step is O(l d^2)).

Exactly, one step k+1 -> k (pending blocks in the slot frame of `frame`, slot sigma = k mod l)
replaces slot sigma's rows by ``row`` (du_{k-l} against the pending commands), its columns by row',
and adds M'W + W'M, with M, W [d, l d] the delay feedback and W = H Kfb / 2 + G at the pending
columns (docs/derivation.md §4).

**The stale-column invariant.** Only the rows are written: R is stored with each slot's row block
exact as of the step that last replaced it, and its column block stale. Slots are replaced in
cyclic order, so the slot read next (k - 1 mod l) is the one replaced longest ago, and its exact
values are in its *columns*, which every newer row wrote. Each update therefore returns, besides
the stored R, the exact rows ``R_next`` [d, l d] of the slot the next step eliminates, and
`exact` rebuilds the symmetric R from the stored one.

Three strategies, one interface (`RStrategy` picks; `update`, `flush` and
`exact` act on R and its ``factors``):

* dense, ``factors = ()``: M'W + W'M is added at once, one loop over R that XLA fuses and runs
  in place (per step it reads and writes R: memory-bound for large l d);
* copied factors (l d >= ``COPIED_FACTORS_MIN_LD``): as dense, but the value update's product also
  copies out W and Kfb, and M, W are read from that copy (a change in the fused step only);
* deferred blocks (l d >= ``DEFER_MIN_LD``, block q = ``DEFER_BLOCK``), ``factors = (F,)``, F
  [2 q d, l d]: the factors M_p, W_p of the steps p of the block so far are kept (step p at rows
  2 p d), the exact R being R + sum_p M_p'W_p + W_p'M_p, and `flush` adds them with one
  matrix product per block. A step then only corrects the rows it writes and the column block it
  reads by products with the factors, O(q d^2 l d) instead of O((l d)^2).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._kernels.dense import add_symmetric_product, matmul_t
from .frame import add_acting

__all__ = ["RStrategy", "update", "update_framed", "flush", "exact", "COPIED_FACTORS_MIN_LD", "DEFER_MIN_LD", "DEFER_BLOCK"]

# From this l d on, M and W are copied out of the value update's product: keeps XLA from fusing their
# producers into the loop over R (docs/performance.md#copied_factors_min_ld).
COPIED_FACTORS_MIN_LD = 64
# From this l d on, the R update is deferred to one product per block of DEFER_BLOCK steps: pays once
# the per-step loop over R is bound by memory (docs/performance.md#defer_min_ld-and-defer_block).
DEFER_MIN_LD = 300
DEFER_BLOCK = 16


class RStrategy(NamedTuple):
    """How a structured pass with l delay steps and d controls updates R.

    Attributes:
        block: q, the steps whose updates are deferred to one product (1: none deferred).
        copy_factors: whether M and W are read from copies made by the value update's product.
    """

    block: int
    copy_factors: bool

    @classmethod
    def choose(cls, l: int, nd: int, block: int | None = None) -> "RStrategy":
        """The defaults above; ``block`` overrides the deferral (ignored for l = 0: no R)."""
        if block is None:
            block = DEFER_BLOCK if l * nd >= DEFER_MIN_LD else 1
        return cls(block if l > 0 else 1, l * nd >= COPIED_FACTORS_MIN_LD)

    def initial_factors(self, nd: int, ld: int, dtype):
        """The factors at the start of a pass, and after each flush: () or (zeros [2 q d, l d],)."""
        return (jnp.zeros((2 * self.block * nd, ld), dtype),) if self.block > 1 else ()


def update(R, factors, row, M, W, slot, next_slot, factor_row):
    """R at k from R at k+1 (see the module docstring).

    Args:
        R: [l d, l d] stored R of J(k+1); factors: () or (F,) of the deferred strategy.
        row: [d, l d] exact rows of slot sigma at k (du_{k-l} against the pending commands).
        M, W: [d, l d] the step's delay feedback and W at the pending columns, slot order.
        slot, next_slot: sigma d = (k mod l) d and ((k - 1) mod l) d, offsets in the pending axis.
        factor_row: 2 (k mod q) d, the step's rows in the deferred factors.

    Returns:
        (R, factors, R_next): the stored R and factors at k, and the exact rows [d, l d] of the
        slot that step k-1 eliminates.
    """
    nd = row.shape[0]
    if not factors:
        R = add_symmetric_product(R, M, W)
        MWs = jnp.concatenate([jax.lax.dynamic_slice_in_dim(X, slot, nd, axis=1) for X in (M, W)])
        R = jax.lax.dynamic_update_slice(R, row + matmul_t(MWs, jnp.concatenate([W, M])), (slot, 0))
        return R, factors, jax.lax.dynamic_slice_in_dim(R, next_slot, nd, axis=1).T
    (F,) = factors
    # X'F with X = F, its M and W rows swapped, at some columns is (sum_p M_p'W_p + W_p'M_p) at
    # those rows: one product gives the factors' part of slot sigma's rows (written now) and of
    # the next slot's (read next).
    cols = jnp.concatenate([jax.lax.dynamic_slice_in_dim(F, j, nd, axis=1) for j in (slot, next_slot)], axis=1)
    part = matmul_t(_swap_factors(cols, nd), F)                               # [2d, l d]
    # stored rows = exact rows - the factors' part (this step's own part cancels: added to both)
    R = jax.lax.dynamic_update_slice(R, row - part[:nd], (slot, 0))
    F = jax.lax.dynamic_update_slice_in_dim(F, jnp.concatenate([M, W]), factor_row, axis=0)
    own = jnp.concatenate([jax.lax.dynamic_slice_in_dim(X, next_slot, nd, axis=1) for X in (W, M)])
    R_next = jax.lax.dynamic_slice_in_dim(R, next_slot, nd, axis=1).T + part[nd:] + matmul_t(own, jnp.concatenate([M, W]))
    return R, (F,), R_next


def update_framed(R, factors, Y, X, M, W, slot, acting, next_slot, factor_row):
    """R at k from R at k+1 in a frame of L slots with the delay as data (docs/derivation.md §17).

    The stale-column invariant above rests on the slot written being the slot eliminated, which
    a frame breaks (du_{k-l} is written into slot alpha = (k - l) mod L, du_{k-L}'s slot sigma is
    cleared): R is kept symmetric instead, rows and columns written alike. With w_a = P w the
    acting components of the frame w at k (P the selection ``acting``), substituting
    x_{k+1} = ... + B1 P w into J(k+1) adds P'Y + Y'P + P'X P = P'V + V'P, V = Y + X P / 2, to R
    with its slot sigma cleared: Y = B1'Rt (Rt of J(k+1), slot sigma excluded) and X = B1'S B1 +
    sum_j C1_j'S C1_j. With one tap per channel the acting rows of R are zero before (the command
    has acted, Y is zero there) and this writes them; a fractional delay's second tap reads a
    command that is still pending (§20).

    P'V + V'P is added to R's acting rows and columns (m of each, read-add-write of slices: no
    scatter, see `frame.add_acting`). Without deferral (``factors = ()``) the clearing of slot sigma
    (a mask) and M'W + W'M are one elementwise loop over R, which XLA runs in place. Deferred
    (``factors = (F,)``, as in `update`), R + sum_p M_p'W_p + W_p'M_p over the block's steps p is
    the exact R: clearing slot sigma clears its rows and columns in R and its columns in F, and the
    step's M, W join F, so that a step costs O(q d^2 L d) instead of O((L d)^2).

    Args:
        R: [L d, L d] the stored R of J(k+1) (symmetric); factors: () or (F,), see `update`.
        Y: [m, L d] B1'Rt (slot sigma is cleared here); X: [m, m] (m = d, or t d taps).
        M, W: [d, L d] the step's delay feedback and W.
        slot, acting, next_slot: sigma d, alpha d and ((k - 1) mod L) d (``acting``: the [m]
            indices of the acting components with per-channel delays or taps, `frame.acting_offset`).
        factor_row: 2 (k mod q) d, the step's rows in the deferred factors.

    Returns:
        (R, factors, R_next): the stored R and factors at k, and the exact rows [d, L d] of the slot
        that step k-1 eliminates.
    """
    nd, Ld = M.shape
    index = jnp.arange(Ld)
    kept = (index < slot) | (index >= slot + nd)
    V = add_acting(jnp.where(kept, Y, 0.0), 0.5 * X, acting, axis=1)
    if factors:
        (F,) = factors
        clear = jnp.zeros((nd, Ld), R.dtype)
        R = jax.lax.dynamic_update_slice(R, clear, (slot, 0))
        R = jax.lax.dynamic_update_slice(R, clear.T, (0, slot))
        F = jax.lax.dynamic_update_slice(F, jnp.zeros((F.shape[0], nd), F.dtype), (0, slot))
        F = jax.lax.dynamic_update_slice_in_dim(F, jnp.concatenate([M, W]), factor_row, axis=0)
        factors = (F,)
    else:
        R = add_symmetric_product(jnp.where(kept[:, None] & kept[None, :], R, 0.0), M, W)
    R = add_acting(add_acting(R, V, acting, axis=0), V.T, acting, axis=1)
    R_next = jax.lax.dynamic_slice_in_dim(R, next_slot, nd, axis=0)
    if factors:
        R_next = R_next + matmul_t(_swap_factors(jax.lax.dynamic_slice_in_dim(F, next_slot, nd, axis=1), nd), F)
    return R, factors, R_next


def _swap_factors(F, nd: int):
    """[2 q d, m] factors with M_p, W_p at rows 2 p d: the same with W_p, M_p."""
    return F.reshape(-1, 2, nd, F.shape[1])[:, ::-1].reshape(F.shape)


def flush(R, factors, nd: int):
    """End of a block of the deferred strategy: (R + sum_p M_p'W_p + W_p'M_p, factors reset)."""
    (F,) = factors
    return R + F.T @ _swap_factors(F, nd), (jnp.zeros_like(F),)


def exact(R, factors, k, l: int, nd: int, stale: bool = True):
    """The exact (symmetric) R from its stored form, after step k (``stale=False``: a framed R,
    stored symmetric, see `update_framed`).

    The pass runs down in k, so slot s was last replaced at step k + ((s - k) mod l), that many
    steps ago; entry (i, j) is exact in the row of whichever of the two slots was replaced more
    recently (for slots never replaced, both copies hold the same sum of updates).
    """
    if factors:
        (F,) = factors
        R = R + F.T @ _swap_factors(F, nd)
    if not stale:
        return R
    age = (jnp.arange(l) - k) % l                           # steps since slot s was replaced
    age = jnp.repeat(age, nd)
    return jnp.where(age[:, None] <= age[None, :], R, R.T)
