"""One iteration's backward pass: linearise the problem at the nominal and solve the delayed LQG
(Theorem 1, or augmentation with ``Options(method="augmented")``), with the solver's gain rules.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..lqg.augmented import augmented_scan
from ..lqg.frame import SlotGains, to_slots
from ..lqg.gains import boxed_gains, margin_width, unconstrained_gains, unregularized_feedback
from ..lqg.structured import structured_slot_scan
from ..problem import Problem
from .bounded import bounded_step
from .line_search import predicted_change
from .linearize import linearize, step_models

__all__ = ["BackwardPass", "backward"]


class BackwardPass(NamedTuple):
    """The LQG solved at a nominal.

    Attributes:
        gains: the law (6) in the slot frame.
        S: [K+1, n, n] value Hessians (None without noise in the structured pass, where nothing uses them).
        expected_cost: s_tilde_0 = J(0) of the regularised LQG.
        positive_definite: [] bool, every H_k + lambda I was positive definite.
        predicted: (a, b), the model's merit change alpha a + alpha^2 b for the step size alpha.
    """

    gains: SlotGains
    S: jax.Array | None
    expected_cost: jax.Array
    positive_definite: jax.Array
    predicted: tuple


def backward(problem: Problem, xs, us, reg, method: str, limit_margin: float, held=None) -> BackwardPass:
    """Linearise (eq. 3-4) at the nominal (xs [K+1, n], us [K, d]) and solve the LQG with H + reg I.

    The structured pass linearises each step as it reaches it (``ilqg.linearize.step_models``: the model
    is never stored) and predicts (a, b) as it goes. The augmented reference linearises into a
    stored model and predicts by ``line_search.predicted_change``.

    With control limits and no noise the law's plan minimises the LQG over the box
    u_min - u_k <= du_k <= u_max - u_k (``ilqg.bounded``: projected Newton, epsilon-active set of
    width ``limit_margin`` (u_max - u_min)); with limits and noise the feedforward of each step
    solves its own box QP and clamped commands get no feedback (``lqg.gains.boxed_gains``, margin
    ``limit_margin``), and ``held`` [K, d] bool (None: none) marks commands that get no feedback
    whatever their nominal (the noisy solver's feedback latch, derivation §12). With noise, lambda
    regularises the feedforward only (``lqg.gains.unregularized_feedback``).
    """
    if problem.has_limits and problem.noise is None:
        lqg = linearize(problem, xs, us)
        eps = margin_width(limit_margin, problem.u_min, problem.u_max)
        gains, expected_cost, ok, predicted = bounded_step(lqg, reg, problem.u_min - us, problem.u_max - us, eps,
                                                           method)
        return BackwardPass(gains, None, expected_cost, ok, predicted)
    kw = dict(gains_fn=unconstrained_gains)
    if problem.has_limits:
        bounds = (problem.u_min - us, problem.u_max - us) + (() if held is None else (held,))
        kw = dict(gains_fn=partial(boxed_gains, margin=limit_margin), bounds=bounds)
    if problem.noise is not None:
        kw["gains_fn"] = unregularized_feedback(kw["gains_fn"])
    if method == "augmented":
        lqg = linearize(problem, xs, us)
        gains, value = augmented_scan(lqg, reg, **kw)
        gains = to_slots(gains)
        return BackwardPass(gains, value.S, value.s_tilde[0], value.positive_definite,
                            predicted_change(lqg, gains, value.S))
    noisy = problem.noise is not None
    models = step_models(problem, xs, us)
    gains, (s_tilde, *s_and_S), ok, predicted = structured_slot_scan(models, reg, store_value=False, predict=True,
                                                                     store_S=noisy, **kw)
    # S enters the merit and the line search only through the noise terms
    S = jnp.concatenate([s_and_S[1], models.terminal[2][None]]) if noisy else None
    return BackwardPass(gains, S, s_tilde[0], ok, predicted)
