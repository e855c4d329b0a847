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
            ``[2, 3, 4]``.
        probabilities: P(l_k = steps[i]) (finite, non-negative, summing to 1), e.g.
            ``[0.25, 0.5, 0.25]``.

    ``DelayJitter.fixed(l)`` is the point mass at l (no jitter). Instances are hashable and static
    (they fix the compiled programs' frame of ``longest`` pending commands).
    """

    def __init__(self, steps, probabilities):
        _validate.static(steps, "delay_jitter steps")
        _validate.static(probabilities, "delay_jitter probabilities")
        steps_list = list(np.asarray(steps).reshape(-1)) if np.ndim(steps) else [steps]
        probs = np.asarray(probabilities, dtype=float).reshape(-1) if np.ndim(probabilities) else \
            np.asarray([probabilities], dtype=float)
        if not steps_list:
            raise ValueError("delay_jitter steps must list at least one delay; got an empty list")
        if len(steps_list) != probs.shape[0]:
            raise ValueError(f"delay_jitter needs one probability per delay; got {len(steps_list)} steps "
                             f"{[_plain(s) for s in steps_list]} and {probs.shape[0]} probabilities {probs.tolist()}")
        checked = []
        for i, s in enumerate(steps_list):
            if isinstance(s, (bool, np.bool_)) or not isinstance(s, (numbers.Real, np.number)) \
                    or not float(s).is_integer() or s < 0:
                raise ValueError(f"delay_jitter steps[{i}] must be a non-negative integer number of steps; got {s!r}")
            checked.append(int(s))
        if len(set(checked)) != len(checked):
            raise ValueError(f"delay_jitter steps must not repeat a delay; got {checked}")
        if not np.all(np.isfinite(probs)) or np.any(probs < 0):
            raise ValueError(f"delay_jitter probabilities must be finite and non-negative; got {probs.tolist()}")
        if abs(float(np.sum(probs)) - 1.0) > SUM_TOLERANCE:
            raise ValueError(f"delay_jitter probabilities must sum to 1; got {probs.tolist()} (sum "
                             f"{float(np.sum(probs))!r})")
        order = np.argsort(checked)
        self.steps = tuple(checked[i] for i in order)
        self.probabilities = tuple(float(probs[i]) for i in order)

    @classmethod
    def fixed(cls, delay_steps: int) -> "DelayJitter":
        """The point mass at ``delay_steps``: every step's delay is l (no jitter)."""
        return cls([_validate.delay_steps(delay_steps)], [1.0])

    @property
    def longest(self) -> int:
        """l_max: the number of commands in flight the controller keeps (the policy's frame)."""
        return self.steps[-1]

    @property
    def shortest(self) -> int:
        """l_min."""
        return self.steps[0]

    @property
    def mean(self) -> float:
        """E[l_k] in steps."""
        return float(np.dot(self.steps, self.probabilities))

    def by_delay(self) -> np.ndarray:
        """p over the delays 0..l_max: [l_max + 1], zero where a delay does not occur."""
        p = np.zeros(self.longest + 1)
        p[list(self.steps)] = self.probabilities
        return p

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
        logits = jnp.log(jnp.asarray(self.probabilities))
        index = jax.random.categorical(key, logits, shape=shape)
        return jnp.asarray(self.steps, jnp.int32)[index]

    def check_horizon(self, horizon: int, name: str = "delay_jitter") -> None:
        """Every delay below the horizon K (with l >= K a command never acts within it)."""
        if self.longest >= horizon:
            raise ValueError(f"{name} must have its support within the horizon: a command sent at step k acts at "
                             f"k + l, so delays l >= K never act; got steps {list(self.steps)} with horizon={horizon}")

    def __eq__(self, other):
        return isinstance(other, DelayJitter) and (self.steps, self.probabilities) == (other.steps,
                                                                                         other.probabilities)

    def __hash__(self):
        return hash((self.steps, self.probabilities))

    def __repr__(self):
        return f"DelayJitter(steps={list(self.steps)}, probabilities={list(self.probabilities)})"


def _plain(value):
    return value.item() if isinstance(value, np.generic) else value
