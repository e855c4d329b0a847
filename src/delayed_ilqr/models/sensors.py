"""The models' default sensors: ``sensory_delay=`` of [`point_mass`][delayed_ilqr.models.point_mass], [`arm2`][delayed_ilqr.models.arm2]
and [`arm2_muscle6`][delayed_ilqr.models.arm2_muscle6] attaches one (``docs/models.md`` §1.1 has the levels and their sources).

The sensory noise is additive and given as a density: a component with density s has the
per-sample standard deviation s / sqrt(dt), so that refining dt does not make the sensors more
informative (the same convention as the motor noise's diffusion). At dt = 10 ms:

| sensed | per-sample SD at dt = 10 ms | used by |
|---|---|---|
| joint angle | 0.02 rad (1.15 deg) | arm2, arm2_muscle6 (proprioception) |
| joint velocity | 0.2 rad/s | arm2, arm2_muscle6 |
| position | 5 mm | point_mass (the mass: vision of the hand) |
| velocity | 0.05 m/s | point_mass |
| hand position (vision) | 5 mm | arm2, arm2_muscle6 with ``vision_delay=`` (`vision_sensors`) |

Vision and proprioception together (`proprioception_and_vision`) are two sensors with their own
delays, fused by one filter without augmenting the state. The delays are the caller's, in seconds;
`PROPRIOCEPTION_DELAY` and `VISION_DELAY` are cited typical values (``docs/models.md`` §1.1).
"""
from __future__ import annotations

import math

import numpy as np

from ..observation import Observation
from ._common import delay_to_steps

__all__ = ["JOINT_ANGLE_DENSITY", "JOINT_VELOCITY_DENSITY", "POSITION_DENSITY", "VELOCITY_DENSITY",
           "HAND_POSITION_DENSITY", "PROPRIOCEPTION_DELAY", "VISION_DELAY", "joint_sensors", "point_sensors",
           "vision_sensors", "proprioception_and_vision", "arm_sensors"]

JOINT_ANGLE_DENSITY = 0.002        # rad sqrt(s): 0.02 rad per 10 ms sample
JOINT_VELOCITY_DENSITY = 0.02      # rad/s sqrt(s): 0.2 rad/s per 10 ms sample
POSITION_DENSITY = 0.0005          # m sqrt(s): 5 mm per 10 ms sample
VELOCITY_DENSITY = 0.005           # m/s sqrt(s): 0.05 m/s per 10 ms sample
HAND_POSITION_DENSITY = 0.0005     # m sqrt(s): 5 mm per 10 ms sample, as the point mass's position
# the long-latency stretch response, 50-100 ms after a perturbation (short-latency 20-50 ms), and
# visuomotor corrections from about 100 ms (Pruszynski & Scott 2012; docs/models.md section 1.1)
PROPRIOCEPTION_DELAY = 0.05        # s
VISION_DELAY = 0.1                 # s


def sensory_steps(delay, dt: float, name: str) -> int:
    """A sensory delay in seconds as whole steps. A fractional one is refused: the delayed filter
    and the joint moments of the pair are exact for measurements of x_{k-l_s}, and a measurement
    between two states (say the interpolation of x_{k-l_s} and x_{k-l_s-1}) would need a filter
    over both, not available yet (docs/derivation.md §20)."""
    try:
        return delay_to_steps(delay, dt, name)
    except ValueError as exc:
        if "whole number of steps" not in str(exc):
            raise
        raise ValueError(f"{exc}: a sensory delay must be whole steps (unlike the input delay, a fractional "
                         "sensory delay is not available: the delayed filter is exact for whole steps only)") from None


def _sensors(n_states: int, densities, sensory_delay, dt: float) -> Observation:
    """Sensors of the first len(densities) states, each with additive noise density / sqrt(dt)."""
    m = len(densities)
    H = np.zeros((m, n_states))
    H[:, :m] = np.eye(m)
    G = np.diag(np.asarray(densities, float) / math.sqrt(dt))
    return Observation(H, G, delay_steps=sensory_steps(sensory_delay, dt, "sensory_delay"))


def joint_sensors(n_states: int, sensory_delay, dt: float, angle_density: float = JOINT_ANGLE_DENSITY,
                  velocity_density: float = JOINT_VELOCITY_DENSITY) -> Observation:
    """Proprioception of an arm whose states begin [q1, q2, dq1, dq2]: joint angles and velocities,
    with the noise densities ``angle_density`` (rad s^1/2) and ``velocity_density`` (rad s^-1/2)."""
    return _sensors(n_states, (angle_density,) * 2 + (velocity_density,) * 2, sensory_delay, dt)


def point_sensors(sensory_delay, dt: float) -> Observation:
    """The point mass's position and velocity [px, py, vx, vy]."""
    return _sensors(4, (POSITION_DENSITY,) * 2 + (VELOCITY_DENSITY,) * 2, sensory_delay, dt)


def vision_sensors(vision_delay, dt: float, params=None, period: int = 1) -> Observation:
    """Vision of the hand of an arm whose states begin [q1, q2]: its position e(q) [2] through the
    arm's kinematics (``arm2.HandPosition``), with additive noise `HAND_POSITION_DENSITY` / sqrt(dt)
    per coordinate, seen ``vision_delay`` seconds late, a sample every ``period`` steps."""
    from .arm2 import ARM2_PARAMS, HandPosition

    G = np.eye(2) * HAND_POSITION_DENSITY / math.sqrt(dt)
    return Observation(HandPosition(ARM2_PARAMS if params is None else params), G,
                       delay_steps=sensory_steps(vision_delay, dt, "vision_delay"), period=period)


def proprioception_and_vision(n_states: int, dt: float, proprioception_delay=PROPRIOCEPTION_DELAY,
                              vision_delay=VISION_DELAY, params=None) -> list:
    """[proprioception (`joint_sensors`), vision of the hand (`vision_sensors`)]: two sensors with
    their own delays (in seconds), for ``Problem(observation=...)``."""
    return [joint_sensors(n_states, proprioception_delay, dt), vision_sensors(vision_delay, dt, params)]


def arm_sensors(n_states: int, dt: float, sensory_delay, vision_delay, params=None,
                joint_densities=(JOINT_ANGLE_DENSITY, JOINT_VELOCITY_DENSITY)):
    """The arms' ``observation``: None, proprioception (``sensory_delay``; ``joint_densities``, the
    angle's and the velocity's noise density, `joint_sensors`), vision (``vision_delay``), or both
    (a list of two sensors)."""
    sensors = ([] if sensory_delay is None else [joint_sensors(n_states, sensory_delay, dt, *joint_densities)]) + (
        [] if vision_delay is None else [vision_sensors(vision_delay, dt, params)])
    return None if not sensors else sensors[0] if len(sensors) == 1 else sensors
