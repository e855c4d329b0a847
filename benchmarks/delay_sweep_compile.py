"""The 16-delay arm sweep in fresh processes, first calls included.

``solve(arm2(delay=t))`` for 16 delays t = 0, 10, ..., 150 ms, each run in a fresh process:

* without the persistent compilation cache (every delay compiles its solver);
* with an empty cache folder (the same, plus writing the cache);
* with the cache that run left (a second process: the solvers are read, not compiled);
* in one delay frame, ``arm2(delay=t).replace(delay_frame=15)``, without the cache (one solver
  for all delays, docs/derivation.md §17).

Per run: the time of each delay's first call (trace, lower, compile or cache read, solve), their
sum (the whole sweep), and the ratio of the sum to the first delay's first call (the goal:
at most 2.5). Then, in the framed process, the solve time of each delay once compiled, framed and
unframed interleaved (median of 9 each): what the frame costs per solve.

    .venv/bin/python benchmarks/delay_sweep_compile.py [--noise]
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
framed, noise = sys.argv[2] == "framed", sys.argv[3] == "noise"
delays = [round(0.01 * i, 2) for i in range(16)]
problem = lambda t: arm2(delay=t, noise=noise)
chosen = (lambda t: problem(t).replace(delay_frame=15)) if framed else problem
first, solve = [], {}
start = time.perf_counter()
for t in delays:
    p = chosen(t)
    s = time.perf_counter(); jax.block_until_ready(di.solve(p)); first.append(time.perf_counter() - s)
total = time.perf_counter() - start
if framed:      # per-solve cost of the frame: framed and unframed interleaved, once compiled
    for t in delays:
        pair = (problem(t), problem(t).replace(delay_frame=15))
        times = ([], [])
        for p in pair:
            jax.block_until_ready(di.solve(p))
        for _ in range(9):
            for p, out in zip(pair, times):
                s = time.perf_counter(); jax.block_until_ready(di.solve(p)); out.append(time.perf_counter() - s)
        solve[t] = [sorted(x)[4] for x in times]
print(json.dumps(dict(first=first, total=total, solve=solve)))
"""


def run(cache: str, mode: str, noise: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", _CHILD, cache, mode, noise], env=env, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    noise = "noise" if "--noise" in sys.argv[1:] else "-"
    with tempfile.TemporaryDirectory() as tmp:
        rows = [("no cache", run("-", "-", noise)), ("empty cache (first process)", run(tmp, "-", noise)),
                ("warm cache (second process)", run(tmp, "-", noise)),
                ("one frame of 15 steps, no cache", run("-", "framed", noise))]
    print(f"16 delays 0-150 ms, `solve(arm2(delay=t{', noise=True' if noise == 'noise' else ''}))`, "
          "fresh processes\n")
    print("| run | sweep incl. first calls [s] | first delay's first call [s] | ratio | first calls, min-max [s] |")
    print("|---|---|---|---|---|")
    for name, r in rows:
        f = r["first"]
        print(f"| {name} | {r['total']:.2f} | {f[0]:.2f} | {r['total'] / f[0]:.2f} | {min(f):.2f}-{max(f):.2f} |")
    solve = rows[-1][1]["solve"]
    print("\nsolve time once compiled (median of 9, framed and unframed interleaved) [ms], by delay steps l:\n")
    print("| l | " + " | ".join(str(l) for l in range(16)) + " |")
    print("|---|" + "---|" * 16)
    print("| unframed | " + " | ".join(f"{1e3 * solve[t][0]:.2f}" for t in solve) + " |")
    print("| frame of 15 | " + " | ".join(f"{1e3 * solve[t][1]:.2f}" for t in solve) + " |")
    print("| ratio | " + " | ".join(f"{solve[t][1] / solve[t][0]:.2f}" for t in solve) + " |")
    plain, framed = (sum(v[i] for v in solve.values()) for i in (0, 1))
    print(f"\nsum over the 16 delays: unframed {1e3 * plain:.2f} ms, framed {1e3 * framed:.2f} ms "
          f"({framed / plain:.2f}x)")


if __name__ == "__main__":
    main()
