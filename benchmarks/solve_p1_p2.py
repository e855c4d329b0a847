"""P1 and P2 at delays 0, 30 and 100 ms: converged cost, iterations, solve time after compilation,
and agreement with an independent direct method (L-BFGS-B over all commands, autodiff gradients).

Run: .venv/bin/python benchmarks/solve_p1_p2.py
"""
import sys
from pathlib import Path

import jax

import delayed_ilqr as di
from delayed_ilqr.models import arm2, point_mass

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from direct import direct_optimum  # noqa: E402  (tests/direct.py: a test reference, not in the package)
from timing import first_and_median  # noqa: E402


def main():
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    print(f"{'problem':8} {'delay':>6} {'l':>3} {'cost':>14} {'iters':>5} {'status':>18} "
          f"{'first call':>10} {'solve':>9} {'direct (L-BFGS)':>16} {'rel. diff':>10}")
    for name, factory in (("P1", point_mass), ("P2", arm2)):
        for delay in (0.0, 0.03, 0.1):
            problem = factory(delay=delay)
            sol, first, median = first_and_median(lambda: di.solve(problem), repeats=7, slow_repeats=7, fill_s=0.0)
            reference = direct_optimum(problem)
            print(f"{name:8} {delay:6.2f} {problem.delay_steps:3d} {float(sol.cost):14.8e} {int(sol.iterations):5d} "
                  f"{di.Status(int(sol.status)).name:>18} {first:9.2f}s {median * 1e3:7.1f}ms {reference:16.8e} "
                  f"{(float(sol.cost) - reference) / reference:10.1e}")


if __name__ == "__main__":
    main()
