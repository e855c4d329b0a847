"""The six-muscle arm's center-out study with the calibrated noise
(docs/results/noise_calibration.md §3): 8 targets x delays, TRIALS per target; one row per delay
and design, then per-target details.

    .venv/bin/python benchmarks/studies/muscle_center_out_results.py SIGMA DELAYS TRIALS
    e.g. ... 0.01 0,0.05,0.1,0.15 2000
"""
import sys, time, jax
jax.config.update("jax_enable_x64", True)
import delayed_ilqr; delayed_ilqr.configure_cpu()
from delayed_ilqr.experiments import center_out as co, tables
sigma = float(sys.argv[1]); delays = [float(d) for d in sys.argv[2].split(",")]; n = int(sys.argv[3])
t0 = time.time()
res = co.center_out(delays, 8, 0.1, n, 0, sigma_u=sigma)
print(tables.markdown_table(tables.center_out_rows(res)))
for r in res:
    for j, t in enumerate(r.targets):
        cs = t.cost_stats
        print(f"{1e3*r.delay:g}ms {r.design:13s} target {j+1} {t.status:22s} it {t.iterations:3d} err {1e3*t.hand_error:.2f}mm "
              f"speed {1e2*t.hand_speed:.2f}cm/s pred {t.predicted_cost:.3g} mc {cs.mean:.3g} [{cs.ci95[0]:.3g},{cs.ci95[1]:.3g}] "
              f"ratio {cs.mean/t.predicted_cost:.2f} med {cs.median:.3g} div {cs.n_diverged} spread {1e3*t.spread:.2f}mm")
print("elapsed", time.time() - t0)
