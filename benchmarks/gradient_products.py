"""Where the time of a reverse-mode gradient of ``solve`` goes: the price of one product of the
implicit tangent's Krylov solve against one solve (ilqg/implicit.py, docs/derivation.md §16,
docs/performance.md#gradients).

At the converged nominal u* of each problem, each jitted alone: the solve; one product with dF/du
(``jvp``, the forward system) and with its transpose (``vjp``, the system that reverse mode
solves); five products chained in one ``fori_loop`` (``jvp5``, ``vjp5``: the work that does not
depend on the direction, F's primal and the backward pass that makes S(u), is the same in every
product, and XLA computes it once, so (x5 - x1) / 4 is the price of one more product); and five
applications of the Gauss-Newton preconditioner (``pre5``). Minima over interleaved repeats, in
ms: the machine's load only adds time.

Run: .venv/bin/python benchmarks/gradient_products.py [--repeats N]
"""
import argparse
import time

import jax
import jax.numpy as jnp

import delayed_ilqr as di
from delayed_ilqr.ilqg import implicit
from delayed_ilqr.ilqg.linearize import linearize
from delayed_ilqr.models import arm2

CHAIN = 5


def chained(product, u, v):
    # the 1e-3 keeps the chained directions of the size of v
    return jax.lax.fori_loop(0, CHAIN, lambda i, w: 1e-3 * product(u, w), v)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=301)
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    margin = di.Options().limit_margin
    print(f"{'delay':>6} {'noise':>6} {'iters':>5} " + " ".join(f"{k:>7}" for k in
          ("solve", "jvp", "vjp", "jvp5", "vjp5", "pre5", "+jvp", "+vjp", "+pre")) + "   (ms)")
    for noisy in (False, True):
        for delay in (0.0, 0.05):
            problem = arm2(delay=delay, noise=noisy)
            solve = jax.jit(lambda p: di.solve(p))
            sol = solve(problem)
            us, xs = sol.u, sol.x
            fixed, bound = implicit.fixed_commands(problem, us, margin)
            F = lambda u: implicit.stationarity(problem, u, fixed, bound, margin)
            jvp = lambda u, v: jax.jvp(F, (u,), (v,))[1]
            vjp = lambda u, v: jax.vjp(F, u)[1](v)[0]
            pre = lambda u, v: implicit.preconditioner(linearize(problem, xs, u), fixed)(v)
            v = 0.1 * jnp.ones_like(us)
            calls = {"solve": (solve, problem), "jvp": (jax.jit(jvp), us, v), "vjp": (jax.jit(vjp), us, v),
                     "jvp5": (jax.jit(lambda u, v: chained(jvp, u, v)), us, v),
                     "vjp5": (jax.jit(lambda u, v: chained(vjp, u, v)), us, v),
                     "pre5": (jax.jit(lambda u, v: chained(pre, u, v)), us, v)}
            best = {}
            for name, (fn, *a) in calls.items():
                jax.block_until_ready(fn(*a))
                best[name] = float("inf")
            for _ in range(args.repeats):
                for name, (fn, *a) in calls.items():
                    start = time.perf_counter()
                    jax.block_until_ready(fn(*a))
                    best[name] = min(best[name], time.perf_counter() - start)
            ms = {k: t * 1e3 for k, t in best.items()}
            extra = [(ms["jvp5"] - ms["jvp"]) / (CHAIN - 1), (ms["vjp5"] - ms["vjp"]) / (CHAIN - 1), ms["pre5"] / CHAIN]
            print(f"{delay:6.2f} {str(noisy):>6} {int(sol.iterations):5d} "
                  + " ".join(f"{t:7.3f}" for t in [*ms.values(), *extra]))


if __name__ == "__main__":
    main()
