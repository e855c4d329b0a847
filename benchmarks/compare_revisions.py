"""Solve times of the working tree against another git revision, measured in one process.

    .venv/bin/python benchmarks/compare_revisions.py HEAD~1 [--problems P1,P3,P4-200] [--rounds 30]

These 2-core machines are shared and their speed moves by a third within minutes, so two versions
timed in separate processes, even alternately, can differ by more than the change under test. Here
``git archive REV src/delayed_ilqr`` is unpacked as a second package, ``delayed_ilqr_base``, both
versions compile the same problems, and their solves alternate one by one: each round times one
solve of each. It prints the medians and minima of both, the ratio of the medians (working tree /
revision) and the relative difference of the costs. The package's imports are relative, so the
copy runs under its new name. The process turns float64 and XLA's CPU flags on first
(``configure_cpu``); a revision that set them at import keeps them as they are.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr
from timing import interleaved

ROOT = Path(__file__).resolve().parents[1]
# name -> (model, keyword arguments): the benchmark problems of docs/models.md §2, variants, the
# six-muscle arm, and "P2-vmap64": 64 P2 targets in one jax.jit(jax.vmap(solve)) call (its time is
# that of the whole batch)
PROBLEMS = {
    "P1": ("point_mass", dict(delay=0.1)),
    "P2": ("arm2", dict(delay=0.1)),
    "P2-noisy": ("arm2", dict(delay=0.1, noise="benchmark")),
    "P3": ("arm2", dict(delay=0.1, dt=0.002)),
    **{f"P4-{l}": ("point_mass", dict(dt=0.001, delay=l * 0.001)) for l in (1, 10, 100, 200)},
    "muscle": ("arm2_muscle6", dict(delay=0.05)),
    "P2-vmap64": ("arm2", dict(delay=0.1)),
}
VMAP_OFFSETS = [(a, b) for a in np.linspace(-0.2, 0.2, 8) for b in np.linspace(-0.2, 0.2, 8)]   # rad


def import_revision(rev: str, where: Path):
    """The package as it is at ``rev``, imported as ``delayed_ilqr_base``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "src/delayed_ilqr"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(where)], input=archive, check=True)
    (where / "src" / "delayed_ilqr").rename(where / "delayed_ilqr_base")
    sys.path.insert(0, str(where))
    return importlib.import_module("delayed_ilqr_base")


def compiled_solve(package, name: str):
    """(a function running one compiled solve, its cost) for problem ``name`` of ``package``."""
    models = importlib.import_module(f"{package.__name__}.models")
    # the solver module moved to ilqg/ in a redesign; older revisions have it at the top
    layout = "ilqg.solver" if importlib.util.find_spec(f"{package.__name__}.ilqg") else "solver"
    solver = importlib.import_module(f"{package.__name__}.{layout}")
    model, kwargs = PROBLEMS[name]
    problem = getattr(models, model)(**kwargs)
    if name == "P2-vmap64":
        return _batched_solve(package, problem, getattr(models, model), kwargs)
    run = solver.compiled_solver(problem)
    u_init = jnp.zeros((problem.horizon, problem.n_controls))
    options = package.Options()
    cost = float(jax.block_until_ready(run(problem, u_init, options)).cost)
    return lambda: jax.block_until_ready(run(problem, u_init, options)), cost


def _batched_solve(package, problem, factory, kwargs):
    """(one compiled vmapped solve of 64 targets around ``problem``'s, the sum of their costs)."""
    target = np.asarray(problem.cost.x_target)
    problems = [factory(**kwargs, x_target=target + [a, b, 0.0, 0.0]) for a, b in VMAP_OFFSETS]
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *problems)
    run = jax.jit(jax.vmap(package.solve))
    cost = float(jnp.sum(jax.block_until_ready(run(stacked)).cost))
    return lambda: jax.block_until_ready(run(stacked)), cost


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("revision", help="git revision to compare the working tree against, e.g. HEAD~1")
    parser.add_argument("--problems", default=",".join(PROBLEMS),
                        help=f"comma-separated, from {', '.join(PROBLEMS)}")
    parser.add_argument("--rounds", type=int, default=30, help="timed solves of each version per problem")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    delayed_ilqr.configure_cpu()
    names = args.problems.split(",")
    unknown = [n for n in names if n not in PROBLEMS]
    if unknown:
        parser.error(f"unknown problems {unknown}; choose from {', '.join(PROBLEMS)}")
    with tempfile.TemporaryDirectory() as tmp:
        base = import_revision(args.revision, Path(tmp))
        print(f"working tree against {args.revision}: medians (minima) of {args.rounds} interleaved solves each")
        for name in names:
            (run_base, cost_base), (run_new, cost_new) = (compiled_solve(p, name) for p in (base, delayed_ilqr))
            times = interleaved(dict(base=run_base, new=run_new), args.rounds, warmup=False)   # compiled above
            (med_base, min_base), (med_new, min_new) = ((1e3 * med, 1e3 * low) for med, low in times.values())
            print(f"{name:9s} {args.revision}: {med_base:9.3f} ms ({min_base:.3f})   working tree: "
                  f"{med_new:9.3f} ms ({min_new:.3f})   ratio {med_new / med_base:5.2f}   "
                  f"cost rel. diff {abs(cost_new - cost_base) / abs(cost_base):.1e}")


if __name__ == "__main__":
    main()
