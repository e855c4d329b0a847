"""Why replaying the planned history holds the planar quadrotor on a plant two steps slower than
the model (docs/results/mpc_baselines.md, planar quadrotor at 20 ms): the delay margin of each
compensation and the gain of the command it sends.

1. The delay margin: each controller of the 20 ms model (l = 2 ticks) against plants whose true
   delay is 0..6 ticks, and of a 40 ms model (l = 4) against plants of 2..4 ticks; the same
   trials as ``run_scenario`` (seed 0). Per plant: median cost, failure rate, RMS roll over the
   second half of the run (a limit cycle shows there).
2. The gain: d(T_1 - T_2)/d(roll) and d(T_1 - T_2)/d(roll rate) of the command each controller
   sends from hover at the waypoint, nothing in flight, a converged tick (40 iterations), by
   central differences.

Run ``python benchmarks/mpc_quadrotor_delay_margin.py [--trials 4]``: about 8 minutes on the
shared 2-core machine under load.
"""
from __future__ import annotations

import argparse

import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr import mpc
from delayed_ilqr.experiments.mpc_baselines import SCENARIOS

CONTROLLERS = (("predict", "predict", "sent"), ("replay (planned)", "replay", "planned"),
               ("inflight", "inflight", "sent"), ("none", "none", "sent"))


def margin(model_delay, plant_delays, n_trials, controllers=CONTROLLERS):
    scenario = SCENARIOS["planar_quadrotor"]
    model = scenario.model(model_delay)
    rng = np.random.default_rng(0)
    x0 = np.asarray(model.x0) + rng.standard_normal((n_trials, model.n_states)) * np.asarray(scenario.spread)
    plants = [model.replace(delay_steps=lp, delay_frame=max(plant_delays)) for lp in plant_delays]
    for label, compensation, history in controllers:
        ctrl = mpc.MPC(model, compensation=compensation, replay_history=history)
        runs = mpc.simulate(ctrl, plants, ticks=scenario.ticks, n_trials=n_trials, seed=0, x0=x0,
                            failure=scenario.failure, bound=scenario.bound)
        roll = np.asarray(runs.x)[..., scenario.ticks // 2:, 2]
        cells = [f"{np.median(np.asarray(runs.cost[i])):.3g} / {np.mean(np.asarray(runs.failed[i])):.0%} / "
                 f"{np.sqrt(np.mean(roll[i] ** 2)):.3f} rad" for i in range(len(plant_delays))]
        print(f"| {model.delay_steps} | {label} | " + " | ".join(cells) + " |", flush=True)


def gains(model_delay):
    model = SCENARIOS["planar_quadrotor"].model(model_delay)
    hover = np.asarray(model.cost.x_target, float)
    model = model.replace(x0=hover)
    for label, compensation, history in CONTROLLERS:
        ctrl = mpc.MPC(model, iterations=40, compensation=compensation, replay_history=history)
        state, g = ctrl.init(), []
        for index, eps in ((2, 0.02), (5, 0.1)):
            dx = np.zeros(6)
            dx[index] = eps
            up, down = (np.asarray(ctrl.step(state, hover + s * dx)[1].command) for s in (1, -1))
            g.append(((up[0] - up[1]) - (down[0] - down[1])) / (2 * eps))
        print(f"| {label} | {g[0]:.2f} N/rad | {g[1]:.3f} N s/rad |", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=4)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    print("median cost / failure rate / RMS roll over the last second, per true delay (ticks)")
    margin(0.02, (0, 1, 2, 3, 4, 5, 6), args.trials)
    margin(0.04, (2, 3, 4), args.trials, CONTROLLERS[:3])
    print("\ngain of the command sent on the roll, 20 ms model")
    gains(0.02)


if __name__ == "__main__":
    main()
