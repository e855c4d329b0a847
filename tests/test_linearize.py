"""Eq. (3)-(4): the linearisation against central finite differences of the discrete step, the
general-cost path against the quadratic one, and the model built inside the pass against the stored one."""
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.ilqg.linearize import delayed_commands, linearize, rollout, step_models, trajectory_cost
from delayed_ilqr.lqg.gains import boxed_gains
from delayed_ilqr.lqg.structured import structured_slot_scan
from delayed_ilqr.models import arm2, cart_pole, point_mass


def _central(fun, z, h=1e-6):
    cols = []
    for i in range(z.size):
        dz = np.zeros_like(z)
        dz[i] = h
        cols.append((np.asarray(fun(z + dz)) - np.asarray(fun(z - dz))) / (2 * h))
    return np.stack(cols, axis=-1)


def test_dynamics_and_noise_jacobians_match_finite_differences():
    problem = arm2(delay=0.03, noise="benchmark")
    rng = np.random.default_rng(0)
    us = jnp.asarray(rng.normal(size=(problem.horizon, 2)))
    xs = rollout(problem, us)
    lqg = linearize(problem, xs, us)
    uds = delayed_commands(problem, us)
    dt, f, F = problem.dt, problem.dynamics, problem.noise
    for k in (0, 7, 31, problem.horizon - 1):
        x, u, ud = (np.asarray(a[k]) for a in (xs, us, uds))
        np.testing.assert_allclose(lqg.A[k], _central(lambda z: z + dt * f(z, u, ud), x), rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(lqg.B0[k], _central(lambda z: dt * f(x, z, ud), u), rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(lqg.B1[k], _central(lambda z: dt * f(x, u, z), ud), rtol=1e-6, atol=1e-8)
        # noise column j of one step is sqrt(dt) F[:, j] (erratum E7: sqrt(dt), not dt, for C0 and C1)
        np.testing.assert_allclose(lqg.c[k], np.sqrt(dt) * np.asarray(F(x, u, ud)).T, rtol=1e-12)
        C1 = _central(lambda z: np.sqrt(dt) * np.asarray(F(x, u, z)).T, ud)          # [p, n, d]
        np.testing.assert_allclose(lqg.C1[k], C1, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(lqg.C0[k], 0.0, atol=1e-15)                       # F ignores u


def test_cost_expansion_matches_eq_4():
    """d_k = dt P x_k, D_k = dt P, e_k = dt Q u_k, E_k = dt Q; final d = P_f (x - x*), D = P_f."""
    problem = arm2(delay=0.03)
    rng = np.random.default_rng(1)
    us = jnp.asarray(rng.normal(size=(problem.horizon, 2)))
    xs = rollout(problem, us)
    lqg = linearize(problem, xs, us)
    c = problem.cost
    np.testing.assert_allclose(lqg.e, problem.dt * us @ np.asarray(c.Q), rtol=1e-12)
    np.testing.assert_allclose(lqg.E, np.broadcast_to(problem.dt * np.asarray(c.Q), lqg.E.shape), rtol=1e-12)
    err = np.asarray(xs[-1] - c.x_target)
    np.testing.assert_allclose(lqg.d[-1], np.asarray(c.P_final) @ err, rtol=1e-12)
    np.testing.assert_allclose(lqg.D[-1], np.asarray(c.P_final), rtol=1e-12)
    np.testing.assert_allclose(lqg.d_tilde[-1], err @ np.asarray(c.P_final) @ err, rtol=1e-12)


def test_general_cost_gives_the_quadratic_cost_solution():
    quadratic = arm2(delay=0.1)
    c = quadratic.cost
    general = quadratic.replace(cost=di.GeneralCost(
        lambda x, u, p: x @ p["P"] @ x + u @ p["Q"] @ u,
        lambda x, p: (x - p["target"]) @ p["P_final"] @ (x - p["target"]),
        dict(P=c.P, Q=c.Q, P_final=c.P_final, target=c.x_target)))
    a, b = di.solve(quadratic), di.solve(general)
    assert int(a.iterations) == int(b.iterations)
    np.testing.assert_allclose(float(b.cost), float(a.cost), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(b.u), np.asarray(a.u), rtol=1e-9, atol=1e-12)


def test_cross_term_of_a_general_cost_reaches_the_lqg():
    """running = (u - G x)'(u - G x) has a u-x cross term: N = dt * (-G) in the factor-2 convention."""
    G = np.array([[0.5, 0.0, 0.1, 0.0], [0.0, 0.3, 0.0, 0.2]])
    base = arm2(delay=0.03)
    problem = base.replace(cost=di.GeneralCost(lambda x, u, p: (u - p @ x) @ (u - p @ x),
                                               lambda x, p: jnp.sum(x ** 2), jnp.asarray(G)))
    us = jnp.zeros((problem.horizon, 2))
    lqg = linearize(problem, rollout(problem, us), us)
    np.testing.assert_allclose(lqg.N, np.broadcast_to(-problem.dt * G, lqg.N.shape), rtol=1e-12)


def test_trajectory_cost_is_eq_2_step_by_step():
    """Eq. (2) discretised, summed here one step at a time: dt sum_k running(x_k, u_k) + final(x_K)."""
    problem = arm2(delay=0.03)
    rng = np.random.default_rng(1)
    us = jnp.asarray(rng.normal(size=(problem.horizon, 2)))
    xs = rollout(problem, us)
    expected = sum(problem.dt * float(problem.cost.running(xs[k], us[k])) for k in range(problem.horizon))
    expected += float(problem.cost.final(xs[-1]))
    np.testing.assert_allclose(float(trajectory_cost(problem, xs, us)), expected, rtol=1e-13)


@pytest.mark.parametrize("model, delay, noise, block", [
    ("arm2", 0.0, False, None), ("arm2", 0.01, True, None), ("arm2", 0.05, True, 7), ("cart_pole", 0.1, False, 4),
    ("point_mass", 0.15, False, None)],                # l d = 300: blocked by default, K = 600 padded to 608
    ids=lambda v: str(v))
def test_linearising_in_the_pass_equals_the_stored_model(model, delay, noise, block):
    """The solver's structured pass builds each step's model from the nominal as it reaches it
    (``step_models``); on the stored model of ``linearize`` the same pass must give the same
    gains, value, positive-definiteness and predicted change (l = 0, l = 1, blocks padded with
    idle steps, noise, control limits)."""
    factory = {"arm2": arm2, "cart_pole": cart_pole, "point_mass": point_mass}[model]
    kw = dict(noise=noise) if model == "arm2" else {}
    problem = factory(delay=delay, **({"dt": 0.001} if model == "point_mass" else {}), **kw)
    rng = np.random.default_rng(3)
    us = jnp.asarray(0.3 * rng.normal(size=(problem.horizon, problem.n_controls)))
    if problem.has_limits:
        us = jnp.clip(us, problem.u_min, problem.u_max)
    xs = rollout(problem, us)
    kw = dict(store_value=False, predict=True, block=block)
    if problem.has_limits:
        kw.update(gains_fn=partial(boxed_gains, margin=1e-5), bounds=(problem.u_min - us, problem.u_max - us))
    run = jax.jit(lambda models: structured_slot_scan(models, 1e-3, **kw))
    stored = run(linearize(problem, xs, us))
    in_pass = jax.jit(lambda xs, us: structured_slot_scan(step_models(problem, xs, us), 1e-3, **kw))(xs, us)
    assert bool(stored[2]) and bool(in_pass[2])
    for want, got in zip(jax.tree_util.tree_leaves(stored), jax.tree_util.tree_leaves(in_pass)):
        scale = float(jnp.max(jnp.abs(want)))
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-11, atol=1e-13 * scale)
    assert float(jnp.max(jnp.abs(stored[0].feedback))) > 0     # a real comparison: gains are not zero
