"""The circular slot frame of the pending commands: the only code that knows it.

At step k the pending commands are du_{k-l}, ..., du_{k-1} (eq. 6's order i = 0..l-1: du_{k+i-l}).
The structured recursion and the rollouts store them in a flat [l d] vector in which du_j lives in
*slot* j mod l, components (j mod l) d ... (j mod l) d + d. The command that stops being pending at
step k (du_{k-l}, acting now) and the one that becomes pending (du_k) share slot k mod l, so one
step writes one slot and no block ever moves: the backward pass updates its value blocks in place
and a rollout writes one slot per step instead of shifting a buffer.

With a frame of L >= l slots and the delay l as data (``delay_frame``, docs/derivation.md §17),
du_j lives in slot j mod L and the command acting at step k, du_{k-l}, in slot (k - l) mod L
(`acting_offset`); the other L - l slots hold commands that have acted, with zero blocks
and zero gains, and for l = L the two slots coincide as above.

With one delay per command channel (``delay_steps`` a [d] vector l_j, always in a frame of
L >= max_j l_j slots, docs/derivation.md §18) component j of slot (k - l_j) mod L is channel j's
command acting at step k: `acting_offset` then returns the [d] indices of those components, and
`take_acting` reads them and the recursion writes its blocks there (`move_acting`, `add_acting`): a
contiguous slice for one delay, one slice per component for several (no gather or scatter, which
would keep XLA from compiling the loops as one function).

More generally ``delay_steps`` may hold t d *tap* delays (a multiple of d): tap i acts on channel
i mod d with that channel's command sent l_i steps ago. A fractional delay (l + phi) dt is two
taps per channel, l and l + 1 (docs/derivation.md §20). Two taps may then read the same command
at different steps, so the recursion *adds* the acting blocks into the frame (`add_acting`).

Eq. (6)'s order and the slot order differ by a rotation that depends on k: `pending_order`
gives the permutation, `to_slots` / `from_slots` convert gains and
`value_blocks` the value's pending blocks. For l = 0 there is no pending command and every
slot offset is 0.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .model import Gains

__all__ = ["SlotGains", "slot_offsets", "acting_offset", "take_acting", "add_acting", "acting_blocks", "move_acting",
           "current_taps", "acting_commands", "tap_channels", "to_slots", "from_slots", "pending_order", "value_blocks"]


class SlotGains(NamedTuple):
    """The law (6) in the slot frame, as the recursion makes it and the rollouts use it.

    du_k = I_k + F_k [dx_k; pending_k], with pending_k the flat [l d] vector in slot order.

    Attributes:
        feedforward: [K, d] I_k.
        feedback: [K, d, n + l d] F_k = [L_k, M_k by slot].
    """

    feedforward: jax.Array
    feedback: jax.Array


def slot_offsets(K: int, l: int, nd: int):
    """(k mod l) d for k = 0..K-1: where du_k sits in the flat pending vector (0 when l = 0)."""
    return (jnp.arange(K) % max(l, 1)) * nd


def acting_offset(slot, l, frame: int, nd: int):
    """((k - l) mod L) d from slot = (k mod L) d: where du_{k-l}, the command acting at step k,
    sits in a frame of L >= 1 slots (``l`` traced); for l = 0 that is du_k's own slot (folded, see
    derivation §17). Computed inside the loops from the step's slot: a per-step array of these
    offsets as a scan input made the closed loop three times slower (docs/performance.md).

    With one delay per channel (``l`` [d]): the [d] indices ((k - l_j) mod L) d + j of the
    components that act at step k, channel j's command sent l_j steps ago; with t d taps (``l``
    [t d]), the indices ((k - l_i) mod L) d + (i mod d)."""
    offset = (slot - l * nd) % (frame * nd)
    return offset if jnp.ndim(l) == 0 else offset + tap_channels(jnp.shape(l)[0], nd)


def tap_channels(m: int, nd: int):
    """The channel i mod d of each of the m taps (m = d: the channels themselves)."""
    return jnp.arange(m) % nd


def take_acting(v, acting, nd: int, axis: int = 0):
    """The [d] entries of ``v`` along ``axis`` at ``acting`` (an offset from `acting_offset`, or
    its [d] indices for per-channel delays)."""
    if jnp.ndim(acting) == 0:
        return jax.lax.dynamic_slice_in_dim(v, acting, nd, axis=axis)
    return jnp.concatenate([jax.lax.dynamic_slice_in_dim(v, acting[i], 1, axis=axis)
                            for i in range(jnp.shape(acting)[0])], axis=axis)


def current_taps(u, l):
    """The current command u [d] as the acting one of each tap or channel with delay 0 (the
    width of ``l``: u itself for one delay or one per channel, u repeated for t d taps)."""
    m = jnp.shape(l)[0] if jnp.ndim(l) else u.shape[-1]
    return u if m == u.shape[-1] else jnp.tile(u, m // u.shape[-1])


def add_acting(v, new, acting, axis: int = 0):
    """``v`` with ``new`` added at ``acting`` along ``axis`` (repeated indices add up): the
    recursion's write of the acting blocks. For one tap per channel the entries there are zero
    (the command has acted, docs/derivation.md §17-18) and this writes them; a second tap
    reads a command that is still pending at k+1, whose blocks must be kept (§20).

    Written as one read-add-write of a slice per block (`acting_blocks`), not a scatter: XLA does
    not compile a loop that holds a scatter as one function (docs/performance.md#per-channel-delays)."""
    for offset, part in acting_blocks(acting, new.shape[axis]):
        block = jax.lax.slice_in_dim(new, part.start, part.stop, axis=axis)
        old = jax.lax.dynamic_slice_in_dim(v, offset, block.shape[axis], axis=axis)
        v = jax.lax.dynamic_update_slice_in_dim(v, old + block, offset, axis=axis)
    return v


def acting_blocks(acting, m: int):
    """The writes of m acting components at ``acting`` as contiguous blocks: [(offset, part)],
    ``part`` the slice of the m components that goes to ``offset``. One block of d for one
    delay (an offset); one component each for per-channel delays or taps (m indices)."""
    if jnp.ndim(acting) == 0:
        return [(acting, slice(0, m))]
    return [(acting[i], slice(i, i + 1)) for i in range(m)]


def move_acting(blocks, new, slot, acting, axis: int, nd: int):
    """``blocks`` with the acting command's ``new`` blocks written at its slot, along ``axis``.

    Without a frame (``acting`` None) they replace slot sigma's, where du_{k-l} follows du_k. With
    one, slot sigma (``nd`` wide) is cleared first (du_{k-L} has acted) and slot alpha = ``acting``
    receives them; alpha = sigma where l = L. With one delay per channel ``acting`` holds the
    [d] indices of the channels' acting components, and column j of ``new`` goes to index j; with
    taps (a fractional delay), [t d] indices, and the blocks are added (`add_acting`: a
    command read by the later tap is still pending at k+1)."""
    start = lambda offset: (offset,) if blocks.ndim == 1 else ((0, offset) if axis == 1 else (offset, 0))
    if acting is not None:
        axis = axis if blocks.ndim > 1 else 0
        blocks = jax.lax.dynamic_update_slice(blocks, jnp.zeros(new.shape[:axis] + (nd,) + new.shape[axis + 1:],
                                                                new.dtype), start(slot))
        return add_acting(blocks, new, acting, axis)
    return jax.lax.dynamic_update_slice(blocks, new, start(slot))


def acting_commands(us, l, framed: bool):
    """u_{k-l} for k = 0..K-1, zeros before t = 0 ([K, ...] from ``us`` [K, ...]): a static shift,
    or with a frame (``framed``, l traced) a dynamic slice; l = 0 gives ``us`` itself. With one
    delay per channel (``l`` [d], ``us`` [K, d]), column j is u_{k-l_j, j}; with taps (``l`` [t d])
    [K, t d], column i u_{k-l_i, i mod d}."""
    if framed:      # one dynamic slice of us behind K zeros (a gather made the loops that read it slower)
        K = us.shape[0]
        padded = jnp.concatenate([jnp.zeros_like(us), us])
        if jnp.ndim(l) == 1:    # column i (tap or channel) reads channel i mod d, one slice each
            nd = us.shape[1]
            return jnp.stack([jax.lax.dynamic_slice_in_dim(padded[:, i % nd], K - jnp.minimum(l[i], K), K)
                              for i in range(jnp.shape(l)[0])], axis=1)
        return jax.lax.dynamic_slice_in_dim(padded, K - jnp.minimum(l, K), K)
    if l == 0:
        return us
    return jnp.concatenate([jnp.zeros((l,) + us.shape[1:], us.dtype), us])[: us.shape[0]]


def pending_order(k, l: int, nd: int):
    """Positions in the slot-ordered pending axis of du_{k-l}, ..., du_{k-1} (eq. 6's order i = 0..l-1):
    [l d] indices into the flattened (slot, component) axis."""
    slots = (k + jnp.arange(l)) % l
    return (slots[:, None] * nd + jnp.arange(nd)).reshape(-1)


def to_slots(gains: Gains) -> SlotGains:
    """[`Gains`][delayed_ilqr.lqg.Gains] -> `SlotGains`: M_k^i multiplies du_{k+i-l}, which is in slot (k+i) mod l."""
    I, L, M = gains
    K, l, nd = M.shape[:3]
    i_of_slot = (jnp.arange(l)[None, :] - jnp.arange(K)[:, None]) % l           # [K, l]
    by_slot = jnp.take_along_axis(M, i_of_slot[:, :, None, None], axis=1)       # [K, slot, d, d]
    return SlotGains(I, jnp.concatenate([L, jnp.swapaxes(by_slot, 1, 2).reshape(K, nd, l * nd)], axis=2))


def from_slots(gains: SlotGains, n_states: int) -> Gains:
    """`SlotGains` -> [`Gains`][delayed_ilqr.lqg.Gains] (one gather over all steps)."""
    I, F = gains
    K, nd = I.shape
    l = (F.shape[2] - n_states) // nd
    if l == 0:
        return Gains(I, F[:, :, :n_states], jnp.zeros((K, 0, nd, nd), F.dtype))
    slot_of_i = (jnp.arange(K)[:, None] + jnp.arange(l)[None, :]) % l          # [K, l]
    by_slot = F[:, :, n_states:].reshape(K, nd, l, nd)
    M = jnp.moveaxis(jnp.take_along_axis(by_slot, slot_of_i[:, None, :, None], axis=2), 2, 1)
    return Gains(I, F[:, :, :n_states], M)


def value_blocks(r, Rt, R, k, l: int, nd: int):
    """J(k)'s pending blocks from slot order (r [l d], Rt [n, l d], R [l d, l d], exact) to eq. 7's
    order: r [l, d], Rt [l, n, d], R [l, l, d, d]."""
    if l == 0:
        nx = Rt.shape[0]
        return (jnp.zeros((0, nd)), jnp.zeros((0, nx, nd)), jnp.zeros((0, 0, nd, nd)))
    order = pending_order(k, l, nd)
    nx = Rt.shape[0]
    return (r[order].reshape(l, nd),
            jnp.moveaxis(Rt[:, order].reshape(nx, l, nd), 1, 0),
            jnp.moveaxis(R[order][:, order].reshape(l, nd, l, nd), 2, 1))
