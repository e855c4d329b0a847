"""Planar quadrotor with delayed rotor thrusts.

The planar (2-D) quadrotor of Tedrake's *Underactuated Robotics* (the ``Quadrotor2D`` example),
with its parameters from Bouadi, Bouchoucha & Tadjine (2007). Two rotors at distance r from the
centre of mass push along the body axis; the commands are the thrusts relative to hover, so that
u = 0 hovers and the quadratic cost u'Qu penalises the effort above hover:

    x = [y, z, phi, dy, dz, dphi]   (horizontal, vertical position [m], roll [rad], their rates)
    T_i = m g / 2 + ud_i            the rotor thrusts acting after the delay [N]
    ddy = -sin(phi) (T_1 + T_2) / m,   ddz = cos(phi) (T_1 + T_2) / m - g,   ddphi = r (T_1 - T_2) / I

Parameters:

|  |  |  |
|---|---|---|
| m | 0.486 kg | Bouadi et al. (2007), as in Underactuated Robotics' Quadrotor2D |
| r | 0.25 m | rotor arm, same source |
| I | 0.00383 kg m^2 | roll inertia, same source |
| g | 9.81 m/s^2 | same source |
| limits | 0 <= T_i <= m g | chosen: each rotor lifts at most the whole weight (&#124;u_i&#124; <= m g / 2) |
| noise (opt.) | sigma_u = 0.05 | chosen: F = sigma_u T_i d f / d ud_i (p = 2), thrust noise proportional to each rotor's thrust |
| dt | 0.01 s | chosen |
| tf | 1 s | horizon K = 100 |
| cost | chosen | P = diag(10, 10, 1, 0.1, 0.1, 0.01), Q = 0.1 I_2 (per unit time); P_final = diag(100, 100, 10, 10, 10, 1); target hover at the origin |

The roll axis is fast (r / I = 65 rad/s^2 per newton of differential thrust), which makes the
vehicle sensitive to actuation latency of a few tens of milliseconds.
"""
from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from ..problem import Problem, QuadraticCost
from . import _common
from .metadata import ModelMetadata, StateComponents, TaskSpace

__all__ = ["planar_quadrotor", "PlanarQuadrotorDynamics", "PlanarQuadrotorNoise", "MASS", "ARM", "INERTIA", "GRAVITY"]

MASS = 0.486  # kg
ARM = 0.25  # m
INERTIA = 0.00383  # kg m^2
GRAVITY = 9.81  # m / s^2
FINAL_TIME = 1.0  # s
P_RUNNING = (10.0, 10.0, 1.0, 0.1, 0.1, 0.01)
P_FINAL = (100.0, 100.0, 10.0, 10.0, 10.0, 1.0)
Q_U = 0.1
SIGMA_U = 0.05

METADATA = ModelMetadata(
    state_labels=("horizontal position y [m]", "height z [m]", "roll phi [rad]", "horizontal velocity [m/s]",
                  "vertical velocity [m/s]", "roll rate [rad/s]"),
    control_labels=("rotor 1 thrust above hover [N]", "rotor 2 thrust above hover [N]"),
    task=TaskSpace(map=StateComponents((0, 1)), name="position", unit="m", point="vehicle"))


@dataclass(frozen=True)
class PlanarQuadrotorDynamics:
    """f(x, u, ud) of the planar quadrotor (module docstring); the parameters are data (a pytree),
    so plants that differ only in them share one compiled loop."""

    mass: float = MASS
    arm: float = ARM
    inertia: float = INERTIA
    gravity: float = GRAVITY

    def __call__(self, x, u, ud):
        hover = 0.5 * MASS * self.gravity      # relative to the *model's* hover: a heavier plant sinks
        thrust = 2.0 * hover + ud[0] + ud[1]
        phi = x[2]
        ddy = -jnp.sin(phi) * thrust / self.mass
        ddz = jnp.cos(phi) * thrust / self.mass - self.gravity
        ddphi = self.arm * (ud[0] - ud[1]) / self.inertia
        return jnp.concatenate([x[3:], jnp.stack([ddy, ddz, ddphi])])


jax.tree_util.register_dataclass(PlanarQuadrotorDynamics, data_fields=["mass", "arm", "inertia", "gravity"],
                                 meta_fields=[])


@dataclass(frozen=True)
class PlanarQuadrotorNoise:
    """F(x, u, ud) [6, 2] = sigma_u T_i d f / d ud_i: each rotor's thrust noise proportional to its
    thrust T_i = m g / 2 + ud_i (f is affine in ud, so d f / d ud_i is exact)."""

    dynamics: PlanarQuadrotorDynamics = PlanarQuadrotorDynamics()
    sigma_u: float = SIGMA_U

    def __call__(self, x, u, ud):
        d = self.dynamics
        phi = x[2]
        per_newton = jnp.stack([-jnp.sin(phi) / d.mass, jnp.cos(phi) / d.mass])
        thrust = 0.5 * MASS * d.gravity + ud
        columns = [jnp.concatenate([jnp.zeros(3), per_newton, jnp.stack([sign * d.arm / d.inertia])])
                   for sign in (1.0, -1.0)]
        return jnp.stack(columns, axis=1) * (self.sigma_u * thrust)[None, :]


def planar_quadrotor(delay=0.0, noise=False, dt=0.01, horizon=None, x0=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                     x_target=(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), limits=True) -> Problem:
    """The planar quadrotor flying to (and holding) a target with delayed thrusts (module docstring).

    Args:
        delay: actuation delay tau in seconds, any tau >= 0
            (a fraction of a step of ``dt`` by the zero-order hold, docs/derivation.md §20).
        noise: add the thrust noise (p = 2, sigma_u = 0.05).
        dt: time step in seconds.
        horizon: K; default ``round(1.0 / dt)``.
        x0: [6] initial state; x_target: [6] target.
        limits: True gives 0 <= T_i <= m g (|u_i| <= m g / 2).

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"planar_quadrotor"``.
    """
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, FINAL_TIME)
    noise = _common.flag(noise, "noise")
    limits = _common.flag(limits, "limits")
    x0 = _common.vector(x0, "x0", 6)
    x_target = _common.vector(x_target, "x_target", 6)
    cost = QuadraticCost(P=jnp.diag(jnp.array(P_RUNNING)), Q=Q_U * jnp.eye(2), P_final=jnp.diag(jnp.array(P_FINAL)),
                         x_target=jnp.array(x_target))
    bound = 0.5 * MASS * GRAVITY
    lo, hi = ((-bound, -bound), (bound, bound)) if limits else (None, None)
    dynamics = PlanarQuadrotorDynamics()
    return Problem(dynamics=dynamics, x0=jnp.array(x0), dt=dt, horizon=horizon, delay_steps=delay_steps,
                   cost=cost, noise=PlanarQuadrotorNoise(dynamics) if noise else None, u_min=lo, u_max=hi,
                   n_controls=2, name="planar_quadrotor", metadata=METADATA)
