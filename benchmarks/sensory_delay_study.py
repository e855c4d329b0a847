"""The six-muscle arm with its motor delay fixed and proprioception seen
0-150 ms late.

The study: per sensory delay, the estimator-based design (the delayed Kalman filter made
for l_s) and one that ignores the sensory delay (the filter made for l_s = 0, run on the delayed
sensors), on the same trials: the expected cost (exact on the linearisation, aware design only),
the Monte Carlo cost, the endpoint spread and error of the hand, and the latency of the
correction of a lateral kick of the hand (first command that responds, half-peak of the mean
command response), ``experiments.sensing_study``.

The benchmark: what the sensors add to a solve. The output-feedback solve is the
full-state solve plus the filter's design and the exact cost of the pair at the returned nominal
(``ilqg.estimation.with_estimator``); both parts are timed (median wall time after compilation),
the full-state solve and the added design, on the same problem.

Run: .venv/bin/python benchmarks/sensory_delay_study.py [--trials N] [--delay S] [--sensory-delays a,b,...]
"""
import argparse

import jax

import delayed_ilqr as di
from delayed_ilqr.experiments import tables
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS
from delayed_ilqr.ilqg.estimation import with_estimator
from delayed_ilqr.experiments.sensing_study import sensory_delay_study, study_rows
from delayed_ilqr.models import arm2_muscle6, rest_commands
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV
from timing import median_time


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=500)
    parser.add_argument("--delay", type=float, default=0.05)
    parser.add_argument("--sensory-delays", default="0,0.05,0.1,0.15")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    delays = [float(v) for v in args.sensory_delays.split(",")]

    print(f"# study: arm2_muscle6, motor delay {args.delay:g} s, {args.trials} trials, seed {args.seed}")
    results = sensory_delay_study(delays, delay=args.delay, trials=args.trials, seed=args.seed,
                                  options=DEFAULT_OPTIONS)
    print(tables.markdown_table(tables.records_table(study_rows(results))))

    print("\n# benchmark: median wall time after compilation [s]")
    rows = []
    for ls in delays:
        plant = arm2_muscle6(**{**LI_TODOROV, "sensory_delay": ls}, delay=args.delay)
        full = plant.replace(observation=None)
        u0 = rest_commands(plant)
        t_full = median_time(lambda: di.solve(full, u_init=u0, options=DEFAULT_OPTIONS))
        sol = di.solve(full, u_init=u0, options=DEFAULT_OPTIONS)
        t_design = median_time(lambda: with_estimator(plant, sol, DEFAULT_OPTIONS))
        rows.append({"sensory delay [ms]": 1000 * ls, "iterations": int(sol.iterations),
                     "full-state solve": t_full, "filter design + exact cost": t_design,
                     "added": t_design / t_full})
    print(tables.markdown_table(tables.records_table(rows)))


if __name__ == "__main__":
    main()
