"""Per-channel input delays (``delay_steps=[l_1, l_2]``, docs/derivation.md §18): the structured
pass and solver against the augmented reference, in one run.

P4 (the point mass at dt = 1 ms, K = 600, n = 4, d = 2; docs/models.md §2) with channel delays
(l/2, l) and (l, l) for l = 50 and 200 steps:

1. the backward pass alone, linearised at u = 0: the compiled per-channel structured pass
   (``structured_slot_scan(store_value=False, predict=True)``, what the solver runs) against the
   compiled augmented pass (``augmented_scan``), and, for scale, the structured pass of the same
   plant with one delay L for both channels (no frame): 9 rounds of the three, interleaved,
   after a first (compiling) call of each;
2. the whole solve, ``solve(problem)`` against ``solve(problem, Options(method="augmented"))``,
   9 rounds after a first call at l = 50, 3 at l = 200 (1 with ``--quick``).

Each time is given as the median and the minimum of its calls.

Every timed call is wrapped in ``jax.block_until_ready``. The machine is shared, so only the
ratios of one run mean anything. XLA's CPU flags for small loops are on (``configure_cpu``, as in
the other benchmarks): without them the structured solve's many small operations pay a thunk
each, and on a loaded machine its ratio at l = 50 fell to 13 (docs/performance.md).

    .venv/bin/python benchmarks/channels.py [--quick] [--no-configure-cpu]
"""
from __future__ import annotations

import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.ilqg.linearize import linearize, rollout  # noqa: E402
from delayed_ilqr.lqg.augmented import augmented_scan  # noqa: E402
from delayed_ilqr.lqg.structured import structured_slot_scan  # noqa: E402
from delayed_ilqr.models import point_mass  # noqa: E402
from timing import interleaved  # noqa: E402

CHANNEL_DELAYS = ((25, 50), (50, 50), (100, 200), (200, 200))


def problem(delays) -> di.Problem:
    """P4 with channel j delayed by delays[j] steps."""
    return point_mass(dt=0.001).replace(delay_steps=list(delays))


def ms(t) -> str:
    return f"{t[0] * 1e3:.1f} / {t[1] * 1e3:.1f}"


def main(quick: bool):
    structured = jax.jit(lambda q: (lambda gains, out, ok, model: (out[0][0], *model))(
        *structured_slot_scan(q, 0.0, store_value=False, predict=True)))
    augmented = jax.jit(lambda q: augmented_scan(q, 0.0)[1].s_tilde[0])
    augmented_options = di.Options(method="augmented")
    print("Times in ms, median / min; ratios augmented / structured of the medians and of the minima.\n")
    print("| channel delays | N = n + L d | pass: structured | pass: one delay L | pass: augmented | ratio "
          "| J(0) rel. diff | solve: structured | solve: augmented | ratio | cost rel. diff |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for delays in CHANNEL_DELAYS:
        p, l = problem(delays), max(delays)
        us = jnp.zeros((p.horizon, p.n_controls))
        lqg = linearize(p, rollout(p, us), us)
        single = p.replace(delay_steps=l, delay_frame=None)
        single_lqg = linearize(single, rollout(single, us), us)
        t = interleaved(dict(s=lambda: structured(lqg), one=lambda: structured(single_lqg),
                             a=lambda: augmented(lqg)), 9)
        j_s, j_a = structured(lqg)[0], augmented(lqg)
        # the augmented solve takes about a second at l = 50 and 40 s at l = 200
        T = interleaved(dict(s=lambda: di.solve(p), a=lambda: di.solve(p, options=augmented_options)),
                        1 if quick else 9 if l <= 50 else 3)
        sol_s, sol_a = di.solve(p), di.solve(p, options=augmented_options)
        ratio = lambda x: f"{x['a'][0] / x['s'][0]:.0f} / {x['a'][1] / x['s'][1]:.0f}"
        print(f"| {list(delays)} | {4 + 2 * l} | {ms(t['s'])} | {ms(t['one'])} | {ms(t['a'])} | {ratio(t)} "
              f"| {abs(float(j_s) - float(j_a)) / abs(float(j_a)):.1e} | {ms(T['s'])} | {ms(T['a'])} | {ratio(T)} "
              f"| {abs(float(sol_s.cost) - float(sol_a.cost)) / abs(float(sol_a.cost)):.1e} |", flush=True)


if __name__ == "__main__":
    if "--no-configure-cpu" not in sys.argv[1:]:
        di.configure_cpu()
    main("--quick" in sys.argv[1:])
