"""Why the muscle arm's Monte Carlo mean leaves the predicted expected cost with delay
(docs/results/noise_calibration.md §5). Read-only diagnostics: for one reach (delay, target, design)
it compares, on the SAME returned policy,

  pred   Solution.expected_cost (J(0) of the solver's last LQG)
  exact  lqg.policy_cost of the policy's gains (feedforward 0) on the LQG around its nominal
  linMC  lqg.simulate_lqg of the same linear closed loop
  MC     simulate on the plant (clipped to [0, 1], as in the study)
  MCfree simulate on the plant with the limits removed (the same policy, commands not clipped)

and, per Monte Carlo trial, the fraction of commands the plant clipped (the law asked for u < 0 or
u > 1) with its correlation with the trial's cost.

    .venv/bin/python benchmarks/studies/muscle_prediction_gap.py DELAY_MS TARGETS SIGMA TRIALS DESIGN [PLANT_SIGMAS]
    e.g. ... 50 1,2,3,4,5,6,7,8 0.01 2000 noise-aware
         ... 50 8 0.01 1000 noise-aware 0.01,0.001,0.0001   (the same policy on plants of other noise)

U_FLOOR=0.05 raises the lower excitation limit (design and plant) to 0.05 (a tonic co-activation floor).
LIMIT_MARGIN=0.01 in the environment designs with Options(limit_margin=0.01) (default 1e-5).
"noise excess" compares the parts due to noise: (MC - nominal cost) / (exact - nominal cost).
"""
import os
import sys
import time

import jax
jax.config.update("jax_enable_x64", True)
import delayed_ilqr; delayed_ilqr.configure_cpu()
import jax.numpy as jnp
import numpy as np
from delayed_ilqr import Options, simulate, solve
from delayed_ilqr.experiments import designs
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.lqg import Gains, policy_cost, simulate_lqg
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets, rest_commands


def unclipped_commands(policy, runs, l):
    """[N, K, d] the law's commands before clipping, recomputed from the trials' states and sent commands."""
    xs, us = np.asarray(runs.x[:, :-1]), np.asarray(runs.u)
    xb, ub = np.asarray(policy.x_nominal[:-1]), np.asarray(policy.u_nominal)
    L, M = np.asarray(policy.state_feedback), np.asarray(policy.delay_feedback)
    du = np.einsum("kdn,tkn->tkd", L, xs - xb)
    dev = us - ub
    K = ub.shape[0]
    for k in range(K):
        for i in range(l):
            j = k + i - l
            if j >= 0:
                du[:, k] += dev[:, j] @ M[k, i].T
    return ub + du


def one(delay_ms, j, sigma, n, name, plant_sigmas=None):
    target = tuple(center_out_targets(8, 0.1)[j - 1])
    floor = float(os.environ.get("U_FLOOR", 0.0))
    plant = arm2_muscle6(**LI_TODOROV, delay=delay_ms / 1e3, target=target, noise=True, sigma_u=sigma).replace(u_min=floor)
    margin = float(os.environ.get("LIMIT_MARGIN", Options().limit_margin))
    problem, options = designs.design(plant, name, Options(max_iterations=300, limit_margin=margin))
    sol = solve(problem, u_init=rest_commands(plant), options=options)
    for s in plant_sigmas or [sigma]:
        evaluate(arm2_muscle6(**LI_TODOROV, delay=delay_ms / 1e3, target=target, noise=True, sigma_u=s).replace(u_min=floor), sol, j, n, name,
                 f"{delay_ms:g}ms t{j} {name:13s} margin {margin:g} floor {floor:g} design sigma {sigma:g} plant sigma {s:g}")


def evaluate(plant, sol, j, n, name, label):
    """The policy of ``sol`` (designed elsewhere) on ``plant``: the comparisons of the module docstring."""
    pol = sol.policy
    nominal = float(sol.cost) if name == "deterministic" else float(
        plant.replace(noise=None).cost.final(pol.x_nominal[-1]) + plant.dt * jnp.sum(
            jax.vmap(plant.cost.running)(pol.x_nominal[:-1], pol.u_nominal)))
    lqg = linearize(plant, pol.x_nominal, pol.u_nominal)
    gains = Gains(jnp.zeros_like(pol.feedforward), pol.state_feedback, pol.delay_feedback)
    exact = float(policy_cost(lqg, gains))
    lin = np.asarray(simulate_lqg(lqg, gains, n, seed=j).cost)
    runs = simulate(plant, pol, n, seed=j)
    mc = np.asarray(runs.cost)
    free = plant.replace(u_min=None, u_max=None)
    mc_free = np.asarray(simulate(free, pol, n, seed=j).cost)
    raw = unclipped_commands(pol, runs, plant.delay_steps)
    clipped = (raw < np.asarray(plant.u_min) - 1e-12) | (raw > 1 + 1e-12)
    frac = clipped.reshape(n, -1).mean(axis=1)
    ub = np.asarray(pol.u_nominal)
    at_bound = float(np.mean(ub < np.asarray(plant.u_min) + 1e-5))
    corr = float(np.corrcoef(frac, mc)[0, 1]) if frac.std() > 0 else float("nan")
    top = np.argsort(mc)[-n // 10:]
    excess = (mc.mean() - nominal) / (exact - nominal)
    excess_free = (np.nanmean(mc_free) - nominal) / (exact - nominal)
    print(f"{label} st {int(sol.status)} it {int(sol.iterations):3d} | nominal {nominal:.3e} pred {float(sol.expected_cost):.3e} "
          f"exact {exact:.3e} linMC {lin.mean():.3e} MC {mc.mean():.3e} (med {np.median(mc):.3e}) "
          f"MCfree {np.nanmean(mc_free):.3e} (nan {int(np.sum(~np.isfinite(mc_free)))}) | MC/exact {mc.mean() / exact:.1f} "
          f"free/exact {np.nanmean(mc_free) / exact:.2f} | noise excess MC/exact {excess:.1f} free/exact {excess_free:.2f} | nominal<1e-5 {at_bound:.2f} clipped/trial {frac.mean():.3f} "
          f"(top10% {frac[top].mean():.3f}, trials with any {np.mean(frac > 0):.2f}) corr(clip,cost) {corr:.2f}",
          flush=True)


if __name__ == "__main__":
    delay_ms = float(sys.argv[1])
    targets = [int(t) for t in sys.argv[2].split(",")]
    sigma, n, name = float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
    plant_sigmas = [float(s) for s in sys.argv[6].split(",")] if len(sys.argv) > 6 else None
    t0 = time.time()
    for j in targets:
        one(delay_ms, j, sigma, n, name, plant_sigmas)
    print("elapsed", round(time.time() - t0, 1), "s")
