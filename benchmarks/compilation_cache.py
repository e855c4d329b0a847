"""The persistent compilation cache across processes: `delayed-ilqr solve` run three times in fresh
processes, the first two sharing a new, empty cache folder, the third with --no-cache.

Each process sums JAX's own duration events (jax.monitoring): the backend compilation (XLA, or the
read of a cached executable: ``/jax/core/compile/backend_compile_duration``), the tracing and the
lowering to MLIR (not cached: they run in every process), and the process's wall time.

    .venv/bin/python benchmarks/compilation_cache.py [MODEL] [--delay S] [--noise]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

# runs the command line in this process after installing a listener for JAX's duration events
_WRAPPER = r"""
import atexit, collections, json, sys
import jax.monitoring
totals, path = collections.defaultdict(float), sys.argv[1]
jax.monitoring.register_event_duration_secs_listener(lambda event, secs, **kw: totals.__setitem__(event, totals[event] + secs))
def dump():
    with open(path, "w") as f:
        f.write(json.dumps(totals))
atexit.register(dump)
sys.argv = ["delayed-ilqr"] + sys.argv[2:]
from delayed_ilqr.cli import main
main()
"""
EVENTS = {"compile": "/jax/core/compile/backend_compile_duration",
          "trace": "/jax/core/compile/jaxpr_trace_duration",
          "lower": "/jax/core/compile/jaxpr_to_mlir_module_duration"}


def run(args: list[str], env: dict) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", _WRAPPER, out.name, *args], env=env, check=True,
                       stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        totals = json.loads(open(out.name).read())
    return dict(wall=wall, **{name: totals.get(event, 0.0) for name, event in EVENTS.items()},
                saved=totals.get("/jax/compilation_cache/compile_time_saved_sec", 0.0))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", nargs="?", default="arm2")
    parser.add_argument("--delay", default="0.1")
    parser.add_argument("--noise", action="store_true")
    a = parser.parse_args()
    solve = ["solve", a.model, "--delay", a.delay] + (["--noise"] if a.noise else [])
    env = {k: v for k, v in os.environ.items() if k not in ("DELAYED_ILQR_NO_CACHE", "XLA_FLAGS")}
    with tempfile.TemporaryDirectory() as cache:
        env["DELAYED_ILQR_CACHE_DIR"] = cache
        rows = [("first process, empty cache", run(solve, env)),
                ("second process, same cache", run(solve, env)),
                ("--no-cache", run(["--no-cache"] + solve, env))]
        files = len(os.listdir(cache))
    print(f"`delayed-ilqr {' '.join(solve)}` in fresh processes; cache entries written: {files}\n")
    print("| process | backend compile [s] | trace [s] | lower [s] | wall [s] |")
    print("|---|---|---|---|---|")
    for name, r in rows:
        print(f"| {name} | {r['compile']:.3f} | {r['trace']:.3f} | {r['lower']:.3f} | {r['wall']:.2f} |")
    first, second = rows[0][1], rows[1][1]
    print(f"\nsecond / first backend compile: {second['compile'] / first['compile']:.3f}; "
          f"compile + trace + lower: {(second['compile'] + second['trace'] + second['lower']) / (first['compile'] + first['trace'] + first['lower']):.3f}")


if __name__ == "__main__":
    main()
