"""Speed of the receding-horizon controller (``delayed_ilqr.mpc``), measured as ratios in one run.

On the two-link arm (``models.arm2``, dt = 10 ms) with a 50-step horizon:

1. one tick at l = 10 (100 ms), compiled (``MPC.step``, one real-time iteration, warm-started):
   per-tick latency median and 99th percentile over ``--ticks`` calls from Python (dispatch
   included), against a solve from scratch at every tick (``solve``'s compiled body from zero
   commands, run to convergence, same states), and the ticks per second inside the compiled closed
   loop (``mpc.simulate``, one trial: no Python between ticks);
2. the tick's cost against the delay l in {0, 2, 5, 10, 20, 40} (closed loop, ticks per second,
   and the time per tick relative to l = 0; the structured pass grows like l^2 d^3 per step), with
   the exponent p of time ~ l^p fitted over l = 10..40 (the goal: p <= 2);
3. batched rollouts: ``mpc.simulate`` of ``--trials`` seeds (default 1000) on the noisy arm,
   ``--rollout-ticks`` ticks each, under ``vmap``: rollouts per second and trial-ticks per second,
   with the trials one after another (what ``mpc.simulate`` does on CPU) and batched by JAX.

Run ``python benchmarks/mpc_speed.py`` (about two minutes on the shared 2-core machine); numbers
in docs/performance.md ("Receding-horizon control").
"""
from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr import mpc
from delayed_ilqr.ilqg.solver import _solve_body
from delayed_ilqr.models.arm2 import SIGMA_U_HUMAN
from delayed_ilqr.mpc import closed_loop
from delayed_ilqr.mpc.receding import at_tick


def _arm(l, horizon):
    return di.models.arm2(delay=l * 0.01, dt=0.01, horizon=horizon)


def latency(horizon: int, l: int, ticks: int):
    """Per-tick latency of the compiled tick against a solve from scratch (same states)."""
    problem = _arm(l, horizon)
    ctrl = mpc.MPC(problem)
    run = mpc.simulate(ctrl, problem, ticks=ticks)
    states = np.asarray(run.x[0, :-1])
    state = ctrl.init()
    state, tick = ctrl.step(state, states[0])          # compile
    jax.block_until_ready(tick)
    warm = []
    for x in states:
        t = time.perf_counter()
        state, tick = ctrl.step(state, x)
        jax.block_until_ready(tick.command)
        warm.append(time.perf_counter() - t)

    # from scratch: the tick problem of each state (same in-flight commands), zero commands, converged
    options = di.Options()
    scratch_fn = jax.jit(lambda p: _solve_body(p, jnp.zeros((horizon, 2)), options))
    in_flight = np.asarray(run.u[0])
    problems = [at_tick(ctrl.template, jnp.asarray(x),
                        jnp.asarray(np.concatenate([np.zeros((l, 2)), in_flight])[k:k + l]), 0.01 * k)
                for k, x in enumerate(states)]
    jax.block_until_ready(scratch_fn(problems[0]).u)
    scratch, iterations = [], []
    for p in problems:
        t = time.perf_counter()
        sol = scratch_fn(p)
        jax.block_until_ready(sol.u)
        scratch.append(time.perf_counter() - t)
        iterations.append(int(sol.iterations))

    t = time.perf_counter()
    jax.block_until_ready(mpc.simulate(ctrl, problem, ticks=ticks, seed=1).x)
    loop = ticks / (time.perf_counter() - t)
    return np.asarray(warm), np.asarray(scratch), loop, np.mean(iterations)


def closed_loop_rate(horizon: int, l: int, ticks: int) -> float:
    """Ticks per second of the compiled closed loop (one trial), compilation excluded."""
    problem = _arm(l, horizon)
    ctrl = mpc.MPC(problem)
    jax.block_until_ready(mpc.simulate(ctrl, problem, ticks=ticks).x)
    best = np.inf
    for seed in (1, 2, 3):
        t = time.perf_counter()
        jax.block_until_ready(mpc.simulate(ctrl, problem, ticks=ticks, seed=seed).x)
        best = min(best, time.perf_counter() - t)
    return ticks / best


def rollouts(horizon: int, l: int, ticks: int, trials: int, sequential: bool):
    """Rollouts per second of ``trials`` seeds on the noisy arm (compilation excluded), with the
    trials one after another under the vmap (``mpc.simulate`` on CPU) or batched (JAX's rule)."""
    model = _arm(l, horizon)
    plant = di.models.arm2(delay=l * 0.01, dt=0.01, horizon=horizon, noise=True, sigma_u=SIGMA_U_HUMAN)
    ctrl = mpc.MPC(model)
    data, static = jax.tree_util.tree_flatten(plant)
    run = lambda seed: closed_loop._run(ctrl, static, data, ticks, None, float("inf"), trials, jax.random.PRNGKey(seed),
                                        plant.x0, jnp.zeros((ticks, 4)), sequential)
    jax.block_until_ready(run(0)[0])
    t = time.perf_counter()
    out = run(1)
    jax.block_until_ready(out[0])
    elapsed = time.perf_counter() - t
    return trials / elapsed, trials * ticks / elapsed, float(np.mean(np.asarray(out[4])))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--ticks", type=int, default=300)
    parser.add_argument("--trials", type=int, default=1000)
    parser.add_argument("--rollout-ticks", type=int, default=50)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    di.configure_cpu()
    K = args.horizon

    warm, scratch, loop, its = latency(K, 10, args.ticks)
    print(f"arm2, K = {K}, l = 10, {args.ticks} ticks")
    print("| per tick | median | p99 | ticks/s (median) |")
    print("|---|---|---|---|")
    for name, t in (("MPC.step (1 iteration, warm)", warm), (f"solve from scratch ({its:.1f} iterations)", scratch)):
        print(f"| {name} | {1e6 * np.median(t):.0f} us | {1e6 * np.percentile(t, 99):.0f} us | "
              f"{1 / np.median(t):.0f} |")
    print(f"ratio scratch / warm (median): {np.median(scratch) / np.median(warm):.1f}")
    print(f"compiled closed loop (mpc.simulate, 1 trial): {loop:.0f} ticks/s ({1e6 / loop:.0f} us per tick)\n")

    print("| l | ticks/s (closed loop) | us per tick | relative to l = 0 |")
    print("|---|---|---|---|")
    base, per_tick = None, {}
    for l in (0, 2, 5, 10, 20, 40):
        rate = closed_loop_rate(K, l, args.ticks)
        base = base or rate
        per_tick[l] = 1 / rate
        print(f"| {l} | {rate:.0f} | {1e6 / rate:.0f} | {base / rate:.2f} |")
    ls = np.array([10, 20, 40])
    exponent = np.polyfit(np.log(ls), np.log([per_tick[int(l)] for l in ls]), 1)[0]
    print(f"time per tick ~ l^{exponent:.2f} over l = 10..40 (O(l^2) allows 2)")

    print(f"\n{args.trials} seeds x {args.rollout_ticks} ticks (noisy arm, l = 10):")
    for name, sequential in (("one after another (mpc.simulate on CPU)", True), ("batched by JAX's vmap", False)):
        per_s, tick_trials, failed = rollouts(K, 10, args.rollout_ticks, args.trials, sequential)
        print(f"  {name}: {per_s:.1f} rollouts/s, {tick_trials:.0f} trial-ticks/s (failure rate {failed:.2f})")


if __name__ == "__main__":
    main()
