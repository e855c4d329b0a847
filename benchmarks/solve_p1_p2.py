"""P1 and P2 at delays 0, 30 and 100 ms: converged cost, iterations, solve time after compilation,
and agreement with an independent direct method (L-BFGS-B over all commands, autodiff gradients).

Run: .venv/bin/python benchmarks/solve_p1_p2.py
"""
import time

import jax
import numpy as np
import scipy.optimize

import delayed_ilqr as di
from delayed_ilqr.linearize import rollout, trajectory_cost
from delayed_ilqr.models import arm2, point_mass


def direct_optimum(problem):
    K, nd = problem.horizon, problem.n_controls

    def cost(flat):
        us = flat.reshape(K, nd)
        return trajectory_cost(problem, rollout(problem, us), us)

    fun, grad = jax.jit(cost), jax.jit(jax.grad(cost))
    u = np.zeros(K * nd)
    for _ in range(3):        # L-BFGS-B's ftol has an absolute floor: rescale to O(1) and restart
        scale = 1.0 / float(fun(u))
        u = scipy.optimize.minimize(lambda v: scale * float(fun(v)), u, jac=lambda v: scale * np.asarray(grad(v)),
                                    method="L-BFGS-B", options=dict(maxiter=50000, maxfun=100000, ftol=1e-16,
                                                                    gtol=1e-14, maxcor=50)).x
    return float(fun(u))


def timed_solve(problem, repeats=7):
    start = time.perf_counter()
    sol = jax.block_until_ready(di.solve(problem))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(di.solve(problem))
        times.append(time.perf_counter() - start)
    return sol, first, float(np.median(times))


def main():
    print(f"{'problem':8} {'delay':>6} {'l':>3} {'cost':>14} {'iters':>5} {'status':>18} "
          f"{'first call':>10} {'solve':>9} {'direct (L-BFGS)':>16} {'rel. diff':>10}")
    for name, factory in (("P1", point_mass), ("P2", arm2)):
        for delay in (0.0, 0.03, 0.1):
            problem = factory(delay=delay)
            sol, first, median = timed_solve(problem)
            reference = direct_optimum(problem)
            print(f"{name:8} {delay:6.2f} {problem.delay_steps:3d} {float(sol.cost):14.8e} {int(sol.iterations):5d} "
                  f"{di.Status(int(sol.status)).name:>18} {first:9.2f}s {median * 1e3:7.1f}ms {reference:16.8e} "
                  f"{(float(sol.cost) - reference) / reference:10.1e}")


if __name__ == "__main__":
    main()
