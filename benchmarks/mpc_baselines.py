"""The compensations of actuation delay in receding-horizon control, compared in closed loop
(``delayed_ilqr.experiments.mpc_baselines``): cart-pole balancing, the two-link arm tracking a
moving target, the planar quadrotor flying to a waypoint; each at several actuation delays,
against plants that match the model, differ by +-20 % in their inertial parameters, or have a true
delay two steps off. Prints one markdown table per scenario (median cost / failure rate / RMS
tracking error) and, with ``--out FILE``, writes them there.

Run ``python benchmarks/mpc_baselines.py [--trials 16] [--scenario NAME ...] [--out FILE]``: 5 to
25 minutes per scenario with 12 trials on the shared 2-core machine under load (one compilation
per controller and model delay), and over an hour for the quadrotor, whose thrust limits put the
box-constrained solver in every tick. The measured tables are in docs/results/mpc_baselines.md.
"""
from __future__ import annotations

import argparse
import time

import jax

import delayed_ilqr as di
from delayed_ilqr.experiments import mpc_baselines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=1)
    parser.add_argument("--scenario", action="append", choices=sorted(mpc_baselines.SCENARIOS))
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    text = []
    for name in args.scenario or list(mpc_baselines.SCENARIOS):
        t = time.perf_counter()
        rows = mpc_baselines.run_scenario(mpc_baselines.SCENARIOS[name], n_trials=args.trials, seed=args.seed,
                                          iterations=args.iterations)
        table = mpc_baselines.markdown(rows)
        print(table, f"({time.perf_counter() - t:.0f} s)\n", flush=True)
        text.append(table)
        if args.out:
            with open(args.out, "w") as f:
                f.write("\n".join(text))


if __name__ == "__main__":
    main()
