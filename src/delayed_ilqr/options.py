"""Solver settings: [`Options`][delayed_ilqr.Options], immutable and validated when built.

``Options`` is a JAX pytree: its numbers (tolerances, the regularisation schedule, the step sizes'
values, ``z_min``, ``limit_margin``) are its leaves, which the compiled solver receives as traced
arguments, and its structure (``method``, ``max_iterations``, ``max_alternations``, the number of
step sizes) is the pytree's static part. One compilation of the solver therefore serves every
value of the numbers; a new structure compiles it again (docs/guide/solver.md, "Options and
compilation")."""
from __future__ import annotations

import dataclasses

import jax
import numpy as np

from . import _validate

__all__ = ["Options"]

#: The fields that decide the compiled program: the solver's method, the length of its iteration
#: record (max_iterations), the alternation's loop bound. The pytree's static part.
STRUCTURE = ("method", "max_iterations", "max_alternations")
#: The fields that are numbers inside the compiled program: the pytree's leaves (``alphas`` a
#: tuple of them, whose length is structure).
NUMBERS = ("tol_cost", "tol_grad", "alphas", "reg_init", "reg_min", "reg_max", "reg_factor", "z_min",
           "limit_margin")


@dataclasses.dataclass(frozen=True)
class Options:
    """Solver settings (immutable, validated when built; defaults follow Tassa's iLQG.m where sensible).

    Attributes:
        method: "structured" (Theorem 1, the default) or "augmented" (state-augmentation reference).
        max_iterations: iteration limit (rejected steps count).
        tol_cost: stop when an accepted step would reduce the merit by less than
            tol_cost * |merit| (relative: costs of motor tasks are often ~1e-4, where an absolute
            test stops early). Without noise that last step is not taken, so the returned policy
            is the one of the last backward pass, with no extra pass for the returned nominal; and
            when the backward pass's model predicts less than that for every alpha, the solve
            stops before the line search. Below ``ilqg.solver.ROUNDOFF`` (about 2e-13) no
            comparison of merits can resolve a step: once the Newton step promises less than that,
            full Newton steps are taken without a line search and only tol_grad ends the solve.
        tol_grad: stop when mean_k max_i |I_k,i| / (|u_k,i| + 1) < tol_grad (and lambda < 1e-5).
        alphas: line-search step sizes, tried in parallel (default 10^linspace(0, -3, 11)).
        reg_init: initial lambda. 0 tries the exact Newton (LQG) step first, which makes a
            linear-quadratic problem converge in one step; Tassa uses 1.
        reg_min, reg_max, reg_factor: Tassa's schedule (lambda below reg_min is set to 0; the
            solve stops when lambda exceeds reg_max).
        z_min: minimal accepted ratio of actual to expected reduction, in [0, 1).
        limit_margin: with control limits, the width limit_margin * (u_max - u_min) of the
            epsilon-active set (limit_margin itself, in the command's unit, for a command
            bounded on one side only: ``lqg.gains.margin_width``): without noise, that of the projected Newton method on the box
            (``ilqg.bounded``); with noise, commands whose nominal lies that close to a bound get
            no feedback (``lqg.gains.boxed_gains``).
        max_alternations: for a problem with delayed sensors (``Problem.observation``) and
            signal-dependent motor noise, the limit on Todorov's alternation between the filter
            and the feedback at the returned nominal (``lqg.alternation``, derivation §14); it
            stops earlier when an alternation lowers the exact expected cost by less than
            tol_cost times its value. 0 keeps the separation design (iLQG's feedback on the
            Kalman filter of the nominal commands' noise).

    A convergence status (``Status.converged``) is reported only at a first-order point of the LQG
    model: lambda < 1e-5 (the step is the Newton step, projected with the limits) and, for
    ``CONVERGED_COST``, the full step promising a merit reduction g' H^-1 g / 2 below
    tol_cost |merit| (``ilqg.solver.first_order``). Tiny ``alphas`` or a large ``reg_init``
    cannot end a solve as converged.
    """

    method: str = "structured"
    max_iterations: int = 100
    tol_cost: float = 1e-10
    tol_grad: float = 1e-7
    alphas: tuple = tuple(float(a) for a in 10.0 ** np.linspace(0.0, -3.0, 11))
    reg_init: float = 0.0
    reg_min: float = 1e-6
    reg_max: float = 1e10
    reg_factor: float = 1.6
    z_min: float = 0.0
    limit_margin: float = 1e-5
    max_alternations: int = 20

    def __post_init__(self):
        if self.method not in ("structured", "augmented"):
            raise ValueError(f"method must be 'structured' or 'augmented'; got {self.method!r}")
        _validate.positive_int(self.max_iterations, "max_iterations")
        _validate.non_negative_int(self.max_alternations, "max_alternations")
        margin = _validate.real(self.limit_margin, "limit_margin", "a number in [0, 0.5)")
        if not (np.isfinite(margin) and 0 <= margin < 0.5):
            raise ValueError(f"limit_margin must be a number in [0, 0.5); got {self.limit_margin!r}")
        # each number is kept as a Python float, so that every Options gives the compiled solver
        # arguments of one type (a NumPy float64 would be a strongly typed leaf: a second compilation)
        for name in ("tol_cost", "tol_grad", "reg_min", "reg_max"):
            object.__setattr__(self, name, _validate.positive_float(getattr(self, name), name))
        object.__setattr__(self, "reg_init", _validate.non_negative_float(self.reg_init, "reg_init"))
        object.__setattr__(self, "limit_margin", margin)
        if not self.reg_min < self.reg_max:
            raise ValueError(f"reg_min must be below reg_max; got reg_min={self.reg_min!r}, reg_max={self.reg_max!r}")
        factor = _validate.real(self.reg_factor, "reg_factor", "a finite number greater than 1")
        if not factor > 1:
            raise ValueError(f"reg_factor must be greater than 1; got {self.reg_factor!r}")
        if not np.isfinite(factor):
            raise ValueError(f"reg_factor must be a finite number greater than 1; got {self.reg_factor!r}")
        object.__setattr__(self, "reg_factor", factor)
        # actual / predicted reduction tends to 1 as alpha -> 0 on any smooth problem, so from
        # z_min = 1 on a step is accepted only where the model is wrong; below 0 a step that
        # raises the merit is accepted
        z_min = _validate.real(self.z_min, "z_min", "a number in [0, 1)")
        if not 0 <= z_min < 1:
            raise ValueError(f"z_min must be a number in [0, 1); got {self.z_min!r}")
        object.__setattr__(self, "z_min", z_min)
        alphas = tuple(float(a) for a in np.atleast_1d(np.asarray(self.alphas, dtype=float)))
        if not alphas or not all(0 < a <= 1 for a in alphas):
            raise ValueError(f"alphas must be a non-empty sequence of step sizes in (0, 1]; got {self.alphas!r}")
        object.__setattr__(self, "alphas", alphas)


def unchecked(**fields) -> Options:
    """An ``Options`` built from ``fields`` (every field) without the checks, for the pytree's
    rebuilding inside JAX transformations, where the numbers may be tracers (or JAX's
    placeholders) that no check can read."""
    options = object.__new__(Options)
    for name, value in fields.items():
        object.__setattr__(options, name, value)
    return options


def replaced(options: Options, **structure) -> Options:
    """``options`` with fields of its static part (``STRUCTURE``) replaced, its numbers kept as they
    are (traced or not): ``dataclasses.replace`` for an ``Options`` inside a transformation."""
    if set(structure) - set(STRUCTURE):
        raise ValueError(f"replaced changes only {STRUCTURE}; got {sorted(structure)}")
    if "max_alternations" in structure:
        _validate.non_negative_int(structure["max_alternations"], "max_alternations")
    if "max_iterations" in structure:
        _validate.positive_int(structure["max_iterations"], "max_iterations")
    if structure.get("method", "structured") not in ("structured", "augmented"):
        raise ValueError(f"method must be 'structured' or 'augmented'; got {structure['method']!r}")
    return unchecked(**{**{f.name: getattr(options, f.name) for f in dataclasses.fields(Options)}, **structure})


jax.tree_util.register_pytree_with_keys(
    Options,
    lambda o: (tuple((jax.tree_util.GetAttrKey(n), getattr(o, n)) for n in NUMBERS),
               tuple(getattr(o, n) for n in STRUCTURE)),
    lambda structure, numbers: unchecked(**dict(zip(STRUCTURE, structure)), **dict(zip(NUMBERS, numbers))),
    flatten_func=lambda o: (tuple(getattr(o, n) for n in NUMBERS), tuple(getattr(o, n) for n in STRUCTURE)))
