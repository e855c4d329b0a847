"""Bad input found by the user-surface campaign: each is refused
with a message that names the argument, or works as documented."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import lqg
from delayed_ilqr.models import arm2, point_mass

COST = di.QuadraticCost(P=np.zeros((2, 2)), Q=np.eye(1), P_final=np.eye(2), x_target=np.ones(2))
BASE = dict(dynamics=lambda x, u, ud: jnp.array([x[1], ud[0]]), x0=np.zeros(2), dt=0.1, horizon=10, delay_steps=2,
            cost=COST)


def problem(**changes):
    return di.Problem(**{**BASE, **changes})


# delay at or beyond the horizon ---------------------------------------------------------------
@pytest.mark.parametrize("l", [10, 11, 20000])
def test_a_delay_at_or_beyond_the_horizon_is_refused(l):
    with pytest.raises(ValueError, match=f"delay_steps must be below the horizon.*delay_steps={l}, horizon=10"):
        problem(delay_steps=l)
    assert problem(delay_steps=9).delay_steps == 9


def test_a_model_delay_beyond_its_horizon_is_refused():
    with pytest.raises(ValueError, match="delay_steps must be below the horizon"):
        point_mass(delay=1.0)                    # 100 steps against K = 60


# dt's type ------------------------------------------------------------------------------------
@pytest.mark.parametrize("dt", ["0.01", True, np.bool_(True), [0.1]])
def test_dt_must_be_a_number(dt):
    with pytest.raises(ValueError, match="dt must be a positive finite number"):
        problem(dt=dt)


def test_limits_of_the_wrong_shape_are_refused_by_name():
    with pytest.raises(ValueError, match=r"u_min must have shape \(1,\); got shape \(1, 1\)"):
        problem(u_min=np.zeros((1, 1)))
    assert problem(u_min=-1.0, u_max=[1.0]).has_limits


def test_huge_and_float32_delays():
    with pytest.raises(ValueError, match="delay must be a finite number of steps"):
        point_mass(delay=1e308)
    assert arm2(delay=np.float32(0.03)).delay_steps == 3
    with pytest.raises(ValueError, match=r"sensory_delay must be a whole number of steps.*got 0.025 s \(2.5 steps\)"):
        arm2(sensory_delay=0.025)


def test_general_cost_params_must_be_numbers():
    with pytest.raises(TypeError, match="GeneralCost params must be a pytree of numeric arrays"):
        di.GeneralCost(lambda x, u, p: 0.0, lambda x, p: 0.0, params="abc")


def test_integer_dynamics_are_refused_at_construction():
    with pytest.raises(ValueError, match="dynamics.*floating-point.*int32"):
        problem(dynamics=lambda x, u, ud: jnp.zeros(2, jnp.int32))


# Options' values ------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, match", [
    (dict(tol_cost="1e-3"), "tol_cost must be a positive finite number"),
    (dict(z_min=float("nan")), "z_min must be a number in"),
    (dict(z_min=1.0), "z_min must be a number in"),
    (dict(z_min=-0.1), "z_min must be a number in"),
    (dict(reg_min=1.0, reg_max=0.5), "reg_min must be below reg_max"),
    (dict(reg_init="1"), "reg_init must be a finite number >= 0"),
    (dict(reg_factor=float("inf")), "reg_factor must be a finite number greater than 1"),
])
def test_options_refuse(kwargs, match):
    with pytest.raises(ValueError, match=match):
        di.Options(**kwargs)


# the LQG layer's arguments --------------------------------------------------------------------
def _lqg():
    K, n, d = 4, 2, 1
    return lqg.DelayedLQG(A=np.tile(np.eye(n), (K, 1, 1)), B0=np.zeros((K, n, d)), B1=np.ones((K, n, d)), c=None,
                          C0=None, C1=None, d_tilde=np.zeros(K + 1), d=np.ones((K + 1, n)),
                          D=np.tile(np.eye(n), (K + 1, 1, 1)), e=np.zeros((K, d)), E=np.tile(np.eye(d), (K, 1, 1)),
                          delay_steps=1)


@pytest.mark.parametrize("entry", [lqg.backward_pass, lqg.augmented_backward_pass])
def test_lqg_backward_passes_check_reg_and_type(entry):
    for reg in (-1.0, float("nan"), "1"):
        with pytest.raises(ValueError, match="reg must be a finite number >= 0"):
            entry(_lqg(), reg)
    with pytest.raises(TypeError, match="lqg must be a delayed_ilqr.lqg.DelayedLQG; got dict"):
        entry({}, 0.0)
    gains, value = entry(_lqg(), 0.5)
    assert np.isfinite(float(value.expected_cost))


@pytest.mark.parametrize("seed, error", [(-1, ValueError), (1.5, TypeError), ("a", TypeError), (2 ** 70, ValueError)])
def test_simulate_lqg_checks_the_seed_as_simulate_does(seed, error):
    model = _lqg()
    gains, _ = lqg.backward_pass(model)
    with pytest.raises(error, match="seed must be a non-negative integer"):
        lqg.simulate_lqg(model, gains, 4, seed=seed)


# replace under jit and vmap -------------------------------------------------------------------
def test_replace_under_jit_and_a_problem_built_inside_vmap():
    p = point_mass()
    x0s = np.stack([np.asarray(p.x0), np.asarray(p.x0) + 0.01])
    jitted = jax.jit(lambda x0: di.solve(p.replace(x0=x0)).cost)
    np.testing.assert_allclose(float(jitted(x0s[1])), float(di.solve(p.replace(x0=x0s[1])).cost), rtol=1e-10)
    batched = jax.vmap(lambda x0: di.solve(p.replace(x0=x0)).cost)(x0s)
    np.testing.assert_allclose(np.asarray(batched), [float(di.solve(p.replace(x0=x)).cost) for x in x0s], rtol=1e-10)
    limited = jax.vmap(lambda hi: p.replace(u_min=-hi, u_max=hi).u_max)(jnp.ones((2, 2)))
    assert limited.shape == (2, 2)
    with pytest.raises(ValueError, match="dt cannot be traced"):
        jax.vmap(lambda dt: p.replace(dt=dt).x0)(jnp.array([0.01, 0.02]))


# the status's name and x0 ---------------------------------------------------------------------
def test_status_prints_its_name_and_x0_is_named():
    sol = di.solve(point_mass())
    assert str(sol.status) == "CONVERGED_GRADIENT" and f"{sol.status}" == "CONVERGED_GRADIENT"
    assert sol.status == 0 and int(sol.status) == di.Status.CONVERGED_GRADIENT and sol.converged
    with pytest.raises(ValueError, match=r"x0 must have shape \(4,\).*got shape \(3,\)"):
        point_mass().replace(x0=np.zeros(3))


def test_the_readme_batching_patterns_agree_and_replace_reuses_the_compilation():
    """README "Batching and compilation": replace under vmap and jit, a stacked Problem;
    replace reuses the compiled solver, a new lambda compiles again."""
    from delayed_ilqr.ilqg import solver
    base = point_mass(delay=0.03)
    x0s = jnp.stack([base.x0, base.x0 + 0.01, base.x0 - 0.01])
    loop = np.array([float(di.solve(base.replace(x0=x)).cost) for x in x0s])
    batch = jax.vmap(lambda x0: di.solve(base.replace(x0=x0)))(x0s)
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[base.replace(x0=x) for x in x0s])
    np.testing.assert_allclose(np.asarray(batch.cost), loop, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(jax.vmap(di.solve)(stacked).cost), loop, rtol=1e-10)
    size = solver._solve._cache_size()
    di.solve(base.replace(x0=x0s[2] + 0.01))
    assert solver._solve._cache_size() == size
    fresh = base.replace(dynamics=lambda x, u, ud: base.dynamics(x, u, ud))
    di.solve(fresh)
    assert solver._solve._cache_size() == size + 1
