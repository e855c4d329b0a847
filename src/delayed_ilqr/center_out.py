"""Center-out reaching with the six-muscle arm and delayed excitations (Li & Todorov 2004).

For each delay and design: the reaches to ``n_targets`` hand targets on a circle around the start
hand position are solved in one compiled, vectorised call (``jax.vmap`` of
:func:`~delayed_ilqr.solve` over the targets, which are cost parameters), then each target's
delayed feedback policy runs ``n_trials`` times on the noisy plant (signal-dependent excitation
noise, ``arm2_muscle6``'s ``noise=True``).

Two designs of the same plant:

* ``"noise-aware"`` (iLQG, the default): designed on the noisy arm itself, so the signal-dependent
  noise enters the backward pass (Todorov & Li 2005): the nominal trades accuracy for smaller,
  less noisy excitations and the feedback is the LQG optimum for the multiplicative noise.
* ``"deterministic"`` (iLQR): designed on the noise-free arm, then run in the noise.

Per delay and design the study reports iterations, solve time, the final hand error of the
nominal, the predicted expected cost (J(0) of the last LQG) against the Monte Carlo mean, and the
endpoint spread (mean hand error and the 2-sigma ellipse of the final hand positions).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .models.arm2 import ARM2_PARAMS, hand_position
from .models.arm2_muscle6 import SIGMA_U, arm2_muscle6, center_out_targets, rest_commands
from .simulate import simulate
from .solution import Policy, Solution, Status
from .ilqg.solver import solve
from .options import Options

__all__ = ["TargetResult", "DelayResult", "center_out", "format_table", "to_records", "DEFAULT_OPTIONS", "DESIGNS"]

#: Muscle reaches take 30-200 iterations (the excitations saturate at 0 and 1 on long stretches,
#: where the box-QP's active set changes slowly); 300 leaves a margin.
DEFAULT_OPTIONS = Options(max_iterations=300)

#: The designs the study compares, by name.
DESIGNS = ("noise-aware", "deterministic")


@dataclass(frozen=True)
class TargetResult:
    """One reach of the study (lengths in metres).

    Attributes:
        target: [2] hand target.
        status: the solver's :class:`~delayed_ilqr.Status` name; iterations: its iteration count.
        cost: eq. (2) of the noise-free nominal.
        predicted_cost: the design's expected cost J(0) of its last LQG (for the deterministic
            design, the noise-free cost: it does not know the noise).
        hand_error: distance of the nominal's final hand position from the target.
        endpoints: [N, 2] final hand positions of the noisy trials.
        mc_error: [N] their distances from the target.
        mc_cost: [N] eq. (2) of each noisy trial.
    """

    target: np.ndarray
    status: str
    iterations: int
    cost: float
    predicted_cost: float
    hand_error: float
    endpoints: np.ndarray
    mc_error: np.ndarray
    mc_cost: np.ndarray

    @property
    def converged(self) -> bool:
        return Status[self.status].converged

    @property
    def endpoint_cov(self) -> np.ndarray:
        """[2, 2] covariance of the final hand positions."""
        return np.cov(self.endpoints, rowvar=False)

    @property
    def spread(self) -> float:
        """Endpoint spread: sqrt of the largest eigenvalue of the covariance (1-sigma major axis)."""
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.endpoint_cov))))


@dataclass(frozen=True)
class DelayResult:
    """All reaches at one delay with one design.

    Attributes:
        delay: tau in seconds; delay_steps: l; dt: the time step (s).
        design: "noise-aware" or "deterministic" (see the module docstring).
        solve_time: seconds of the compiled batched solve of all targets (second call).
        first_call: seconds of the first call (compilation included).
        targets: one :class:`TargetResult` per target.
        solutions: the batched :class:`~delayed_ilqr.Solution` (leading axis: target).
        runs: the Monte Carlo :class:`~delayed_ilqr.Runs` per target.
    """

    delay: float
    delay_steps: int
    dt: float
    design: str
    solve_time: float
    first_call: float
    targets: list
    solutions: Solution
    runs: list

    def policy(self, j: int) -> Policy:
        """The delayed feedback policy of target j."""
        return _take(self.solutions.policy, j)


def _take(tree, j: int):
    """Entry j of a batched pytree (the leading axis of every leaf)."""
    return jax.tree_util.tree_map(lambda a: a[j], tree)


def _hand(x):
    """Hand positions [..., 2] of arm states [..., 10] (the muscle arm uses P2's rigid body)."""
    return np.asarray(hand_position(jnp.asarray(x)[..., :2], ARM2_PARAMS))


def _stack(problems):
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *problems)


# Module level, so that a later study with the same shapes (delay, number of targets) reuses the
# compilation instead of tracing a new function.
_batched_solve = jax.jit(jax.vmap(solve, in_axes=(0, None, None)), static_argnums=2)


def _solve_all(problems, options: Options):
    """One compiled, vmapped solve over problems that differ only in their targets; (solutions,
    seconds of the second call, seconds of the first)."""
    u_init = rest_commands(problems[0])
    stacked = _stack(problems)
    start = time.perf_counter()
    jax.block_until_ready(_batched_solve(stacked, u_init, options))
    first = time.perf_counter() - start
    start = time.perf_counter()
    sols = jax.block_until_ready(_batched_solve(stacked, u_init, options))
    return sols, time.perf_counter() - start, first


def center_out(delays: Sequence[float] = (0.0, 0.05, 0.1), n_targets: int = 8, radius: float = 0.1,
               n_trials: int = 200, seed: int = 0, options: Optional[Options] = None,
               geometry: str = "angle_dependent", sigma_u: float = SIGMA_U,
               designs: Sequence[str] = DESIGNS) -> list[DelayResult]:
    """Runs the center-out study; one :class:`DelayResult` per delay and design (delay-major).

    Args:
        delays: input delays in seconds (whole multiples of the 10 ms step).
        n_targets: targets on the circle (8 in the classic task), the first one to the right.
        radius: circle radius in metres (start hand position at the centre).
        n_trials: noisy trials per target; seed: their seed (target j uses seed + j, so every
            design meets the same noise).
        options: solver options (default :data:`DEFAULT_OPTIONS`).
        geometry: muscle moment arms, "angle_dependent" (default) or "constant".
        sigma_u: excitation noise of the plant (the model's default 0.1); the noise-aware design
            is made for it.
        designs: a non-empty selection of :data:`DESIGNS`.
    """
    options = DEFAULT_OPTIONS if options is None else options
    if not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    designs = tuple(designs)
    if not designs or any(d not in DESIGNS for d in designs):
        raise ValueError(f"designs must be a non-empty selection of {DESIGNS}; got {designs!r}")
    targets = center_out_targets(n_targets, radius)
    results = []
    for delay in delays:
        plants = [arm2_muscle6(delay=delay, target=tuple(t), noise=True, geometry=geometry, sigma_u=sigma_u)
                  for t in targets]
        for design in designs:
            problems = plants if design == "noise-aware" else [p.replace(noise=None) for p in plants]
            results.append(_study(delay, design, targets, problems, plants, options, n_trials, seed))
    return results


def _study(delay, design, targets, problems, plants, options, n_trials, seed) -> DelayResult:
    """One delay and design: the batched solve, then the Monte Carlo of each target's policy."""
    sols, solve_time, first = _solve_all(problems, options)
    per_target, runs_all = [], []
    for j, (target, plant) in enumerate(zip(targets, plants)):
        runs = simulate(plant, _take(sols.policy, j), n_trials, seed=seed + j)
        ends = _hand(runs.x[:, -1])
        per_target.append(TargetResult(
            target=np.asarray(target), status=Status(int(sols.status[j])).name,
            iterations=int(sols.iterations[j]), cost=float(sols.cost[j]),
            predicted_cost=float(sols.expected_cost[j]),
            hand_error=float(np.linalg.norm(_hand(sols.x[j, -1]) - target)),
            endpoints=ends, mc_error=np.linalg.norm(ends - target, axis=1), mc_cost=np.asarray(runs.cost)))
        runs_all.append(runs)
    return DelayResult(delay=float(delay), delay_steps=problems[0].delay_steps, dt=problems[0].dt, design=design,
                       solve_time=solve_time, first_call=first, targets=per_target, solutions=sols, runs=runs_all)


def _row(r: DelayResult) -> list[str]:
    its = [t.iterations for t in r.targets]
    n = len(r.targets)
    return [f"{1e3 * r.delay:g} ms", r.design, f"{sum(t.converged for t in r.targets)}/{n}",
            f"{int(np.median(its))} [{min(its)}-{max(its)}]", f"{1e3 * r.solve_time / n:.0f} ms",
            f"{1e3 * max(t.hand_error for t in r.targets):.2f} mm",
            f"{np.mean([t.predicted_cost for t in r.targets]):.3g}",
            f"{np.mean([t.mc_cost.mean() for t in r.targets]):.3g}",
            f"{1e3 * np.mean([t.mc_error.mean() for t in r.targets]):.1f} mm",
            f"{1e3 * np.mean([np.median(t.mc_error) for t in r.targets]):.1f} mm",
            f"{1e3 * np.mean([t.spread for t in r.targets]):.1f} mm"]


_HEADER = ["delay", "design", "converged", "iterations median [range]", "solve time per target",
           "nominal hand error (max)", "predicted E[J] (mean)", "MC mean J (mean)", "MC hand error (mean)",
           "MC hand error (median, mean over targets)", "MC endpoint spread (1-sigma major axis, mean)"]


def format_table(results: Sequence[DelayResult]) -> str:
    """A Markdown table, one row per delay and design."""
    lines = ["| " + " | ".join(_HEADER) + " |", "|" + "---|" * len(_HEADER)]
    lines += ["| " + " | ".join(_row(r)) + " |" for r in results]
    return "\n".join(lines)


def to_records(results: Sequence[DelayResult]) -> list[dict]:
    """Every number of the study as JSON-ready dicts (one per delay and design, with a list of targets)."""
    return [dict(delay=r.delay, delay_steps=r.delay_steps, dt=r.dt, design=r.design, solve_time=r.solve_time,
                 first_call=r.first_call,
                 targets=[dict(target=t.target.tolist(), status=t.status, iterations=t.iterations, cost=t.cost,
                               predicted_cost=t.predicted_cost, mc_cost_mean=float(t.mc_cost.mean()),
                               hand_error=t.hand_error, mc_error_mean=float(t.mc_error.mean()),
                               mc_error_median=float(np.median(t.mc_error)),
                               endpoint_mean=t.endpoints.mean(axis=0).tolist(),
                               endpoint_cov=t.endpoint_cov.tolist(), spread=t.spread)
                          for t in r.targets])
            for r in results]
