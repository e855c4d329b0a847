"""The prediction of the expected cost of the torque arm's nonlinear closed loop
(``prediction.closed_loop_prediction``, each rule) against the linearised one
(``Solution.expected_cost``) and Monte Carlo (mean +- standard error), for the noise-aware design of
``arm2(delay=d, noise=True, sigma_u=SIGMA_U_HUMAN)``; the seconds per call after compilation.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/arm2_closed_loop_prediction.py DELAYS TRIALS [DT] [moments]
    e.g. ... 0,0.05,0.1,0.15 4000      (DT: the time step, 0.01 by default; P3's grid: ... 0.1 2000 0.002)
    ... 0.1 4000 0.01 moments    also: at steps 20, 30, 40, 45, K the Monte Carlo mean deviation from
                            the nominal, SD and excess kurtosis of x_k against the second-order
                            prediction's mean and SD and the linear one's SD (predict)
    ... 0.1,0.15 4000 0.01 roots    also: the cubature rule with the square root of P_k rotated
                            by three random orthogonal matrices (an equally valid root)
"""
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402
from delayed_ilqr import prediction  # noqa: E402
from delayed_ilqr.prediction import RULES, closed_loop_prediction, predict  # noqa: E402


def moments(problem, sol, x):
    """The Monte Carlo states x [N, K+1, n] against the second-order and linear predictions."""
    dx = x - np.asarray(sol.x)[None]
    second, linear = closed_loop_prediction(problem, sol.policy), predict(problem, sol)
    fmt = lambda a: np.array2string(np.asarray(a), precision=5)
    for k in (20, 30, 40, 45, problem.horizon):
        mean, sd = dx[:, k].mean(0), dx[:, k].std(0)
        kurtosis = ((dx[:, k] - mean) ** 4).mean(0) / sd ** 4 - 3
        print(f"step {k}: MC mean {fmt(mean)} SD {fmt(sd)} excess kurtosis {np.array2string(kurtosis, precision=2)}\n"
              f"  second order mean {fmt(second.state.mean[k] - sol.x[k])} SD "
              f"{fmt(np.sqrt(np.diag(second.state.cov[k])))}; linear SD {fmt(np.sqrt(np.diag(linear.cov[k])))}")


def rotated_cubature(problem, policy, seed):
    """E[J] by the cubature rule on the root R Q of eq. P5 (``prediction._rule_root``), Q a random
    orthogonal matrix (R Q (R Q)' = R R' still): the rule's points, and its answer beyond degree 3,
    depend on that choice."""
    symmetric = prediction._rule_root

    def rotated(cov, inputs):
        root, rest = symmetric(cov, inputs)
        r = root.shape[1]
        Q = jnp.linalg.qr(jax.random.normal(jax.random.PRNGKey(seed), (r, r), cov.dtype))[0]
        return root @ Q, rest

    prediction._rule_root = rotated
    prediction._closed_loop_prediction.clear_cache()
    try:
        return float(closed_loop_prediction(problem, policy, "cubature").expected_cost)
    finally:
        prediction._rule_root = symmetric
        prediction._closed_loop_prediction.clear_cache()


def main(argv):
    delays, n = [float(d) for d in argv[1].split(",")], int(argv[2])
    print(f"| delay | MC mean +- SE ({n} trials) | linear | " + " | ".join(RULES) + " | seconds per call (" +
          ", ".join(RULES) + ") |")
    print("|---" * (len(RULES) + 4) + "|")
    for delay in delays:
        problem = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN, dt=float(argv[3]) if argv[3:] else 0.01)
        sol = di.solve(problem)
        runs = di.simulate(problem, sol.policy, n, seed=1)
        cost = np.asarray(runs.cost)
        mc, se = cost.mean(), cost.std(ddof=1) / np.sqrt(n)
        cells, seconds = [], []
        for rule in RULES:
            closed_loop_prediction(problem, sol.policy, rule).expected_cost.block_until_ready()   # compile
            t0 = time.perf_counter()
            value = float(closed_loop_prediction(problem, sol.policy, rule).expected_cost)
            seconds.append(time.perf_counter() - t0)
            cells.append(f"{value:.4g} ({value / mc:.3f})")
        lin = float(sol.expected_cost)
        print(f"| {delay * 1e3:.0f} ms | {mc:.4g} +- {se:.2g} | {lin:.4g} ({lin / mc:.3f}) | " + " | ".join(cells) +
              " | " + ", ".join(f"{t:.3f}" for t in seconds) + " |", flush=True)
        if argv[4:] == ["moments"]:
            moments(problem, sol, np.asarray(runs.x))
        if argv[4:] == ["roots"]:
            rotated = [rotated_cubature(problem, sol.policy, seed) for seed in (1, 2, 3)]
            print("  cubature, rotated roots: " + ", ".join(f"{v:.4g} ({v / mc:.3f})" for v in rotated))


if __name__ == "__main__":
    main(sys.argv)
