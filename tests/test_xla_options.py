"""The XLA backend option set at import (``delayed_ilqr._xla_options``)."""
import jax
import numpy as np

import delayed_ilqr as di
from delayed_ilqr import _xla_options
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.solver import compiled_solver

OPTION = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000"


def test_configure_adds_the_threshold_and_keeps_other_flags():
    env = {}
    _xla_options.configure(env)
    assert env["XLA_FLAGS"] == OPTION
    env = {"XLA_FLAGS": "--xla_cpu_enable_fast_math=false"}
    _xla_options.configure(env)
    assert env["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false " + OPTION


def test_configure_keeps_a_threshold_the_user_set():
    env = {"XLA_FLAGS": "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024"}
    _xla_options.configure(env)
    assert env["XLA_FLAGS"] == "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024"


def test_small_scans_compile_as_single_functions():
    # The three scans (initial rollout, backward pass, line search) become calls that XLA compiles
    # whole (P1's iteration loop too); with XLA's default threshold (1024 bytes) only the rollout
    # does, and with YNNPACK fusions P3's backward pass does not. This checks that both settings reached XLA in this
    # process (the package was imported before JAX's first computation).
    for problem in (point_mass(delay=0.1), arm2(delay=0.1, dt=0.002)):
        u_init = np.zeros((problem.horizon, 2))
        hlo = compiled_solver(problem).lower(problem, u_init, di.Options()).compile().as_text()
        assert hlo.count('xla_cpu_small_call="true"') >= 3


def test_long_delays_keep_library_fusions():
    problem = point_mass(dt=0.001, delay=0.15)                    # l d = 300: the deferred R update
    assert compiled_solver(problem) is not compiled_solver(point_mass(dt=0.001, delay=0.149))


def test_solve_inside_jit_compiles_with_the_outer_options():
    # JAX refuses compiler options on a nested jit: inside a transformation solve uses the
    # compilation with XLA's defaults
    problem = point_mass(delay=0.1)
    inside = jax.jit(di.solve)(problem)
    np.testing.assert_allclose(float(inside.cost), float(di.solve(problem).cost), rtol=1e-12)
    assert int(inside.status) == int(di.solve(problem).status)
