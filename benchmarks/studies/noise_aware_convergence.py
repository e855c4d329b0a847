"""Does every noise-aware center-out reach converge?

The grid: 8 hand targets on a 10 cm circle x delays 0, 50, 100, 150 ms x noise 0.5x, 1x, 2x the
default x both arm models -- ``arm2_muscle6`` (default sigma_u = SIGMA_U = 0.01) and the torque arm
``arm2`` with its signal-dependent noise at the human level (default SIGMA_U_HUMAN = 0.01; targets
by inverse kinematics, elbow up as at x0). Each (model, noise, delay) is one batched solve of the
8 reaches with the center-out study's options (``experiments.center_out.DEFAULT_OPTIONS``).
Prints one row per (model, noise, delay): converged count, statuses, iterations median / max, and
the wall time of the batched call (compilation included, first call).

    PYTHONPATH=src .venv/bin/python benchmarks/studies/noise_aware_convergence.py [MODELS] [FACTORS] [DELAYS] [OUT.json] [WIDTH]
    e.g. ... muscle,arm2 0.5,1,2 0,0.05,0.1,0.15 /tmp/grid.json

WIDTH (optional) replaces ``models.muscle.SWITCH_WIDTH`` for the run (derivation §12, cause 4).
"""
import json
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import delayed_ilqr  # noqa: E402

delayed_ilqr.configure_cpu()
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from delayed_ilqr import Status, solve  # noqa: E402
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, SIGMA_U, arm2_muscle6, center_out_targets  # noqa: E402
from delayed_ilqr.models import muscle  # noqa: E402
from delayed_ilqr.models.arm2 import ARM2_PARAMS, SIGMA_U_HUMAN, arm2  # noqa: E402
from delayed_ilqr.models.metadata import default_u_init  # noqa: E402

TARGETS = center_out_targets(8, 0.1)
X0_ARM2 = (np.pi / 4, np.pi / 2, 0.0, 0.0)
DEFAULT_SIGMA = {"muscle": SIGMA_U, "arm2": SIGMA_U_HUMAN}


def joint_target(hand, p=ARM2_PARAMS):
    """Joint angles (elbow up, q2 > 0) that put the hand at ``hand`` (analytic inverse kinematics)."""
    x, y = hand
    q2 = np.arccos((x * x + y * y - p.l1 ** 2 - p.l2 ** 2) / (2 * p.l1 * p.l2))
    q1 = np.arctan2(y, x) - np.arctan2(p.l2 * np.sin(q2), p.l1 + p.l2 * np.cos(q2))
    return (q1, q2, 0.0, 0.0)


def problems(model, sigma, delay):
    if model == "muscle":
        return [arm2_muscle6(**LI_TODOROV, delay=delay, target=tuple(t), noise=True, sigma_u=sigma) for t in TARGETS]
    return [arm2(delay=delay, noise=True, sigma_u=sigma, x0=X0_ARM2, x_target=joint_target(t)) for t in TARGETS]


_batched = jax.jit(jax.vmap(solve, in_axes=(0, None, None)), static_argnums=2)


def run(model, factor, delay, options=DEFAULT_OPTIONS):
    ps = problems(model, factor * DEFAULT_SIGMA[model], delay)
    u0 = default_u_init(ps[0])
    u0 = jnp.zeros((ps[0].horizon, ps[0].n_controls)) if u0 is None else u0
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *ps)
    t0 = time.perf_counter()
    sol = jax.block_until_ready(_batched(stacked, u0, options))
    seconds = time.perf_counter() - t0
    status = [Status(int(s)).name for s in np.asarray(sol.status)]
    it = np.asarray(sol.iterations)
    return dict(model=model, factor=factor, delay=delay, seconds=seconds, status=status, iterations=it.tolist(),
                cost=np.asarray(sol.cost).tolist(), expected_cost=np.asarray(sol.expected_cost).tolist(),
                merit=np.asarray(sol.trace.merit).tolist(), reg=np.asarray(sol.trace.reg).tolist(),
                grad_norm=np.asarray(sol.trace.grad_norm).tolist())


def main(argv):
    models = argv[1].split(",") if len(argv) > 1 else ["muscle", "arm2"]
    factors = [float(f) for f in argv[2].split(",")] if len(argv) > 2 else [0.5, 1.0, 2.0]
    delays = [float(d) for d in argv[3].split(",")] if len(argv) > 3 else [0.0, 0.05, 0.1, 0.15]
    out = argv[4] if len(argv) > 4 else None
    if len(argv) > 5:
        muscle.SWITCH_WIDTH = float(argv[5])
    rows = []
    print("| model | noise | delay (ms) | converged | statuses | iterations median / max | time (s) |")
    print("|---|---|---|---|---|---|---|")
    for model in models:
        for factor in factors:
            for delay in delays:
                r = run(model, factor, delay)
                rows.append(r)
                conv = sum(Status[s].converged for s in r["status"])
                names = {s: r["status"].count(s) for s in sorted(set(r["status"]))}
                print(f"| {model} | {factor:g}x | {1e3 * delay:g} | {conv}/8 | "
                      + ", ".join(f"{k} {v}" for k, v in names.items())
                      + f" | {np.median(r['iterations']):g} / {max(r['iterations'])} | {r['seconds']:.1f} |", flush=True)
                if out:
                    with open(out, "w") as f:
                        json.dump(rows, f)
    total = sum(sum(Status[s].converged for s in r["status"]) for r in rows)
    print(f"converged {total}/{8 * len(rows)}; time {sum(r['seconds'] for r in rows):.0f} s")


if __name__ == "__main__":
    main(sys.argv)
