"""The designs' ordering at no delay: is the noise-aware design's Monte Carlo advantage on the six-muscle
arm the noise, or target 5's local minimum (docs/results/reach_shape.md §5)?

Runs the center-out study at 0 ms with both designs (``center_out(delays=(0,), designs=("noise-aware",
"deterministic"))``, 8 targets, TRIALS trials, seed 0: every design meets the same noise) and prints
per target the two Monte Carlo means with their bootstrap 95 % intervals, the mean of the
per-trial differences (the same noise drives both designs' trial i) with two standard errors, and
the noise-free nominal costs; then re-solves the deterministic design of target 5 warm-started from the noise-aware
commands (where it reaches the curved optimum instead of the straight local minimum it reaches
from rest) and runs it on the same noise.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/zero_delay_ordering.py [TRIALS]   (default 2000)
"""
import sys

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.experiments import center_out as co, designs  # noqa: E402
from delayed_ilqr.experiments.engine import monte_carlo  # noqa: E402
from delayed_ilqr.statistics import divergence_bound, diverged_trials, sample_stats  # noqa: E402

TARGET = 5       # the reach whose deterministic solve from rest stops at a local minimum


def _paired(deterministic_cost, aware_cost) -> str:
    """The mean of the per-trial differences (same noise in both) +- 2 standard errors, relative to
    the noise-aware mean."""
    diff = np.asarray(deterministic_cost) - np.asarray(aware_cost)
    mean = np.mean(aware_cost)
    return f"{np.mean(diff) / mean:+.2e} +- {2 * np.std(diff, ddof=1) / np.sqrt(diff.size) / mean:.1e}"


def _interval(stats) -> str:
    return f"{stats.mean:.5g} [{stats.ci95[0]:.5g}, {stats.ci95[1]:.5g}]"


def main(n_trials: int) -> None:
    aware, deterministic = co.center_out(delays=(0.0,), n_trials=n_trials, seed=0,
                                         designs=("noise-aware", "deterministic"))
    print("| target | noise-aware MC mean [95 % CI] | deterministic | (det - aware) / aware, paired | "
          "nominal cost noise-aware / deterministic |")
    print("|---|---|---|---|---|")
    for j, (a, d) in enumerate(zip(aware.targets, deterministic.targets)):
        print(f"| {j + 1} | {_interval(a.cost_stats)} | {_interval(d.cost_stats)} | {_paired(d.mc_cost, a.mc_cost)} "
              f"| {a.cost:.5g} / {d.cost:.5g} |")
    plant = deterministic.plants[TARGET - 1]
    problem, options = designs.design(plant, "deterministic", co.DEFAULT_OPTIONS)
    warm = di.solve(problem, aware.solutions.u[TARGET - 1], options=options)
    trials = monte_carlo(plant, warm.policy, n_trials, TARGET - 1)      # the study's seed of this target
    cost = np.asarray(trials.runs.cost)
    stats = sample_stats(cost, diverged_trials(cost, divergence_bound(plant)))     # the study's rule
    print(f"target {TARGET}, deterministic warm-started from the noise-aware commands: "
          f"{warm.status.name}, nominal {float(warm.cost):.5g}, MC mean {_interval(stats)}, "
          f"(det - aware) / aware {_paired(cost, aware.targets[TARGET - 1].mc_cost)}")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2000)
