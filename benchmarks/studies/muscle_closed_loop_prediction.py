"""The nonlinear closed-loop prediction (``prediction.closed_loop_prediction``, each rule)
of the six-muscle arm's center-out reaches, against the linearised one (``Solution.expected_cost``)
and Monte Carlo, for the noise-aware design (the center-out study's, ``experiments.center_out``) at
each delay and target: the ratio prediction / Monte Carlo mean, and the Monte Carlo mean / median
(the weight of the tail).

    PYTHONPATH=src .venv/bin/python benchmarks/studies/muscle_closed_loop_prediction.py DELAYS TRIALS
    e.g. ... 0.05,0.1 2000
"""
import sys

import jax

jax.config.update("jax_enable_x64", True)

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.experiments.engine import solve_batch  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets  # noqa: E402
from delayed_ilqr.prediction import closed_loop_prediction  # noqa: E402
from delayed_ilqr.statistics import divergence_bound, diverged_trials, sample_stats  # noqa: E402


def main(delays, trials):
    di.configure_cpu()
    targets = center_out_targets(8, 0.1)
    print("| delay | target | linear / MC | second order / MC | fifth degree / MC | MC mean | MC mean / median |")
    print("|---|---|---|---|---|---|---|")
    for delay in delays:
        problems = [arm2_muscle6(**LI_TODOROV, delay=delay, target=t) for t in targets]
        sols = solve_batch(problems)
        for j, problem in enumerate(problems):
            sol = jax.tree_util.tree_map(lambda a: a[j], sols)
            runs = di.simulate(problem, sol.policy, trials, seed=0)
            stats = sample_stats(runs.cost, diverged_trials(runs.cost, divergence_bound(problem)))
            ratios = [float(sol.expected_cost) / stats.mean]
            ratios += [float(closed_loop_prediction(problem, sol.policy, rule).expected_cost) / stats.mean
                       for rule in ("second_order", "fifth_degree")]
            print(f"| {1e3 * delay:.0f} ms | {j + 1} | " + " | ".join(f"{r:.3g}" for r in ratios)
                  + f" | {stats.mean:.3g} | {stats.mean / stats.median:.3g} |", flush=True)


if __name__ == "__main__":
    main([float(d) for d in sys.argv[1].split(",")], int(sys.argv[2]))
