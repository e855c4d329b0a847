"""Motor delays identified from reaches: per-channel delays of 50-150 ms recovered by gradient with
the noise level and the effort weight (docs/fitting.md, "Delays identified from data").

The torque arm (``arm2``, the human noise preset sigma_u = 0.01, K = 60 steps of 10 ms, four
joint-space targets) with effort weight r (Q = r I; the final weights fixed: only ratios of weights
are identifiable) and a motor delay per joint that is not a whole number of steps. For each row of
true delays:

1. data: TRIALS reaches per target of the nonlinear plant (``di.simulate``) under the optimal policy
   at the truth; their mean hand paths and endpoint covariances; the mean's precision s is the
   standard error of a mean endpoint coordinate;
2. the fit (``experiments.delay_fitting.fit_delays``, one delay per channel) from 100 ms on both
   joints, sigma_u and r 50 % off, by L-BFGS-B on the implicit gradients through the fractional
   delay (docs/derivation.md §20), ending when an iteration gains less than FTOL = 1e-7 of the
   loss;
3. 95 % intervals by a parametric bootstrap: REPLICATES new data sets of TRIALS reaches per target
   from the fitted model, each fitted again from the estimate.

Every row, fit and replicate shares one compilation (one frame of 18 slots holds delays to 170 ms).
Prints the recovery table of docs/fitting.md.

Run: .venv/bin/python benchmarks/studies/delay_recovery.py [--trials 100] [--replicates 8]
"""
import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.experiments import delay_fitting, fitting
from delayed_ilqr.models import arm2

jax.config.update("jax_enable_x64", True)

W_P = 1e3
TRUTH = dict(r=1e-4, sigma_u=0.01)
START = dict(r=1.5e-4, sigma_u=0.015)
DELAY0, MAX_DELAY = 0.1, 0.17
FTOL = 1e-7          # L-BFGS-B ends when an iteration decreases the loss by less than this (relative)
ROWS = [(0.054, 0.071), (0.1035, 0.0875), (0.148, 0.1265)]      # s, shoulder and elbow
TARGETS = jnp.array([[np.pi / 2, np.pi / 3, 0.0, 0.0], [1.2, 1.4, 0.0, 0.0], [1.0, 2.0, 0.0, 0.0],
                     [1.6, 1.0, 0.0, 0.0]])


def reach(params, target, delay):
    """The human-noise torque arm (K = 60) reaching ``target`` with effort weight r and noise sigma_u."""
    base = arm2(delay=delay, noise="human", horizon=60)
    cost = base.cost._replace(Q=params["r"] * jnp.eye(2), P_final=jnp.diag(jnp.array([W_P, W_P, 10.0, 10.0])),
                              x_target=target)
    return base.replace(cost=cost, noise=dataclasses.replace(base.noise, sigma_u=params["sigma_u"]))


def sampled_data(model, params, trials, seed):
    """(ReachData of TRIALS reaches per target of the nonlinear plant, s the mean's precision)."""
    stats = []
    for c in range(TARGETS.shape[0]):
        problem = model(params, TARGETS[c])
        runs = di.simulate(problem, di.solve(problem).policy, trials, seed=seed + c)
        stats.append(fitting.observed_reach(problem, runs))
    data = fitting.ReachData(jnp.asarray(np.stack([s[0] for s in stats])), jnp.asarray(np.stack([s[1] for s in stats])))
    scale = float(np.sqrt(np.mean([np.trace(s[1]) / 2 for s in stats]) / trials))
    return data, scale


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--replicates", type=int, default=8, help="0: the fits alone, no intervals")
    parser.add_argument("--rows", type=str, default="0,1,2", help="which rows of ROWS, e.g. 1,2")
    args = parser.parse_args()
    model = delay_fitting.DelayedModel(reach, DELAY0, delay_fitting._frame_for(MAX_DELAY, 0.01, 60), per_channel=True)
    bounds = {"delay_0": (None, MAX_DELAY), "delay_1": (None, MAX_DELAY)}
    print("| true delays [ms] | fitted [ms] | error [ms] | 95 % bootstrap interval [ms] | sigma_u | r | "
          "evaluations | time [s] |")
    print("|---|---|---|---|---|---|---|---|")
    for row in (int(r) for r in args.rows.split(",")):
        delays = ROWS[row]
        start = time.perf_counter()
        truth = dict(TRUTH, delay_0=delays[0], delay_1=delays[1])
        data, scale = sampled_data(model, truth, args.trials, seed=1000 * row)
        result, fitted_model = delay_fitting.fit_delays(reach, TARGETS, data, START, DELAY0, MAX_DELAY,
                                                        per_channel=True, mean_scale=scale, ftol=FTOL)
        assert fitted_model == model
        if args.replicates == 0:
            fitted = [result.params[f"delay_{j}"] for j in range(2)]
            print(f"| {1e3 * delays[0]:.1f}, {1e3 * delays[1]:.1f} | {1e3 * fitted[0]:.2f}, {1e3 * fitted[1]:.2f} | "
                  f"{result.evaluations} ({'converged' if result.converged else 'not converged'}) | "
                  f"{time.perf_counter() - start:.0f} | {result.message}", flush=True)
            continue
        boot = delay_fitting.bootstrap(model, TARGETS, result, args.trials, args.replicates, seed=1000 * row + 100,
                                       mean_scale=scale, bounds=bounds, ftol=FTOL)
        elapsed = time.perf_counter() - start
        fitted = [result.params[f"delay_{j}"] for j in range(2)]
        print(f"| {1e3 * delays[0]:.1f}, {1e3 * delays[1]:.1f} | {1e3 * fitted[0]:.2f}, {1e3 * fitted[1]:.2f} | "
              f"{1e3 * (fitted[0] - delays[0]):+.2f}, {1e3 * (fitted[1] - delays[1]):+.2f} | "
              + ", ".join(f"[{1e3 * boot.low[f'delay_{j}']:.1f}, {1e3 * boot.high[f'delay_{j}']:.1f}]" for j in range(2))
              + f" | {result.params['sigma_u']:.4f} [{boot.low['sigma_u']:.4f}, {boot.high['sigma_u']:.4f}] | "
              f"{result.params['r']:.3g} | {result.evaluations} ({'converged' if result.converged else 'not converged'},"
              f" {int(boot.converged.sum())}/{args.replicates} replicates) | {elapsed:.0f} |", flush=True)


if __name__ == "__main__":
    main()
