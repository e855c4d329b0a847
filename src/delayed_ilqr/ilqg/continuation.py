"""Starts for a bounded solve: a continuation on the limits, and several starts under one ``vmap``.

A bounded solve is local, and on a swing-up whose limit forces the plant to be pumped the solve
from rest can stop at a partial swing, a true local minimum of the bounded problem (derivation
§15). Two continuations on the limits lead elsewhere:

- [`augmented_lagrangian_start`][delayed_ilqr.augmented_lagrangian_start]: the box is lifted and replaced by an augmented-Lagrangian
  term on the commands (Powell-Hestenes-Rockafellar), whose penalty rises over a few outer
  iterations; the first ones let the swing use commands outside the box, the later ones bring it
  back in, along a path a feasible method started at rest never sees. Its commands, clipped into
  the box, are a start for the bounded solve.
- [`solve_from_starts`][delayed_ilqr.solve_from_starts]: the bounded problem solved at once (one ``vmap``, one compilation)
  from ``u_init``, from the solutions of looser problems clipped into the box, and from the
  augmented-Lagrangian start; the cheapest is kept.

The augmented Lagrangian of the box g(u) = [u - u_max, u_min - u] <= 0 with multipliers
nu >= 0 and penalty rho, per step and command component:

    phi(u; nu, rho) = (max(0, nu + rho g(u))^2 - nu^2) / (2 rho)
    nu <- max(0, nu + rho g(u))  after each outer iteration,   rho <- growth * rho

It is added to the running cost at step k (divided by dt, so that the cost (2) gains exactly
sum_k phi(u_k)); the delayed plant is unchanged, the penalty acts on the command sent, u_k. The
multipliers and the penalty are the wrapped cost's ``params``, data, so every outer iteration runs
the one compiled solver of the lifted problem.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _validate
from ..options import Options
from ..problem import GeneralCost, Problem
from ..solution import Solution, Status
from .solver import solve

__all__ = ["augmented_lagrangian_start", "Continuation", "solve_from_starts", "Starts", "lifted_problem"]


@dataclass(frozen=True)
class _AugmentedRunning:
    """running(x, u, params, t) = cost.running(x, u, t) + phi(u; nu_k, rho) / dt, k = t / dt.

    ``params``: the original ``cost`` (a pytree), the multipliers ``upper``, ``lower`` [K, d] of
    u - u_max <= 0 and u_min - u <= 0, the penalty ``rho`` and the limits ``u_min``, ``u_max`` [d]
    (an infinite limit adds nothing).
    """

    dt: float

    def __call__(self, x, u, params, t):
        k = jnp.round(t / self.dt).astype(jnp.int32)     # t = k dt exactly (Problem.step_times)
        rho = params["rho"]
        lo, hi = params["u_min"], params["u_max"]
        phi = 0.0
        for nu, limit, sign in ((params["upper"][k], hi, 1.0), (params["lower"][k], lo, -1.0)):
            finite = jnp.isfinite(limit)      # an infinite limit enters no arithmetic, and adds a constant
            g = sign * (u - jnp.where(finite, limit, 0.0))
            shifted = jnp.where(finite, nu + rho * g, 0.0)
            phi = phi + jnp.sum(jnp.maximum(shifted, 0.0) ** 2 - nu ** 2) / (2 * rho)
        return params["cost"].running(x, u, t) + phi / self.dt


@dataclass(frozen=True)
class _OriginalFinal:
    """final(x, params, t) = cost.final(x, t): the box adds nothing to the final cost."""

    def __call__(self, x, params, t):
        return params["cost"].final(x, t)


def lifted_problem(problem: Problem, upper, lower, rho) -> Problem:
    """``problem`` without its limits, its running cost plus the augmented-Lagrangian term phi.

    Args:
        problem: a [`Problem`][delayed_ilqr.Problem] (any cost; with or without delay and noise).
        upper, lower: [K, d] multipliers (>= 0) of u_k - u_max <= 0 and u_min - u_k <= 0.
        rho: the penalty (> 0), a scalar.

    Returns:
        The lifted problem. Its cost is a time-dependent [`GeneralCost`][delayed_ilqr.GeneralCost] whose
        ``params`` hold ``problem.cost``, the multipliers, the penalty and the limits, so lifted
        problems that differ in these share one compiled solver.
    """
    params = {"cost": problem.cost, "upper": upper, "lower": lower, "rho": jnp.asarray(rho, jnp.float64),
              "u_min": problem.u_min, "u_max": problem.u_max}
    cost = GeneralCost(_AugmentedRunning(problem.dt), _OriginalFinal(), params, time_dependent=True)
    return problem.replace(cost=cost, u_min=None, u_max=None)


class Continuation(NamedTuple):
    """What [`augmented_lagrangian_start`][delayed_ilqr.augmented_lagrangian_start] returns.

    Attributes:
        u: [K, d] the last outer iteration's commands clipped into the box: the start.
        iterations: [outer_iterations] the inner solves' iterations.
        violation: [outer_iterations] how far each outer iteration's commands leave the box (the
            largest excess over a limit; 0 inside it).
    """

    u: jax.Array
    iterations: jax.Array
    violation: jax.Array


def augmented_lagrangian_start(problem: Problem, u_init=None, options: Options | None = None, *,
                               penalty: float = 1.0, penalty_growth: float = 10.0,
                               outer_iterations: int = 6) -> Continuation:
    """A start for the bounded solve of ``problem``: an augmented-Lagrangian continuation on its limits.

    Each outer iteration solves `lifted_problem` (the box replaced by the term phi of the
    module docstring) from the previous one's commands, then updates the multipliers
    nu <- max(0, nu + rho g(u)) and raises the penalty rho <- ``penalty_growth`` * rho. The first
    outer iteration's penalty is ``penalty``, so its swing may use commands outside the box; the
    later ones bring it back in. trajax's ``constrained_ilqr`` has the same schedule by default
    (penalty 1, times 10). All outer iterations run one compiled solver.

    Args:
        problem: a [`Problem`][delayed_ilqr.Problem] with limits (any cost, delay and noise).
        u_init: [K, d] the first outer iteration's start (default zeros; it is not clipped: the
            lifted problem has no box).
        options: [`Options`][delayed_ilqr.Options] of every inner solve (default ``Options()``).
        penalty: rho of the first outer iteration (> 0), in the cost's unit per squared command
            unit: small lets the first solve leave the box far, large keeps it near the box.
        penalty_growth: the factor (>= 1) that raises rho after each outer iteration.
        outer_iterations: the number of outer iterations (>= 1).

    Returns:
        [`Continuation`][delayed_ilqr.Continuation]: ``u`` [K, d], the last outer iteration's commands clipped into the
        box, is the start to polish with ``solve(problem, u, options)`` (or one of
        [`solve_from_starts`][delayed_ilqr.solve_from_starts]' starts); with each outer iteration's inner iterations and box
        violation. The number of outer iterations is fixed (no early stop, so that it runs under
        ``vmap`` over problems as it does alone); once the box holds, an outer iteration costs one
        or two inner iterations.
    """
    _check_bounded(problem, "augmented_lagrangian_start")
    rho = _validate.positive_float(penalty, "penalty")
    growth = _validate.real(penalty_growth, "penalty_growth", "a finite number >= 1")
    if not (np.isfinite(growth) and growth >= 1):
        raise ValueError(f"penalty_growth must be a finite number >= 1; got {penalty_growth!r}")
    outer = _validate.positive_int(outer_iterations, "outer_iterations")
    shape = (problem.horizon, problem.n_controls)
    us = jnp.zeros(shape) if u_init is None else _validate.array(u_init, "u_init", shape)
    upper = lower = jnp.zeros(shape)
    iterations, violation = [], []
    for _ in range(outer):
        sol = solve(lifted_problem(problem, upper, lower, rho), us, options)
        us = sol.u
        iterations.append(sol.iterations)
        violation.append(jnp.maximum(jnp.max(us - problem.u_max), jnp.max(problem.u_min - us)).clip(0.0))
        upper = jnp.maximum(0.0, upper + rho * jnp.where(jnp.isfinite(problem.u_max), us - problem.u_max, 0.0))
        lower = jnp.maximum(0.0, lower + rho * jnp.where(jnp.isfinite(problem.u_min), problem.u_min - us, 0.0))
        rho = rho * growth
    return Continuation(jnp.clip(us, problem.u_min, problem.u_max), jnp.stack(iterations), jnp.stack(violation))


class Starts(NamedTuple):
    """What [`solve_from_starts`][delayed_ilqr.solve_from_starts] returns.

    Attributes:
        solution: the cheapest [`Solution`][delayed_ilqr.Solution] (the batch's member ``best``):
            lowest ``cost``, or with noise lowest ``expected_cost``, the cost the solver minimises.
        solutions: every start's solution, a batched [`Solution`][delayed_ilqr.Solution] (leading axis S).
        names: S names of the starts ("u_init", "looser x2", "unbounded", "augmented Lagrangian").
        best: the index of the cheapest finite (expected) cost (an int outside ``jit`` and ``vmap``).
    """

    solution: Solution
    solutions: Solution
    names: tuple
    best: jax.Array


def solve_from_starts(problem: Problem, options: Options | None = None, *, u_init=None,
                      looser=(math.inf,), augmented_lagrangian: bool = True, **continuation) -> Starts:
    """The bounded ``problem`` solved from several starts at once (one ``vmap``), keeping the cheapest
    (with noise: the lowest expected cost).

    The starts: ``u_init`` (default zeros: rest); for each factor s of ``looser``, the solution
    from ``u_init`` of the problem with looser limits, clipped into the box (a continuation on the
    limit); and, with ``augmented_lagrangian``, [`augmented_lagrangian_start`][delayed_ilqr.augmented_lagrangian_start] from ``u_init``.
    The looser problems are solved under one ``vmap`` (their limits are data), and so are the
    bounded solves from the starts; the bounded solver is compiled once for both, the lifted one
    once for the continuation.

    Args:
        problem: a [`Problem`][delayed_ilqr.Problem] with limits.
        options: [`Options`][delayed_ilqr.Options] of every solve (default ``Options()``).
        u_init: [K, d] the first start (default zeros).
        looser: factors s > 1: the box widened s times about its centre, each two-sided component
            (components with an infinite side keep their limits); ``math.inf``: no limits at all.
        augmented_lagrangian: add [`augmented_lagrangian_start`][delayed_ilqr.augmented_lagrangian_start] as a start.
        **continuation: ``penalty``, ``penalty_growth``, ``outer_iterations`` of
            [`augmented_lagrangian_start`][delayed_ilqr.augmented_lagrangian_start].

    Returns:
        [`Starts`][delayed_ilqr.Starts]: the cheapest solution, all of them, the starts' names and the winner's index.
    """
    _check_bounded(problem, "solve_from_starts")
    shape = (problem.horizon, problem.n_controls)
    u0 = jnp.zeros(shape) if u_init is None else jnp.asarray(_validate.array(u_init, "u_init", shape))
    factors = tuple(looser)
    for s in factors:
        s = _validate.real(s, "looser", "factors > 1 or math.inf")
        if not s > 1:
            raise ValueError(f"looser must hold factors > 1 (or math.inf); got {looser!r}")
    options = Options() if options is None else options
    if not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    names, starts = ["u_init"], [u0]
    if factors:
        lo, hi = _looser_limits(problem, jnp.asarray(factors, jnp.float64))
        loose = _solve_each_box(problem, lo, hi, u0, options).u
        names += ["unbounded" if math.isinf(s) else f"looser x{s:g}" for s in factors]
        starts += list(jnp.clip(loose, problem.u_min, problem.u_max))
    if augmented_lagrangian:
        names.append("augmented Lagrangian")
        starts.append(augmented_lagrangian_start(problem, u0, options, **continuation).u)
    sols = _solve_each_start(problem, jnp.stack(starts), options)
    # what the solver minimises: with noise the expected cost, not the nominal's
    score = sols.cost if problem.noise is None else sols.expected_cost
    best = jnp.argmin(jnp.where(jnp.isfinite(score), score, jnp.inf))
    solution = jax.tree_util.tree_map(lambda a: a[best], sols)
    if not isinstance(best, jax.core.Tracer):      # as solve returns it outside transformations
        best = int(best)
        solution = solution._replace(status=Status(int(solution.status)))
    return Starts(solution, sols, tuple(names), best)


# jitted, so that the batches of a second call on a problem of the same structure reuse the
# compilation (an eager vmap of solve compiles its batch again at every call); the options are a
# pytree argument, their numbers traced
@jax.jit
def _solve_each_start(problem: Problem, starts, options: Options) -> Solution:
    """``solve(problem, u, options)`` for each u of ``starts`` [S, K, d], under ``vmap``."""
    return jax.vmap(lambda u: solve(problem, u, options))(starts)


@jax.jit
def _solve_each_box(problem: Problem, lower, upper, u_init, options: Options) -> Solution:
    """``solve`` of ``problem`` with limits ``lower[s]``, ``upper[s]`` ([S, d]) from ``u_init``, under ``vmap``."""
    return jax.vmap(lambda a, b: solve(problem.replace(u_min=a, u_max=b), u_init, options))(lower, upper)


def _looser_limits(problem: Problem, factors):
    """([S, d], [S, d]) the box widened by each factor about its centre (module: ``looser``)."""
    lo, hi = problem.u_min, problem.u_max
    two_sided = jnp.isfinite(lo) & jnp.isfinite(hi)
    centre, half = jnp.where(two_sided, (lo + hi) / 2, 0.0), jnp.where(two_sided, (hi - lo) / 2, 0.0)
    s = factors[:, None]
    free = jnp.isinf(s)
    wide_lo = jnp.where(free, -jnp.inf, jnp.where(two_sided, centre - s * half, lo))
    wide_hi = jnp.where(free, jnp.inf, jnp.where(two_sided, centre + s * half, hi))
    return wide_lo, wide_hi


def _check_bounded(problem: Problem, caller: str) -> None:
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
    if not problem.has_limits:
        raise ValueError(f"{caller} needs a problem with limits (u_min or u_max finite); got {problem!r} "
                         "without any")
