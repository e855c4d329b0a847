"""XLA's CPU flags (``delayed_ilqr.configure_cpu``, module ``_cpu``): what they add to
``XLA_FLAGS``, when they refuse, and that they reached XLA in this process (conftest.py calls
``configure_cpu`` before any JAX computation)."""
import os

import jax
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import _cpu
from delayed_ilqr.ilqg import solver
from delayed_ilqr.models import arm2, point_mass
from delayed_ilqr.ilqg.solver import compiled_solver

THRESHOLD = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000"
NO_YNN = "--xla_cpu_experimental_ynn_fusion_type=-individual_dot"
MY_THRESHOLD = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024"
MY_YNN = "--xla_cpu_experimental_ynn_fusion_type=+individual_dot"
MY_LLVM = "--xla_backend_extra_options=-inline-threshold=225"


@pytest.fixture
def before_jax(monkeypatch):
    """``configure_cpu`` as before JAX's first computation (this process's backend has started)."""
    monkeypatch.setattr(_cpu, "_backend_started", lambda: False)
    monkeypatch.delenv("XLA_FLAGS", raising=False)


@pytest.mark.parametrize("before, after, added", [
    (None, f"{THRESHOLD} {NO_YNN}", (THRESHOLD, NO_YNN)),
    ("--xla_cpu_enable_fast_math=false", f"--xla_cpu_enable_fast_math=false {THRESHOLD} {NO_YNN}",
     (THRESHOLD, NO_YNN)),
    (MY_THRESHOLD, f"{MY_THRESHOLD} {NO_YNN}", (NO_YNN,)),                    # what the user set is kept
    (MY_YNN, f"{MY_YNN} {THRESHOLD}", (THRESHOLD,)),
    (f"{MY_THRESHOLD} {MY_YNN}", f"{MY_THRESHOLD} {MY_YNN}", ()),
    # a second --xla_backend_extra_options would replace the user's: the threshold joins it
    (MY_LLVM, f"{MY_LLVM},xla_cpu_small_while_loop_byte_threshold=1000000 {NO_YNN}", (THRESHOLD, NO_YNN)),
])
def test_configure_cpu_adds_the_flags_the_user_did_not_set(before_jax, monkeypatch, before, after, added):
    if before is not None:
        monkeypatch.setenv("XLA_FLAGS", before)
    assert di.configure_cpu() == added
    assert os.environ["XLA_FLAGS"] == after
    assert di.configure_cpu() == ()                   # idempotent
    assert os.environ["XLA_FLAGS"] == after


def test_configure_cpu_after_the_first_computation_warns_and_changes_nothing(monkeypatch):
    jax.numpy.zeros(1).block_until_ready()            # the backend starts (with conftest's flags)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    with pytest.warns(UserWarning, match="before any JAX computation"):
        assert di.configure_cpu() == ()
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false"


def test_a_flag_the_installed_jaxlib_does_not_know_is_left_out(before_jax, monkeypatch):
    # as with a future jaxlib without the experimental YNNPACK flag: XLA would abort on it
    known = _cpu._known_names
    monkeypatch.setattr(_cpu, "_known_names", lambda names: {
        **known(names), "xla_cpu_experimental_ynn_fusion_type": False})
    with pytest.warns(UserWarning, match="does not know --xla_cpu_experimental_ynn_fusion_type"):
        assert di.configure_cpu() == (THRESHOLD,)
    assert os.environ["XLA_FLAGS"] == THRESHOLD


def test_the_installed_jaxlib_knows_the_flags_and_only_those_names():
    names = ("xla_backend_extra_options", "xla_cpu_small_while_loop_byte_threshold",
             "xla_cpu_experimental_ynn_fusion_type", "xla_cpu_no_such_flag",
             "cpu_experimental_ynn_fusion_type")      # the end of a known name is not a name
    assert _cpu._known_names(names) == {**dict.fromkeys(names[:3], True), **dict.fromkeys(names[3:], False)}


def test_small_scans_compile_as_single_functions():
    # The three scans (initial rollout, backward pass, line search) become calls that XLA compiles
    # whole (P1's iteration loop too); with XLA's default threshold (1024 bytes) only the rollout
    # does, and with YNNPACK fusions P3's backward pass does not. This checks that both settings
    # reached XLA in this process (conftest.py called configure_cpu before JAX's first computation).
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
    # the batching rule of ilqg.solver._one_after_another: one scan over the problems, each solved by
    # the unbatched solver (whose scans XLA compiles as one function), not one batched while loop
    problems = [point_mass(delay=0.1, x0=(0.0, x, 0.0, 0.0)) for x in (0.0, 0.1, 0.2)]
    stacked = jax.tree_util.tree_map(lambda *leaves: jax.numpy.stack(leaves), *problems)
    jaxpr = jax.make_jaxpr(jax.vmap(di.solve))(stacked).jaxpr
    # traced, solve is the differentiable one (ilqg.implicit: a custom_jvp around the solver)
    [wrapper] = jaxpr.eqns
    assert wrapper.primitive.name == "custom_jvp_call"
    inner = wrapper.params["call_jaxpr"].jaxpr
    assert [eqn.primitive.name for eqn in inner.eqns if eqn.primitive.name in ("scan", "while")] == ["scan"]
