"""Swing-ups from rest with limits (issue 21): the acrobot rows of docs/derivation.md §15.

For each elbow limit, ``models.acrobot(u_max=...)`` (trajax's acrobot, dt = 0.1 s, K = 50):

- "from rest": ``solve`` from u_init = 0 with ``Options(max_iterations=1000)``: iterations, status, cost;
- "several starts": the same solve from rest, from the clipped unbounded optimum and from the
  clipped solution at the default 5 N m, run at once under ``jax.vmap``; the cheapest, and which
  start gave it;
- "L-BFGS-B": bounded L-BFGS-B (``tests/direct.py``) from zero and from ``STARTS - 1`` uniform
  random starts in the box (``numpy.random.default_rng(0)``): the cost from zero, the best, and
  how many of the starts reached the best (to 1e-6).

Run ``python benchmarks/swing_up.py [u_max ...]`` (default: 5 3 2.4 2.2 2): about five minutes on
the shared 2-core machine, most of it L-BFGS-B. Not part of ``make bench`` (a correctness table,
not a timing).
"""
from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.models import acrobot

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from direct import direct_optimum  # noqa: E402  (tests/direct.py: a test reference, not in the package)

LIMITS, STARTS = (5.0, 3.0, 2.4, 2.2, 2.0), 5
START_NAMES = ("rest", "clipped unbounded", "clipped 5 N m")


def main(limits) -> None:
    jax.config.update("jax_enable_x64", True)
    options = di.Options(max_iterations=1000)
    free = di.solve(acrobot(limits=False), options=options)
    loose = di.solve(acrobot(), options=options)
    print(f"unbounded: {int(free.iterations)} it, {float(free.cost):.10g}, peak |u| "
          f"{float(jnp.max(jnp.abs(free.u))):.3g} N m; 5 N m: {int(loose.iterations)} it, {float(loose.cost):.10g}")
    print("| u_max | from rest (it, status, cost) | several starts (cost, start) | L-BFGS-B from zero | "
          "L-BFGS-B best of 5 (starts at it) |")
    print("|---|---|---|---|---|")
    for lim in limits:
        problem = acrobot(u_max=lim)
        starts = jnp.stack([jnp.zeros((problem.horizon, 1)), jnp.clip(free.u, -lim, lim), jnp.clip(loose.u, -lim, lim)])
        sols = jax.vmap(lambda u: di.solve(problem, u, options))(starts)
        costs = np.asarray(sols.cost)
        rng = np.random.default_rng(0)
        direct = [direct_optimum(problem, u_init=u) for u in
                  [None] + [rng.uniform(-lim, lim, (problem.horizon, 1)) for _ in range(STARTS - 1)]]
        best = min(direct)
        hits = sum(abs(c - best) <= 1e-6 * best for c in direct)
        print(f"| {lim:g} N m | {int(sols.iterations[0])}, {di.Status(int(sols.status[0])).name}, {costs[0]:.8g} | "
              f"{costs.min():.8g} ({START_NAMES[int(costs.argmin())]}) | {direct[0]:.8g} | {best:.8g} ({hits}/{STARTS}) |",
              flush=True)


if __name__ == "__main__":
    main([float(a) for a in sys.argv[1:]] or LIMITS)
