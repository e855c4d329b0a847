"""Model zoo: factories that return a ready [`Problem`][delayed_ilqr.Problem].

Every factory takes ``delay`` in seconds (any tau >= 0: a fraction of a step of ``dt`` is
the zero-order hold of docs/derivation.md §20; sensory delays are whole steps, `delay_to_steps`), ``noise`` (bool), ``dt`` and ``horizon`` (default: the model's final time
over dt). Dynamics and noise callables are frozen dataclasses compared and hashed by value, so two
problems built with the same arguments share one compiled solver. Each factory attaches a
[`ModelMetadata`][delayed_ilqr.models.metadata.ModelMetadata] (``Problem.metadata``: state and control labels with units, the task space
such as the hand position, the default initial commands), which studies and figures read; the
equations, parameters and their sources are in ``docs/models.md``. Noise is a continuous-time
diffusion (``sqrt(dt) F xi`` per step); [`per_step_noise_to_diffusion`][delayed_ilqr.models.per_step_noise_to_diffusion] converts the per-step
sigma of Todorov's and Li's discrete-time code (`noise`).

| factory | model |
|---|---|
| point_mass | P1 / P1-noisy / P4 of ``docs/models.md`` (damped planar point mass) |
| arm2 | P2 / P2-noisy / P3 (torque-driven two-link arm, Li & Todorov 2004 parameters) |
| arm2_muscle6 | the same arm driven by six muscles through delayed excitations u in [0, 1]^6 (Li & Todorov 2004 muscle model; ``center_out_targets`` for 8-target reaching) |
| pendulum | torque-limited pendulum swing-up |
| cart_pole | cart-pole swing-up (Florian's frictionless equations) |
| planar_quadrotor | planar quadrotor with delayed rotor thrusts (Underactuated Robotics' Quadrotor2D) |
| acrobot | acrobot swing-up with a limited elbow torque (trajax's test problem, Spong's equations) |

"""
from __future__ import annotations

from typing import Callable, NamedTuple

from ._common import delay_to_steps
from .acrobot import acrobot
from .arm2 import (ARM2_PARAMS, ARM2_PARAMS_ARM_DYN, Arm2Params, arm2, coriolis, hand_jacobian, hand_position,
                   hand_velocity, joint_acceleration, mass_matrix, mass_matrix_inverse)
from .arm2_muscle6 import arm2_muscle6, center_out_targets, rest_commands
from .cart_pole import cart_pole
from .metadata import ModelMetadata, TaskSpace
from .noise import diffusion_to_per_step, per_step_noise_to_diffusion
from .pendulum import pendulum
from .planar_quadrotor import planar_quadrotor
from .point_mass import point_mass

__all__ = ["point_mass", "arm2", "arm2_muscle6", "center_out_targets", "rest_commands", "pendulum", "cart_pole", "acrobot", "planar_quadrotor",
           "REGISTRY", "ModelInfo", "ModelMetadata", "TaskSpace", "delay_to_steps", "per_step_noise_to_diffusion",
           "diffusion_to_per_step",
           "Arm2Params", "ARM2_PARAMS", "ARM2_PARAMS_ARM_DYN", "mass_matrix", "mass_matrix_inverse", "coriolis",
           "joint_acceleration", "hand_position", "hand_jacobian", "hand_velocity"]


class ModelInfo(NamedTuple):
    """A registry entry: ``factory(delay=..., noise=..., dt=..., horizon=...) -> Problem``."""

    factory: Callable
    description: str


REGISTRY = {
    "point_mass": ModelInfo(point_mass, "P1: damped planar point mass (m=1, b=0.5) pushed by a delayed force, "
                                        "4 states, 2 controls, tf=0.6 s"),
    "arm2": ModelInfo(arm2, "P2: two-link arm driven by delayed joint torques (Li & Todorov 2004), "
                            "4 states, 2 controls, tf=0.5 s"),
    "arm2_muscle6": ModelInfo(arm2_muscle6, "two-link arm driven by six muscles (Li & Todorov 2004 muscle model, "
                                            "angle-dependent moment arms) through delayed excitations in [0, 1], "
                                            "hand reaching cost, 10 states, 6 controls, tf=0.5 s"),
    "pendulum": ModelInfo(pendulum, "pendulum swing-up with a delayed torque limited to |u| <= 4 N m, "
                                    "2 states, 1 control, tf=3 s"),
    "cart_pole": ModelInfo(cart_pole, "cart-pole swing-up with a delayed force limited to |u| <= 10 N "
                                      "(Florian's equations), 4 states, 1 control, tf=3 s"),
    "acrobot": ModelInfo(acrobot, "acrobot swing-up with a delayed elbow torque limited to |u| <= 5 N m "
                                  "(trajax's test problem), 4 states, 1 control, tf=5 s"),
    "planar_quadrotor": ModelInfo(planar_quadrotor, "planar quadrotor flying to a hover target with delayed rotor "
                                                    "thrusts (Underactuated Robotics' Quadrotor2D parameters), "
                                                    "6 states, 2 controls, tf=1 s"),
}
