"""The XLA backend options set at import (``delayed_ilqr._xla_options``)."""
import jax
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import _xla_options
from delayed_ilqr.ilqg import solver
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.ilqg.solver import compiled_solver

THRESHOLD = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000"
NO_YNN = "--xla_cpu_experimental_ynn_fusion_type=-individual_dot"


MY_THRESHOLD = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024"
MY_YNN = "--xla_cpu_experimental_ynn_fusion_type=+individual_dot"


@pytest.mark.parametrize("before, after", [
    (None, f"{THRESHOLD} {NO_YNN}"),
    ("--xla_cpu_enable_fast_math=false", f"--xla_cpu_enable_fast_math=false {THRESHOLD} {NO_YNN}"),
    (MY_THRESHOLD, f"{MY_THRESHOLD} {NO_YNN}"),                    # what the user set is kept
    (MY_YNN, f"{MY_YNN} {THRESHOLD}"),
])
def test_configure_adds_the_flags_the_user_did_not_set(before, after):
    env = {} if before is None else {"XLA_FLAGS": before}
    _xla_options.configure(env)
    assert env["XLA_FLAGS"] == after


def test_small_scans_compile_as_single_functions():
    # The three scans (initial rollout, backward pass, line search) become calls that XLA compiles
    # whole (P1's iteration loop too); with XLA's default threshold (1024 bytes) only the rollout
    # does, and with YNNPACK fusions P3's backward pass does not. This checks that both settings reached XLA in this
    # process (the package was imported before JAX's first computation).
    for problem in (point_mass(delay=0.1), arm2(delay=0.1, dt=0.002)):
        u_init = np.zeros((problem.horizon, 2))
        hlo = compiled_solver(problem).lower(problem, u_init, di.Options()).compile().as_text()
        assert hlo.count('xla_cpu_small_call="true"') >= 3


def test_long_delays_turn_library_dots_back_on():
    long, short = point_mass(dt=0.001, delay=0.15), point_mass(dt=0.001, delay=0.149)   # l d = 300, 298
    assert compiled_solver(long) is solver._solve_large and compiled_solver(short) is solver._solve

    def library_fusions(jitted):
        return jitted.lower(long, np.zeros((long.horizon, 2)), di.Options()).compile().as_text().count("ynn_fusion")

    assert library_fusions(solver._solve_large) > library_fusions(solver._solve)


def test_solve_inside_jit_compiles_with_the_outer_options():
    # JAX refuses compiler options on a nested jit (those of _solve_large): inside a transformation
    # solve compiles with the process's options, and the result is the same
    problem = point_mass(delay=0.1)
    inside = jax.jit(di.solve)(problem)
    np.testing.assert_allclose(float(inside.cost), float(di.solve(problem).cost), rtol=1e-12)
    assert int(inside.status) == int(di.solve(problem).status)


def test_vmap_on_cpu_solves_one_problem_after_another():
    # the batching rule of solver._one_after_another: one scan over the problems, each solved by
    # the unbatched solver (whose scans XLA compiles as one function), not one batched while loop
    problems = [point_mass(delay=0.1, x0=(0.0, x, 0.0, 0.0)) for x in (0.0, 0.1, 0.2)]
    stacked = jax.tree_util.tree_map(lambda *leaves: jax.numpy.stack(leaves), *problems)
    jaxpr = jax.make_jaxpr(jax.vmap(di.solve))(stacked).jaxpr
    assert [eqn.primitive.name for eqn in jaxpr.eqns if eqn.primitive.name in ("scan", "while")] == ["scan"]
