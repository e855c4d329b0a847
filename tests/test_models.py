"""Model zoo: each model against an independent NumPy transcription of its reference definition.

References: ``docs/models.md`` §2 (P1-P4 and their noisy variants) and
``docs/models.md`` §3 (arm) and §5 (Florian's cart-pole, trajax's acrobot). The NumPy code below is
written from those formulas, not from the library.
"""
import importlib
import math
import re

import delayed_ilqr  # noqa: F401  (enables float64 in JAX)
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr import models
from delayed_ilqr.models.pendulum import PendulumDynamics
from delayed_ilqr.problem import Problem, QuadraticCost

# the package attributes models.arm2 etc. are the factories; the modules are reached by name
arm2_module = importlib.import_module("delayed_ilqr.models.arm2")
cart_pole_module = importlib.import_module("delayed_ilqr.models.cart_pole")

RNG_SEED = 20240531


# --------------------------------------------------------------------------------------------
# Independent NumPy transcriptions of docs/models.md §2
# --------------------------------------------------------------------------------------------
def np_point_mass_f(x, ud, m=1.0, b=0.5):
    return np.array([x[2], x[3], (ud[0] - b * x[2]) / m, (ud[1] - b * x[3]) / m])


def np_point_mass_F(ud, m=1.0, sigma_u=0.5, sigma_a=0.05):
    F = np.zeros((4, 4))
    e = np.eye(4)
    for j in (1, 2):  # signal-dependent: sigma_u ud_j / m e_{2+j} (1-based)
        F[:, j - 1] = sigma_u * ud[j - 1] / m * e[:, 2 + j - 1]
    for j in (3, 4):  # additive: sigma_a / m e_j
        F[:, j - 1] = sigma_a / m * e[:, j - 1]
    return F


ARM = dict(m1=1.4, m2=1.1, l1=0.30, l2=0.33, s1=0.11, s2=0.16, I1=0.025, I2=0.045,
           B=np.array([[0.05, 0.025], [0.025, 0.05]]))


def np_arm_M(q):
    a1 = ARM["I1"] + ARM["I2"] + ARM["m2"] * ARM["l1"] ** 2
    a2 = ARM["m2"] * ARM["l1"] * ARM["s2"]
    a3 = ARM["I2"]
    c = math.cos(q[1])
    return np.array([[a1 + 2 * a2 * c, a3 + a2 * c], [a3 + a2 * c, a3]])


def np_arm_C(q, dq):
    a2 = ARM["m2"] * ARM["l1"] * ARM["s2"]
    return a2 * math.sin(q[1]) * np.array([-dq[1] * (2 * dq[0] + dq[1]), dq[0] ** 2])


def np_arm_f(x, ud):
    q, dq = x[:2], x[2:]
    ddq = np.linalg.solve(np_arm_M(q), ud - np_arm_C(q, dq) - ARM["B"] @ dq)
    return np.concatenate([dq, ddq])


def np_hand(q):
    l1, l2 = ARM["l1"], ARM["l2"]
    return np.array([l1 * math.cos(q[0]) + l2 * math.cos(q[0] + q[1]),
                     l1 * math.sin(q[0]) + l2 * math.sin(q[0] + q[1])])


def np_florian_up(phi, dphi, F, mc=1.0, mp=0.1, l=1.0, g=9.80665):
    """docs/models.md §5, the source's form: phi measured from upright. Returns (ddx, ddphi)."""
    tmp = (F + mp * l * dphi ** 2 * math.sin(phi)) / (mc + mp)
    ddphi = (g * math.sin(phi) - math.cos(phi) * tmp) / (l * (4.0 / 3.0 - mp * math.cos(phi) ** 2 / (mc + mp)))
    ddx = tmp - mp * l * ddphi * math.cos(phi) / (mc + mp)
    return ddx, ddphi


def np_cart_pole_energy(x, mc=1.0, mp=0.1, l=1.0, g=9.80665):
    """Uniform rod of half-length l, theta from hanging down, centre of mass at (x + l sin, -l cos)."""
    _, th, dx, dth = x
    vx, vy = dx + l * math.cos(th) * dth, l * math.sin(th) * dth
    kinetic = 0.5 * mc * dx ** 2 + 0.5 * mp * (vx ** 2 + vy ** 2) + 0.5 * (mp * (2 * l) ** 2 / 12) * dth ** 2
    return kinetic - mp * g * l * math.cos(th)


ACRO = dict(m1=1.0, m2=1.0, l1=1.0, lc1=0.5, lc2=0.5, I1=1.0, I2=1.0, g=9.8)


def np_acrobot_trajax(x, a):
    """trajax's ``tests/optimizers_test.py`` acrobot (Gym's "book" closed form), transcribed."""
    m1, m2, l1, lc1, lc2, I1, I2, g = ACRO.values()
    theta1, theta2, dtheta1, dtheta2 = x
    d1 = m1 * lc1 ** 2 + m2 * (l1 ** 2 + lc2 ** 2 + 2 * l1 * lc2 * math.cos(theta2)) + I1 + I2
    d2 = m2 * (lc2 ** 2 + l1 * lc2 * math.cos(theta2)) + I2
    phi2 = m2 * lc2 * g * math.cos(theta1 + theta2 - math.pi / 2.0)
    phi1 = (-m2 * l1 * lc2 * dtheta2 ** 2 * math.sin(theta2) - 2 * m2 * l1 * lc2 * dtheta2 * dtheta1 * math.sin(theta2)
            + (m1 * lc1 + m2 * l1) * g * math.cos(theta1 - math.pi / 2) + phi2)
    ddtheta2 = ((a + d2 / d1 * phi1 - m2 * l1 * lc2 * dtheta1 ** 2 * math.sin(theta2) - phi2)
                / (m2 * lc2 ** 2 + I2 - d2 ** 2 / d1))
    ddtheta1 = -(d2 * ddtheta2 + phi1) / d1
    return np.array([dtheta1, dtheta2, ddtheta1, ddtheta2])


def np_acrobot_energy(x):
    """Kinetic energy of the two centres of mass and the links' rotation, and gravity; zero hanging at rest."""
    m1, m2, l1, lc1, lc2, I1, I2, g = ACRO.values()
    t1, t2, w1, w2 = x
    v1 = lc1 * w1 * np.array([math.cos(t1), math.sin(t1)])          # centre 1 at lc1 (sin t1, -cos t1)
    v2 = l1 * w1 * np.array([math.cos(t1), math.sin(t1)]) + lc2 * (w1 + w2) * np.array([math.cos(t1 + t2),
                                                                                         math.sin(t1 + t2)])
    kinetic = 0.5 * m1 * v1 @ v1 + 0.5 * m2 * v2 @ v2 + 0.5 * I1 * w1 ** 2 + 0.5 * I2 * (w1 + w2) ** 2
    height1, height2 = -lc1 * math.cos(t1), -l1 * math.cos(t1) - lc2 * math.cos(t1 + t2)
    return kinetic + g * (m1 * (height1 + lc1) + m2 * (height2 + l1 + lc2))


def call(f, x, u, ud):
    return np.asarray(f(jnp.asarray(x), jnp.asarray(u), jnp.asarray(ud)))


@pytest.fixture
def rng():
    return np.random.default_rng(RNG_SEED)


# --------------------------------------------------------------------------------------------
# Dynamics against the reference formulas
# --------------------------------------------------------------------------------------------
def test_point_mass_dynamics_match_reference_and_only_ud_drives(rng):
    f = models.point_mass().dynamics
    for _ in range(5):
        x, u, u2, ud = rng.normal(size=4), rng.normal(size=2), rng.normal(size=2), rng.normal(size=2)
        np.testing.assert_allclose(call(f, x, u, ud), np_point_mass_f(x, ud), rtol=1e-14, atol=1e-14)
        np.testing.assert_array_equal(call(f, x, u, ud), call(f, x, u2, ud))
    assert not np.allclose(call(f, x, u, ud), call(f, x, u, ud + 1.0))


def test_arm2_dynamics_match_reference_and_only_ud_drives(rng):
    f = models.arm2().dynamics
    for _ in range(5):
        x = np.concatenate([rng.uniform(-np.pi, np.pi, 2), rng.normal(scale=3.0, size=2)])
        u, u2, ud = rng.normal(size=2), rng.normal(size=2), rng.normal(size=2)
        np.testing.assert_allclose(call(f, x, u, ud), np_arm_f(x, ud), rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(call(f, x, u, ud), call(f, x, u2, ud))
    assert not np.allclose(call(f, x, u, ud), call(f, x, u, ud + 1.0))


def test_arm2_building_blocks_match_reference(rng):
    p = models.ARM2_PARAMS
    assert (p.m1, p.m2, p.l1, p.l2, p.s1, p.s2, p.I1, p.I2) == (1.4, 1.1, 0.30, 0.33, 0.11, 0.16, 0.025, 0.045)
    np.testing.assert_array_equal(np.asarray(p.B), ARM["B"])
    q, dq, tau = rng.normal(size=2), rng.normal(size=2), rng.normal(size=2)
    np.testing.assert_allclose(models.mass_matrix(jnp.asarray(q), p), np_arm_M(q), rtol=1e-14)
    np.testing.assert_allclose(models.mass_matrix_inverse(jnp.asarray(q), p), np.linalg.inv(np_arm_M(q)), rtol=1e-12)
    np.testing.assert_allclose(models.coriolis(jnp.asarray(q), jnp.asarray(dq), p), np_arm_C(q, dq), rtol=1e-14)
    np.testing.assert_allclose(models.joint_acceleration(jnp.asarray(q), jnp.asarray(dq), jnp.asarray(tau), p),
                               np_arm_f(np.concatenate([q, dq]), tau)[2:], rtol=1e-12)
    np.testing.assert_allclose(models.hand_position(jnp.asarray(q), p), np_hand(q), rtol=1e-14)
    # hand velocity = d/dt e(q + t dq) at t = 0, by central differences of the NumPy kinematics
    h = 1e-6
    fd = (np_hand(q + h * dq) - np_hand(q - h * dq)) / (2 * h)
    np.testing.assert_allclose(models.hand_velocity(jnp.asarray(q), jnp.asarray(dq), p), fd, rtol=1e-7, atol=1e-9)
    # leading batch axes are supported
    qs, dqs = rng.normal(size=(3, 5, 2)), rng.normal(size=(3, 5, 2))
    assert models.mass_matrix(jnp.asarray(qs), p).shape == (3, 5, 2, 2)
    batched = models.joint_acceleration(jnp.asarray(qs), jnp.asarray(dqs), jnp.zeros((3, 5, 2)), p)
    np.testing.assert_allclose(batched[1, 2], np_arm_f(np.concatenate([qs[1, 2], dqs[1, 2]]), np.zeros(2))[2:],
                               rtol=1e-12)
    assert models.hand_velocity(jnp.asarray(qs), jnp.asarray(dqs), p).shape == (3, 5, 2)


def test_cart_pole_matches_florian_equations_after_change_of_angle(rng):
    # theta (from hanging down, counter-clockwise) = pi - phi (Florian's angle from upright)
    f = models.cart_pole().dynamics
    for _ in range(5):
        x = np.array([rng.normal(), rng.uniform(-np.pi, np.pi), rng.normal(), rng.normal(scale=3.0)])
        force = rng.normal(scale=5.0)
        ddx, ddphi = np_florian_up(np.pi - x[1], -x[3], force)
        out = call(f, x, np.array([7.0]), np.array([force]))
        np.testing.assert_allclose(out, [x[2], x[3], ddx, -ddphi], rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(out, call(f, x, np.array([-3.0]), np.array([force])))


def test_acrobot_matches_trajax_closed_form_and_only_the_delayed_elbow_torque_drives(rng):
    f = models.acrobot().dynamics
    for _ in range(5):
        x = np.concatenate([rng.uniform(-np.pi, np.pi, 2), rng.normal(scale=3.0, size=2)])
        torque = rng.normal(scale=5.0)
        out = call(f, x, np.array([7.0]), np.array([torque]))
        np.testing.assert_allclose(out, np_acrobot_trajax(x, torque), rtol=1e-12, atol=1e-12)
        np.testing.assert_array_equal(out, call(f, x, np.array([-3.0]), np.array([torque])))
        np.testing.assert_allclose(float(f.energy(jnp.asarray(x))), np_acrobot_energy(x), rtol=1e-13)
    assert not np.allclose(out, call(f, x, np.zeros(1), np.array([torque + 1.0])))


def test_acrobot_cost_of_rest_is_trajax_pinned_value():
    # trajax's testAcrobotSolve: objective of U = 0 from x0 = 0 (Euler, dt = 0.1, T = 50) is 4959.476212
    from delayed_ilqr.ilqg.linearize import rollout, trajectory_cost
    problem = models.acrobot()
    us = jnp.zeros((problem.horizon, 1))
    assert abs(float(trajectory_cost(problem, rollout(problem, us), us)) - 4959.476212) < 1e-6
    # the running cost is trajax's 0.5 * 0.1 |x - x*|^2 + 0.5 * 0.01 u^2 per step of 0.1 s
    x, u = np.array([0.3, -0.2, 1.0, 0.5]), np.array([2.0])
    err = x - np.array([np.pi, 0, 0, 0])
    running = float(problem.cost.running(jnp.asarray(x), jnp.asarray(u))) * problem.dt
    np.testing.assert_allclose(running, 0.05 * err @ err + 0.005 * u @ u, rtol=1e-14)
    np.testing.assert_allclose(float(problem.cost.final(jnp.asarray(x))), 500.0 * err @ err, rtol=1e-14)


def test_power_balance_of_pendulum_cart_pole_and_acrobot(rng):
    """dE/dt along f equals the power of the acting input (minus damping): an exact identity."""
    pend = models.pendulum().dynamics
    m, l, g, b = 1.0, 1.0, 9.81, 0.01
    for _ in range(5):
        x, ud = rng.normal(size=2), rng.normal(size=1)
        dth, ddth = call(pend, x, np.zeros(1), ud)
        dE = m * l ** 2 * x[1] * ddth + m * g * l * math.sin(x[0]) * dth  # E = ml^2 w^2/2 + mgl(1 - cos)
        np.testing.assert_allclose(dE, ud[0] * x[1] - b * x[1] ** 2, rtol=1e-12, atol=1e-12)
    # the input's power: the force times the cart's speed, the elbow torque times the elbow's rate
    for dynamics, energy, driven in ((models.cart_pole().dynamics, np_cart_pole_energy, 2),
                                     (models.acrobot().dynamics, np_acrobot_energy, 3)):
        for _ in range(5):
            x, ud = rng.normal(size=4), rng.normal(size=1)
            xdot = call(dynamics, x, np.zeros(1), ud)
            h = 1e-6
            dE = (energy(x + h * xdot) - energy(x - h * xdot)) / (2 * h)
            np.testing.assert_allclose(dE, ud[0] * x[driven], rtol=1e-6, atol=1e-7)


def _euler_energy_drift(f, energy, x0, dt, steps):
    @jax.jit
    def run(x0):
        def step(x, _):
            return x + dt * f(x, jnp.zeros(1), jnp.zeros(1)), None
        return jax.lax.scan(step, x0, None, length=steps)[0]
    xT = np.asarray(run(jnp.asarray(x0)))
    return energy(np.asarray(x0)), energy(xT), xT


def test_undamped_pendulum_conserves_energy_under_small_step_euler():
    f = PendulumDynamics(damping=0.0)
    energy = lambda x: 0.5 * x[1] ** 2 + 9.81 * (1 - math.cos(x[0]))  # noqa: E731  (m = l = 1)
    e0, eT, xT = _euler_energy_drift(f, energy, [1.0, 0.0], 1e-5, 100_000)  # 1 s
    assert not np.allclose(xT, [1.0, 0.0])  # it did move
    assert abs(eT - e0) < 1e-3 * e0
    # with the default damping the energy decreases
    e0, eT, _ = _euler_energy_drift(models.pendulum().dynamics, energy, [1.0, 0.0], 1e-4, 10_000)
    assert eT < e0 - 1e-4


def test_cart_pole_conserves_energy_under_small_step_euler():
    f = models.cart_pole().dynamics
    e0, eT, xT = _euler_energy_drift(f, np_cart_pole_energy, [0.0, 1.0, 0.3, -0.5], 1e-5, 100_000)
    assert abs(xT[1] - 1.0) > 0.1
    assert abs(eT - e0) < 1e-3 * abs(e0 - np_cart_pole_energy(np.zeros(4))) + 1e-9


def test_acrobot_conserves_energy_under_small_step_euler():
    f = models.acrobot().dynamics
    e0, eT, xT = _euler_energy_drift(f, np_acrobot_energy, [1.0, -0.5, 0.3, 0.8], 1e-5, 100_000)
    assert abs(xT[0] - 1.0) > 0.1 and abs(xT[1] + 0.5) > 0.1
    assert abs(eT - e0) < 1e-3 * e0


def test_acrobot_hanging_and_upright_are_equilibria():
    problem = models.acrobot()
    f, z = problem.dynamics, np.zeros(1)
    down, up = np.zeros(4), np.array([np.pi, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(call(f, down, z, z), np.zeros(4), atol=1e-15)
    np.testing.assert_allclose(call(f, up, z, z), np.zeros(4), atol=1e-14)
    np.testing.assert_allclose(np.asarray(problem.cost.params["x_target"]), up)
    jac = lambda x: np.asarray(jax.jacfwd(f)(jnp.asarray(x), jnp.zeros(1), jnp.zeros(1)))  # noqa: E731
    assert np.max(np.abs(np.linalg.eigvals(jac(down)).real)) <= 1e-12   # undamped: oscillates
    assert np.max(np.linalg.eigvals(jac(up)).real) > 1.0
    # the elbow torque acts on both joints through the mass matrix (underactuated: one input, two joints)
    b = np.asarray(jax.jacfwd(f, argnums=2)(jnp.asarray(down), jnp.zeros(1), jnp.zeros(1)))[:, 0]
    assert b[0] == 0 and b[1] == 0 and b[2] < 0 < b[3]


@pytest.mark.parametrize("factory, n", [(models.pendulum, 2), (models.cart_pole, 4)])
def test_hanging_and_upright_are_equilibria(factory, n):
    problem = factory()
    f, z = problem.dynamics, np.zeros(1)
    down, up = np.zeros(n), np.zeros(n)
    up[n // 2 - 1] = np.pi  # theta is the last position coordinate
    np.testing.assert_allclose(call(f, down, z, z), np.zeros(n), atol=1e-15)
    np.testing.assert_allclose(call(f, up, z, z), np.zeros(n), atol=1e-14)
    np.testing.assert_allclose(np.asarray(problem.cost.x_target), up)
    # down is stable, up is unstable: the linearisation about up has an eigenvalue with positive real part
    jac = lambda x: np.asarray(jax.jacfwd(f)(jnp.asarray(x), jnp.zeros(1), jnp.zeros(1)))  # noqa: E731
    assert np.max(np.linalg.eigvals(jac(down)).real) <= 1e-12
    assert np.max(np.linalg.eigvals(jac(up)).real) > 1.0


# --------------------------------------------------------------------------------------------
# Problem data
# --------------------------------------------------------------------------------------------
PF_REF = np.diag([1e3, 1e3, 1e1, 1e1])
REFERENCE_DATA = [  # factory, kwargs, x0, x_target, dt, K, l
    (models.point_mass, dict(), [0, 0, 0, 0], [0.2, 0.1, 0, 0], 0.01, 60, 0),
    (models.point_mass, dict(delay=0.03), [0, 0, 0, 0], [0.2, 0.1, 0, 0], 0.01, 60, 3),
    (models.point_mass, dict(delay=0.1), [0, 0, 0, 0], [0.2, 0.1, 0, 0], 0.01, 60, 10),
    (models.arm2, dict(), [np.pi / 4, np.pi / 2, 0, 0], [np.pi / 2, np.pi / 3, 0, 0], 0.01, 50, 0),
    (models.arm2, dict(delay=0.03), [np.pi / 4, np.pi / 2, 0, 0], [np.pi / 2, np.pi / 3, 0, 0], 0.01, 50, 3),
    (models.arm2, dict(delay=0.1), [np.pi / 4, np.pi / 2, 0, 0], [np.pi / 2, np.pi / 3, 0, 0], 0.01, 50, 10),
    (models.arm2, dict(dt=0.002, delay=0.1), [np.pi / 4, np.pi / 2, 0, 0], [np.pi / 2, np.pi / 3, 0, 0],
     0.002, 250, 50),  # P3
] + [(models.point_mass, dict(dt=0.001, delay=l * 0.001), [0, 0, 0, 0], [0.2, 0.1, 0, 0], 0.001, 600, l)
     for l in (1, 10, 50, 100, 200)]  # P4


@pytest.mark.parametrize("factory, kwargs, x0, x_target, dt, K, l", REFERENCE_DATA)
def test_reference_problem_data(factory, kwargs, x0, x_target, dt, K, l):
    problem = factory(**kwargs)
    assert isinstance(problem, Problem) and isinstance(problem.cost, QuadraticCost)
    assert problem.name == factory.__name__
    assert (problem.horizon, problem.delay_steps, problem.n_states, problem.n_controls) == (K, l, 4, 2)
    assert problem.dt == dt and problem.n_noise == 0 and not problem.has_limits
    np.testing.assert_array_equal(np.asarray(problem.x0), np.array(x0, float))
    np.testing.assert_array_equal(np.asarray(problem.cost.x_target), np.array(x_target, float))
    np.testing.assert_array_equal(np.asarray(problem.cost.P), np.zeros((4, 4)))
    np.testing.assert_array_equal(np.asarray(problem.cost.Q), 1e-4 * np.eye(2))
    np.testing.assert_array_equal(np.asarray(problem.cost.P_final), PF_REF)


def test_p1_noisy_diffusion_matches_hand_built_matrix(rng):
    problem = models.point_mass(noise=True)
    assert problem.n_noise == 4
    x, u, ud = rng.normal(size=4), rng.normal(size=2), rng.normal(size=2)
    F = call(problem.noise, x, u, ud)
    hand = np.array([[0, 0, 0, 0], [0, 0, 0, 0], [0.5 * ud[0], 0, 0.05, 0], [0, 0.5 * ud[1], 0, 0.05]])
    np.testing.assert_allclose(F, hand, rtol=1e-15, atol=1e-16)
    np.testing.assert_allclose(F, np_point_mass_F(ud), rtol=1e-15)
    np.testing.assert_array_equal(F, call(problem.noise, x + 1, u + 1, ud))  # depends on ud only


def test_p2_noisy_diffusion_matches_reference(rng):
    problem = models.arm2(noise="benchmark")
    assert problem.n_noise == 2
    for _ in range(3):
        x, u, ud = rng.normal(size=4), rng.normal(size=2), rng.normal(size=2)
        F = call(problem.noise, x, u, ud)
        expected = np.vstack([np.zeros((2, 2)), np.linalg.inv(np_arm_M(x[:2])) @ (0.2 * np.diag(ud))])
        np.testing.assert_allclose(F, expected, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("factory, n", [(models.pendulum, 2), (models.cart_pole, 4)])
def test_swing_up_problem_data(factory, n):
    problem = factory()
    sizes = (problem.n_states, problem.n_controls, problem.dt, problem.horizon, problem.delay_steps)
    assert sizes == (n, 1, 0.02, 150, 0)
    np.testing.assert_array_equal(np.asarray(problem.x0), np.zeros(n))
    assert problem.has_limits
    u_max = 4.0 if factory is models.pendulum else 10.0
    np.testing.assert_array_equal(np.asarray(problem.u_min), [-u_max])
    np.testing.assert_array_equal(np.asarray(problem.u_max), [u_max])
    free = factory(limits=False, delay=0.1)
    assert not free.has_limits and free.delay_steps == 5
    noisy = factory(noise=True)
    assert noisy.n_noise == 1
    x, ud = np.full(n, 0.3), np.array([2.0])
    F = call(noisy.noise, x, np.zeros(1), ud)
    drift = call(noisy.dynamics, x, np.zeros(1), ud) - call(noisy.dynamics, x, np.zeros(1), np.zeros(1))
    np.testing.assert_allclose(F[:, 0], 0.1 * drift, rtol=1e-12, atol=1e-15)  # sigma_u ud df/dud, f affine in ud


def test_acrobot_problem_data():
    problem = models.acrobot()
    sizes = (problem.n_states, problem.n_controls, problem.dt, problem.horizon, problem.delay_steps)
    assert sizes == (4, 1, 0.1, 50, 0) and problem.name == "acrobot" and problem.n_noise == 0
    np.testing.assert_array_equal(np.asarray(problem.x0), np.zeros(4))
    np.testing.assert_array_equal(np.asarray(problem.u_min), [-5.0])
    np.testing.assert_array_equal(np.asarray(problem.u_max), [5.0])
    free = models.acrobot(limits=False, delay=0.3, dt=0.05)
    assert not free.has_limits and (free.delay_steps, free.horizon) == (6, 100)
    assert float(models.acrobot(u_max=2.0).u_max[0]) == 2.0
    noisy = models.acrobot(noise=True)
    x, ud = np.array([0.3, -1.0, 0.5, 2.0]), np.array([2.0])
    F = call(noisy.noise, x, np.zeros(1), ud)
    drift = call(noisy.dynamics, x, np.zeros(1), ud) - call(noisy.dynamics, x, np.zeros(1), np.zeros(1))
    np.testing.assert_allclose(F[:, 0], 0.1 * drift, rtol=1e-12, atol=1e-15)


def test_delayed_acrobot_is_the_undelayed_one_driven_by_the_shifted_commands(rng):
    # l = 2 (0.2 s): the command sent at step k acts at k + 2, and u = 0 acts before the first one arrives
    from delayed_ilqr.ilqg.linearize import rollout
    delayed, plain = models.acrobot(delay=0.2, limits=False), models.acrobot(limits=False)
    us = rng.uniform(-3.0, 3.0, (plain.horizon, 1))
    shifted = np.concatenate([np.zeros((2, 1)), us[:-2]])
    np.testing.assert_allclose(np.asarray(rollout(delayed, jnp.asarray(us))),
                               np.asarray(rollout(plain, jnp.asarray(shifted))), rtol=1e-13, atol=1e-13)
    assert not np.allclose(np.asarray(rollout(delayed, jnp.asarray(us))), np.asarray(rollout(plain, jnp.asarray(us))))


# --------------------------------------------------------------------------------------------
# Derivatives
# --------------------------------------------------------------------------------------------
ALL_PROBLEMS = [models.point_mass(noise=True), models.arm2(noise="benchmark"), models.pendulum(noise=True),
                models.cart_pole(noise=True), models.acrobot(noise=True)]


def _central_differences(fn, args, which, h=1e-6):
    base = [np.array(a, float) for a in args]
    out = []
    for i in range(base[which].size):
        plus, minus = [a.copy() for a in base], [a.copy() for a in base]
        plus[which][i] += h
        minus[which][i] -= h
        out.append((np.asarray(fn(*map(jnp.asarray, plus))) - np.asarray(fn(*map(jnp.asarray, minus)))) / (2 * h))
    return np.stack(out, axis=-1)


@pytest.mark.parametrize("problem", ALL_PROBLEMS, ids=lambda p: p.name)
def test_jacobians_match_central_differences(problem, rng):
    n, d = problem.n_states, problem.n_controls
    x = rng.normal(size=n)
    u, ud = rng.normal(size=d), rng.normal(size=d)
    for fn in (problem.dynamics, problem.noise):
        # the three Jacobians compiled as one program (outside a jit each operation compiles apart)
        jacobians = jax.jit(jax.jacfwd(fn, argnums=(0, 1, 2)))(jnp.asarray(x), jnp.asarray(u), jnp.asarray(ud))
        for which in range(3):
            fd = _central_differences(fn, (x, u, ud), which)
            np.testing.assert_allclose(np.asarray(jacobians[which]), fd, rtol=1e-6, atol=1e-7)
        # the plant and its noise do not depend on the command sent now (u): only ud acts
        assert np.all(np.asarray(jacobians[1]) == 0)


# --------------------------------------------------------------------------------------------
# delay_to_steps and argument checks
# --------------------------------------------------------------------------------------------
def test_delay_to_steps_accepts_whole_steps_despite_rounding():
    assert models.delay_to_steps(0.03, 0.01) == 3
    assert models.delay_to_steps(0.0, 0.01) == 0
    assert models.delay_to_steps(0.1, 0.002) == 50
    assert models.delay_to_steps(0.7, 0.1) == 7
    assert all(models.delay_to_steps(l * 0.001, 0.001) == l for l in range(0, 1001))
    assert type(models.delay_to_steps(np.float64(0.06), 0.02)) is int


def test_delay_to_steps_rejects_bad_delays():
    with pytest.raises(ValueError, match=re.escape(
            "delay must be a whole number of steps of dt=0.01 s; got 0.025 s (2.5 steps)")):
        models.delay_to_steps(0.025, 0.01)
    with pytest.raises(ValueError, match=re.escape("delay must be a non-negative finite number of seconds; got -0.01")):
        models.delay_to_steps(-0.01, 0.01)
    with pytest.raises(ValueError, match=re.escape("delay must be a non-negative finite number of seconds; got nan")):
        models.delay_to_steps(float("nan"), 0.01)
    with pytest.raises(ValueError, match=re.escape("tau must be a non-negative finite number of seconds; got inf")):
        models.delay_to_steps(float("inf"), 0.01, name="tau")
    with pytest.raises(ValueError, match=re.escape("delay must be a non-negative finite number of seconds; got True")):
        models.delay_to_steps(True, 0.01)
    with pytest.raises(ValueError, match=re.escape("dt must be a positive finite number; got 0")):
        models.delay_to_steps(0.0, 0)


@pytest.mark.parametrize("factory", [models.point_mass, models.arm2, models.pendulum, models.cart_pole,
                                     models.acrobot])
def test_factories_validate_arguments_by_name(factory):
    assert np.allclose(factory(delay=0.025, dt=0.01).delay_in_steps, 2.5)      # a fractional delay (§20)
    with pytest.raises(ValueError, match=re.escape("delay must be a non-negative finite number of seconds; got -0.1")):
        factory(delay=-0.1)
    with pytest.raises(ValueError, match=re.escape("dt must be a positive finite number; got -0.01")):
        factory(dt=-0.01)
    with pytest.raises(ValueError, match=re.escape("horizon must be a positive integer; got 0")):
        factory(horizon=0)
    with pytest.raises(ValueError, match=re.escape("horizon must be a positive integer; got 2.5")):
        factory(horizon=2.5)
    with pytest.raises((TypeError, ValueError), match=re.escape("noise must be True")):
        factory(noise="yes")                        # a name no model has as a noise preset
    with pytest.raises(ValueError, match=re.escape("x0 must have shape")):
        factory(x0=(0.0,))
    with pytest.raises(ValueError, match=re.escape("x_target must be finite")):
        factory(x_target=(np.nan,) * factory().n_states)
    assert factory(horizon=7).horizon == 7


def test_arm2_params_are_validated_and_presets_differ():
    with pytest.raises(TypeError, match=re.escape("params must be an Arm2Params; got dict")):
        models.arm2(params={})
    with pytest.raises(ValueError, match=re.escape("params.l1 must be positive; got -0.3")):
        models.arm2(params=models.ARM2_PARAMS._replace(l1=-0.3))
    alt = models.arm2(params=models.ARM2_PARAMS_ARM_DYN)
    np.testing.assert_array_equal(np.asarray(models.ARM2_PARAMS_ARM_DYN.B), [[0.5, 0.1], [0.1, 0.5]])
    x = np.array([0.3, 1.0, 1.0, -1.0])
    z = np.zeros(2)
    assert not np.allclose(call(alt.dynamics, x, z, z), call(models.arm2().dynamics, x, z, z))


# --------------------------------------------------------------------------------------------
# Hashing by value: equal problems share one compilation
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("factory", [models.point_mass, models.arm2, models.pendulum, models.cart_pole,
                                     models.acrobot])
def test_equal_arguments_give_equal_hashable_callables_and_no_recompilation(factory):
    a, b = factory(noise=True), factory(noise=True)
    assert a.dynamics == b.dynamics and hash(a.dynamics) == hash(b.dynamics)
    assert a.noise == b.noise and hash(a.noise) == hash(b.noise)
    traces = []

    @jax.jit
    def evaluate(problem):
        traces.append(1)
        z = jnp.zeros(problem.n_controls)
        return problem.dynamics(problem.x0, z, z), problem.noise(problem.x0, z, z)

    evaluate(a)
    evaluate(b)
    evaluate(factory(noise=True, x0=np.asarray(a.x0) + 0.1))  # x0 is data, not static
    assert len(traces) == 1
    evaluate(factory(noise=True, delay=2 * a.dt))  # a different delay is a different static problem
    assert len(traces) == 2


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------
def test_registry_lists_every_model_with_a_description():
    assert set(models.REGISTRY) == {"point_mass", "arm2", "pendulum", "cart_pole", "acrobot",
                                    "arm2_muscle6", "planar_quadrotor"}
    for name, info in models.REGISTRY.items():
        assert isinstance(info.description, str) and info.description and "\n" not in info.description
        problem = info.factory(delay=0.0, noise=False)
        assert isinstance(problem, Problem) and problem.name == name
    assert models.REGISTRY["pendulum"].factory is models.pendulum
    assert arm2_module.FINAL_TIME == 0.5 and cart_pole_module.FINAL_TIME == 3.0


# --------------------------------------------------------------------------------------------
# Metadata: labels, task space, warm start (what studies and figures read instead of the name)
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(models.REGISTRY))
def test_every_model_carries_labels_with_units_and_a_task_space(name):
    problem = models.REGISTRY[name].factory(delay=0.0, noise=True)
    meta = problem.metadata
    assert isinstance(meta, models.ModelMetadata)
    assert len(meta.state_labels) == problem.n_states and len(meta.control_labels) == problem.n_controls
    assert len(set(meta.state_labels)) == problem.n_states
    assert isinstance(meta.task, models.TaskSpace) and meta.task.unit in ("m", "rad")
    assert all(re.search(r"\[.+\]$", s) for s in meta.state_labels[:4])     # mechanical states have units
    # metadata survives replace and the pytree round trip (static data, equal by value)
    assert problem.replace(delay_steps=1).metadata == meta
    leaves, treedef = jax.tree_util.tree_flatten(problem)
    assert jax.tree_util.tree_unflatten(treedef, leaves).metadata == meta
    assert models.REGISTRY[name].factory(delay=0.0, noise=True).metadata == meta


def test_task_spaces_map_states_to_positions_and_targets():
    from delayed_ilqr.models.metadata import default_u_init, task_position, task_target
    arm = models.arm2()
    np.testing.assert_allclose(task_target(arm), models.hand_position(jnp.asarray(arm.cost.x_target[:2])))
    x = np.random.default_rng(RNG_SEED).standard_normal((3, 5, 4))
    np.testing.assert_array_equal(task_position(arm, x), models.hand_position(jnp.asarray(x[..., :2])))
    mass = models.point_mass()
    np.testing.assert_array_equal(task_position(mass, x), x[..., :2])
    np.testing.assert_array_equal(task_target(mass), [0.2, 0.1])
    muscle = models.arm2_muscle6(target=(0.02, 0.4))
    np.testing.assert_array_equal(task_target(muscle), [0.02, 0.4])
    np.testing.assert_array_equal(default_u_init(muscle), models.rest_commands(muscle))
    assert default_u_init(arm) is None
    np.testing.assert_array_equal(task_target(models.cart_pole()), [math.pi])
    np.testing.assert_array_equal(task_target(models.acrobot()), [math.pi, 0.0])
    np.testing.assert_array_equal(task_target(models.acrobot(x_target=(3.0, 0.1, 0, 0))), [3.0, 0.1])
    # a plant without metadata: no task space, zero initial commands
    bare = mass.replace(metadata=None)
    assert task_target(bare) is None and task_position(bare, x) is None and default_u_init(bare) is None


def test_metadata_must_be_hashable_and_well_formed():
    with pytest.raises(TypeError, match="metadata must be None or a hashable ModelMetadata; got dict"):
        models.point_mass().replace(metadata={"labels": ()})
    with pytest.raises(TypeError, match="state_labels must be a tuple of strings"):
        models.ModelMetadata(state_labels=["x"], control_labels=("u",))
