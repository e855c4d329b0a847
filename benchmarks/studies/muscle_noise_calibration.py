"""Endpoint spread of the six-muscle arm's center-out reaches against the noise level
(docs/results/noise_calibration.md §1).

    .venv/bin/python benchmarks/studies/muscle_noise_calibration.py SIGMAS [DELAYS] [TRIALS]
    e.g. ... 0.01,0.02 0,0.1 200
"""
import sys, time, jax
jax.config.update("jax_enable_x64", True)
import delayed_ilqr; delayed_ilqr.configure_cpu()
import numpy as np
from delayed_ilqr.experiments import center_out as co
sig = [float(s) for s in sys.argv[1].split(",")]
delays = [float(d) for d in (sys.argv[2] if len(sys.argv) > 2 else "0").split(",")]
n = int(sys.argv[3]) if len(sys.argv) > 3 else 200
for s in sig:
    t0 = time.time()
    res = co.center_out(delays, 8, 0.1, n, 0, sigma_u=s)
    for r in res:
        sp = [t.spread*1e3 for t in r.targets]
        he = [t.hand_error*1e3 for t in r.targets]
        print(f"sigma {s:g} delay {r.delay:g} {r.design:13s} conv {sum(t.converged for t in r.targets)}/8 its {[t.iterations for t in r.targets]} "
              f"spread mm mean {np.mean(sp):.2f} [{min(sp):.2f},{max(sp):.2f}] nominal err max {max(he):.2f} "
              f"pred {np.mean([t.predicted_cost for t in r.targets]):.4g} mc {np.mean([t.mc_cost.mean() for t in r.targets]):.4g} "
              f"mcerr {np.mean([t.mc_error.mean() for t in r.targets])*1e3:.2f}", flush=True)
    print("time", time.time()-t0, flush=True)
