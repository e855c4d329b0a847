"""Throughput of a sweep: solves with Monte Carlo per second, measured in one run.

The sweep: the noisy two-link arm (``arm2(noise=True, sigma_u=0.01)``) reaching to N targets
around P2's at two delays (0 and 50 ms), ``--trials`` Monte Carlo trials per cell, one seed. Four
ways, one after another in this process (and its workers):

* naive loop: for each cell, ``solve(arm2(...))``, ``simulate``, ``statistics.summarize``;
* ``sweep`` here, in memory (cells of one delay solved by one vmap, batches of 16);
* the same with ``delay_frame="auto"`` (both delays in one frame: one structure, docs/sweeps.md);
* ``sweep`` here, into a Zarr store (the same, plus the writes and checksummed markers);
* ``sweep`` on a ``LocalCluster`` of 2 worker processes, into a Zarr store.

Every way is run once on a small grid of the same structures first (so compilation is left out:
each way's compile time is reported separately, as the first run's extra time), then timed on
the full grid. The workers share a persistent compilation cache with this process. Memory per
worker: its resident set size after the sweep.

    .venv/bin/python benchmarks/sweep.py [--cells 1024] [--trials 100]   (2 x 512: every batch holds 16 cells)
"""
from __future__ import annotations

import argparse
import math
import os
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr import statistics  # noqa: E402
from delayed_ilqr.models import arm2  # noqa: E402
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN  # noqa: E402

DELAYS = (0.0, 0.05)


def targets(n: int) -> list[tuple]:
    """n final states around P2's target: joint angles on a grid of +-0.3 rad, at rest."""
    side = math.ceil(math.sqrt(n))
    q1, q2 = np.meshgrid(np.linspace(-0.3, 0.3, side), np.linspace(-0.3, 0.3, side))
    pts = np.stack([q1.ravel(), q2.ravel()], axis=1)[:n]
    return [(math.pi / 2 + a, math.pi / 3 + b, 0.0, 0.0) for a, b in pts]


def naive(grid, trials):
    for delay in grid["delay"]:
        for target in grid["x_target"]:
            problem = arm2(delay=delay, noise=True, sigma_u=SIGMA_U_HUMAN, x_target=target)
            sol = di.solve(problem)
            runs = di.simulate(problem, sol.policy, trials, seed=0)
            statistics.summarize(runs.cost, runs.x[:, -1], statistics.divergence_bound(problem))


def timed(fn):
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=1024)
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2)
    a = parser.parse_args()
    per_delay = a.cells // len(DELAYS)
    grid = {"delay": list(DELAYS), "x_target": targets(per_delay)}
    small = {"delay": list(DELAYS), "x_target": targets(16)}      # batches of 16: the full grid's shapes
    fixed = dict(noise=True, sigma_u=SIGMA_U_HUMAN)
    common = dict(seeds=[0], trials=a.trials, fixed=fixed, progress=False)
    n = len(DELAYS) * per_delay
    with tempfile.TemporaryDirectory() as tmp:
        di.enable_compilation_cache(os.path.join(tmp, "cache"))
        rows = []

        def way(name, run):
            first = timed(lambda: run(small, os.path.join(tmp, name + "-small")))
            full = timed(lambda: run(grid, os.path.join(tmp, name)))
            rows.append((name, full, first))

        way("naive loop", lambda g, store: naive(g, a.trials))
        way("sweep, in memory", lambda g, store: di.sweep("arm2", g, **common))
        way("sweep, in memory, one delay frame", lambda g, store: di.sweep("arm2", g, delay_frame="auto", **common))
        way("sweep, Zarr store", lambda g, store: di.sweep("arm2", g, store=store, **common))

        from distributed import Client, LocalCluster
        cluster = LocalCluster(n_workers=a.workers, threads_per_worker=1, processes=True, dashboard_address=None)
        with Client(cluster) as client:
            cache = os.path.join(tmp, "cache")
            way(f"sweep, LocalCluster {a.workers} workers, Zarr store",
                lambda g, store: di.sweep("arm2", g, store=store, scheduler=client, cache_dir=cache, **common))
            import psutil
            rss = client.run(lambda: psutil.Process().memory_info().rss)
        cluster.close()
    print(f"{n} cells (arm2, noise sigma_u={SIGMA_U_HUMAN}, delays {DELAYS}, {per_delay} targets), "
          f"{a.trials} trials per cell, one seed; cpu count {os.cpu_count()}\n")
    print("| way | seconds | cells (solve + Monte Carlo) per second | first run on 32 cells, with compilation [s] |")
    print("|---|---|---|---|")
    for name, full, first in rows:
        print(f"| {name} | {full:.2f} | {n / full:.1f} | {first:.1f} |")
    print("\nresident memory per worker after the sweep: "
          + ", ".join(f"{v / 2 ** 20:.0f} MiB" for v in rss.values()))


if __name__ == "__main__":
    main()
