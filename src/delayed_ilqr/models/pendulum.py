"""Torque-limited pendulum swing-up with a delayed torque.

A point mass m on a massless rod of length l, hinged at the top, with viscous damping b:

    x = [theta, dtheta]   theta = 0 hanging down, theta = pi upright (counter-clockwise positive)
    m l^2 ddtheta = ud - m g l sin(theta) - b dtheta          u = torque at the hinge (N m)

What is borrowed (``docs/models.md`` §5): m = l = 1 and the swing-up from 0 to pi as in the
TrajectoryOptimization.jl simple pendulum (with its viscous friction coefficient 0.01); the torque
limit in the spirit of Gym Pendulum-v1 (m = l = 1, |u| <= 2 with g = 10) and of Todorov & Li's (2005)
"limited-torque inverted pendulum", whose parameters were not retrieved. Chosen here:

| parameter | value | source or note |
|---|---|---|
| m, l | 1 kg, 1 m | point mass on a massless rod (inertia m l^2 = 1 kg m^2) |
| g | 9.81 m/s^2 |  |
| b | 0.01 | viscous damping, N m s / rad |
| u_max | 4 N m | 0.41 m g l, close to Gym Pendulum-v1's ratio of largest torque to largest gravity torque (6 / 15 = 0.4 in its rod model): the pendulum cannot be lifted directly and must be swung; ``limits=False`` drops the limit (the unconstrained optimum peaks near 5.7 N m, so the limit binds) |
| dt | 0.02 s |  |
| tf | 3 s | horizon K = 150 steps |
| cost | P = 0, Q = 1e-2, P_f = diag(100, 10) on (theta - pi, dtheta) |  |
| x0, target | [0, 0] -> [pi, 0] |  |
| noise (opt.) | F = [0; sigma_u ud / (m l^2)] (p = 1), sigma_u = 0.1: signal-dependent torque noise |  |

The torque that acts now is the command sent tau = l dt earlier (``ud``); ``u`` does not enter the
plant. Note that x0 = [0, 0] with u = 0 is an equilibrium, so the swing-up must come from the
target cost alone (its gradient through the linearised dynamics is non-zero).

Check of the choice (single shooting with L-BFGS-B, zero and random initial guesses): with the
limit and tf = 3 s the swing-up reaches theta_K = 3.138 (cost 0.40) without delay and 3.10 with a
0.1 s delay; u_max = 3 N m needs tf = 4 s, u_max = 2 N m fails within 4 s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp

from ..problem import Problem, QuadraticCost
from . import _common
from .metadata import ModelMetadata, StateComponents, TaskSpace

__all__ = ["pendulum", "PendulumDynamics", "PendulumNoise", "FINAL_TIME", "U_MAX"]

MASS = 1.0  # kg
LENGTH = 1.0  # m
GRAVITY = 9.81  # m / s^2
DAMPING = 0.01  # N m s / rad
U_MAX = 4.0  # N m
SIGMA_U = 0.1
FINAL_TIME = 3.0  # s
Q_U = 1e-2
P_FINAL = (100.0, 10.0)

METADATA = ModelMetadata(
    state_labels=("angle theta [rad]", "angular velocity [rad/s]"), control_labels=("torque u [N m]",),
    task=TaskSpace(map=StateComponents((0,)), name="angle", unit="rad", point="pendulum"))
"""Labels, and the angle theta as the task space (the endpoint error is |theta_K - theta_target|)."""


@dataclass(frozen=True)
class PendulumDynamics:
    """f(x, u, ud) = [dtheta, (ud - m g l sin theta - b dtheta) / (m l^2)]; equal by value."""

    mass: float = MASS
    length: float = LENGTH
    gravity: float = GRAVITY
    damping: float = DAMPING

    def __call__(self, x, u, ud):
        theta, dtheta = x[0], x[1]
        inertia = self.mass * self.length ** 2
        ddtheta = (ud[0] - self.mass * self.gravity * self.length * jnp.sin(theta) - self.damping * dtheta) / inertia
        return jnp.stack([dtheta, ddtheta])

    def energy(self, x):
        """Mechanical energy [J], zero hanging at rest: m l^2 dtheta^2 / 2 + m g l (1 - cos theta)."""
        return (0.5 * self.mass * self.length ** 2 * x[..., 1] ** 2
                + self.mass * self.gravity * self.length * (1.0 - jnp.cos(x[..., 0])))


@dataclass(frozen=True)
class PendulumNoise:
    """F(x, u, ud) = [0; sigma_u ud / (m l^2)], shape [2, 1]: torque noise proportional to the acting torque."""

    mass: float = MASS
    length: float = LENGTH
    sigma_u: float = SIGMA_U

    def __call__(self, x, u, ud):
        col = self.sigma_u * ud[0] / (self.mass * self.length ** 2)
        return jnp.stack([jnp.zeros_like(col), col])[:, None]


def pendulum(delay=0.0, noise=False, dt=0.02, horizon=None, limits=True, u_max=U_MAX,
             x0=(0.0, 0.0), x_target=(math.pi, 0.0)) -> Problem:
    """The pendulum swing-up with a delayed, optionally limited torque (parameters: module docstring).

    Args:
        delay: input delay tau in seconds, any tau >= 0
            (a fraction of a step of ``dt`` by the zero-order hold, docs/derivation.md §20).
        noise: add the signal-dependent torque noise F = [0; 0.1 ud / (m l^2)] (p = 1).
        dt: time step in seconds.
        horizon: K; default ``round(3.0 / dt)`` (150 at dt = 0.02).
        limits: True gives box limits |u| <= u_max (``Problem.u_min/u_max``); False none.
        u_max: the torque limit in N m (used only when ``limits`` is True).
        x0: [2] initial [theta, dtheta] (theta = 0 hanging down).
        x_target: [2] final target (default upright at rest).

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"pendulum"``.
    """
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, FINAL_TIME)
    noise = _common.flag(noise, "noise")
    limits = _common.flag(limits, "limits")
    u_max = _common.positive(u_max, "u_max")
    x0 = _common.vector(x0, "x0", 2)
    x_target = _common.vector(x_target, "x_target", 2)
    cost = QuadraticCost(P=jnp.zeros((2, 2)), Q=Q_U * jnp.eye(1), P_final=jnp.diag(jnp.array(P_FINAL)),
                         x_target=jnp.array(x_target))
    lo, hi = ((-u_max,), (u_max,)) if limits else (None, None)
    return Problem(dynamics=PendulumDynamics(), x0=jnp.array(x0), dt=dt, horizon=horizon,
                   delay_steps=delay_steps, cost=cost, noise=PendulumNoise() if noise else None,
                   u_min=lo, u_max=hi, n_controls=1, name="pendulum", metadata=METADATA)
