"""P2: the planar two-link arm driven by delayed joint torques (``docs/models.md`` §2, P2 and P3).

Rigid-body dynamics (``docs/models.md`` §3, Todorov's ``arm_dyn.m``):

    M(q) ddq + C(q, dq) + B dq = tau
    M(q) = [[a1 + 2 a2 cos q2, a3 + a2 cos q2], [a3 + a2 cos q2, a3]]
    C(q, dq) = a2 sin q2 [-dq2 (2 dq1 + dq2), dq1^2]
    a1 = I1 + I2 + m2 l1^2,  a2 = m2 l1 s2,  a3 = I2          (I1, I2 used as given)

x = [q1, q2, dq1, dq2] (shoulder, elbow; rad), u = joint torques (N m) acting after the delay:
f(x, u, ud) = [dq, M(q)^{-1} (ud - C(q, dq) - B dq)]. Cost: P = 0, Q = 1e-4 I_2,
P_f = diag(1e3, 1e3, 1e1, 1e1); x0 = [pi/4, pi/2, 0, 0], target [pi/2, pi/3, 0, 0]; tf = 0.5 s.
P2-noisy (``noise="benchmark"``): F(x, u, ud) = [0_{2x2}; M(q)^{-1} sigma_u diag(ud)], p = 2,
sigma_u = 0.2. P3 is ``arm2(dt=0.002, delay=0.1)`` (K = 250, l = 50).

Noise presets (``noise=``). F is a continuous-time diffusion (`delayed_ilqr.models.noise`):
the torque acting is ud (1 + sigma_u w) with w white noise, signal-dependent motor noise in the
sense of Harris & Wolpert 1998 and van Beers, Haggard & Wolpert 2004 (SD proportional to the mean
torque, a constant coefficient of variation).

- ``noise=True`` or ``"human"``: `SIGMA_U_HUMAN` = 0.01, human force variability
  (``docs/models.md`` §4.5). White noise has no finite CV; the CV refers to the torque of a held
  command low-pass filtered at the muscles' activation time constant t (a muscle turns its
  neural command into force at that bandwidth), whose stationary SD is sigma_u ud / sqrt(2 t):
  [`HUMAN_TORQUE_CV`][delayed_ilqr.models.arm2.HUMAN_TORQUE_CV] = 3.2 % at t = 50 ms (2.8 % at 66 ms), equivalently the CV of the mean
  torque over a window of 2 t = 100 ms. Isometric force and joint torque vary by a few per cent
  of the mean (Jones, Hamilton & Wolpert 2002; Hamilton, Jones & Wolpert 2004; sources and their
  tags in ``docs/models.md`` §4.5).
- ``noise="benchmark"``: `SIGMA_U` = 0.2, P2-noisy exactly (the CV above would be 63 %; the
  per-step relative noise sigma_u / sqrt(dt) is 2.0 at dt = 10 ms): a numerical stress test, not a
  human level.
- ``noise=True, sigma_u=s``: any other level (``"custom"``);
  [`per_step_noise_to_diffusion`][delayed_ilqr.models.per_step_noise_to_diffusion] converts a per-step sigma.

The preset's name is in ``problem.metadata.noise``.

The functions [`mass_matrix`][delayed_ilqr.models.mass_matrix], [`mass_matrix_inverse`][delayed_ilqr.models.mass_matrix_inverse], [`coriolis`][delayed_ilqr.models.coriolis],
[`joint_acceleration`][delayed_ilqr.models.joint_acceleration], [`hand_position`][delayed_ilqr.models.hand_position], [`hand_jacobian`][delayed_ilqr.models.hand_jacobian] and [`hand_velocity`][delayed_ilqr.models.hand_velocity]
are pure ``jax.numpy`` functions of (q, dq, params) for reuse by other arm models (e.g. the
six-muscle arm); they accept leading batch axes on q, dq, tau ([..., 2]).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._kernels.dense import small_matvec
from ..problem import Problem
from . import _common
from .metadata import ModelMetadata, TaskSpace
from .muscle import T_ACT
from .sensors import arm_sensors

__all__ = ["arm2", "Arm2Params", "ARM2_PARAMS", "ARM2_PARAMS_ARM_DYN", "Arm2Dynamics", "Arm2Noise",
           "mass_matrix", "mass_matrix_inverse", "coriolis", "joint_acceleration", "hand_position",
           "hand_jacobian", "hand_velocity", "HandPosition", "ARM_STATE_LABELS", "FINAL_TIME", "SIGMA_U",
           "SIGMA_U_HUMAN", "HUMAN_TORQUE_CV", "ACTIVATION_TIME", "NOISE_PRESETS"]

FINAL_TIME = 0.5  # s, tf of P2
SIGMA_U = 0.2  # P2-noisy signal-dependent torque noise (a benchmark, not a human level)
SIGMA_U_HUMAN = 0.01  # torque noise calibrated to human force variability (module docstring)
ACTIVATION_TIME = T_ACT  # s, the muscles' activation time constant the CV refers to (docs/models.md §4.2)
HUMAN_TORQUE_CV = SIGMA_U_HUMAN / math.sqrt(2 * ACTIVATION_TIME)
"""Coefficient of variation of a held torque under the ``"human"`` preset, 0.032: the torque
low-pass filtered at `ACTIVATION_TIME` (module docstring)."""
NOISE_PRESETS = {"human": SIGMA_U_HUMAN, "benchmark": SIGMA_U}
"""The torque arm's noise presets, name -> sigma_u; ``noise=True`` is ``"human"``."""


class Arm2Params(NamedTuple):
    """Parameters of the two-link arm (SI units); defaults are P2's Li & Todorov 2004 values.

    A NamedTuple of floats: hashable by value (so it can sit in a static dynamics object) and a
    JAX pytree (so it can also be passed as traced data).

    Attributes:
        m1, m2: link masses [kg] (m1 does not enter the dynamics).
        l1, l2: link lengths [m].
        s1, s2: distance of each link's centre of mass from its proximal joint [m] (s1 unused).
        I1, I2: link moments of inertia [kg m^2], used as given (a1 = I1 + I2 + m2 l1^2, a3 = I2).
        b11, b12, b21, b22: joint viscous friction matrix B [N m s / rad].
    """

    m1: float = 1.4
    m2: float = 1.1
    l1: float = 0.30
    l2: float = 0.33
    s1: float = 0.11
    s2: float = 0.16
    I1: float = 0.025
    I2: float = 0.045
    b11: float = 0.05
    b12: float = 0.025
    b21: float = 0.025
    b22: float = 0.05

    @property
    def a1(self):
        return self.I1 + self.I2 + self.m2 * self.l1 ** 2

    @property
    def a2(self):
        return self.m2 * self.l1 * self.s2

    @property
    def a3(self):
        return self.I2

    @property
    def B(self):
        """The friction matrix [2, 2] as a jax array."""
        return jnp.array([[self.b11, self.b12], [self.b21, self.b22]])


ARM2_PARAMS = Arm2Params()
"""Li & Todorov 2004 parameters as fixed by P2 (m2 = 1.1 kg, B = [[0.05, 0.025], [0.025, 0.05]])."""

ARM2_PARAMS_ARM_DYN = Arm2Params(b11=0.5, b12=0.1, b21=0.1, b22=0.5)
"""Todorov's web ``arm_dyn.m`` variant (``docs/models.md`` §3): stronger friction B = [[0.5, 0.1], [0.1, 0.5]]."""

ARM_STATE_LABELS = ("shoulder angle q1 [rad]", "elbow angle q2 [rad]", "shoulder velocity dq1 [rad/s]",
                    "elbow velocity dq2 [rad/s]")
"""Labels of the rigid body's states [q1, q2, dq1, dq2] (shared with the six-muscle arm)."""


def _mat2(m11, m12, m21, m22):
    return jnp.stack([jnp.stack([m11, m12], axis=-1), jnp.stack([m21, m22], axis=-1)], axis=-2)


def mass_matrix(q, params: Arm2Params = ARM2_PARAMS):
    """M(q) [..., 2, 2] for joint angles q [..., 2]."""
    c2 = jnp.cos(q[..., 1])
    m12 = params.a3 + params.a2 * c2
    return _mat2(params.a1 + 2 * params.a2 * c2, m12, m12, jnp.full_like(c2, params.a3))


def mass_matrix_inverse(q, params: Arm2Params = ARM2_PARAMS):
    """M(q)^{-1} [..., 2, 2] in closed form; det M = a3 (a1 - a3) - a2^2 cos^2 q2 > 0."""
    c2 = jnp.cos(q[..., 1])
    m11, m12, m22 = params.a1 + 2 * params.a2 * c2, params.a3 + params.a2 * c2, jnp.full_like(c2, params.a3)
    det = params.a3 * (params.a1 - params.a3) - (params.a2 * c2) ** 2
    return _mat2(m22, -m12, -m12, m11) / det[..., None, None]


def coriolis(q, dq, params: Arm2Params = ARM2_PARAMS):
    """C(q, dq) [..., 2]: the Coriolis and centripetal torques a2 sin q2 [-dq2 (2 dq1 + dq2), dq1^2]."""
    s2 = params.a2 * jnp.sin(q[..., 1])
    dq1, dq2 = dq[..., 0], dq[..., 1]
    return jnp.stack([-s2 * dq2 * (2 * dq1 + dq2), s2 * dq1 ** 2], axis=-1)


def joint_acceleration(q, dq, tau, params: Arm2Params = ARM2_PARAMS):
    """ddq = M(q)^{-1} (tau - C(q, dq) - B dq) [..., 2] for joint torques tau [..., 2]."""
    rhs = tau - coriolis(q, dq, params) - small_matvec(jnp.asarray(params.B), dq)
    return small_matvec(mass_matrix_inverse(q, params), rhs)


def hand_position(q, params: Arm2Params = ARM2_PARAMS):
    """Hand (end-point) position e [..., 2] in metres, shoulder at the origin."""
    q1, q12 = q[..., 0], q[..., 0] + q[..., 1]
    return jnp.stack([params.l1 * jnp.cos(q1) + params.l2 * jnp.cos(q12),
                      params.l1 * jnp.sin(q1) + params.l2 * jnp.sin(q12)], axis=-1)


def hand_jacobian(q, params: Arm2Params = ARM2_PARAMS):
    """J(q) = de/dq [..., 2, 2]."""
    q1, q12 = q[..., 0], q[..., 0] + q[..., 1]
    s1, c1, s12, c12 = jnp.sin(q1), jnp.cos(q1), jnp.sin(q12), jnp.cos(q12)
    return _mat2(-params.l1 * s1 - params.l2 * s12, -params.l2 * s12,
                 params.l1 * c1 + params.l2 * c12, params.l2 * c12)


def hand_velocity(q, dq, params: Arm2Params = ARM2_PARAMS):
    """Hand velocity de/dt = J(q) dq [..., 2] in m/s."""
    return jnp.sum(hand_jacobian(q, params) * dq[..., None, :], axis=-1)


@dataclass(frozen=True)
class HandPosition:
    """The task map of the arms: the hand position e(q) [..., 2] in metres of states x [..., n >= 2]."""

    params: Arm2Params = ARM2_PARAMS

    def __call__(self, x):
        return hand_position(jnp.asarray(x)[..., :2], self.params)


def hand_task(params: Arm2Params, target=None) -> TaskSpace:
    """The arms' task space: the hand position in metres (target: the hand at the target state, or
    ``target(problem)``)."""
    return TaskSpace(map=HandPosition(params), name="hand position", unit="m", point="hand", target=target,
                     paths=True)


@dataclass(frozen=True)
class Arm2Dynamics:
    """f(x, u, ud) = [dq, M^{-1}(ud - C - B dq)]; equal (and hashed) by value."""

    params: Arm2Params = ARM2_PARAMS

    def __call__(self, x, u, ud):
        q, dq = x[:2], x[2:4]
        return jnp.concatenate([dq, joint_acceleration(q, dq, ud, self.params)])


@dataclass(frozen=True)
class Arm2Noise:
    """F(x, u, ud) = [0_{2x2}; M(q)^{-1} sigma_u diag(ud)], shape [4, 2]: torque noise proportional to ud."""

    params: Arm2Params = ARM2_PARAMS
    sigma_u: float = SIGMA_U

    def __call__(self, x, u, ud):
        lower = mass_matrix_inverse(x[:2], self.params) * (self.sigma_u * ud)[None, :]
        return jnp.concatenate([jnp.zeros_like(lower), lower], axis=0)


# sigma_u is data (a pytree leaf): derivatives with respect to the noise scale, and problems that
# differ only in it share one compiled solver; the arm's parameters stay static
jax.tree_util.register_dataclass(Arm2Noise, data_fields=["sigma_u"], meta_fields=["params"])


def _check_params(params) -> Arm2Params:
    if not isinstance(params, Arm2Params):
        raise TypeError(f"params must be an Arm2Params; got {type(params).__name__}")
    values = {}
    for field, value in params._asdict().items():
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"params.{field} must be a finite number; got {value!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"params.{field} must be a finite number; got {value!r}")
        values[field] = v
    checked = Arm2Params(**values)
    for field in ("m2", "l1", "l2", "I1", "I2"):
        if getattr(checked, field) <= 0:
            raise ValueError(f"params.{field} must be positive; got {getattr(checked, field)!r}")
    if checked.a3 * (checked.a1 - checked.a3) - checked.a2 ** 2 <= 0:
        raise ValueError("params must give a positive definite mass matrix (a3 (a1 - a3) > a2^2); "
                         f"got a1={checked.a1:.4g}, a2={checked.a2:.4g}, a3={checked.a3:.4g}")
    return checked


def arm2(delay=0.0, noise=False, dt=0.01, horizon=None, x0=(math.pi / 4, math.pi / 2, 0.0, 0.0),
         x_target=(math.pi / 2, math.pi / 3, 0.0, 0.0), params: Arm2Params = ARM2_PARAMS,
         sigma_u=None, sensory_delay=None, vision_delay=None) -> Problem:
    """P2 of ``docs/models.md`` §2: a torque-driven reach in joint space.

    Args:
        delay: input delay tau in seconds, any tau >= 0 (0, 0.03, 0.1 in P2;
            a fraction of a step of ``dt`` by the zero-order hold, docs/derivation.md §20).
        noise: False (P2), True or ``"human"`` (signal-dependent torque noise at the human level,
            `SIGMA_U_HUMAN`), or ``"benchmark"`` (P2-noisy, sigma_u = 0.2): the presets of
            the module docstring, F = [0; M(q)^{-1} sigma_u diag(ud)], p = 2.
        dt: time step in seconds (0.01 in P2, 0.002 in P3).
        horizon: K; default ``round(0.5 / dt)`` (50 at dt = 0.01, 250 at dt = 0.002).
        x0: [4] initial state [q1, q2, dq1, dq2].
        x_target: [4] final target state.
        params: arm parameters; P2 uses [`ARM2_PARAMS`][delayed_ilqr.models.ARM2_PARAMS].
        sigma_u: None (the preset's level) or the diffusion scale of the torque noise, with
            ``noise=True`` (a ``"custom"`` level).
        sensory_delay: None (default): the controller sees the state. A delay in seconds (a
            whole number of steps of ``dt``, 0 allowed): proprioception, joint angles and
            velocities seen that late through additive noise (`sensors.joint_sensors`).
        vision_delay: None (default): no vision. A delay in seconds: the hand position seen that
            late (`sensors.vision_sensors`), fused with proprioception when ``sensory_delay`` is set.

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"arm2"``; its metadata's task space is the hand
        position (target: the hand at ``x_target``).
    """
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, FINAL_TIME)
    x0 = _common.vector(x0, "x0", 4)
    cost = _common.benchmark_cost(_common.vector(x_target, "x_target", 4))
    params = _check_params(params)
    preset, sigma_u = _common.noise_setting(noise, sigma_u, NOISE_PRESETS, "human", "arm2")
    return Problem(dynamics=Arm2Dynamics(params), x0=jnp.array(x0), dt=dt, horizon=horizon,
                   delay_steps=delay_steps, cost=cost, noise=None if preset is None else Arm2Noise(params, sigma_u),
                   name="arm2", metadata=ModelMetadata(
                       state_labels=ARM_STATE_LABELS,
                       control_labels=("shoulder torque u1 [N m]", "elbow torque u2 [N m]"),
                       task=hand_task(params), noise=preset),
                   observation=arm_sensors(4, dt, sensory_delay, vision_delay, params))
