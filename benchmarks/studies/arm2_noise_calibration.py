"""The P2 reach (arm2) at a given signal-dependent noise level: noise-aware and deterministic
designs, Monte Carlo on the noisy plant (docs/results/noise_calibration.md §2).

    .venv/bin/python benchmarks/studies/arm2_noise_calibration.py SIGMAS DELAYS TRIALS [EXTRA_STEPS]
    e.g. ... 0.01 0,0.05,0.1,0.15 2000
"""
import sys, jax
jax.config.update("jax_enable_x64", True)
import delayed_ilqr as di; di.configure_cpu()
import numpy as np, jax.numpy as jnp
from delayed_ilqr.models import arm2
from delayed_ilqr.models.arm2 import hand_position, hand_velocity, Arm2Noise, ARM2_PARAMS
sig = [float(s) for s in sys.argv[1].split(",")]
delays = [float(d) for d in sys.argv[2].split(",")]
n = int(sys.argv[3]); horizon_extra = int(sys.argv[4]) if len(sys.argv) > 4 else 0
for s in sig:
  for tau in delays:
    p = arm2(delay=tau, noise="benchmark")
    p = p.replace(noise=Arm2Noise(ARM2_PARAMS, s))
    if horizon_extra: p = p.replace(horizon=p.horizon + p.delay_steps)
    for name, des in (("noise-aware", p), ("deterministic", p.replace(noise=None))):
        sol = di.solve(des)
        runs = di.simulate(p, sol.policy, n, seed=0)
        x = np.asarray(runs.x[:, -1]); tgt = np.asarray(hand_position(jnp.asarray(p.cost.x_target[:2])))
        e = np.asarray(hand_position(jnp.asarray(x[:, :2]))); fin = np.all(np.isfinite(e), 1)
        cov = np.cov(e[fin].T); sp = np.sqrt(np.linalg.eigvalsh(cov).max())*1e3
        xn = np.asarray(sol.x[-1]); en = np.asarray(hand_position(jnp.asarray(xn[:2])))
        vn = np.linalg.norm(np.asarray(hand_velocity(jnp.asarray(xn[:2]), jnp.asarray(xn[2:4]))))
        c = np.asarray(runs.cost)
        print(f"s {s:g} tau {tau:g} {name:13s} {di.Status(int(sol.status)).name} it {int(sol.iterations)} nomerr {np.linalg.norm(en-tgt)*1e3:.2f}mm speed {vn*100:.2f}cm/s pred {float(sol.expected_cost):.4g} mc {np.mean(c[np.isfinite(c)]):.4g} med {np.median(c):.4g} max {np.max(c):.3g} div {np.sum(~np.isfinite(c))} spread {sp:.2f}mm", flush=True)
