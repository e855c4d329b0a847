"""A jittered input delay: the distribution of the age of the command that acts at each step.

At step k the plant receives u_{k - l_k}, where the delay l_k is drawn afresh at every step,
independently of every other step and of the noise, from a known distribution p over whole steps
{l_min, ..., l_max} (docs/derivation.md §21). The controller does not know l_k when it chooses
u_k; it keeps the last l_max commands it sent, since any of them may still act.

This is the independent-delay model of networked control (Nilsson 1998, "Real-time control systems
with delays", PhD thesis, Lund; Nilsson, Bernhardsson & Wittenmark, Automatica 34(1), 1998): the
actuator applies the command whose age is the step's delay, drawn independently each step. A command may
then act after a younger one has acted already, which an actuator that holds the latest arrived
command would not do; derivation §21 says why the independent model is the one built here and what
the other one would need.
"""
from __future__ import annotations

import numbers

import jax
import jax.numpy as jnp
import numpy as np

from . import _validate

__all__ = ["DelayJitter"]

# |sum p - 1| allowed: the probabilities of a user's list (thirds, say) sum to 1 within round-off
SUM_TOLERANCE = 1e-9


class DelayJitter:
    """The distribution p of the input delay l_k, drawn independently at every step.

    Args:
        steps: the delays in whole steps that occur (non-negative integers, no repeats), e.g.
            ``[2, 3, 4]``; a delay may be listed with probability 0.
        probabilities: P(l_k = steps[i]) (finite, non-negative, summing to 1), e.g.
            ``[0.25, 0.5, 0.25]``; inside ``jax.jit`` or ``jax.vmap`` they may be traced, and are
            then not checked.

    ``DelayJitter.fixed(l)`` is the point mass at l (no jitter). A DelayJitter is a JAX pytree:
    the support ``steps`` is static (it fixes the compiled programs' frame of ``longest`` pending
    commands), the probabilities are its one leaf (data). So problems whose jitters share a support
    share one compiled solver, and a stack of them (``jax.tree_util.tree_map(lambda *a:
    jnp.stack(a), *jitters)``) runs under ``jax.vmap``; give distributions of different supports
    their union, with zeros.
    """

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        _register(cls)          # a subclass (another way to draw the delays) is a pytree as well

    def __init__(self, steps, probabilities):
        _validate.static(steps, "delay_jitter steps")
        steps_list = list(np.asarray(steps).reshape(-1)) if np.ndim(steps) else [steps]
        traced = isinstance(probabilities, jax.core.Tracer)
        if traced:
            probs = jnp.reshape(probabilities, (-1,)).astype(jnp.float64)
        else:
            probs = np.asarray(probabilities, dtype=float).reshape(-1)
        if not steps_list:
            raise ValueError("delay_jitter steps must list at least one delay; got an empty list")
        if len(steps_list) != probs.shape[0]:
            raise ValueError(f"delay_jitter needs one probability per delay; got {len(steps_list)} steps "
                             f"{[_plain(s) for s in steps_list]} and {probs.shape[0]} probabilities"
                             + ("" if traced else f" {probs.tolist()}"))
        checked = []
        for i, s in enumerate(steps_list):
            if isinstance(s, (bool, np.bool_)) or not isinstance(s, (numbers.Real, np.number)) \
                    or not float(s).is_integer() or s < 0:
                raise ValueError(f"delay_jitter steps[{i}] must be a non-negative integer number of steps; got {s!r}")
            checked.append(int(s))
        if len(set(checked)) != len(checked):
            raise ValueError(f"delay_jitter steps must not repeat a delay; got {checked}")
        if not traced:
            if not np.all(np.isfinite(probs)) or np.any(probs < 0):
                raise ValueError(f"delay_jitter probabilities must be finite and non-negative; got {probs.tolist()}")
            if abs(float(np.sum(probs)) - 1.0) > SUM_TOLERANCE:
                raise ValueError(f"delay_jitter probabilities must sum to 1; got {probs.tolist()} (sum "
                                 f"{float(np.sum(probs))!r})")
        order = np.argsort(checked)
        self.steps = tuple(checked[i] for i in order)
        self._p = probs[order]

    @classmethod
    def fixed(cls, delay_steps: int) -> "DelayJitter":
        """The point mass at ``delay_steps``: every step's delay is l (no jitter)."""
        return cls([_validate.delay_steps(delay_steps)], [1.0])

    @property
    def probabilities(self):
        """P(l_k = steps[i]): a tuple of floats, or the traced [len(steps)] array under jit/vmap."""
        return self._p if self._traced else tuple(float(q) for q in self._p)

    @property
    def _traced(self) -> bool:
        return isinstance(self._p, jax.core.Tracer) or np.ndim(self._p) != 1

    @property
    def longest(self) -> int:
        """l_max: the number of commands in flight the controller keeps (the policy's frame)."""
        return self.steps[-1]

    @property
    def shortest(self) -> int:
        """l_min (the shortest delay listed)."""
        return self.steps[0]

    @property
    def mean(self):
        """E[l_k] in steps: a float (traced under jit/vmap)."""
        value = jnp.dot(jnp.asarray(self.steps, jnp.float64), jnp.asarray(self._p))
        return value if self._traced else float(value)

    def by_delay(self) -> jax.Array:
        """p over the delays 0..l_max: [l_max + 1], zero where a delay does not occur."""
        return jnp.zeros(self.longest + 1, jnp.float64).at[np.asarray(self.steps)].set(jnp.asarray(self._p))

    def as_json(self) -> dict:
        """``{"steps": [...], "probabilities": [...]}``: the record saved files keep (`from_json`)."""
        return dict(steps=list(self.steps), probabilities=list(self.probabilities))

    @classmethod
    def from_json(cls, record) -> "DelayJitter":
        """The distribution of an `as_json` record, checked as the constructor checks it."""
        if not isinstance(record, dict) or set(record) != {"steps", "probabilities"}:
            raise ValueError(f"a delay_jitter record must be a dict with keys 'steps' and 'probabilities'; "
                             f"got {record!r}")
        return cls(record["steps"], record["probabilities"])

    def sample(self, key, shape=()) -> jax.Array:
        """Delays drawn from p (int32, ``shape``), from a JAX key: reproducible from the key."""
        logits = jnp.log(jnp.asarray(self._p))
        index = jax.random.categorical(key, logits, shape=shape)
        return jnp.asarray(self.steps, jnp.int32)[index]

    def check_horizon(self, horizon: int, name: str = "delay_jitter") -> None:
        """Every delay below the horizon K (with l >= K a command never acts within it)."""
        if self.longest >= horizon:
            raise ValueError(f"{name} must have its support within the horizon: a command sent at step k acts at "
                             f"k + l, so delays l >= K never act; got steps {list(self.steps)} with horizon={horizon}")

    def __eq__(self, other):
        """The same support and probabilities (a traced one equals only itself)."""
        if isinstance(other, DelayJitter) and (self._traced or other._traced):
            return self is other
        return isinstance(other, DelayJitter) and (self.steps, self.probabilities) == (other.steps,
                                                                                         other.probabilities)

    def __hash__(self):
        return id(self) if self._traced else hash((self.steps, self.probabilities))

    def __repr__(self):
        p = "traced" if isinstance(self._p, jax.core.Tracer) else np.asarray(self._p).tolist()
        return f"DelayJitter(steps={list(self.steps)}, probabilities={p})"


def _register(cls) -> None:
    """``cls`` a pytree: the probabilities its leaf, the support its static part."""
    def unflatten(steps, leaves):
        new = object.__new__(cls)
        new.steps, (new._p,) = steps, leaves
        return new

    jax.tree_util.register_pytree_node(cls, lambda j: ((j._p,), j.steps), unflatten)


_register(DelayJitter)


def _plain(value):
    return value.item() if isinstance(value, np.generic) else value
