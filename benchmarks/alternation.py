"""Todorov's alternation against the separation design, with motor and sensory delay.

For each plant, one full-state iLQG solve, then the two output-feedback designs at its nominal
(``ilqg.estimation.with_estimator``): the separation design (``Options(max_alternations=0)``: iLQG's
feedback on the Kalman filter of the nominal commands' noise) and the alternation (the default).
Printed per plant: the exact expected cost of each pair on the linearisation, their ratio, the
Monte Carlo cost of each on the nonlinear plant (mean and standard error, the same trials for
both), the paired difference, and the design times (median wall time after compilation).

Run: .venv/bin/python benchmarks/alternation.py [--trials N]
"""
import argparse

import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.experiments import tables
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS
from delayed_ilqr.ilqg.estimation import with_estimator
from delayed_ilqr.models import arm2, arm2_muscle6, rest_commands
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV
from timing import median_time

SEPARATION = di.Options(max_iterations=DEFAULT_OPTIONS.max_iterations, max_alternations=0)

PLANTS = [  # (name, factory, motor delay [s], sensory delay [s])
    ("arm2, P2-noisy (sigma_u 0.2)", lambda lm, ls: arm2(delay=lm, noise=True, sensory_delay=ls), 0.03, 0.05),
    ("arm2, sigma_u 0.05", lambda lm, ls: arm2(delay=lm, noise=True, sigma_u=0.05, sensory_delay=ls), 0.03, 0.05),
    ("arm2_muscle6", lambda lm, ls: arm2_muscle6(**{**LI_TODOROV, "sensory_delay": ls}, delay=lm), 0.0, 0.0),
    ("arm2_muscle6", lambda lm, ls: arm2_muscle6(**{**LI_TODOROV, "sensory_delay": ls}, delay=lm), 0.05, 0.05),
    ("arm2_muscle6", lambda lm, ls: arm2_muscle6(**{**LI_TODOROV, "sensory_delay": ls}, delay=lm), 0.05, 0.1),
    ("arm2_muscle6", lambda lm, ls: arm2_muscle6(**{**LI_TODOROV, "sensory_delay": ls}, delay=lm), 0.1, 0.05),
]


def mean_se(values):
    return f"{values.mean():.4g} ± {values.std(ddof=1) / np.sqrt(values.size):.2g}"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    rows = []
    for name, factory, lm, ls in PLANTS:
        problem = factory(lm, ls)
        u_init = rest_commands(problem) if problem.name == "arm2_muscle6" else None
        full = di.solve(problem.replace(observation=None), u_init=u_init, options=DEFAULT_OPTIONS)
        sep = with_estimator(problem, full, SEPARATION)
        alt = with_estimator(problem, full, DEFAULT_OPTIONS)
        cost_sep = np.asarray(di.simulate(problem, sep.policy, args.trials, seed=args.seed).cost)
        cost_alt = np.asarray(di.simulate(problem, alt.policy, args.trials, seed=args.seed).cost)
        t_sep = median_time(lambda: with_estimator(problem, full, SEPARATION))
        t_alt = median_time(lambda: with_estimator(problem, full, DEFAULT_OPTIONS))
        rows.append({
            "plant": name, "motor / sensory delay [ms]": f"{1000 * lm:g} / {1000 * ls:g}",
            "status": str(full.status),
            "exact, separation": f"{float(sep.expected_cost):.4g}", "exact, alternation": f"{float(alt.expected_cost):.4g}",
            "ratio": f"{float(alt.expected_cost / sep.expected_cost):.3f}",
            "Monte Carlo, separation": mean_se(cost_sep), "Monte Carlo, alternation": mean_se(cost_alt),
            "paired difference": mean_se(cost_alt - cost_sep),
            "design time, separation [ms]": f"{1000 * t_sep:.1f}", "design time, alternation [ms]": f"{1000 * t_alt:.1f}",
        })
        print(rows[-1], flush=True)
    print(f"\n# {args.trials} trials, seed {args.seed}")
    print(tables.markdown_table(tables.records_table(rows)))


if __name__ == "__main__":
    main()
