"""Crocoddyl (C++ DDP) on P1 and P4 by state augmentation, timed in this process.

Gives ``make bench`` a crocoddyl time measured on the same machine in the same run, instead of a
figure quoted from another one. Problems as in ``docs/models.md`` §2 (P1: dt = 0.01, K = 60;
P4: dt = 0.001, K = 600; point mass m = 1, b = 0.5, x0 = 0, target [0.2, 0.1, 0, 0],
Q = 1e-4 I2, P_f = diag(1e3, 1e3, 1e1, 1e1)), written here from the spec, not from delayed_ilqr.

Model. The augmented state z_k = [e_k, u_{k-l}, ..., u_{k-1}] (N = 4 + 2 l), with the error
e_k = x_k - x_target, obeys z_{k+1} = Az z_k + Bz u_k + f: Euler on x driven by the oldest buffer
slot u_{k-l}, the buffer shifts and u_k enters last; z_0 = [x0 - x_target, 0], and the drift
f = [(A - I) x_target, 0] is zero here (the target is at rest). The problem is linear-quadratic,
so both stages are crocoddyl's built-in C++ ``ActionModelLQR(A, B, Q, R, N, f, q, r)``, whose cost
is 0.5 [z,u]'[Q N; N' R][z,u] + q'z + r'u (no constant term):

* running (K of them): A = Az, B = Bz, R = 2 dt Q (so 0.5 u'Ru = dt u'Qu), nothing on z;
* terminal (nu = 0): Q = 2 P_f on the e block, so its cost is (x_K - x_target)'P_f(x_K - x_target).

crocoddyl's cost is then J of ``docs/models.md`` itself. In x coordinates instead
(q = -2 P_f x_target) it misses the constant x_target'P_f x_target = 50 and comes out as
-50 + J; adding 50 back loses 1e-11 of J (~5e-4) to rounding.

Solve. ``crocoddyl.ShootingProblem(z0, [running] * K, terminal)``, then ``SolverDDP`` and
``SolverFDDP`` with their default settings (``th_stop`` = 1e-9, ``init_reg`` = 1e-9), started
from us = 0 and xs = their rollout, ``is_feasible=True``.

Threads. One by default: ``problem.nthreads`` (crocoddyl's OpenMP loop over the stages' calc and
calcDiff; its default is the core count) and ``omp_set_num_threads`` (libgomp, which the wheel's
Eigen uses to split large matrix products, those of the backward pass at N >= ~50). With two
OpenMP threads on a 2-core machine where anything else runs, the backward pass of P4 l = 50 took
2.5 to 13 s instead of 0.2 to 0.4 s: OpenMP's threads wait on the busy core. ``--threads`` sets it.

Timing. One warm-up solve, then the median wall time (``time.perf_counter``) of repeated
``solver.solve(xs0, us0, MAXITER, True)`` calls on the same solver object: each call restarts
from the initial guess and runs the whole solve (copy of the guess, calc/calcDiff of every stage,
backward and forward passes, until the stopping test); the problem, the solver, its workspace and
the initial guess (already crocoddyl ``StdVec_VectorXs``, no list conversion) are built once,
outside the timed region. Repeats: at least 7 (3 when one solve takes over 2 s), more for fast
solves until 0.5 s are spent, as ``run.py`` does for delayed_ilqr.

"it" is crocoddyl's ``solver.iter``, the number of steps taken; a solve runs it + 1 backward
passes (the last one's stopping test ends it). On these LQ problems it is 1 for l <= 10 and 2 for
l >= 50, where the first (regularised, ``init_reg`` = 1e-9) step leaves stop = 1.4e-9 > 1e-9.

Run ``python benchmarks/crocoddyl_ref.py``: about 45 s on a 2-core machine, 35 of them for P4
l = 100 (4 s a solve). ``--with-200`` adds P4 l = 200 (about 8x longer a solve: minutes);
``--check`` also solves each case with delayed_ilqr and prints the cost's relative difference
(measured: below 1.1e-12; crocoddyl stops at its ``stop`` < 1e-9 a little short of the optimum).
Needs crocoddyl (3.2.1 tested): ``pip install '.[bench]'``, which ``make bench`` runs; ``run.py``
calls :func:`crocoddyl_solve_times` for its same-run reference.
"""
from __future__ import annotations

import argparse
import ctypes
import crocoddyl
import numpy as np

from timing import median_time

MASS, DAMPING, FINAL_TIME = 1.0, 0.5, 0.6
X_TARGET = np.array([0.2, 0.1, 0.0, 0.0])
Q_U = 1e-4 * np.eye(2)
P_F = np.diag([1e3, 1e3, 1e1, 1e1])
MAXITER = 100
CASES = [("P1", 0.01, 10)] + [("P4", 0.001, l) for l in (1, 10, 50, 100)]
P4_200 = ("P4", 0.001, 200)
SOLVERS = {"DDP": crocoddyl.SolverDDP, "FDDP": crocoddyl.SolverFDDP}


def augmented_lqr(dt: float, l: int, horizon: int, x0=(0.0, 0.0, 0.0, 0.0)):
    """crocoddyl.ShootingProblem of the point mass with delay l (module docstring)."""
    n, d = 4, 2
    N = n + d * l
    A, B = np.zeros((N, N)), np.zeros((N, d))
    A[:n, :n] = np.eye(n)
    A[0:2, 2:4] += dt * np.eye(2)
    A[2:4, 2:4] -= dt * DAMPING / MASS * np.eye(2)
    force = B if l == 0 else A[:, n:n + d]  # the column block that u_{k-l} drives
    force[2:4] = dt / MASS * np.eye(2)
    if l > 0:  # buffer shift: slot i <- slot i + 1, u_k enters the last slot
        A[n:N - d, n + d:] = np.eye(N - n - d)
        B[N - d:] = np.eye(d)
    drift = np.zeros(N)
    drift[:n] = (A[:n, :n] - np.eye(n)) @ X_TARGET
    running = crocoddyl.ActionModelLQR(A, B, np.zeros((N, N)), 2 * dt * Q_U, np.zeros((N, d)),
                                       drift, np.zeros(N), np.zeros(d))
    Qf = np.zeros((N, N))
    Qf[:n, :n] = 2 * P_F
    terminal = crocoddyl.ActionModelLQR(np.eye(N), np.zeros((N, 0)), Qf, np.zeros((0, 0)),
                                        np.zeros((N, 0)), np.zeros(N), np.zeros(N), np.zeros(0))
    z0 = np.zeros(N)
    z0[:n] = np.asarray(x0) - X_TARGET
    return crocoddyl.ShootingProblem(z0, [running] * horizon, terminal)


def crocoddyl_solve_times(cases=CASES, solvers=("DDP", "FDDP"), threads: int = 1, repeats: int = 7):
    """{(problem, K, l, solver): (median seconds, iterations, cost)} for (name, dt, l) in cases.

    The cost is crocoddyl's final ``solver.cost``: J of ``docs/models.md``, directly
    comparable with ``delayed_ilqr.solve(...).cost``.
    ``threads`` sets OpenMP's thread count for this (the calling) thread, for good; ``repeats``
    is the least number of timed solves (3 when one takes over 2 s).
    """
    ctypes.CDLL("libgomp.so.1").omp_set_num_threads(threads)
    out = {}
    for name, dt, l in cases:
        horizon = round(FINAL_TIME / dt)
        for solver_name in solvers:
            problem = augmented_lqr(dt, l, horizon)
            problem.nthreads = threads
            us0 = crocoddyl.StdVec_VectorXs([np.zeros(2)] * horizon)
            xs0 = problem.rollout(us0)
            solver = SOLVERS[solver_name](problem)
            run = lambda: solver.solve(xs0, us0, MAXITER, True)  # noqa: E731
            if not run():
                raise RuntimeError(f"crocoddyl {solver_name} did not converge on {name} l={l}")
            seconds = median_time(run, repeats=repeats, warmup=False, slow_repeats=min(3, repeats), fill_s=0.5)
            out[name, horizon, l, solver_name] = (seconds, solver.iter, solver.cost)
    return out


def _delayed_ilqr_cost(dt: float, l: int) -> float:
    import delayed_ilqr as di
    from delayed_ilqr.models import point_mass

    return float(di.solve(point_mass(dt=dt, delay=l * dt)).cost)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--with-200", action="store_true", help="add P4 l=200 (minutes)")
    parser.add_argument("--check", action="store_true", help="compare costs with delayed_ilqr")
    parser.add_argument("--threads", type=int, default=1, help="OpenMP threads (default 1)")
    args = parser.parse_args()
    if args.check:   # delayed_ilqr's costs, computed in float64 with XLA's CPU flags
        import jax

        import delayed_ilqr as di

        jax.config.update("jax_enable_x64", True)
        di.configure_cpu()
    cases = CASES + [P4_200] * args.with_200
    results = crocoddyl_solve_times(cases, threads=args.threads)
    print(f"crocoddyl {crocoddyl.__version__}, state augmentation, {args.threads} thread(s), "
          "median of solver.solve()")
    print("| problem | K | l | N | solver | median | it | cost | rel. diff vs delayed_ilqr |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, dt, l in cases:
        horizon = round(FINAL_TIME / dt)
        reference = _delayed_ilqr_cost(dt, l) if args.check else None
        for solver_name in SOLVERS:
            seconds, iters, cost = results[name, horizon, l, solver_name]
            diff = f"{abs(cost - reference) / abs(reference):.1e}" if args.check else "-"
            print(f"| {name} | {horizon} | {l} | {4 + 2 * l} | {solver_name} | "
                  f"{seconds * 1e3:.3g} ms | {iters} | {cost:.8e} | {diff} |")


if __name__ == "__main__":
    main()
