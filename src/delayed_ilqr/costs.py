"""The costs of eq. (2) a [`Problem`][delayed_ilqr.Problem] takes: [`QuadraticCost`][delayed_ilqr.QuadraticCost]
(x'P x + u'Q u per unit time, a quadratic final cost) and [`GeneralCost`][delayed_ilqr.GeneralCost] (any
running and final cost, with parameters that are data and, if declared, the time as an argument).
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["QuadraticCost", "GeneralCost"]


class QuadraticCost(NamedTuple):
    """Eq. (2): running cost x'P x + u'Q u (per unit time), final cost (x - x_target)'P_final (x - x_target).

    Attributes:
        P: [n, n] symmetric positive semi-definite state weight.
        Q: [d, d] symmetric positive definite command weight.
        P_final: [n, n] symmetric positive semi-definite final weight.
        x_target: [n] final target state.
    """

    P: Any
    Q: Any
    P_final: Any
    x_target: Any

    time_dependent = False        # a class attribute, not a field: eq. (2) does not depend on time

    def running(self, x, u, t=None):
        """x'P x + u'Q u (``t`` is accepted and ignored, as for any time-independent cost)."""
        return x @ self.P @ x + u @ self.Q @ u

    def final(self, x, t=None):
        err = x - self.x_target
        return err @ self.P_final @ err


class GeneralCost:
    """A cost that is not quadratic in x, e.g. a hand-position error through the arm's kinematics.

    Args:
        running: ``running(x, u, params) -> scalar``, cost per unit time (multiplied by dt, eq. 2).
        final: ``final(x, params) -> scalar`` (not multiplied by dt).
        params: a pytree of arrays (targets, weights) passed to both; it is data, so problems that
            differ only in ``params`` share one compiled solver.
        time_dependent: if True, the functions take the time as a last argument:
            ``running(x, u, params, t)`` at t = k dt and ``final(x, params, t)`` at t = K dt
            (seconds), for via-points and moving targets. Static: it is part of the compiled solver.

    The quadratisation keeps the x-u cross term of ``running``; the running cost may not depend on
    the delayed command (eq. 4 has no such terms).
    """

    def __init__(self, running: Callable, final: Callable, params=None, time_dependent: bool = False):
        t = ", t" if time_dependent else ""
        if not callable(running):
            raise TypeError(f"running must be callable as running(x, u, params{t}); got {type(running).__name__}")
        if not callable(final):
            raise TypeError(f"final must be callable as final(x, params{t}); got {type(final).__name__}")
        if not isinstance(time_dependent, (bool, np.bool_)):
            raise TypeError(f"time_dependent must be True or False; got {time_dependent!r}")
        self.running_fn, self.final_fn, self.time_dependent = running, final, bool(time_dependent)
        self.params = jax.tree_util.tree_map(_param, params)

    def running(self, x, u, t=None):
        """The running cost at (x, u), at time t (s) if the cost is time-dependent."""
        args = (x, u, self.params) + self._time(t, "running")
        return jnp.asarray(self.running_fn(*args), x.dtype)     # a constant may be a float

    def final(self, x, t=None):
        """The final cost at x, at the final time t = K dt if the cost is time-dependent."""
        return jnp.asarray(self.final_fn(*(x, self.params) + self._time(t, "final")), x.dtype)

    def _time(self, t, what):
        if not self.time_dependent:
            return ()
        if t is None:
            raise TypeError(f"this GeneralCost is time-dependent: cost.{what} needs the time t (s); got t=None")
        return (t,)

    def __repr__(self):
        flag = ", time_dependent=True" if self.time_dependent else ""
        return f"GeneralCost(running={self.running_fn!r}, final={self.final_fn!r}{flag})"


def _param(leaf):
    """A leaf of GeneralCost.params as an array of numbers (checked here, not inside the solver)."""
    if isinstance(leaf, jax.core.Tracer):
        return leaf
    arr = np.asarray(leaf) if not isinstance(leaf, jax.Array) else leaf
    if arr.dtype.kind not in "biuf":
        raise TypeError(f"GeneralCost params must be a pytree of numeric arrays; got a leaf {leaf!r} of dtype {arr.dtype}")
    return jnp.asarray(leaf)


jax.tree_util.register_pytree_node(
    GeneralCost,
    lambda c: ((c.params,), (c.running_fn, c.final_fn, c.time_dependent)),
    lambda aux, data: _general_cost_from(aux, data[0]),
)


def _general_cost_from(aux, params):
    new = object.__new__(GeneralCost)
    new.running_fn, new.final_fn, new.time_dependent = aux
    new.params = params
    return new
