"""What a controller designed for the wrong motor delay costs (docs/fitting.md, "A wrong delay").

The torque arm (``arm2``, human noise preset, K = 60 steps of 10 ms) with a true motor delay of
TRUE ms on both joints. The optimal policy is designed for each assumed delay (whole steps or not:
the fractional delay of docs/derivation.md §20, all in one frame, one compilation) and run on the
true plant by Monte Carlo (TRIALS trials, the same noise samples for every design). Printed per
assumed delay: the mean cost with its 95 % interval and its ratio to the matched design's, the RMS
endpoint error of the hand, and the largest joint-velocity oscillation after the movement (the
RMS of dq over the last 100 ms), the signature of a feedback loop that compensates the wrong delay.

Run: .venv/bin/python benchmarks/studies/delay_mismatch.py [--trials 1000] [--true 0.1]
"""
import argparse
import time

import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.models import arm2

jax.config.update("jax_enable_x64", True)

ASSUMED = (0.06, 0.07, 0.08, 0.09, 0.095, 0.1, 0.105, 0.11, 0.12, 0.13, 0.14)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--true", type=float, default=0.1)
    args = parser.parse_args()
    plant = arm2(delay=args.true, noise="human", horizon=60)
    frame = int(np.ceil(max(ASSUMED) / plant.dt)) + 1
    task = plant.metadata.task
    target = np.asarray(task.map(plant.cost.x_target[None]))[0]
    rows, matched = [], None
    start = time.perf_counter()
    for assumed in ASSUMED:
        design = plant.replace(delay_steps=np.array(assumed / plant.dt), delay_frame=frame)
        sol = di.solve(design)
        runs = di.simulate(plant, sol.policy, args.trials, seed=7)
        cost = np.asarray(runs.cost)
        hand = np.asarray(task.map(runs.x[:, -1]))
        late = np.asarray(runs.x[:, -10:, 2:])
        rows.append((assumed, sol.status.converged, cost.mean(), 1.96 * cost.std(ddof=1) / np.sqrt(cost.size),
                     np.sqrt(np.mean(np.sum((hand - target) ** 2, axis=1))), np.sqrt(np.mean(late ** 2))))
        if abs(assumed - args.true) < 1e-12:
            matched = cost.mean()
    print(f"true delay {1e3 * args.true:g} ms, {args.trials} trials per design, {time.perf_counter() - start:.0f} s")
    print("| assumed delay [ms] | mean cost [95 % CI] | ratio to matched | RMS endpoint error [mm] | "
          "RMS joint velocity, last 100 ms [rad/s] |")
    print("|---|---|---|---|---|")
    for assumed, converged, mean, half, endpoint, late in rows:
        flag = "" if converged else " (design not converged)"
        print(f"| {1e3 * assumed:g}{flag} | {mean:.3g} [{mean - half:.3g}, {mean + half:.3g}] | {mean / matched:.3g} | "
              f"{1e3 * endpoint:.3g} | {late:.3g} |")


if __name__ == "__main__":
    main()
