"""Issue 19 item 4: the sigma-point prediction of the expected cost of the torque arm's closed loop
(``prediction.sigma_point_prediction``) against the linearised one (``Solution.expected_cost``)
and Monte Carlo, for the noise-aware design of ``arm2(delay=d, noise=True, sigma_u=SIGMA_U_HUMAN)``.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/arm2_sigma_point_prediction.py DELAYS TRIALS
    e.g. ... 0,0.05,0.1,0.15 4000
"""
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402
from delayed_ilqr.prediction import sigma_point_prediction  # noqa: E402


def main(argv):
    delays, n = [float(d) for d in argv[1].split(",")], int(argv[2])
    print("| delay | linear pred | cubature | unscented | second order | fifth degree | MC mean +- SE | linear / MC | cubature / MC | unscented / MC | second order / MC | fifth degree / MC |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for delay in delays:
        problem = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN)
        sol = di.solve(problem)
        t0 = time.perf_counter()
        cub = float(sigma_point_prediction(problem, sol.policy, "cubature").expected_cost)
        t1 = time.perf_counter()
        ut = float(sigma_point_prediction(problem, sol.policy, "unscented").expected_cost)
        so = float(sigma_point_prediction(problem, sol.policy, "second_order").expected_cost)
        fd = float(sigma_point_prediction(problem, sol.policy, "fifth_degree").expected_cost)
        cost = np.asarray(di.simulate(problem, sol.policy, n, seed=1).cost)
        mc, se = cost.mean(), cost.std(ddof=1) / np.sqrt(n)
        lin = float(sol.expected_cost)
        print(f"| {delay * 1e3:.0f} ms | {lin:.4g} | {cub:.4g} | {ut:.4g} | {so:.4g} | {fd:.4g} | {mc:.4g} +- {se:.2g} | {lin / mc:.3f} | "
              f"{cub / mc:.3f} | {ut / mc:.3f} | {so / mc:.3f} | {fd / mc:.3f} |", flush=True)
        print(f"  (status {sol.status}, cubature incl. compile {t1 - t0:.2f} s)", file=sys.stderr)


if __name__ == "__main__":
    main(sys.argv)
