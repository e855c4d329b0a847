"""Where the muscle arm's Monte Carlo cost leaves the prediction (docs/results/noise_calibration.md §5):
for one reach, the cost split (effort, final position, final velocity), the hand's deviation from the
nominal over time (nonlinear plant, the plant without limits, the linear closed loop), and how far the
activations leave the nominal, where the force-activation curve A(a) ~ a^N_f is far from linear.

    .venv/bin/python benchmarks/studies/muscle_gap_anatomy.py DELAY_MS TARGET SIGMA TRIALS DESIGN
"""
import sys

import jax
jax.config.update("jax_enable_x64", True)
import delayed_ilqr; delayed_ilqr.configure_cpu()
import jax.numpy as jnp
import numpy as np
from delayed_ilqr import Options, simulate, solve
from delayed_ilqr.experiments import designs
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.lqg import Gains, simulate_lqg
from delayed_ilqr.models.arm2 import hand_position, hand_velocity
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets, rest_commands

delay_ms, j, sigma, n, name = float(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
target = tuple(center_out_targets(8, 0.1)[j - 1])
plant = arm2_muscle6(**LI_TODOROV, delay=delay_ms / 1e3, target=target, noise=True, sigma_u=sigma)
problem, options = designs.design(plant, name, Options(max_iterations=300))
sol = solve(problem, u_init=rest_commands(plant), options=options)
pol = sol.policy
p = plant.cost.params
hand = jax.vmap(jax.vmap(lambda x: hand_position(x[:2])))
speed = jax.vmap(jax.vmap(lambda x: hand_velocity(x[:2], x[2:4])))


def split(xs, us):
    xs, us = jnp.asarray(xs), jnp.asarray(us)
    effort = plant.dt * p["r"] * jnp.sum(us ** 2, axis=(1, 2))
    e = hand(xs[:, -1:])[:, 0] - p["target"]
    v = speed(xs[:, -1:])[:, 0]
    return [np.mean(np.asarray(t)) for t in (effort, p["w_p"] * jnp.sum(e ** 2, 1), p["w_v"] * jnp.sum(v ** 2, 1))]


runs = simulate(plant, pol, n, seed=j)
free = simulate(plant.replace(u_min=None, u_max=None), pol, n, seed=j)
lqg = linearize(plant, pol.x_nominal, pol.u_nominal)
lin = simulate_lqg(lqg, Gains(jnp.zeros_like(pol.feedforward), pol.state_feedback, pol.delay_feedback), n, seed=j)
lin_x = pol.x_nominal[None] + lin.dx
lin_u = pol.u_nominal[None] + lin.du
print("cost split (effort, w_p |e|^2, w_v |v|^2):")
print("  nominal", ["%.3e" % c for c in split(pol.x_nominal[None], pol.u_nominal[None])])
for label, xs, us in (("MC", runs.x, runs.u), ("MCfree", free.x, free.u), ("linear", lin_x, lin_u)):
    print(f"  {label:7s}", ["%.3e" % c for c in split(xs, us)])
hb = hand(pol.x_nominal[None])[0]
print("RMS hand deviation from the nominal (mm) at t = 0.1 .. 0.5 s:")
for label, xs in (("MC", runs.x), ("MCfree", free.x), ("linear", lin_x)):
    dev = np.sqrt(np.mean(np.sum((np.asarray(hand(jnp.asarray(xs))) - np.asarray(hb)) ** 2, -1), 0))
    print(f"  {label:7s}", " ".join(f"{1e3 * dev[k]:7.2f}" for k in range(10, 51, 10)),
          f"| 99th pct final {1e3 * np.percentile(np.linalg.norm(np.asarray(hand(jnp.asarray(xs[:, -1:])))[:, 0] - np.asarray(hb[-1]), axis=-1), 99):.2f}")
a_bar = np.asarray(pol.x_nominal[:, 4:])
print("nominal activations: fraction of (step, muscle) with a_bar < 0.01:", round(float(np.mean(a_bar < 0.01)), 3),
      " min", float(a_bar.min()))
for label, xs in (("MC", runs.x), ("MCfree", free.x), ("linear", lin_x)):
    a = np.asarray(xs)[:, :, 4:]
    rel = np.abs(a - a_bar) / np.maximum(a_bar, 1e-12)
    print(f"  {label:7s} |a - a_bar| / a_bar: median {np.median(rel):.3f}, 90th pct {np.percentile(rel, 90):.3f};"
          f" fraction with a <= 0: {np.mean(a <= 0):.4f}; trials with any a <= 0: {np.mean(np.any(a <= 0, axis=(1, 2))):.3f}")
u_bar = np.asarray(pol.u_nominal)
print("nominal excitations: fraction at the bound (< 1e-5):", round(float(np.mean(u_bar < 1e-5)), 3),
      " in (1e-5, 0.01):", round(float(np.mean((u_bar >= 1e-5) & (u_bar < 0.01))), 3))
gain = np.abs(np.asarray(pol.state_feedback)).sum(-1)
print("feedback on commands with nominal < 1e-5 (should be 0):", float(gain[u_bar < 1e-5].max(initial=0)),
      "; on (1e-5, 0.01):", float(gain[(u_bar >= 1e-5) & (u_bar < 0.01)].max(initial=0)))
