"""A [`Problem`][delayed_ilqr.Problem] as a JAX pytree: its arrays (x0, the cost's arrays or parameters,
the limits, the sensors, a jitter's probabilities; a framed delay and a fractional delay's phi) are
leaves, its callables and sizes static, so that problems that differ only in data share one compiled
solver and ``jax.vmap`` runs over a batch of them.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .lqg.model import frame_delay_leaf

__all__ = ["register"]


def _data_or_static(fn):
    """(data, static) of a dynamics or noise callable: one registered as a JAX pytree (a dataclass
    registered with ``jax.tree_util.register_dataclass``, an equinox module) is data, so its array
    fields are leaves (differentiable, and problems that differ only in them share one compiled
    solver); any other callable is static, hashed into the compilation as before."""
    if fn is None or jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(fn)):
        return None, fn
    return fn, None


def _problem_flatten(p):
    dynamics, dynamics_static = _data_or_static(p.dynamics)
    noise, noise_static = _data_or_static(p.noise)
    # with a frame the delay is data (a leaf), so that problems of different delays share a treedef
    # a fractional delay's phi is a leaf too: the solve is differentiable in it (derivation §20);
    # a jitter's probabilities are leaves (its support is its own static part)
    framed, fractional = p.delay_frame is not None, p.delay_fraction is not None
    return ((p.x0, p.cost, p.u_min, p.u_max, p.observation, dynamics, noise, p.delay_jitter)
            + ((_delay_leaf(p.delay_steps),) if framed else ()) + ((p.delay_fraction,) if fractional else ()),
            (dynamics_static, noise_static, p.dt, p.horizon, None if framed else p.delay_steps, p.n_controls, p.name,
             p._has_limits, p.metadata, p.time_dependent, p.delay_frame, fractional))


def _delay_leaf(delay_steps):
    """A framed problem's delay as its leaf: a whole number of steps held as a float64 scalar, so
    that ``jax.grad`` over a whole problem takes it (its derivative is zero: the delay is discrete)."""
    leaf = frame_delay_leaf(delay_steps)
    dtype = getattr(leaf, "dtype", None)
    return leaf.astype(np.float64 if isinstance(leaf, np.ndarray) else jnp.float64) \
        if dtype is not None and np.issubdtype(dtype, np.integer) else leaf


def _delay_from_leaf(leaf):
    """The delay l (int32) from its leaf (`_delay_leaf`); anything that is not an array of
    numbers (JAX's own placeholders) as it is."""
    dtype = getattr(leaf, "dtype", None)
    if dtype is None or not np.issubdtype(dtype, np.floating):
        return leaf
    return leaf.astype(np.int32) if isinstance(leaf, np.ndarray) else leaf.astype(jnp.int32)


def _problem_unflatten(cls, aux, data):
    new = object.__new__(cls)
    (dynamics_static, noise_static, new.dt, new.horizon, new.delay_steps, new.n_controls, new.name,
     new._has_limits, new.metadata, new.time_dependent, new.delay_frame, fractional) = aux
    new.delay_fraction = None
    if fractional:
        *data, new.delay_fraction = data
    if new.delay_frame is not None:
        *data, leaf = data
        new.delay_steps = _delay_from_leaf(leaf)
    new.x0, new.cost, new.u_min, new.u_max, new.observation, dynamics, noise, new.delay_jitter = data
    new.dynamics = dynamics_static if dynamics is None else dynamics
    new.noise = noise_static if noise is None else noise
    return new


def register(cls) -> None:
    """Registers the class ``cls`` ([`Problem`][delayed_ilqr.Problem]) as a pytree."""
    jax.tree_util.register_pytree_node(cls, _problem_flatten, lambda aux, data: _problem_unflatten(cls, aux, data))
