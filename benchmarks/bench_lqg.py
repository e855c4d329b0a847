"""Cost of one delayed-LQG backward pass: structured Theorem 1 vs state augmentation.

Times ``backward_pass`` (structured, O(l^2 d^3 + l n^2 d + n^3) per step) and
``augmented_backward_pass`` (Riccati on the augmented state, O((n + l d)^3) per step) for
n = 4, d = 2, K = 600 on random stable time-varying data with multiplicative noise. Each entry is
the median wall time of at least 3 runs with ``block_until_ready``, after ahead-of-time compilation
and a warm-up run (for a pass slower than 5 s, the warm-up run is counted as the first timed run:
it carries no compilation, and this keeps the whole script under about 3 minutes on 2 cores).
The structured/augmented ratio of each row is measured in the same run. A second table times the
structured pass alone over more delays and fits the exponent of time vs l (log-log least squares).

The column "structured, no value" is ``structured_scan(..., store_value=False)``, which keeps only
s_tilde, s, S per step (what the solver uses for long delays): the stored R blocks of
``backward_pass`` are K l^2 d^2 numbers (770 MB at l = 200), and writing them costs time too.

Usage: python benchmarks/bench_lqg.py [--quick]
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from delayed_ilqr import lqg as L  # noqa: E402

N_STATES, N_CONTROLS, N_NOISE, HORIZON = 4, 2, 1, 600


def random_stable_lqg(l: int, K: int = HORIZON, n: int = N_STATES, d: int = N_CONTROLS,
                      p: int = N_NOISE, seed: int = 0) -> L.DelayedLQG:
    """Time-varying A_k = 0.97 Q_k (Q_k orthogonal, so |eig| = 0.97), convex stage costs."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((K, n, n)))
    A = 0.97 * Q
    m = n + d + 1
    X = rng.standard_normal((K + 1, m, m))
    W = X @ np.swapaxes(X, 1, 2) / m + 0.1 * np.eye(m)
    return L.DelayedLQG(
        A=A, B0=0.1 * rng.standard_normal((K, n, d)), B1=0.1 * rng.standard_normal((K, n, d)),
        c=0.05 * rng.standard_normal((K, p, n)), C0=0.02 * rng.standard_normal((K, p, n, d)),
        C1=0.02 * rng.standard_normal((K, p, n, d)),
        d_tilde=W[:, -1, -1], d=W[:, :n, -1], D=W[:, :n, :n], e=W[:-1, n:n + d, -1],
        E=W[:-1, n:n + d, n:n + d], N=W[:-1, n:n + d, :n], delay_steps=l)


PASSES = {
    "structured": L.backward_pass,
    "structured, no value": jax.jit(lambda lqg, reg: L.structured_scan(lqg, reg, store_value=False)),
    "augmented": L.augmented_backward_pass,
}


def median_time(jitted, lqg, *, min_runs: int = 3, max_runs: int = 7, budget_s: float = 6.0,
                slow_s: float = 5.0) -> float:
    """Median wall time of compiled runs of ``jitted(lqg, 0.0)``."""
    compiled = jitted.lower(lqg, 0.0).compile()              # ahead of time: no compile in timings

    def run() -> float:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(lqg, 0.0))
        return time.perf_counter() - t0

    warm = run()
    times = [warm] if warm > slow_s else []
    start = time.perf_counter()
    while len(times) < max_runs and (len(times) < min_runs or time.perf_counter() - start < budget_s):
        times.append(run())
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter horizon (K = 150), for smoke tests")
    args = parser.parse_args()
    K = 150 if args.quick else HORIZON

    print(f"delayed-LQG backward pass, n = {N_STATES}, d = {N_CONTROLS}, p = {N_NOISE}, K = {K}; "
          f"JAX {jax.__version__} on {jax.default_backend()} ({platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs); median of >= 3 compiled runs")
    print()
    delays = (10, 20, 50, 100, 200)
    compared = (10, 50, 200)
    times, rel = {}, {}
    for l in delays:
        lqg = random_stable_lqg(l, K)
        names = PASSES if l in compared else ("structured", "structured, no value")
        times[l] = {name: median_time(PASSES[name], lqg) for name in names}
        if l in compared:
            js = float(L.backward_pass(lqg, 0.0)[1].expected_cost)
            ja = float(L.augmented_backward_pass(lqg, 0.0)[1].expected_cost)
            rel[l] = abs(js - ja) / abs(ja)

    header = (f"{'l':>5} {'N = n+ld':>9} {'structured':>12} {'struct, no value':>17} {'augmented':>12} "
              f"{'struct/aug':>11} {'J0 rel diff':>12}")
    print(header)
    print("-" * len(header))
    for l in compared:
        t = times[l]
        print(f"{l:>5} {N_STATES + l * N_CONTROLS:>9} {t['structured'] * 1e3:>10.1f}ms "
              f"{t['structured, no value'] * 1e3:>15.1f}ms {t['augmented'] * 1e3:>10.1f}ms "
              f"{t['structured'] / t['augmented']:>11.3f} {rel[l]:>12.1e}")

    print()
    print(f"{'l':>5} {'structured':>12} {'struct, no value':>17}")
    for l in delays:
        print(f"{l:>5} {times[l]['structured'] * 1e3:>10.1f}ms {times[l]['structured, no value'] * 1e3:>15.1f}ms")
    logl = np.log(np.asarray(delays, float))
    for name in ("structured", "structured, no value"):
        slope, _ = np.polyfit(logl, np.log([times[l][name] for l in delays]), 1)
        print(f"fitted exponent, {name} time ~ l^a over l = {', '.join(map(str, delays))}: a = {slope:.2f}")
    print("(per-step cost model: l^2 d^3 + l n^2 d + n^3; the augmented pass is (n + l d)^3)")


if __name__ == "__main__":
    main()
