"""A diagnostic variant of the six-muscle arm whose force is linear in the activation.

Li & Todorov's muscle (docs/models.md §4.1) turns activation into force through
A(a, l) = 1 - exp(-(a / (0.56 N_f(l)))^N_f(l)), about (a / (0.56 N_f))^N_f for small a, with
N_f = 2.11 at the optimal length and more for shortened fibres. Replacing A by a isolates what that
curve does to the optimal reach (docs/results/reach_shape.md). For tests and studies only: it is
not a published model.
"""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from delayed_ilqr.models import muscle
from delayed_ilqr.models.arm2 import joint_acceleration
from delayed_ilqr.models.arm2_muscle6 import Arm2Muscle6Dynamics, default_x0
from delayed_ilqr.models.muscle import small_matvec

__all__ = ["LinearForceDynamics", "linear_force"]


@dataclasses.dataclass(frozen=True)
class LinearForceDynamics(Arm2Muscle6Dynamics):
    """``Arm2Muscle6Dynamics`` with T(a, l, v) = a (F_L(l) F_V(l, v) + F_P(l)) (A(a, l) = a)."""

    def __call__(self, x, u, ud):
        q, dq, a = x[:2], x[2:4], x[4:]
        lengths, velocities = self.geometry.lengths(q), self.geometry.velocities(q, dq)
        tension = jnp.maximum(a, 0.0) * (muscle.force_length(lengths) * muscle.force_velocity(lengths, velocities)
                                         + muscle.passive_force(lengths))
        tau = small_matvec(self.geometry.moment_arms(q), jnp.asarray(self.f_max) * tension)
        da = muscle.activation_rate(ud, a, self.t_act, self.t_deact)
        return jnp.concatenate([dq, joint_acceleration(q, dq, tau, self.arm), da])


def linear_force(problem):
    """``problem`` (an ``arm2_muscle6`` with the default geometry) with :class:`LinearForceDynamics`
    and every activation starting at 0 (A's slope is not zero there, so no rest activation is needed;
    start the solver from u = 0)."""
    d = problem.dynamics
    dynamics = LinearForceDynamics(d.arm, d.geometry, d.f_max, d.t_act, d.t_deact)
    return problem.replace(dynamics=dynamics, x0=jnp.asarray(default_x0(problem.x0[:2], a0=0.0)))
