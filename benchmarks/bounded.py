"""Bounded solves: delayed_ilqr with box limits against its unbounded solve and against
crocoddyl's BoxDDP and BoxFDDP on the augmented problem, in the same run.

Problem: P4 of ``docs/models.md`` §2 (the point mass, dt = 0.001, K = 600) at delays l = 0, 10 and
50 steps, limits at ``FRACTION`` of the unbounded optimum's peak command per control (so that they
bind). crocoddyl solves the augmented LQR of ``crocoddyl_ref.augmented_lqr`` (the same problem,
written from the spec) with ``u_lb``/``u_ub`` set on its running model, from us = 0, default
settings; delayed_ilqr solves ``point_mass(dt, delay).replace(u_min, u_max)`` with the default
``Options()``. Times: the median of repeated solves after a first one (compilation for
delayed_ilqr), one thread for crocoddyl (``crocoddyl_ref``'s reasons). "it" is the iteration count
(delayed_ilqr's ``Solution.iterations``; crocoddyl's ``solver.iter``, steps taken).

Run ``python benchmarks/bounded.py`` (``make bench`` runs it): about three minutes on a 2-core
machine, most of them crocoddyl at l = 50 (20-40 s a solve, timed once).
"""
from __future__ import annotations

import ctypes

import crocoddyl
import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.models import point_mass

from crocoddyl_ref import MAXITER, augmented_lqr
from timing import median_time

DT, HORIZON, DELAYS, FRACTION = 0.001, 600, (0, 10, 50), 0.6
SOLVERS = {"BoxDDP": crocoddyl.SolverBoxDDP, "BoxFDDP": crocoddyl.SolverBoxFDDP}


def delayed_ilqr_rows(l: int):
    """(limits, rows): rows of (solver, median s, iterations, cost, converged) for the unbounded and the
    bounded solve at delay l."""
    problem = point_mass(dt=DT, delay=l * DT)
    rows = []
    free = di.solve(problem)
    limit = FRACTION * np.max(np.abs(np.asarray(free.u)), axis=0)
    bounded = problem.replace(u_min=-limit, u_max=limit)
    for name, p in (("delayed_ilqr unbounded", problem), ("delayed_ilqr bounded", bounded)):
        sol = jax.block_until_ready(di.solve(p))
        seconds = median_time(lambda: di.solve(p), warmup=False, slow_repeats=1)   # one call over 2 s
        rows.append((name, seconds, int(sol.iterations), float(sol.cost), sol.converged))
    return limit, rows


def crocoddyl_rows(l: int, limit):
    rows = []
    for name, cls in SOLVERS.items():
        problem = augmented_lqr(DT, l, HORIZON)
        problem.nthreads = 1
        for model in problem.runningModels:
            model.u_lb, model.u_ub = -limit, limit
        us0 = crocoddyl.StdVec_VectorXs([np.zeros(2)] * HORIZON)
        xs0 = problem.rollout(us0)
        solver = cls(problem)
        converged = solver.solve(xs0, us0, MAXITER, True)
        seconds = median_time(lambda: solver.solve(xs0, us0, MAXITER, True), warmup=False, slow_repeats=1)
        rows.append((f"crocoddyl {name}", seconds, solver.iter, solver.cost, converged))
    return rows


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    ctypes.CDLL("libgomp.so.1").omp_set_num_threads(1)
    print(f"P4 point mass (dt = {DT}, K = {HORIZON}), limits at {FRACTION} of the unbounded peak; "
          f"crocoddyl {crocoddyl.__version__} on the augmented problem, 1 thread")
    print("| l | solver | median | it | cost | rel. to best bounded | converged |")
    print("|---|---|---|---|---|---|---|")
    for l in DELAYS:
        limit, rows = delayed_ilqr_rows(l)
        rows += crocoddyl_rows(l, limit)
        best = min(r[3] for r in rows if "unbounded" not in r[0])
        for name, seconds, iters, cost, converged in rows:
            rel = "-" if "unbounded" in name else f"{(cost - best) / best:.1e}"
            print(f"| {l} | {name} | {seconds * 1e3:.3g} ms | {iters} | {cost:.10e} | {rel} | {converged} |")


if __name__ == "__main__":
    main()
