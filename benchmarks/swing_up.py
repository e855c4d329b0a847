"""Swing-ups from rest with limits: the acrobot rows of docs/derivation.md §15.

For each elbow limit, ``models.acrobot(u_max=...)`` (trajax's acrobot, dt = 0.1 s, K = 50):

- "from rest": ``solve`` from u_init = 0 with ``Options(max_iterations=1000)``: iterations, status, cost;
- "several starts": the same solve from rest, from the clipped unbounded optimum and from the
  clipped solution at the default 5 N m, run at once under ``jax.vmap``; the cheapest, and which
  start gave it;
- "augmented-Lagrangian start": ``augmented_lagrangian_start`` from rest (its defaults: penalty 1,
  times 10 per outer iteration, 6 outer iterations), polished by the bounded ``solve``: the inner
  iterations of the outer ones, the box violation after the first and the last, the polish's
  iterations and status, the cost, and the wall time of both (compilation included at the first limit);
- "L-BFGS-B": bounded L-BFGS-B (``tests/direct.py``) from zero and from ``STARTS - 1`` uniform
  random starts in the box (``numpy.random.default_rng(0)``): the cost from zero, the best, and
  how many of the starts reached the best (to 1e-6);
- "AL-iLQR" (only with ``--trajax PATH``): google/trajax's augmented-Lagrangian iLQR,
  ``trajax.optimizers.constrained_ilqr``, from u = 0 on trajax's own problem: its test suite's
  ``acrobot`` (read from ``PATH/tests/optimizers_test.py``), ``trajax.integrators.euler`` at
  dt = 0.1 and ``testAcrobotSolve``'s cost, with the box as the inequality constraint
  [-u_max - u, u - u_max] <= 0 at k < K. Two settings: ``testConstrainedAcrobotSolve``'s
  (``maxiter_al=10, constraints_threshold=1e-3``, the rest trajax's defaults: penalty 1, times 10
  per outer iteration, ``maxiter_ilqr=100``) and the same with ``penalty_update_rate=2`` and
  ``maxiter_al=40``. Each cell: outer and total iLQR iterations, trajax's maximum constraint
  violation against its tolerance, the cost (2) of trajax's commands (its ``objective`` with the
  original cost, not the augmented Lagrangian; the commands may leave the box by the violation),
  and "->" the cost of our ``solve`` started from those commands clipped into the box.

  Before the table it checks that this is the same problem: trajax's Euler step against
  ``x + dt f(x, u, u)`` at 1000 random states and commands, trajax's ``objective`` against
  ``trajectory_cost`` for 20 random command sequences, and trajax's unconstrained ``ilqr`` from
  rest (``maxiter=1000, make_psd=False``, as in ``testAcrobotSolve``) against our unbounded solve.

  trajax is not on PyPI (the PyPI ``trajax`` is an unrelated package) and is not a dependency of
  this project: bring its source (``git clone https://github.com/google/trajax``) and pass the
  directory. Its ``optimizers`` module needs only JAX and SciPy, both in the test environment;
  its test module (absl, not installed) is not imported, only its ``acrobot`` function is read out
  of it. Without ``--trajax`` the column is left out.

Run ``python benchmarks/swing_up.py [u_max ...] [--trajax PATH]`` (default limits: 5 3 2.4 2.2 2):
about five minutes on the shared 2-core machine, most of it L-BFGS-B; trajax adds about three.
Not part of ``make bench`` (a correctness table, not a timing).
"""
from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import rollout, trajectory_cost
from delayed_ilqr.models import acrobot

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from direct import direct_optimum  # noqa: E402  (tests/direct.py: a test reference, not in the package)

LIMITS, STARTS = (5.0, 3.0, 2.4, 2.2, 2.0), 5
START_NAMES = ("rest", "clipped unbounded", "clipped 5 N m")
AL_SETTINGS = {"trajax's test": dict(maxiter_al=10, constraints_threshold=1e-3),
               "penalty rate 2": dict(maxiter_al=40, constraints_threshold=1e-3, penalty_update_rate=2.0)}


class Trajax:
    """trajax's acrobot problem (its test suite's dynamics and cost) and its solvers, from a source tree."""

    def __init__(self, path, horizon, dt):
        root = Path(path).resolve()
        sys.path.insert(0, str(root))
        from trajax import integrators, optimizers  # optional: from the given path, not installed
        self.optimizers, self.horizon = optimizers, horizon
        self.dynamics = integrators.euler(_test_function(root / "tests" / "optimizers_test.py", "acrobot"), dt=dt)
        self.goal = jnp.array([jnp.pi, 0.0, 0.0, 0.0])

    def cost(self, x, u, t):
        """testAcrobotSolve's cost, params (1000, 0.1, 0.01)."""
        delta = x - self.goal
        return jnp.where(t == self.horizon, 0.5 * 1000.0 * delta @ delta,
                         0.5 * 0.1 * delta @ delta + 0.5 * 0.01 * u @ u)

    def objective(self, us):
        return float(self.optimizers.objective(self.cost, self.dynamics, us, jnp.zeros(4)))

    def ilqr_from_rest(self):
        """(cost, iterations, gradient norm) of trajax's unconstrained iLQR from u = 0."""
        _, _, obj, gradient, _, _, iterations = self.optimizers.ilqr(
            self.cost, self.dynamics, jnp.zeros(4), jnp.zeros((self.horizon, 1)), maxiter=1000, make_psd=False)
        return float(obj), int(iterations), float(jnp.linalg.norm(gradient))

    def constrained_from_rest(self, u_max, settings):
        """(commands [K, 1], outer iterations, iLQR iterations, max violation) of constrained_ilqr from u = 0."""
        def box(x, u, t):
            return jnp.where(t == self.horizon, jnp.zeros(2), jnp.array([-u_max - u[0], u[0] - u_max]))

        sol = self.optimizers.constrained_ilqr(self.cost, self.dynamics, jnp.zeros(4), jnp.zeros((self.horizon, 1)),
                                               inequality_constraint=box, **settings)
        return sol[1], int(sol[11]), int(sol[10]), float(sol[7])


def _test_function(test_file, name):
    """The module-level function ``name`` of trajax's test file, without importing the file (absl)."""
    node = next(n for n in ast.parse(test_file.read_text()).body if isinstance(n, ast.FunctionDef) and n.name == name)
    namespace = {"np": jnp, "jax": jax}
    exec(compile(ast.Module(body=[node], type_ignores=[]), str(test_file), "exec"), namespace)
    return namespace[name]


def check_same_problem(trajax: Trajax, problem, free) -> None:
    """Print how far trajax's step, cost and unconstrained iLQR are from ours (module docstring)."""
    rng = np.random.default_rng(1)
    xs, us = rng.normal(size=(1000, 4)) * np.array([3.0, 3.0, 5.0, 5.0]), 5.0 * rng.normal(size=(1000, 1))
    theirs = jax.vmap(lambda x, u: trajax.dynamics(x, u, 0))(xs, us)
    ours = jax.vmap(lambda x, u: x + problem.dt * problem.dynamics(x, u, u))(xs, us)
    step = float(jnp.max(jnp.abs(theirs - ours) / (1 + jnp.abs(ours))))
    sequences = 3.0 * rng.normal(size=(20, problem.horizon, 1))
    cost = max(abs(trajax.objective(u) / float(trajectory_cost(problem, rollout(problem, u), u)) - 1) for u in sequences)
    obj, iterations, gradient = trajax.ilqr_from_rest()
    print(f"trajax vs ours: Euler step max rel. diff {step:.1e} (1000 random x, u), cost max rel. diff {cost:.1e} "
          f"(20 random sequences); trajax ilqr from rest: {iterations} it, {obj:.10g} (|grad| {gradient:.1e}), "
          f"ours unbounded {float(free.cost):.10g}")


def al_cell(trajax: Trajax, problem, settings, options) -> str:
    us, outer, inner, violation = trajax.constrained_from_rest(float(problem.u_max[0]), settings)
    tol = settings["constraints_threshold"]
    polished = di.solve(problem, jnp.clip(us, problem.u_min, problem.u_max), options)
    return (f"{outer}/{inner} it, {violation:.1e} {'<' if violation < tol else '>'} {tol:g}, "
            f"{trajax.objective(us):.8g} -> {float(polished.cost):.8g}")


def main(limits, trajax_path=None) -> None:
    jax.config.update("jax_enable_x64", True)
    options = di.Options(max_iterations=1000)
    free = di.solve(acrobot(limits=False), options=options)
    loose = di.solve(acrobot(), options=options)
    print(f"unbounded: {int(free.iterations)} it, {float(free.cost):.10g}, peak |u| "
          f"{float(jnp.max(jnp.abs(free.u))):.3g} N m; 5 N m: {int(loose.iterations)} it, {float(loose.cost):.10g}")
    trajax = None
    if trajax_path is not None:
        trajax = Trajax(trajax_path, free.u.shape[0], acrobot().dt)
        check_same_problem(trajax, acrobot(limits=False), free)
    al_names = list(AL_SETTINGS) if trajax else []
    print("| u_max | from rest (it, status, cost) | several starts (cost, start) | augmented-Lagrangian start "
          "(outer its, violation, polish it, status, cost, time) | L-BFGS-B from zero | "
          "L-BFGS-B best of 5 (starts at it) |" + "".join(f" AL-iLQR (trajax constrained_ilqr) from rest, {name} |"
                                                         for name in al_names))
    print("|---|---|---|---|---|---|" + "---|" * len(al_names))
    for lim in limits:
        problem = acrobot(u_max=lim)
        starts = jnp.stack([jnp.zeros((problem.horizon, 1)), jnp.clip(free.u, -lim, lim), jnp.clip(loose.u, -lim, lim)])
        sols = jax.vmap(lambda u: di.solve(problem, u, options))(starts)
        costs = np.asarray(sols.cost)
        tic = time.perf_counter()
        continuation = di.augmented_lagrangian_start(problem, options=options)
        continued = di.solve(problem, continuation.u, options)
        continued_time = time.perf_counter() - tic
        rng = np.random.default_rng(0)
        direct = [direct_optimum(problem, u_init=u) for u in
                  [None] + [rng.uniform(-lim, lim, (problem.horizon, 1)) for _ in range(STARTS - 1)]]
        best = min(direct)
        hits = sum(abs(c - best) <= 1e-6 * best for c in direct)
        al = "".join(f" {al_cell(trajax, problem, AL_SETTINGS[name], options)} |" for name in al_names)
        print(f"| {lim:g} N m | {int(sols.iterations[0])}, {di.Status(int(sols.status[0])).name}, {costs[0]:.8g} | "
              f"{costs.min():.8g} ({START_NAMES[int(costs.argmin())]}) | "
              f"{'+'.join(str(int(i)) for i in continuation.iterations)}, {float(continuation.violation[0]):.1e} -> "
              f"{float(continuation.violation[-1]):.1e}, {int(continued.iterations)}, "
              f"{continued.status.name}, {float(continued.cost):.8g}, {continued_time:.1f} s | "
              f"{direct[0]:.8g} | {best:.8g} ({hits}/{STARTS}) |"
              + al, flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("limits", nargs="*", type=float, help="elbow limits u_max in N m (default: 5 3 2.4 2.2 2)")
    parser.add_argument("--trajax", metavar="PATH", help="a google/trajax source tree: adds the AL-iLQR column")
    args = parser.parse_args()
    main(args.limits or LIMITS, args.trajax)
