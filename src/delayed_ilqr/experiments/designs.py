"""Controller designs as problem transforms: what a controller is designed for, given the plant.

Every study measures a controller on the plant it is given; the designs differ only in the problem
the controller is *designed* for and in the backward pass:

| design | the controller is designed for |
|---|---|
| aware | the plant itself (Theorem 1's structured backward pass) |
| ignorant | the plant without its delay (``delay_steps=0``), run on the delayed plant |
| augmented | the plant itself, with the state-augmentation backward pass (reference) |
| noise-aware | the plant itself, noise included (iLQG: the noise enters the backward pass) |
| deterministic | the plant without its noise (``noise=None``: iLQR), run in the noise |

("aware" and "noise-aware" are the same transform under the names of the two studies.)
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple, Optional

from .. import Options, Problem, Solution
from ..ilqg.estimation import with_estimator

__all__ = ["Design", "REGISTRY", "design", "filter_on_plant"]


class Design(NamedTuple):
    """One design: ``transform(plant) -> design problem``; ``method`` forces ``Options.method``;
    ``filter_on_plant``: with sensors, the estimator is designed on the plant (its noise) rather than
    on the design problem (see `filter_on_plant`)."""

    description: str
    transform: Callable[[Problem], Problem]
    method: Optional[str] = None
    filter_on_plant: bool = False


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
    "deterministic": Design("iLQR designed on the noise-free plant, then run in the noise", _without_noise,
                            filter_on_plant=True),
}


def design(problem: Problem, name: str, options: Optional[Options] = None) -> tuple[Problem, Options]:
    """The problem and options the design ``name`` is made with (the plant stays ``problem``).

    Args:
        problem: the plant.
        name: a key of `REGISTRY`.
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


def filter_on_plant(plant: Problem, sol: Solution) -> Solution:
    """A noise-free design's solution ``sol`` with the estimator of the plant's sensors designed for
    the plant's noise (a batch of solutions takes a batch of plants: vmap it).

    A filter designed on the noise-free problem trusts its model completely (no process noise:
    zero Kalman gain), and its controller would run open loop on the sensed plant. The engineer's
    design is iLQR's feedback with the delayed Kalman filter of the plant's motor and sensory noise
    at iLQR's nominal (separation, no alternation: ``ilqg.estimation.design_estimator``). The
    expected cost stays the design's own (the noise-free cost), as without sensors.
    """
    with_filter = with_estimator(plant, sol, Options(max_alternations=0))
    return with_filter._replace(expected_cost=sol.expected_cost, status=sol.status)
