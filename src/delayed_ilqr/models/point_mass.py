"""P1: a damped planar point mass pushed by a delayed force (``docs/models.md`` §2, P1 and P4).

    x = [px, py, vx, vy],  u = [fx, fy] (N)
    f(x, u, ud) = [vx, vy, (ud_x - b vx) / m, (ud_y - b vy) / m]       m = 1 kg, b = 0.5 N s/m

The force that acts now is the command sent tau = l dt earlier (``ud``); the command sent now
(``u``) does not enter the plant. Cost (eq. 2): P = 0, Q = 1e-4 I_2,
P_f = diag(1e3, 1e3, 1e1, 1e1), target [0.2, 0.1, 0, 0]; tf = 0.6 s.

P1-noisy adds the diffusion F(x, u, ud) [4, 4] (p = 4):
columns 1, 2 are signal-dependent, sigma_u ud_j / m on velocity row j (sigma_u = 0.5); columns 3, 4
are additive, sigma_a / m on velocity rows x and y (sigma_a = 0.05).

P4 (scaling sweep) is ``point_mass(dt=0.001, delay=l * 0.001)``: K = 600.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax.numpy as jnp

from ..problem import Problem
from . import _common
from .metadata import ModelMetadata, StateComponents, TaskSpace
from .sensors import point_sensors

__all__ = ["point_mass", "PointMassDynamics", "PointMassNoise", "FINAL_TIME"]

FINAL_TIME = 0.6  # s, tf of P1
MASS = 1.0  # kg
DAMPING = 0.5  # N s / m
SIGMA_U = 0.5  # signal-dependent force noise (relative)
SIGMA_A = 0.05  # additive force noise (N)

METADATA = ModelMetadata(
    state_labels=("position x [m]", "position y [m]", "velocity vx [m/s]", "velocity vy [m/s]"),
    control_labels=("force fx [N]", "force fy [N]"),
    task=TaskSpace(map=StateComponents((0, 1)), name="position", unit="m", point="mass"))
"""Labels, and the position (px, py) as the task space (its paths are states already: no figure)."""


@dataclass(frozen=True)
class PointMassDynamics:
    """f(x, u, ud) of P1; equal (and hashed) by value, so equal problems share one compilation."""

    mass: float = MASS
    damping: float = DAMPING

    def __call__(self, x, u, ud):
        vel = x[2:4]
        return jnp.concatenate([vel, (ud - self.damping * vel) / self.mass])


@dataclass(frozen=True)
class PointMassNoise:
    """F(x, u, ud) [4, 4] of P1-noisy: two signal-dependent and two additive noise columns."""

    mass: float = MASS
    sigma_u: float = SIGMA_U
    sigma_a: float = SIGMA_A

    def __call__(self, x, u, ud):
        signal = jnp.diag(self.sigma_u * ud / self.mass)  # [2, 2]: column j scales velocity row j
        additive = (self.sigma_a / self.mass) * jnp.eye(2, dtype=signal.dtype)
        velocity_rows = jnp.concatenate([signal, additive], axis=1)  # [2, 4]
        return jnp.concatenate([jnp.zeros_like(velocity_rows), velocity_rows], axis=0)


def point_mass(delay=0.0, noise=False, dt=0.01, horizon=None, x_target=(0.2, 0.1, 0.0, 0.0),
               x0=(0.0, 0.0, 0.0, 0.0), sensory_delay=None) -> Problem:
    """P1 of ``docs/models.md`` §2: the point mass reaching to (0.2, 0.1) m and stopping there.

    Args:
        delay: input delay tau in seconds, any tau >= 0 (0, 0.03, 0.1 in P1;
            a fraction of a step of ``dt`` by the zero-order hold, docs/derivation.md §20).
        noise: False for P1; True or ``"benchmark"`` (its one preset, not a human model) for
            P1-noisy (the [4, 4] diffusion of the module docstring).
        dt: time step in seconds (0.01 in P1, 0.001 in P4).
        horizon: K; default ``round(0.6 / dt)`` (60 at dt = 0.01, 600 at dt = 0.001).
        x_target: [4] final target [px, py, vx, vy].
        x0: [4] initial state.
        sensory_delay: None (default): the controller sees the state. A delay in seconds (a
            whole number of steps of ``dt``, 0 allowed): the problem gets the default sensors,
            position and velocity seen that late through additive noise (`sensors`).

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"point_mass"``.
    """
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, FINAL_TIME)
    preset, _ = _common.noise_setting(noise, None, {"benchmark": SIGMA_U}, "benchmark", "point_mass")
    x0 = _common.vector(x0, "x0", 4)
    cost = _common.benchmark_cost(_common.vector(x_target, "x_target", 4))
    return Problem(dynamics=PointMassDynamics(), x0=jnp.array(x0), dt=dt, horizon=horizon,
                   delay_steps=delay_steps, cost=cost, noise=None if preset is None else PointMassNoise(),
                   name="point_mass", metadata=dataclasses.replace(METADATA, noise=preset),
                   observation=None if sensory_delay is None else point_sensors(sensory_delay, dt))
