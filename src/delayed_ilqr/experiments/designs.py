"""Controller designs as problem transforms: what a controller is designed for, given the plant.

Every study measures a controller on the plant it is given; the designs differ only in the problem
the controller is *designed* for and in the backward pass:

=============  =========================================================================
aware          the plant itself (Theorem 1's structured backward pass)
ignorant       the plant without its delay (``delay_steps=0``), run on the delayed plant
augmented      the plant itself, with the state-augmentation backward pass (reference)
noise-aware    the plant itself, noise included (iLQG: the noise enters the backward pass)
deterministic  the plant without its noise (``noise=None``: iLQR), run in the noise
=============  =========================================================================

("aware" and "noise-aware" are the same transform under the names of the two studies.)
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple, Optional

from .. import Options, Problem

__all__ = ["Design", "REGISTRY", "design"]


class Design(NamedTuple):
    """One design: ``transform(plant) -> design problem``; ``method`` forces ``Options.method``."""

    description: str
    transform: Callable[[Problem], Problem]
    method: Optional[str] = None


def _plant(problem: Problem) -> Problem:
    return problem


def _without_delay(problem: Problem) -> Problem:
    return problem.replace(delay_steps=0)


def _without_noise(problem: Problem) -> Problem:
    return problem.replace(noise=None)


REGISTRY = {
    "aware": Design("delay-aware iLQG (Theorem 1)", _plant),
    "ignorant": Design("delay-ignorant iLQG (designed for tau = 0, run on the delayed plant)", _without_delay),
    "augmented": Design("delay-aware iLQG by state augmentation (reference)", _plant, "augmented"),
    "noise-aware": Design("iLQG designed on the noisy plant (the noise enters the backward pass)", _plant),
    "deterministic": Design("iLQR designed on the noise-free plant, then run in the noise", _without_noise),
}


def design(problem: Problem, name: str, options: Optional[Options] = None) -> tuple[Problem, Options]:
    """The problem and options the design ``name`` is made with (the plant stays ``problem``).

    Args:
        problem: the plant.
        name: a key of :data:`REGISTRY`.
        options: solver options (default ``Options()``); a design with a ``method`` overrides it.

    Raises:
        ValueError: for an unknown design; TypeError: for options that are not an ``Options``.
    """
    if name not in REGISTRY:
        raise ValueError(f"design must be one of {sorted(REGISTRY)}; got {name!r}")
    if options is None:
        options = Options()
    elif not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    entry = REGISTRY[name]
    if entry.method is not None:
        options = dataclasses.replace(options, method=entry.method)
    return entry.transform(problem), options
