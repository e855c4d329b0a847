"""Does the jittered solver's line search need the jitter-aware merit? (docs/results/jitter.md)

The jittered solve's line search scores each candidate nominal by its merit: the jittered LQG's
expected cost of the nominal under zero feedforward (the nominal cost (2) plus its noise cost and
its jitter cost sum_k sum_l p_l delta_kl' Phi_k delta_kl, derivation §21), as the fixed-delay
solver scores noise (§12). Here the same problems are solved with the line search on the nominal
cost alone, and both policies run on the same jittered trials (one seed: common random numbers).
Printed per case: status, iterations, nominal cost, expected cost (linearised), the Monte Carlo
mean of each and the paired difference (nominal-cost design minus merit design) with its 95 %
interval, over the trials finite under both.

Run: .venv/bin/python benchmarks/jitter_merit.py [--trials N] [--seed S] [--cases arm-narrow,arm-wide,cart-pole]
"""
import argparse
import time

import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.ilqg.jittered import _solve_jittered
from delayed_ilqr.statistics import divergence_bound

from jitter_study import CASES, paired


def compare(name, trials, seed):
    make, jitter = CASES[name]
    base = make()
    plant = base.replace(delay_steps=jitter.longest, delay_jitter=jitter)
    u0 = np.zeros((plant.horizon, plant.n_controls))
    rows, costs = {}, {}
    for label, aware in (("merit (jitter-aware)", True), ("nominal cost", False)):
        start = time.perf_counter()
        sol = _solve_jittered(plant, u0, di.Options(), aware=aware)
        elapsed = time.perf_counter() - start
        costs[label] = np.asarray(di.simulate(plant, sol.policy, trials, seed=seed).cost)
        rows[label] = (sol, elapsed)
    bound = divergence_bound(base)
    print(f"\n## {name}: {base.name}, delays {list(jitter.steps)} with p = {list(jitter.probabilities)}, "
          f"{trials} trials, seed {seed}\n")
    print("| line search | status | iterations | nominal cost | expected cost (linearised) | MC mean | "
          "minus merit design [95 % CI] | solve s (compile incl.) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, (sol, elapsed) in rows.items():
        c = costs[label]
        ok = np.isfinite(c) & (c <= bound)
        diff = "-" if label.startswith("merit") else "{:.4g} [{:.4g}, {:.4g}]".format(
            *paired(c, costs["merit (jitter-aware)"], bound))
        print(f"| {label} | {di.Status(int(sol.status)).name} | {int(sol.iterations)} | {float(sol.cost):.4g} | "
              f"{float(sol.expected_cost):.4g} | {c[ok].mean():.4g} ({(~ok).sum()} diverged) | {diff} | "
              f"{elapsed:.1f} |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", default=",".join(CASES))
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    for case in args.cases.split(","):
        compare(case, args.trials, args.seed)
