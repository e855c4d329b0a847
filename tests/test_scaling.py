"""Keeps the structured recursion's operation count honest: at l = 200 (n = 4, d = 2, K = 100) one
compiled backward pass must be at least 10x faster than the augmented Riccati pass on the same
problem (measured ~50x on a 2-core machine; per step O(l^2 d^3 + l n^2 d) against O((n + l d)^3)).
A second problem of the same shapes reuses the compiled solver, and the solver's memory stays
within a few times its gains."""
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import delayed_ilqr as di
from delayed_ilqr.lqg import DelayedLQG
from delayed_ilqr.lqg.augmented import augmented_scan
from delayed_ilqr.lqg.structured import structured_scan
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.ilqg.solver import compiled_solver


def _best_time(fn, repeats):
    jax.block_until_ready(fn())                      # compile
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times)


def test_structured_pass_beats_augmentation_at_long_delay():
    K, n, d, l = 100, 4, 2, 200
    rng = np.random.default_rng(0)
    lqg = DelayedLQG(np.eye(n) + 0.01 * rng.normal(size=(K, n, n)), np.zeros((K, n, d)),
                     0.01 * rng.normal(size=(K, n, d)), None, None, None, np.zeros(K + 1), np.zeros((K + 1, n)),
                     np.broadcast_to(np.eye(n), (K + 1, n, n)), np.zeros((K, d)),
                     np.broadcast_to(1e-2 * np.eye(d), (K, d, d)), l)
    structured = jax.jit(lambda q: structured_scan(q, store_value=False)[1][0][0])
    augmented = jax.jit(lambda q: augmented_scan(q)[1].s_tilde[0])
    np.testing.assert_allclose(float(structured(lqg)), float(augmented(lqg)), rtol=1e-10)
    t_structured = _best_time(lambda: structured(lqg), 5)
    t_augmented = _best_time(lambda: augmented(lqg), 2)
    assert t_augmented >= 10 * t_structured, (t_structured, t_augmented)


def test_second_problem_of_the_same_shapes_does_not_recompile():
    options = di.Options(max_iterations=3)          # static: the same object for both solves
    problem = arm2(delay=0.1)
    first = di.solve(problem, options=options)
    solver = compiled_solver(problem)
    compilations = solver._cache_size()
    other = arm2(delay=0.1, x_target=(math.pi / 2 + 0.2, math.pi / 3 - 0.1, 0.0, 0.0))
    second = di.solve(other, options=options)
    assert compiled_solver(other) is solver and solver._cache_size() == compilations
    assert float(second.cost) != float(first.cost)  # the new target was used, not a cached result


def test_the_solver_holds_a_few_times_its_gains_at_a_short_delay():
    """Memory. At l = 1 the gains are 14 numbers per step, fewer than one step's LQ
    model (67 for the point mass) or the line search's 11 candidate trajectories (66): the
    compiled solver stores neither (it linearises inside the backward pass and scores candidates
    as they run), nor packed copies of its scans' inputs and outputs, and holds at most 5 times
    the gains, counting temporaries, outputs and arguments (XLA's memory_analysis: 4.45x measured,
    of which 1.25x is the loop's copy of the last nominal whose gains were finite, its gains and
    nominal, which the solve returns if the final backward pass fails (no NaN in a policy); 3.2x
    without that copy; 15.5x when it stored the model and the candidates, 4.6x + the copy with
    the packed copies)."""
    problem = point_mass(dt=0.001, delay=0.001)              # P4 at l = 1, K = 600
    K, n, d, l = problem.horizon, problem.n_states, problem.n_controls, problem.delay_steps
    gains = K * (d + d * n + l * d * d) * 8
    stats = compiled_solver(problem).lower(problem, jnp.zeros((K, d)), di.Options()).compile().memory_analysis()
    held = stats.temp_size_in_bytes + stats.output_size_in_bytes + stats.argument_size_in_bytes
    assert held <= 5 * gains, (held, gains)
