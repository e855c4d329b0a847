"""Per-channel input delays (``delay_steps=[l_1, l_2]``, docs/derivation.md §18): the structured
pass and solver against the augmented reference, in one run.

P4 (the point mass at dt = 1 ms, K = 600, n = 4, d = 2; docs/models.md §2) with channel delays
(l/2, l) for l = 50 and 200 steps:

1. the backward pass alone, linearised at u = 0: the compiled per-channel structured pass
   (``structured_slot_scan(store_value=False, predict=True)``, what the solver runs) against the
   compiled augmented pass (``augmented_scan``), and, for scale, the structured pass of the same
   plant with one delay L for both channels (no frame): median of 7 calls each after a first
   (compiling) one, the three interleaved;
2. the whole solve, ``solve(problem)`` against ``solve(problem, Options(method="augmented"))``,
   median of 3 solves after a first one (1 with ``--quick``).

Every timed call is wrapped in ``jax.block_until_ready``. The machine is shared, so only the
ratios of one run mean anything.

    .venv/bin/python benchmarks/channels.py [--quick]
"""
from __future__ import annotations

import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.ilqg.linearize import linearize, rollout  # noqa: E402
from delayed_ilqr.lqg.augmented import augmented_scan  # noqa: E402
from delayed_ilqr.lqg.structured import structured_slot_scan  # noqa: E402
from delayed_ilqr.models import point_mass  # noqa: E402

LONGEST = (50, 200)


def problem(l: int) -> di.Problem:
    """P4 with channel 0 delayed by l / 2 steps and channel 1 by l."""
    return point_mass(dt=0.001).replace(delay_steps=[l // 2, l])


def median_time(fn, repeats: int):
    """(result of the first call, median seconds of ``repeats`` calls after it)."""
    first = jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return first, statistics.median(times)


def interleaved_medians(fns: dict, repeats: int) -> dict:
    """{name: median seconds} of ``repeats`` rounds, each calling every function once, after a
    first (compiling) call of each: a change of load hits them alike."""
    for fn in fns.values():
        jax.block_until_ready(fn())
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}


def main(quick: bool):
    structured = jax.jit(lambda q: (lambda gains, out, ok, model: (out[0][0], *model))(
        *structured_slot_scan(q, 0.0, store_value=False, predict=True)))
    augmented = jax.jit(lambda q: augmented_scan(q, 0.0)[1].s_tilde[0])
    print("| channel delays | N = n + L d | pass: structured | pass: one delay L | pass: augmented | ratio "
          "| J(0) rel. diff | solve: structured | solve: augmented | ratio | cost rel. diff |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for l in LONGEST:
        p = problem(l)
        us = jnp.zeros((p.horizon, p.n_controls))
        lqg = linearize(p, rollout(p, us), us)
        single = p.replace(delay_steps=l, delay_frame=None)
        single_lqg = linearize(single, rollout(single, us), us)
        t = interleaved_medians(dict(s=lambda: structured(lqg), one=lambda: structured(single_lqg),
                                     a=lambda: augmented(lqg)), 7)
        t_s, t_one, t_a = t["s"], t["one"], t["a"]
        j_s, j_a = structured(lqg)[0], augmented(lqg)
        sol_s, T_s = median_time(lambda: di.solve(p), 1 if quick else 3)
        sol_a, T_a = median_time(lambda: di.solve(p, options=di.Options(method="augmented")), 1 if quick else 3)
        print(f"| [{l // 2}, {l}] | {4 + 2 * l} | {t_s * 1e3:.2f} ms | {t_one * 1e3:.2f} ms | {t_a * 1e3:.1f} ms "
              f"| {t_a / t_s:.0f} "
              f"| {abs(float(j_s) - float(j_a)) / abs(float(j_a)):.1e} | {T_s * 1e3:.1f} ms | {T_a * 1e3:.0f} ms "
              f"| {T_a / T_s:.0f} | {abs(float(sol_s.cost) - float(sol_a.cost)) / abs(float(sol_a.cost)):.1e} |",
              flush=True)


if __name__ == "__main__":
    main("--quick" in sys.argv[1:])
