"""``packed_scan``: ``lax.scan`` with its per-step inputs and outputs packed into one array per dtype,
optionally run in blocks of steps with deferred work flushed after each block.

Why packing: on CPU, XLA runs every operation of a loop body as a separate thunk, and the steps of
motor-control problems are small (n = 4, d = 2), so the count of operations per step, not the
arithmetic, sets the time. A scan slices each input array once per step and writes each output
array once per step: a backward pass with 13 inputs and 6 outputs spends 19 thunks a step on
bookkeeping alone. Packed, that is one slice per dtype in and one update per dtype out; the static
slices that unpack a row fuse into the operations that consume them (docs/performance.md#packed_scan).
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["Blocks", "packed_scan"]


def _layout(shapes_dtypes):
    """Per leaf: (group, offset, shape) within the packed vector of its dtype; and the dtypes,
    in group order."""
    offsets, layout = {}, []
    for shape, dtype in shapes_dtypes:
        dtype = jnp.dtype(dtype)
        start = offsets.setdefault(dtype, 0)
        layout.append((list(offsets).index(dtype), start, tuple(shape)))
        offsets[dtype] = start + math.prod(shape)
    return layout, tuple(offsets)


def _pack(leaves, dtypes, lead=()):
    """Leaves with leading axes ``lead`` -> one [*lead, total size] array per dtype (a tuple)."""
    flat = {dt: [] for dt in dtypes}
    for leaf in leaves:
        flat[jnp.dtype(leaf.dtype)].append(jnp.reshape(leaf, lead + (-1,)))
    return tuple(jnp.concatenate(flat[dt], axis=-1) for dt in dtypes)


def _unpack(packed, layout, lead=()):
    return [jax.lax.slice_in_dim(packed[group], start, start + math.prod(shape), axis=len(lead)).reshape(lead + shape)
            for group, start, shape in layout]


# Leaves with more numbers per step than this are not packed: their own slice or update per step
# costs nothing next to their size, and packing them would copy them (docs/performance.md#_pack_max).
_PACK_MAX = 128


class Blocks(NamedTuple):
    """Run the steps in blocks of ``size`` (which must divide the length), as a scan over blocks of
    a scan over steps, and apply ``flush(carry)`` after each block: work deferred by the steps is
    done once per block, without a ``lax.cond`` (which ``vmap`` would turn into doing it at every
    step)."""

    size: int
    flush: Callable


def packed_scan(f, init, xs, reverse: bool = False, blocks: Blocks | None = None, pack_outputs: bool = True,
                pack_inputs: bool = True):
    """Same result as ``jax.lax.scan(f, init, xs, reverse=reverse)``; ``xs`` must be non-empty.

    Only the per-step inputs and outputs with at most ``_PACK_MAX`` numbers per step are packed,
    and not at all with ``pack_inputs=False`` / ``pack_outputs=False``: a packed copy is held
    beside the arrays it copies, which costs more memory than it saves time where the loop is
    compiled as one function (see ``_cpu``) and its slices cost nothing
    (docs/performance.md#pack_inputs-and-pack_outputs). The carry is passed as it is (its large
    members, such as the value matrix of the backward pass, are updated in place). ``blocks``:
    see `Blocks`.
    """
    leaves, in_tree = jax.tree_util.tree_flatten(xs)
    K = leaves[0].shape[0]
    in_small = [pack_inputs and math.prod(x.shape[1:]) <= _PACK_MAX for x in leaves]
    in_layout, in_dtypes = _layout([(x.shape[1:], x.dtype) for x, small in zip(leaves, in_small) if small])
    out_spec = []

    def body(carry, rows):
        packed_rows, big_rows = rows
        small_leaves, big_leaves = iter(_unpack(packed_rows, in_layout)), iter(big_rows)
        x = [next(small_leaves) if small else next(big_leaves) for small in in_small]
        carry, ys = f(carry, jax.tree_util.tree_unflatten(in_tree, x))
        y_leaves, out_tree = jax.tree_util.tree_flatten(ys)
        small = [pack_outputs and math.prod(y.shape) <= _PACK_MAX for y in y_leaves]
        layout, dtypes = _layout([(y.shape, y.dtype) for y, s in zip(y_leaves, small) if s])
        out_spec[:] = [out_tree, layout, small]
        return carry, (_pack([y for y, s in zip(y_leaves, small) if s], dtypes),
                       tuple(y for y, s in zip(y_leaves, small) if not s))

    rows = (_pack([x for x, s in zip(leaves, in_small) if s], in_dtypes, (K,)),
            tuple(x for x, s in zip(leaves, in_small) if not s))
    if blocks is None or blocks.size == 1:
        carry, (packed, big) = jax.lax.scan(body, init, rows, reverse=reverse)
    else:
        block = blocks.size
        if K % block:
            raise ValueError(f"the scan length ({K}) must be a multiple of the block size ({block})")

        def block_body(carry, rows):
            carry, ys = jax.lax.scan(body, carry, rows, reverse=reverse)
            return blocks.flush(carry), ys

        by_block = jax.tree_util.tree_map(lambda x: x.reshape((K // block, block) + x.shape[1:]), rows)
        carry, ys = jax.lax.scan(block_body, init, by_block, reverse=reverse)
        packed, big = jax.tree_util.tree_map(lambda y: y.reshape((K,) + y.shape[2:]), ys)
    out_tree, out_layout, out_small = out_spec
    small_leaves, big_leaves = iter(_unpack(packed, out_layout, (K,))), iter(big)
    y = [next(small_leaves) if small else next(big_leaves) for small in out_small]
    return carry, jax.tree_util.tree_unflatten(out_tree, y)
