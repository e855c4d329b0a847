"""Acrobot swing-up with a delayed, limited torque at the elbow (underactuated).

Two links in a vertical plane, hinged at a fixed shoulder; only the elbow is driven. The plant,
its parameters, time step, horizon and cost are those of trajax's test suite (google/trajax,
``tests/optimizers_test.py``: ``acrobot``, ``testAcrobotSolve``, ``testConstrainedAcrobotSolve``),
which writes Gym's Acrobot (the "book" dynamics of Sutton & Barto's Reinforcement Learning, after
Spong 1995, "The swing up control problem for the Acrobot", IEEE Control Systems 15(1)). Here the
same equations are written in Spong's manipulator form (Tedrake, Underactuated Robotics, chapter
"Acrobots, Cart-Poles, and Quadrotors"), with I1, I2 the links' inertias about their centres of
mass:

    x = [theta1, theta2, dtheta1, dtheta2]   theta1 = 0 hanging down, theta2 relative to link 1
    M(q) ddq + C(q, dq) + G(q) = [0, ud]       ud = elbow torque (N m), acting l dt after it is sent
    M11 = m1 lc1^2 + m2 (l1^2 + lc2^2 + 2 l1 lc2 cos theta2) + I1 + I2
    M12 = M21 = m2 (lc2^2 + l1 lc2 cos theta2) + I2,       M22 = m2 lc2^2 + I2
    C   = m2 l1 lc2 sin theta2 [-(2 dtheta1 dtheta2 + dtheta2^2), dtheta1^2]
    G   = [(m1 lc1 + m2 l1) g sin theta1 + m2 lc2 g sin(theta1 + theta2), m2 lc2 g sin(theta1 + theta2)]

Parameters (borrowed from trajax, which has Gym's values; chosen: the rest):

| parameter | value | source or note |
|---|---|---|
| m1, m2 | 1 kg, 1 kg | link masses |
| l1 | 1 m | length of link 1 (link 2's length does not enter) |
| lc1, lc2 | 0.5 m, 0.5 m | joint to centre of mass |
| I1, I2 | 1 kg m^2 | inertias about the centres of mass |
| g | 9.8 m/s^2 |  |
| u_max | 5 N m | trajax's ``testConstrainedAcrobotSolve`` (&#124;u&#124; <= 5); the unbounded optimum peaks at 8.6 N m, so the limit binds; ``limits=False`` drops it |
| dt | 0.1 s | Euler steps, as in trajax's ``testAcrobotSolve`` |
| tf | 5 s | horizon K = 50 |
| cost | trajax's | running (x - x*)'P (x - x*) + u'Q u per unit time with P = 0.5 I, Q = 0.05 (trajax's 0.5 * 0.1 &#124;x - x*&#124;^2 + 0.5 * 0.01 u^2 per step of 0.1 s), final 500 &#124;x - x*&#124;^2 |
| x0, target | [0, 0, 0, 0] -> [pi, 0, 0, 0] |  |
| noise (opt.) | chosen | F = sigma_u ud * d f / d ud (p = 1), sigma_u = 0.1: signal-dependent torque noise |

The cost is a [`GeneralCost`][delayed_ilqr.GeneralCost] (its running term tracks the target, which a
[`QuadraticCost`][delayed_ilqr.QuadraticCost] cannot); its weights and target are ``cost.params``, data.
Check of the transcription: the cost of u = 0 is 4959.476212, trajax's pinned value, and the
unbounded optimum from rest is 44.513 (trajax asserts below 51). x0 = 0 with u = 0 is an
equilibrium; the running cost's gradient starts the swing. With elbow limits of 2.4 N m and less
the swing-up from rest stops at a poor local minimum, and at 3 N m at one 1.1 % above the best
known (``docs/derivation.md`` §15: several starts, [`solve_from_starts`][delayed_ilqr.solve_from_starts]).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp

from ..problem import GeneralCost, Problem
from . import _common
from .metadata import ModelMetadata, StateComponents, TaskSpace

__all__ = ["acrobot", "AcrobotDynamics", "AcrobotNoise", "TrackingRunningCost", "TrackingFinalCost",
           "FINAL_TIME", "U_MAX"]

MASS = (1.0, 1.0)  # kg
LENGTH_1 = 1.0  # m
COM = (0.5, 0.5)  # m, joint to centre of mass
INERTIA = (1.0, 1.0)  # kg m^2, about the centre of mass
GRAVITY = 9.8  # m / s^2
U_MAX = 5.0  # N m
SIGMA_U = 0.1
FINAL_TIME = 5.0  # s
P_RUN = 0.5  # per unit time
Q_U = 0.05  # per unit time
P_FINAL = 500.0


@dataclass(frozen=True)
class _AngleTarget:
    """The task target: the target's joint angles, from ``cost.params["x_target"]``."""

    def __call__(self, problem):
        return problem.cost.params["x_target"][:2]


METADATA = ModelMetadata(
    state_labels=("shoulder angle theta1 [rad]", "elbow angle theta2 [rad]", "shoulder angular velocity [rad/s]",
                  "elbow angular velocity [rad/s]"),
    control_labels=("elbow torque u [N m]",),
    task=TaskSpace(map=StateComponents((0, 1)), name="joint angles", unit="rad", point="acrobot",
                   target=_AngleTarget()))
"""Labels, and the two joint angles as the task space (upright: theta1 = pi, theta2 = 0)."""


@dataclass(frozen=True)
class AcrobotDynamics:
    """f(x, u, ud) = [dq, M(q)^-1 ([0, ud] - C(q, dq) - G(q))] (module docstring); equal by value."""

    masses: tuple = MASS
    length_1: float = LENGTH_1
    com: tuple = COM
    inertias: tuple = INERTIA
    gravity: float = GRAVITY

    def mass_matrix(self, q):
        """M(q) [2, 2] for q = [theta1, theta2]."""
        (m1, m2), (lc1, lc2), (i1, i2), l1 = self.masses, self.com, self.inertias, self.length_1
        cos2 = jnp.cos(q[1])
        m22 = m2 * lc2 ** 2 + i2
        m12 = m22 + m2 * l1 * lc2 * cos2
        m11 = m1 * lc1 ** 2 + m2 * (l1 ** 2 + lc2 ** 2 + 2 * l1 * lc2 * cos2) + i1 + i2
        return jnp.stack([jnp.stack([m11, m12]), jnp.stack([m12, m22])])

    def bias(self, q, dq):
        """C(q, dq) + G(q) [2]: Coriolis, centrifugal and gravity torques."""
        (m1, m2), (lc1, lc2), l1, g = self.masses, self.com, self.length_1, self.gravity
        h = m2 * l1 * lc2 * jnp.sin(q[1])
        gravity_2 = m2 * lc2 * g * jnp.sin(q[0] + q[1])
        return jnp.stack([-h * (2 * dq[0] * dq[1] + dq[1] ** 2) + (m1 * lc1 + m2 * l1) * g * jnp.sin(q[0]) + gravity_2,
                          h * dq[0] ** 2 + gravity_2])

    def accelerations(self, x, torque):
        """ddq [2] for state x [4] and elbow torque ``torque`` (scalar): M^-1 ([0, torque] - C - G)."""
        q, dq = x[:2], x[2:]
        rhs = jnp.stack([jnp.zeros_like(torque), torque]) - self.bias(q, dq)
        return _solve_2x2(self.mass_matrix(q), rhs)

    def __call__(self, x, u, ud):
        return jnp.concatenate([x[2:], self.accelerations(x, ud[0])])

    def energy(self, x):
        """Mechanical energy [J] of x [4] (zero hanging at rest): dq'M(q)dq / 2 + V(q),
        V = (m1 lc1 + m2 l1) g (1 - cos theta1) + m2 lc2 g (1 - cos(theta1 + theta2))."""
        q, dq = x[:2], x[2:]
        (m1, m2), (lc1, lc2), l1, g = self.masses, self.com, self.length_1, self.gravity
        potential = (m1 * lc1 + m2 * l1) * g * (1 - jnp.cos(q[0])) + m2 * lc2 * g * (1 - jnp.cos(q[0] + q[1]))
        return 0.5 * dq @ self.mass_matrix(q) @ dq + potential


def _solve_2x2(m, b):
    """m^-1 b for a symmetric positive definite [2, 2] m, in closed form (Cramer's rule)."""
    det = m[0, 0] * m[1, 1] - m[0, 1] ** 2
    return jnp.stack([m[1, 1] * b[0] - m[0, 1] * b[1], m[0, 0] * b[1] - m[0, 1] * b[0]]) / det


@dataclass(frozen=True)
class AcrobotNoise:
    """F(x, u, ud) [4, 1] = sigma_u ud * (d f / d ud): torque noise proportional to the acting torque.

    f is affine in the torque, so d f / d ud = [0, 0, M(q)^-1 [0, 1]].
    """

    dynamics: AcrobotDynamics = AcrobotDynamics()
    sigma_u: float = SIGMA_U

    def __call__(self, x, u, ud):
        column = _solve_2x2(self.dynamics.mass_matrix(x[:2]), jnp.stack([jnp.zeros_like(ud[0]), jnp.ones_like(ud[0])]))
        scale = self.sigma_u * ud[0]
        return jnp.concatenate([jnp.zeros_like(column), scale * column])[:, None]


@dataclass(frozen=True)
class TrackingRunningCost:
    """running(x, u, params) = (x - x*)'P (x - x*) + u'Q u, per unit time (params: x_target, P, Q)."""

    def __call__(self, x, u, params):
        err = x - params["x_target"]
        return err @ params["P"] @ err + u @ params["Q"] @ u


@dataclass(frozen=True)
class TrackingFinalCost:
    """final(x, params) = (x - x*)'P_final (x - x*)."""

    def __call__(self, x, params):
        err = x - params["x_target"]
        return err @ params["P_final"] @ err


def acrobot(delay=0.0, noise=False, dt=0.1, horizon=None, limits=True, u_max=U_MAX,
            x0=(0.0, 0.0, 0.0, 0.0), x_target=(math.pi, 0.0, 0.0, 0.0)) -> Problem:
    """The acrobot swing-up with a delayed, optionally limited elbow torque (parameters: module docstring).

    Args:
        delay: input delay tau in seconds, any tau >= 0
            (a fraction of a step of ``dt`` by the zero-order hold, docs/derivation.md §20).
        noise: add the signal-dependent torque noise F = 0.1 ud df/dud (p = 1).
        dt: time step in seconds (the cost weights are per unit time: trajax's at dt = 0.1).
        horizon: K; default ``round(5.0 / dt)`` (50 at dt = 0.1).
        limits: True gives box limits |u| <= u_max on the elbow torque; False none.
        u_max: the torque limit in N m (used only when ``limits`` is True).
        x0: [4] initial [theta1, theta2, dtheta1, dtheta2] (0: hanging down at rest).
        x_target: [4] target of the running and final cost (default upright at rest).

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"acrobot"`` with a
        [`GeneralCost`][delayed_ilqr.GeneralCost] whose ``params`` are x_target, P, Q and P_final.
    """
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, FINAL_TIME)
    noise = _common.flag(noise, "noise")
    limits = _common.flag(limits, "limits")
    u_max = _common.positive(u_max, "u_max")
    x0 = _common.vector(x0, "x0", 4)
    x_target = _common.vector(x_target, "x_target", 4)
    params = {"x_target": jnp.array(x_target), "P": P_RUN * jnp.eye(4), "Q": Q_U * jnp.eye(1),
              "P_final": P_FINAL * jnp.eye(4)}
    cost = GeneralCost(TrackingRunningCost(), TrackingFinalCost(), params)
    lo, hi = ((-u_max,), (u_max,)) if limits else (None, None)
    dynamics = AcrobotDynamics()
    return Problem(dynamics=dynamics, x0=jnp.array(x0), dt=dt, horizon=horizon, delay_steps=delay_steps,
                   cost=cost, noise=AcrobotNoise(dynamics) if noise else None, u_min=lo, u_max=hi,
                   n_controls=1, name="acrobot", metadata=METADATA)
