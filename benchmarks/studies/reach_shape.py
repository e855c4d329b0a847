"""Why the six-muscle arm's reaches at no delay are flat-topped and (to targets 1 and 5) curved.

Solves the center-out study's own reaches (``center_out``'s plants, ``DEFAULT_OPTIONS``, the
design's problem) to all 8 targets and prints, per target, the solver status, the cost (2) and the
shape (``experiments.center_out.reach_shape``: speed peaks, path deviation, peak/mean speed). It also
checks the plotted speed (the hand displacement per step over dt) against the hand velocity
J(q) dq of the kinematics.

    PYTHONPATH=src .venv/bin/python benchmarks/studies/reach_shape.py [--delay S] [--design D]
        [--start rest|noise-aware|linear-force] [--force linear] [--lbfgs] [--sigma-u S]
        [--final-time S] [--r R]

--start noise-aware: warm-start from the noise-aware design's commands (README: the deterministic
    design's cost at 0 ms).
--force linear: a diagnostic plant whose force is linear in the activation, A(a, l) = a instead of
    Li & Todorov's 1 - exp(-(a / (0.56 N_f))^N_f) (x0 and the start at a = u = 0, where A's slope
    is not zero); --start linear-force warm-starts the published model from that plant's optimum.
--lbfgs: also bounded L-BFGS-B from rest (``tests/direct.py``), an optimiser that shares nothing
    with iLQG but the rollout and the cost.
docs/results/reach_shape.md has the results.
"""
import argparse
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from direct import direct_optimum  # noqa: E402  (tests/direct.py: a test reference, not in the package)
from linear_force import linear_force  # noqa: E402  (tests/linear_force.py: a diagnostic variant)

import delayed_ilqr as di  # noqa: E402
from delayed_ilqr.experiments import designs  # noqa: E402
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS, reach_shape  # noqa: E402
from delayed_ilqr.experiments.engine import timed_batched_solve  # noqa: E402
from delayed_ilqr.models.arm2 import hand_velocity  # noqa: E402
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--delay", type=float, default=0.0)
    parser.add_argument("--design", default="deterministic", choices=["deterministic", "noise-aware"])
    parser.add_argument("--start", default="rest", choices=["rest", "noise-aware", "linear-force"])
    parser.add_argument("--force", default="published", choices=["published", "linear"])
    parser.add_argument("--sigma-u", type=float, default=0.01)
    parser.add_argument("--final-time", type=float, default=0.5)
    parser.add_argument("--r", type=float, default=1e-4, help="effort weight")
    parser.add_argument("--lbfgs", action="store_true")
    args = parser.parse_args()

    targets = center_out_targets(8, 0.1)
    plants = [arm2_muscle6(**LI_TODOROV, delay=args.delay, target=tuple(t), noise=True, sigma_u=args.sigma_u,
                           final_time=args.final_time, r=args.r) for t in targets]
    problems = [designs.design(p, args.design, DEFAULT_OPTIONS)[0] for p in plants]
    if args.force == "linear":
        problems = [linear_force(p) for p in problems]
    starts = [None] * len(problems)
    if args.start == "noise-aware":
        starts = list(np.asarray(timed_batched_solve(plants, DEFAULT_OPTIONS)[0].u))
    elif args.start == "linear-force":
        lin = [linear_force(p.replace(noise=None)) for p in plants]
        lin_sols = timed_batched_solve(lin, DEFAULT_OPTIONS, jnp.zeros((lin[0].horizon, 6)))[0]
        starts = list(np.clip(np.asarray(lin_sols.u), 0.0, 1.0))
    if args.start == "rest":
        u_init = jnp.zeros((problems[0].horizon, 6)) if args.force == "linear" else None
        sols = timed_batched_solve(problems, DEFAULT_OPTIONS, u_init)[0]
        results = [jax.tree_util.tree_map(lambda leaf: leaf[j], sols) for j in range(len(problems))]
    else:
        results = [di.solve(p, jnp.asarray(u), DEFAULT_OPTIONS) for p, u in zip(problems, starts)]

    print(f"delay {args.delay} s, design {args.design}, force {args.force}, start {args.start}")
    costs = []
    for j, (plant, sol) in enumerate(zip(plants, results)):
        x = np.asarray(sol.x)
        shape = reach_shape(plant, x)
        v = np.asarray(jax.vmap(hand_velocity)(jnp.asarray(x[:-1, :2]), jnp.asarray(x[:-1, 2:4])))
        check = np.max(np.abs(shape.speed - np.linalg.norm(v, axis=1)))
        line = (f"target {j + 1}: {di.Status(int(sol.status)).name} in {int(sol.iterations)} it, "
                f"cost {float(sol.cost):.5g}; {shape.peaks} speed peak(s), peak/mean {shape.peak_to_mean:.2f}, "
                f"path deviation {shape.deviation:.3f}; |plotted speed - |J dq|| <= {100 * check:.3f} cm/s")
        if args.lbfgs:
            line += f"; L-BFGS-B from rest {direct_optimum(problems[j], u_init=np.full((50, 6), 0.05)):.5g}"
        costs.append(float(sol.cost))
        print(line, flush=True)
    print(f"mean cost {np.mean(costs):.5g}")


if __name__ == "__main__":
    main()
