"""The study engine: timed solves (one problem, or a batch in one compiled call), Monte Carlo of a
policy on its plant, and the endpoint error in the model's task space.

Both studies are built from these pieces: the delay study solves one design problem at a time,
the center-out study solves the reaches to all targets in one vectorised call; both run every
policy on its plant with [`simulate`][delayed_ilqr.simulate] and judge the final states in the task
space the model's metadata names ([`delayed_ilqr.models.metadata`][delayed_ilqr.models.metadata]).
"""
from __future__ import annotations

import time
from typing import Callable, NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import Options, Policy, Problem, Runs, Solution, simulate, solve
from ..models.metadata import default_u_init, task_position, task_space, task_target

__all__ = ["Timed", "Trials", "timed_solve", "solve_batch", "timed_batched_solve", "monte_carlo", "endpoint_error", "stack",
           "endpoint_description", "take"]


class Timed(NamedTuple):
    """A solve and its timing: ``seconds`` of a compiled call, ``first_seconds`` of the first call
    (compilation included; about the same when an equal-shaped problem was compiled before)."""

    solution: Solution
    seconds: float
    first_seconds: float


class Trials(NamedTuple):
    """Monte Carlo of one policy on its plant.

    Attributes:
        runs: the [`Runs`][delayed_ilqr.Runs] (N trials).
        endpoints: [N, m] final task-space positions, or None when the model has no task space.
        errors: [N] endpoint errors (`endpoint_error`).
    """

    runs: Runs
    endpoints: Optional[np.ndarray]
    errors: np.ndarray


def _timed(call: Callable[[], Solution]) -> Timed:
    """Calls twice: the first call compiles, the second is timed alone."""
    start = time.perf_counter()
    jax.block_until_ready(call())
    first = time.perf_counter() - start
    start = time.perf_counter()
    solution = jax.block_until_ready(call())
    return Timed(solution, time.perf_counter() - start, first)


def timed_solve(problem: Problem, options: Optional[Options] = None, u_init=None) -> Timed:
    """``solve(problem, u_init, options)`` timed (see `Timed`)."""
    return _timed(lambda: solve(problem, u_init=u_init, options=options))


# Module level, so that a later study with the same shapes (delay, number of problems) reuses the
# compilation instead of tracing a new function.
_batched_solve = jax.jit(jax.vmap(solve, in_axes=(0, None, None)))


def solve_batch(problems: Sequence[Problem], options: Optional[Options] = None, u_init=None) -> Solution:
    """One compiled, vmapped solve of problems that differ only in their arrays (e.g. targets);
    the solution's leaves carry a leading axis over ``problems``. ``u_init`` [K, d] is shared
    (default: the model's, [`default_u_init`][delayed_ilqr.models.metadata.default_u_init] of the first)."""
    if u_init is None:
        u_init = default_u_init(problems[0])
    stacked = stack(problems)
    return _batched_solve(stacked, u_init, Options() if options is None else options)


def timed_batched_solve(problems: Sequence[Problem], options: Options, u_init=None) -> Timed:
    """One compiled, vmapped solve of problems that differ only in their arrays (e.g. targets),
    timed; the solution's leaves carry a leading axis over ``problems``.

    Args:
        problems: design problems of equal structure.
        options: solver options, shared.
        u_init: initial commands [K, d] shared by all; default the model's
            ([`default_u_init`][delayed_ilqr.models.metadata.default_u_init] of the first problem).
    """
    if u_init is None:
        u_init = default_u_init(problems[0])
    stacked = stack(problems)
    return _timed(lambda: _batched_solve(stacked, u_init, options))


def stack(trees):
    """Pytrees of equal structure (e.g. problems that differ only in their arrays) stacked on a new
    leading axis of every leaf: the batch that ``vmap`` and `take` work on."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *trees)


def take(tree, j: int):
    """Entry j of a batched pytree (the leading axis of every leaf), e.g. one policy of a batch."""
    return jax.tree_util.tree_map(lambda a: a[j], tree)


def monte_carlo(plant: Problem, policy: Policy, n_trials: int, seed: int, substeps: int = 1,
                disturbance=None) -> Trials:
    """Runs ``policy`` ``n_trials`` times on ``plant`` (with the disturbance W [K, n] added to every
    trial's state update, if given) and judges the final states (`Trials`)."""
    runs = simulate(plant, policy, n_trials, seed=seed, substeps=substeps, disturbance=disturbance)
    final = np.asarray(runs.x[:, -1], dtype=np.float64)
    return Trials(runs, _positions(plant, final), endpoint_error(plant, final))


def _positions(problem: Problem, x) -> Optional[np.ndarray]:
    with np.errstate(invalid="ignore"):
        return task_position(problem, x)


def endpoint_description(problem: Problem) -> tuple[str, str]:
    """(label, unit) of `endpoint_error` for this problem."""
    task = task_space(problem)
    if task is None or task_target(problem) is None:
        return "final cost", ""
    return f"{task.name} error", task.unit


def endpoint_error(problem: Problem, final_states) -> np.ndarray:
    """How far each final state [N, n] is from the task's goal: [N].

    With a task space (the model's metadata): the distance |map(x_K) - target| in its unit, e.g.
    the hand's distance from the target in metres. Without one: the final cost of eq. (2), never a
    norm over states of mixed units.
    """
    x = np.asarray(final_states, dtype=np.float64)
    target = task_target(problem)
    if target is None:
        return np.asarray(jax.vmap(problem.cost.final, in_axes=(0, None))(jnp.asarray(x), problem.final_time))
    return np.linalg.norm(_positions(problem, x) - target, axis=-1)
