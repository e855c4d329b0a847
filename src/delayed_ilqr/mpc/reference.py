"""The reference r(t) a receding-horizon controller tracks: constant, sampled, or a function.

A `Reference` is a static `Lookup` (how r(t) is read) and its data ``samples``
(an array that ticks pass through the compiled loop without recompiling it):

* constant: the problem's ``x_target`` (samples [1, n]);
* sampled: samples [T_ref, n] at the problem's dt from t = 0, r(t) = samples[round(t / dt)];
  reading past the last sample is refused before the loop runs (`Reference.check_covers`);
* a function: ``r(t) -> [n]`` written with ``jax.numpy`` (a moving target), static.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate

__all__ = ["Lookup", "Reference", "reference"]


@dataclass(frozen=True)
class Lookup:
    """How r(t) is read from the samples: ``fn(t)`` when a function is given, else
    samples[clip(round(t / dt))] (a constant has one sample)."""

    dt: float
    fn: Optional[Callable] = None

    def __call__(self, samples, t):
        if self.fn is not None:
            return jnp.asarray(self.fn(t), samples.dtype)
        j = jnp.clip(jnp.round(t / self.dt).astype(jnp.int32), 0, samples.shape[0] - 1)
        return samples[j]


class Reference:
    """r(t) [n] (module docstring). ``samples``: [T_ref, n]; ``lookup``: the static reader."""

    def __init__(self, lookup: Lookup, samples):
        self.lookup, self.samples = lookup, samples

    @property
    def sampled(self) -> bool:
        """True for a sampled reference with an end (more than one sample, no function)."""
        return self.lookup.fn is None and self.samples.shape[0] > 1

    def check_covers(self, last_step: int) -> None:
        """Raises when a sampled reference ends before step ``last_step`` (the last step a tick's
        horizon reads: the last tick plus the horizon)."""
        if self.sampled and last_step > self.samples.shape[0] - 1:
            raise ValueError(f"reference must cover every step a tick's horizon reads: up to step {last_step} "
                             f"(the tick + horizon); got {self.samples.shape[0]} samples (steps 0.."
                             f"{self.samples.shape[0] - 1}); lengthen the reference or run fewer ticks")


def reference(value, problem) -> Reference:
    """The controller's `Reference` from the ``reference`` argument of ``MPC``: None (the
    problem's ``x_target``, constant), an array [T_ref, n] sampled at dt, or a callable r(t)."""
    n = problem.n_states
    if value is None:
        target = getattr(problem.cost, "x_target", None)
        samples = jnp.zeros((1, n)) if target is None else jnp.asarray(target)[None]
        return Reference(Lookup(problem.dt), samples)
    if callable(value):
        try:
            out = jax.eval_shape(value, jax.ShapeDtypeStruct((), jnp.float64))
        except Exception as exc:
            raise ValueError(f"reference(t) failed on a time t of shape (): {exc}") from exc
        if getattr(out, "shape", None) != (n,):
            raise ValueError(f"reference(t) must return shape ({n},), the problem's state size; got "
                             f"{getattr(out, 'shape', type(out))}")
        return Reference(Lookup(problem.dt, value), jnp.zeros((1, n)))
    samples = _validate.array(value, "reference", (None, n))
    if samples.shape[0] < 1:
        raise ValueError(f"reference must have at least one sample; got shape {np.shape(samples)}")
    return Reference(Lookup(problem.dt), jnp.asarray(samples, jnp.float64))
