"""Issue 23, item 1: the 16-delay arm sweep in fresh processes, first calls included.

``solve(arm2(delay=t))`` for 16 delays t = 0, 10, ..., 150 ms, each in a fresh process:

* without the persistent compilation cache (every delay compiles its solver);
* with an empty cache folder (the same, plus writing the cache);
* with the cache that run left (a second process: the solvers are read, not compiled).

Per run: the time of each delay's first call (trace, lower, compile or cache read, solve), their
sum (the whole sweep), and the ratio of the sum to the first delay's first call (the issue's goal:
at most 2.5). The solve time of each delay once compiled (median of 7) shows what padding every
delay up to 150 ms would cost per solve: the time at l = 15 against the time at l.

    .venv/bin/python benchmarks/delay_sweep_compile.py
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile

_CHILD = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import delayed_ilqr as di
di.configure_cpu()
if sys.argv[1] != "-":
    di.enable_compilation_cache(sys.argv[1])
from delayed_ilqr.models import arm2
delays = [round(0.01 * i, 2) for i in range(16)]
first, solve = [], []
start = time.perf_counter()
for t in delays:
    p = arm2(delay=t)
    s = time.perf_counter(); jax.block_until_ready(di.solve(p)); first.append(time.perf_counter() - s)
total = time.perf_counter() - start
for t in delays:
    p = arm2(delay=t)
    times = []
    for _ in range(7):
        s = time.perf_counter(); jax.block_until_ready(di.solve(p)); times.append(time.perf_counter() - s)
    solve.append(sorted(times)[3])
print(json.dumps(dict(first=first, total=total, solve=solve)))
"""


def run(cache: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", _CHILD, cache], env=env, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    with tempfile.TemporaryDirectory() as tmp:
        rows = [("no cache", run("-")), ("empty cache (first process)", run(tmp)),
                ("warm cache (second process)", run(tmp))]
    print("16 delays 0-150 ms, `solve(arm2(delay=t))`, fresh processes\n")
    print("| run | sweep incl. first calls [s] | first delay's first call [s] | ratio | first calls, min-max [s] |")
    print("|---|---|---|---|---|")
    for name, r in rows:
        f = r["first"]
        print(f"| {name} | {r['total']:.2f} | {f[0]:.2f} | {r['total'] / f[0]:.1f} | {min(f):.2f}-{max(f):.2f} |")
    solve = rows[0][1]["solve"]
    print("\nsolve time once compiled (median of 7) [ms], by delay steps l; padding to l = 15 would cost "
          "the l = 15 time on every solve:\n")
    print("| l | " + " | ".join(str(l) for l in range(16)) + " |")
    print("|---|" + "---|" * 16)
    print("| ms | " + " | ".join(f"{1e3 * s:.2f}" for s in solve) + " |")
    print(f"\nmean over the 16 delays: {1e3 * sum(solve) / 16:.2f} ms; at l = 15 for all: {1e3 * solve[-1]:.2f} ms "
          f"({solve[-1] * 16 / sum(solve):.2f}x)")


if __name__ == "__main__":
    main()
