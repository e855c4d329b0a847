"""The jittered backward pass, structured (``lqg.jittered_backward_pass``, derivation §21) against
its augmented reference (``lqg.jittered_augmented_pass``), on the same random problems: median wall
time after compilation and their ratio, measured in one run, for growing longest delays L.

Run: .venv/bin/python benchmarks/jitter_speed.py [--delays 5,10,20,40] [--horizon K] [--states n] [--controls d]
"""
import argparse
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import delayed_ilqr as di                     # noqa: E402
from delayed_ilqr import lqg                  # noqa: E402
from test_lqg import random_arrays            # noqa: E402  (tests/test_lqg.py: a random convex delayed LQG)
from timing import median_time                # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--delays", default="5,10,20,40")
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--states", type=int, default=4)
    parser.add_argument("--controls", type=int, default=2)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    K, n, d = args.horizon, args.states, args.controls
    print(f"K = {K}, n = {n}, d = {d}, p = 2; the delay uniform over 1..L\n")
    print("| L | structured [ms] | augmented [ms] | augmented / structured | max relative difference of J(0) |")
    print("|---|---|---|---|---|")
    for L in (int(v) for v in args.delays.split(",")):
        problem = lqg.DelayedLQG(**random_arrays(0, K, n, d, 2, L))
        jitter = di.DelayJitter(list(range(1, L + 1)), np.full(L, 1.0 / L))
        structured = median_time(lambda: lqg.jittered_backward_pass(problem, jitter))
        augmented = median_time(lambda: lqg.jittered_augmented_pass(problem, jitter), repeats=3)
        a = lqg.jittered_backward_pass(problem, jitter)[1].expected_cost
        b = lqg.jittered_augmented_pass(problem, jitter)[1].expected_cost
        print(f"| {L} | {1e3 * structured:.1f} | {1e3 * augmented:.1f} | {augmented / structured:.1f} "
              f"| {abs(float(a) - float(b)) / abs(float(b)):.1e} |")


if __name__ == "__main__":
    main()
