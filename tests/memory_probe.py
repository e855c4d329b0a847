"""Run in a child process by tests/test_simulate.py (a peak of resident memory and an address-space
limit are properties of a whole process): prints one JSON line.

    python memory_probe.py peak N SUBSTEPS        the growth of the peak RSS over simulate(arm2, N)
    python memory_probe.py limit LIMIT_BYTES N    simulate(arm2, N) under RLIMIT_AS = LIMIT_BYTES,
                                                  with the memory check, then without it
"""
import importlib
import json
import resource
import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import delayed_ilqr as di                     # noqa: E402
from delayed_ilqr.models import arm2           # noqa: E402

sim = importlib.import_module("delayed_ilqr.simulate")     # the module (the package exports the function)


def _status(field: str) -> int:
    """A size of /proc/self/status in bytes (Linux: kB)."""
    for line in open("/proc/self/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


def reset_peak() -> int:
    """Resets the process's peak resident memory (VmHWM) to its current size and returns that size:
    the peak of what follows is then measured from here, not from an earlier transient (such as a
    compilation) that was larger than the run itself."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    return _status("VmRSS")


def peak() -> int:
    return _status("VmHWM")


def outcome(call) -> str:
    try:
        jax.block_until_ready(call())
        return "ran"
    except Exception as exc:
        return f"{type(exc).__name__}: {exc}"


if __name__ == "__main__":
    problem = arm2(delay=0.05, noise=True)
    policy = di.solve(problem).policy
    mode = sys.argv[1]
    if mode == "peak":
        N, substeps = int(sys.argv[2]), int(sys.argv[3])
        di.simulate(problem, policy, 10, substeps=substeps)          # everything but the trials' arrays
        sim._simulate.lower(problem, policy, N, substeps, jax.random.PRNGKey(0)).compile()
        before = reset_peak()
        runs = di.simulate(problem, policy, N, substeps=substeps)
        np.asarray(runs.x), np.asarray(runs.u), np.asarray(runs.cost)     # as a caller reads them
        print(json.dumps(dict(peak=peak() - before, estimate=sim.memory_estimate(problem, N, substeps))))
    else:
        limit, N = int(sys.argv[2]), int(sys.argv[3])
        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
        checked = outcome(lambda: di.simulate(problem, policy, N))
        sim.check_memory = lambda *args, **kwargs: None                   # as if the check had let it through
        unchecked = outcome(lambda: di.simulate(problem, policy, N))
        print(json.dumps(dict(checked=checked, unchecked=unchecked)))
