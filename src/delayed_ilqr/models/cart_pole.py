"""Cart-pole swing-up with a delayed force on the cart.

Florian's "Correct equations for the dynamics of the cart-pole system" with friction neglected, as
in anassinator/ilqr (``docs/models.md`` §5). The pole is a uniform rod of length 2 l hinged on the cart;
``l`` is the HALF-length (pivot to centre of mass), which is where the 4/3 factor (rod inertia
m_p l^2 / 3 about its centre) comes from. Florian writes the angle phi from upright; here the
angle is theta = pi - phi, measured from hanging DOWN, counter-clockwise positive (the pole's
centre of mass is at (x + l sin theta, -l cos theta)), so that theta = 0 is the rest state and
theta = pi the upright target, as for [`pendulum`][delayed_ilqr.models.pendulum]. With this change of variables:

    x = [x, theta, dx, dtheta],  u = horizontal force on the cart (N), acting after the delay
    tmp      = (ud + m_p l dtheta^2 sin theta) / (m_c + m_p)
    ddtheta  = -(g sin theta + cos theta tmp) / (l (4/3 - m_p cos^2 theta / (m_c + m_p)))
    ddx      = tmp - m_p l ddtheta cos theta / (m_c + m_p)

Parameters (borrowed: m_c, m_p, l, g from anassinator/ilqr; chosen: the rest):

| parameter | value | source or note |
|---|---|---|
| m_c, m_p | 1.0, 0.1 kg | cart and pole masses |
| l | 1.0 m | pole half-length (the pole is 2 m long) |
| g | 9.80665 m/s^2 |  |
| friction | none | (Florian's frictionless case) |
| u_max | 10 N | the classic +-10 N of Barto, Sutton & Anderson (1983); anassinator's +-1 N needs a 25 s horizon. ``limits=False`` drops it |
| dt | 0.02 s |  |
| tf | 3 s | horizon K = 150 (about 1.3 periods of the hanging pole) |
| cost | P = 0, Q = 1e-2, P_f = diag(10, 100, 10, 10) on (x, theta - pi, dx, dtheta) |  |
| x0, target | [0, 0, 0, 0] -> [0, pi, 0, 0] |  |
| noise (opt.) | F = sigma_u ud | * d f / d ud (p = 1), sigma_u = 0.1: signal-dependent force noise |

Check of the choice (single shooting with L-BFGS-B from zero and random initial guesses): the
swing-up reaches theta_K = 3.13-3.14 (cost about 0.9-1.05) with the limit, with and without a 0.1 s
delay; the unconstrained optimum peaks near 11.7 N, so the limit binds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp

from ..problem import Problem, QuadraticCost
from . import _common
from .metadata import ModelMetadata, StateComponents, TaskSpace

__all__ = ["cart_pole", "CartPoleDynamics", "CartPoleNoise", "FINAL_TIME", "U_MAX"]

CART_MASS = 1.0  # kg
POLE_MASS = 0.1  # kg
HALF_LENGTH = 1.0  # m
GRAVITY = 9.80665  # m / s^2
U_MAX = 10.0  # N
SIGMA_U = 0.1
FINAL_TIME = 3.0  # s
Q_U = 1e-2
P_FINAL = (10.0, 100.0, 10.0, 10.0)

METADATA = ModelMetadata(
    state_labels=("cart position x [m]", "pole angle theta [rad]", "cart velocity [m/s]",
                  "pole angular velocity [rad/s]"),
    control_labels=("force on cart u [N]",),
    task=TaskSpace(map=StateComponents((1,)), name="pole angle", unit="rad", point="pole"))
"""Labels, and the pole angle as the task space (the swing-up's goal; states of mixed units are
never summed into one distance)."""


@dataclass(frozen=True)
class CartPoleDynamics:
    """f(x, u, ud) of the frictionless cart-pole (module docstring); equal (and hashed) by value."""

    cart_mass: float = CART_MASS
    pole_mass: float = POLE_MASS
    half_length: float = HALF_LENGTH
    gravity: float = GRAVITY

    def accelerations(self, x, force):
        """(ddx, ddtheta) for state x [4] and cart force ``force`` (scalar)."""
        theta, dtheta = x[1], x[3]
        total = self.cart_mass + self.pole_mass
        sin, cos = jnp.sin(theta), jnp.cos(theta)
        tmp = (force + self.pole_mass * self.half_length * dtheta ** 2 * sin) / total
        ddtheta = -(self.gravity * sin + cos * tmp) / (
            self.half_length * (4.0 / 3.0 - self.pole_mass * cos ** 2 / total))
        ddx = tmp - self.pole_mass * self.half_length * ddtheta * cos / total
        return ddx, ddtheta

    def __call__(self, x, u, ud):
        ddx, ddtheta = self.accelerations(x, ud[0])
        return jnp.stack([x[2], x[3], ddx, ddtheta])

    def energy(self, x):
        """Mechanical energy [J] (zero at rest hanging down): the Lagrangian's T + V.

        T = (m_c + m_p) dx^2 / 2 + m_p l dx dtheta cos theta + (2/3) m_p l^2 dtheta^2,
        V = m_p g l (1 - cos theta).
        """
        theta, dx, dtheta = x[..., 1], x[..., 2], x[..., 3]
        mp, l = self.pole_mass, self.half_length
        kinetic = (0.5 * (self.cart_mass + mp) * dx ** 2 + mp * l * dx * dtheta * jnp.cos(theta)
                   + (2.0 / 3.0) * mp * l ** 2 * dtheta ** 2)
        return kinetic + mp * self.gravity * l * (1.0 - jnp.cos(theta))


@dataclass(frozen=True)
class CartPoleNoise:
    """F(x, u, ud) [4, 1] = sigma_u ud * (d f / d ud): force noise proportional to the acting force.

    The accelerations are affine in the force, so d f / d ud = f(x, ., 1) - f(x, ., 0) exactly.
    """

    dynamics: CartPoleDynamics = CartPoleDynamics()
    sigma_u: float = SIGMA_U

    def __call__(self, x, u, ud):
        a1 = self.dynamics.accelerations(x, 1.0)
        a0 = self.dynamics.accelerations(x, 0.0)
        scale = self.sigma_u * ud[0]
        ddx, ddtheta = scale * (a1[0] - a0[0]), scale * (a1[1] - a0[1])
        return jnp.stack([jnp.zeros_like(ddx), jnp.zeros_like(ddx), ddx, ddtheta])[:, None]


def cart_pole(delay=0.0, noise=False, dt=0.02, horizon=None, limits=True, u_max=U_MAX,
              x0=(0.0, 0.0, 0.0, 0.0), x_target=(0.0, math.pi, 0.0, 0.0)) -> Problem:
    """The cart-pole swing-up with a delayed, optionally limited force (parameters: module docstring).

    Args:
        delay: input delay tau in seconds, any tau >= 0
            (a fraction of a step of ``dt`` by the zero-order hold, docs/derivation.md §20).
        noise: add the signal-dependent force noise (p = 1, sigma_u = 0.1).
        dt: time step in seconds.
        horizon: K; default ``round(3.0 / dt)`` (150 at dt = 0.02).
        limits: True gives box limits |u| <= u_max (``Problem.u_min/u_max``); False none.
        u_max: the force limit in N (used only when ``limits`` is True).
        x0: [4] initial [x, theta, dx, dtheta] (theta = 0 hanging down).
        x_target: [4] final target (default upright at rest at x = 0).

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"cart_pole"``.
    """
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, FINAL_TIME)
    noise = _common.flag(noise, "noise")
    limits = _common.flag(limits, "limits")
    u_max = _common.positive(u_max, "u_max")
    x0 = _common.vector(x0, "x0", 4)
    x_target = _common.vector(x_target, "x_target", 4)
    cost = QuadraticCost(P=jnp.zeros((4, 4)), Q=Q_U * jnp.eye(1), P_final=jnp.diag(jnp.array(P_FINAL)),
                         x_target=jnp.array(x_target))
    lo, hi = ((-u_max,), (u_max,)) if limits else (None, None)
    dynamics = CartPoleDynamics()
    return Problem(dynamics=dynamics, x0=jnp.array(x0), dt=dt, horizon=horizon, delay_steps=delay_steps,
                   cost=cost, noise=CartPoleNoise(dynamics) if noise else None, u_min=lo, u_max=hi,
                   n_controls=1, name="cart_pole", metadata=METADATA)
