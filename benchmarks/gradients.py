"""The cost of a derivative of ``solve`` against the solve itself, measured in one run
(ilqg/implicit.py, docs/derivation.md §16, docs/performance.md#gradients).

For each problem: the jitted solve, the jitted ``value_and_grad`` of a loss that uses every output
of the solution (u, x, cost, expected_cost, the feedback gains) with respect to every array of the
problem (x0, the cost's arrays, the limits, the noise scale), and their ratio; the medians of
repeated calls after compilation. The gradient includes its own solve.

Run: .venv/bin/python benchmarks/gradients.py [--muscle]
"""
import argparse

import jax
import jax.numpy as jnp

import delayed_ilqr as di
from delayed_ilqr.models import arm2, arm2_muscle6
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV
from delayed_ilqr.models.arm2_muscle6 import rest_commands
from timing import median_time


def loss(sol):
    return (jnp.sum(sol.u ** 2) + jnp.sum(sol.x[-1] ** 2) + sol.cost + sol.expected_cost
            + jnp.sum(sol.policy.state_feedback ** 2))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--muscle", action="store_true", help="also the six-muscle arm (long compilations)")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    cases = [("arm2", d, n, arm2(delay=d, noise=n), None) for n in (False, True) for d in (0.0, 0.05)]
    if args.muscle:
        for n in (False, True):
            problem = arm2_muscle6(**LI_TODOROV, delay=0.0, noise=n)
            cases.append(("arm2_muscle6", 0.0, n, problem, rest_commands(problem)))
    print(f"{'problem':13} {'delay':>6} {'noise':>6} {'iters':>5} {'status':>16} {'solve':>9} {'gradient':>9} "
          f"{'ratio':>6}")
    for name, delay, noisy, problem, u_init in cases:
        solve = jax.jit(lambda p: di.solve(p, u_init))
        grad = jax.jit(jax.value_and_grad(lambda p: loss(di.solve(p, u_init))))
        sol = solve(problem)
        t_solve = median_time(solve, problem, repeats=args.repeats)
        t_grad = median_time(grad, problem, repeats=args.repeats)
        print(f"{name:13} {delay:6.2f} {str(noisy):>6} {int(sol.iterations):5d} {di.Status(int(sol.status)).name:>16} "
              f"{t_solve * 1e3:7.2f}ms {t_grad * 1e3:7.2f}ms {t_grad / t_solve:6.2f}")


if __name__ == "__main__":
    main()
