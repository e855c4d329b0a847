"""The CPU batching rule: ``vmap`` of a solve as a loop over the problems.

On CPU a batch of solves runs faster one problem after another in one compiled loop
(``lax.map``) than as one batched solve: each problem's scans stay small enough for XLA to compile
as one function, where a batched step does B times their work through separate operations, and
each problem stops when it converges, where a batched ``while_loop`` runs every problem until the
last one stops (docs/performance.md#one_after_another).
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

__all__ = ["one_after_another"]


def one_after_another(fn: Callable) -> Callable:
    """``fn`` unchanged, except that its ``vmap`` maps ``fn`` over the batch (``lax.map``, one
    problem at a time) instead of batching its operations. Arguments not batched are broadcast."""
    @jax.custom_batching.custom_vmap
    def run(*args):
        return fn(*args)

    @run.def_vmap
    def batched(axis_size, in_batched, *args):
        args = jax.tree_util.tree_map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
                                      args, tuple(in_batched))
        out = jax.lax.map(lambda a: run(*a), args)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return run
