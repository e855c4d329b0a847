"""The two-link arm driven by six muscles through delayed neural excitations (Li & Todorov 2004),
with the defaults of a human reaching arm (``docs/models.md`` §4, the human preset in §4.7).

``docs/models.md`` §4 (the muscle model is in `delayed_ilqr.models.muscle`), rigid body of §3
([`delayed_ilqr.models.arm2`][delayed_ilqr.models.arm2], P2's parameters [`ARM2_PARAMS`][delayed_ilqr.models.ARM2_PARAMS]):

    x = [q1, q2, dq1, dq2, a1..a6] (10),   u = neural excitations in [0, 1]^6 (6)
    f(x, u, ud) = [dq,  M(q)^{-1} (tau - C(q, dq) - B dq),  (ud - a) / t(ud, a)]
    tau = d(q) (F_max * T(a, l(q), v(q, dq)))

The command sent at step k reaches the muscles after the motor delay: the *delayed* excitation
``ud`` = u_{k-l} drives the activation dynamics; ``u`` itself does not enter the plant.

The human preset (``noise=True``, the default; §4.7 has every value with its source):

- Rest: a tonic co-activation (Gribble et al. 2003). The start activations and the rest
  excitations ``cost.params["u_rest"]`` are the static equilibrium at the start posture nearest to
  the level `COACTIVATION` = 0.2 (`rest_activations`: zero net joint torque, every muscle
  active), so the arm stays still when the rest is held and every muscle can raise or lower its
  force.
- Effort (a `GeneralCost`; running cost per unit time, final cost not multiplied by dt):

      running(x, u) = r |u - u_rest|^2 + r_f |A(a, l(q)) - A*(q)|^2
      final(x)      = w_p |e(q) - e*|^2 + w_v |de/dt(q, dq)|^2 + w_a |a|^2

  the squared active forces (fractions of the maximal isometric force, A of §4.1), the common
  choice of the field (sum of squared muscle stresses or forces; Todorov 2005's effort on the
  command of a linear muscle is the same), measured from A*(q), the tonic co-activation that holds
  the current posture q still (`muscle.postural_forces`: the forces nearest to those of the rest
  activations at q with zero net joint torque; at the start posture exactly the rest's), plus a
  small cost on the excitations' departure from rest for regularity. Holding any posture at the
  tonic level costs nothing, as holding the torque-driven arm in the horizontal plane does.
  ``cost.params = {"target", "u_rest", "r", "r_f", "w_p", "w_v", "w_a"}`` (arrays): problems
  with different targets or weights share one compiled solver.
- Motor noise, F [10, 8] (a continuous-time diffusion, `delayed_ilqr.models.noise`):
  signal-dependent on the excitations, ud_i (1 + sigma_u w_i), F[4 + i, i] = sigma_u ud_i / t(ud_i, a_i),
  whose force CV for a held excitation is 4-9 % at `SIGMA_U` = 0.01 (`force_cv`; the
  activation's own CV is 2.8-3.2 %); and signal-independent joint-torque noise
  F[2:4, 6:8] = sigma_tau M(q)^{-1}, `SIGMA_TAU` = 0.004 N m s^1/2 (van Beers, Haggard & Wolpert
  2004 model both). The delayed Kalman filter takes its process noise from F at the nominal, so
  it expects unexplained torques.
- Delays and sensors: a motor (efferent and electromechanical) delay `MOTOR_DELAY` = 20 ms and
  proprioception (joint angles and velocities, `sensors.joint_sensors`, noise densities
  ``joint_angle_noise`` and ``joint_velocity_noise``) delayed by
  `SENSORY_DELAY` = 40 ms: a 60 ms loop, in the long-latency range (50-100 ms; short-latency
  reflexes 20-50 ms, voluntary responses after 100 ms; Pruszynski & Scott 2012).

The idealised loop is asked for explicitly: ``noise=False`` (deterministic, no delay, no sensors
unless given), ``sensory_delay=None`` (the state seen), ``delay=0``. `LI_TODOROV` gives the arm as
Li & Todorov published it (no tonic rest, effort on the excitations from zero, excitation noise
only, the state seen): ``arm2_muscle6(**LI_TODOROV, delay=...)``; its reaches are flat-topped and
curved (``docs/results/reach_shape.md``), because the force A ~ (a / (0.56 N_f))^N_f with
N_f >= 2.11 makes an effort on the excitations concave in the force, which favours bursts.

What the preset gives, measured (``docs/results/center_out_human.md``): on the 8 center-out
reaches of 10 cm, single-peaked hand speed with peak/mean 1.62-1.78, mean paths within 0.5-7.7 %
of straight, endpoint SD 2.8-3.9 mm; the endpoint ellipses are the delayed filter's final error,
along the shoulder's rotation rather than the movement (3 of 8 within 30 deg of it; 5 of 8 with
proprioception at the precision of human position sense, `POSITION_SENSE`), and one unseen reach
(15 cm at 112.5 deg) curves by 10.5 %.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ..problem import GeneralCost, Problem
from . import _common
from . import muscle as _muscle
from .arm2 import (ARM2_PARAMS, ARM_STATE_LABELS, Arm2Params, _check_params, hand_position, hand_task,
                   hand_velocity, joint_acceleration, mass_matrix_inverse)
from .metadata import CostParameter, ModelMetadata
from .sensors import JOINT_ANGLE_DENSITY, JOINT_VELOCITY_DENSITY, arm_sensors

__all__ = ["arm2_muscle6", "center_out_targets", "rest_commands", "rest_activations", "default_x0",
           "force_cv", "Arm2Muscle6Dynamics", "Arm2Muscle6Noise", "ReachRunningCost", "MuscleEffort", "ReachFinalCost", "FINAL_TIME",
           "SIGMA_U", "SIGMA_TAU", "COACTIVATION", "A_REST", "LI_TODOROV", "MOTOR_DELAY", "SENSORY_DELAY", "PRESET", "Q0", "TARGET",
           "GEOMETRIES", "POSITION_SENSE", "DISTURBANCE_TORQUE", "DisturbanceTorqueNoise", "with_disturbance_model"]

FINAL_TIME = 0.5  # s
SIGMA_U = 0.01  # signal-dependent excitation noise (module docstring)
SIGMA_TAU = 0.004  # N m s^1/2, signal-independent joint-torque noise (module docstring)
NOISE_PRESETS = {"human": SIGMA_U}  # noise=True is "human"; another sigma_u is "custom"
COACTIVATION = 0.2  # tonic co-activation of the rest posture (module docstring)
A_REST = 0.05  # start activations of Li & Todorov's arm without a tonic rest (coactivation=None)
MOTOR_DELAY = 0.02  # s, efferent + electromechanical delay of the human preset
SENSORY_DELAY = 0.04  # s, proprioceptive (afferent) delay of the human preset
PRESET = "preset"  # the default of ``delay`` and ``sensory_delay``: the human preset's values
Q0 = (math.pi / 4, math.pi / 2)  # rad, Li 2006 thesis start posture
TARGET = (0.05, 0.5)  # m, Li 2006 thesis hand target
R_EFFORT, R_FORCE, W_POS, W_VEL, W_ACT = 1e-4, 1e-2, 1.0, 0.1, 0.0
#: The arm as Li & Todorov published it, for ``arm2_muscle6(**LI_TODOROV, delay=...)``: no tonic
#: rest (start activations `A_REST`), effort r |u|^2 on the excitations only, excitation noise
#: only, the state seen.
LI_TODOROV = {"coactivation": None, "r_f": 0.0, "sigma_tau": 0.0, "sensory_delay": None}

#: Proprioception at the precision of human position sense, for ``arm2_muscle6(**POSITION_SENSE)``:
#: the joint-angle noise density 0.016 rad s^1/2, with which a held posture averaged for 1 s is
#: known to 0.9 deg (van Beers, Sittig & Denier van der Gon 1998: shoulder and elbow angles are
#: known to the nervous system with a precision of 0.6-1.1 deg), 8 times the preset's, and the
#: velocity noise in the preset's ratio (10 per second). Under it the endpoint scatter is set by the
#: execution noise that the sensors cannot resolve rather than by the filter's final error
#: (``docs/results/center_out_human.md``).
POSITION_SENSE = {"joint_angle_noise": 0.016, "joint_velocity_noise": 0.16}

GEOMETRIES = {"angle_dependent": _muscle.ANGLE_DEPENDENT, "constant": _muscle.CONSTANT}


@dataclass(frozen=True)
class Arm2Muscle6Dynamics:
    """f(x, u, ud) = [dq, ddq(q, dq, tau(q, dq, a)), (ud - a) / t(ud, a)]; equal (and hashed) by value."""

    arm: Arm2Params = ARM2_PARAMS
    geometry: object = _muscle.ANGLE_DEPENDENT
    f_max: tuple = _muscle.F_MAX
    t_act: float = _muscle.T_ACT
    t_deact: float = _muscle.T_DEACT

    def __call__(self, x, u, ud):
        q, dq, a = x[:2], x[2:4], x[4:]
        tau = _muscle.joint_torques(q, dq, a, self.geometry, self.f_max)
        ddq = joint_acceleration(q, dq, tau, self.arm)
        da = _muscle.activation_rate(ud, a, self.t_act, self.t_deact)
        return jnp.concatenate([dq, ddq, da])


@dataclass(frozen=True)
class Arm2Muscle6Noise:
    """F(x, u, ud) [10, 8]: columns 0-5 signal-dependent excitation noise, F[4 + i, i] =
    sigma_u ud_i / t(ud_i, a_i); columns 6-7 signal-independent joint-torque noise,
    F[2:4, 6:8] = sigma_tau M(q)^{-1} (left out, F [10, 6], without ``joint_noise``: the factory
    sets it when sigma_tau > 0, so that the published arm draws the same noise as before)."""

    sigma_u: float = SIGMA_U
    sigma_tau: float = SIGMA_TAU
    t_act: float = _muscle.T_ACT
    t_deact: float = _muscle.T_DEACT
    arm: Arm2Params = ARM2_PARAMS
    joint_noise: bool = True  # False: columns 6-7 left out (F [10, 6], the published arm's noise)

    def __call__(self, x, u, ud):
        q, a = x[:2], x[4:]
        gain = self.sigma_u * ud / _muscle.activation_time_constant(ud, a, self.t_act, self.t_deact)
        zeros = jnp.zeros((2, 6), gain.dtype)
        excitation = jnp.concatenate([zeros, zeros, jnp.diag(gain)], axis=0)
        if not self.joint_noise:
            return excitation
        torque = self.sigma_tau * mass_matrix_inverse(q, self.arm)
        additive = jnp.concatenate([jnp.zeros((2, 2), gain.dtype), torque, jnp.zeros((6, 2), gain.dtype)], axis=0)
        return jnp.concatenate([excitation, additive], axis=1)


# the noise scales are data (pytree leaves): derivatives with respect to them, and problems that
# differ only in them share one compiled solver
jax.tree_util.register_dataclass(Arm2Muscle6Noise, data_fields=["sigma_u", "sigma_tau"],
                                 meta_fields=["t_act", "t_deact", "arm", "joint_noise"])


@dataclass(frozen=True)
class ReachRunningCost:
    """running(x, u, params) = r |u|^2 (per unit time): Li & Todorov's effort, shared with the
    torque arm's reaches (`delayed_ilqr.experiments.reach_tasks`)."""

    def __call__(self, x, u, params):
        return params["r"] * (u @ u)


@dataclass(frozen=True)
class MuscleEffort:
    """running(x, u, params) = r |u - u_rest|^2 + r_f |A(a, l(q)) - A*(q)|^2 (per unit time): the
    excitations' departure from the tonic rest ``params["u_rest"]`` [6], and the muscles' active
    forces' (fractions of the maximal force) departure from A*(q) =
    `muscle.postural_forces`(q, A(u_rest, l(q))), the tonic co-activation that holds posture q
    (with u_rest = 0, Li & Todorov's arm, A* = 0)."""

    geometry: object = _muscle.ANGLE_DEPENDENT

    def __call__(self, x, u, params):
        q, a, rest = x[:2], x[4:], params["u_rest"]
        l = self.geometry.lengths(q)
        du = u - rest
        df = _muscle.activation_force(a, l) - _muscle.postural_forces(q, _muscle.activation_force(rest, l), self.geometry)
        return params["r"] * (du @ du) + params["r_f"] * (df @ df)


@dataclass(frozen=True)
class ReachFinalCost:
    """final(x, params) = w_p |e(q) - target|^2 + w_v |de/dt|^2 + w_a |a|^2 (hand e through the kinematics)."""

    arm: Arm2Params = ARM2_PARAMS

    def __call__(self, x, params):
        q, dq, a = x[:2], x[2:4], x[4:]
        err = hand_position(q, self.arm) - params["target"]
        vel = hand_velocity(q, dq, self.arm)
        return params["w_p"] * (err @ err) + params["w_v"] * (vel @ vel) + params["w_a"] * (a @ a)


def _metadata(arm: Arm2Params) -> ModelMetadata:
    """Labels (activations and excitations are fractions of the maximum), the hand task with the
    target of ``cost.params``, and the warm start [`rest_commands`][delayed_ilqr.models.rest_commands]."""
    return ModelMetadata(
        state_labels=ARM_STATE_LABELS + tuple(f"activation a{i} [-]" for i in range(1, 7)),
        control_labels=tuple(f"excitation u{i} [-]" for i in range(1, 7)),
        task=hand_task(arm, target=CostParameter("target")), u_init=rest_commands)


def _geometry(geometry):
    if isinstance(geometry, str):
        if geometry not in GEOMETRIES:
            raise ValueError(f"geometry must be one of {sorted(GEOMETRIES)}; got {geometry!r}")
        return GEOMETRIES[geometry]
    if isinstance(geometry, (_muscle.AngleDependentGeometry, _muscle.ConstantGeometry)):
        return geometry
    raise TypeError("geometry must be 'angle_dependent', 'constant' or a muscle geometry object; "
                    f"got {type(geometry).__name__}")


@functools.lru_cache(maxsize=64)
def _rest(q0: tuple, level: float, geometry, f_max: tuple) -> tuple:
    return tuple(float(v) for v in _muscle.rest_activations(q0, level, geometry, f_max))


def rest_activations(q0=Q0, coactivation=COACTIVATION, geometry="angle_dependent") -> tuple:
    """[6] the activations of the static equilibrium at posture ``q0`` nearest to the tonic
    ``coactivation`` level (`delayed_ilqr.models.muscle.rest_activations`; cached)."""
    q0 = _common.vector(q0, "q0", 2)
    return _rest(q0, float(coactivation), _geometry(geometry), _muscle.F_MAX)


def default_x0(q0=Q0, a0=None) -> tuple:
    """[q1, q2, 0, 0, a0 (6)]; a0 defaults to the rest equilibrium at q0 (`rest_activations`), a
    scalar gives every muscle that activation."""
    q0 = _common.vector(q0, "q0", 2)
    a0 = rest_activations(q0) if a0 is None else a0
    a0 = (float(a0),) * 6 if np.ndim(a0) == 0 else _common.vector(a0, "a0", 6)
    return q0 + (0.0, 0.0) + a0


def rest_commands(problem: Problem, level=None):
    """A [K, 6] warm start holding the excitations at the start activations ``problem.x0[4:10]``
    (the activations' equilibrium: with the default start, the rest posture held), or at a
    scalar ``level``."""
    rest = problem.x0[4:10] if level is None else jnp.full(problem.n_controls, float(level))
    return jnp.broadcast_to(jnp.asarray(rest, jnp.float64), (problem.horizon, problem.n_controls))


METADATA = _metadata(ARM2_PARAMS)


#: The estimator's expected external torques (N m s^1/2 at each joint), for `with_disturbance_model`
#: [D]: the level at which the delayed filter of the human preset believes most of a 0.15 m/s kick
#: of the hand within two loops (41 % of its displacement one 60 ms loop after it, 73 % after two;
#: 10 % and 24 % without it), 12.5 times `SIGMA_TAU`. A disturbance model in the
#: estimator is how optimal feedback control explains fast goal-directed responses to unexpected
#: loads (Crevecoeur & Scott 2013, PLoS Comput Biol [R]). Not part of the preset: the filter that
#: trusts proprioception this much passes its noise to the commands (``docs/gallery/kick.md``).
DISTURBANCE_TORQUE = 0.05


@dataclass(frozen=True)
class DisturbanceTorqueNoise:
    """F_design(x, u, ud) = [F(x, u, ud), D(q)] with D [n, 2] zero but D[2:4] = sigma_d M(q)^{-1}:
    the columns of the plant's noise ``base`` (None: none) and two of external joint torques of
    density ``sigma_d`` (N m s^1/2) on an arm whose states begin [q1, q2, dq1, dq2]."""

    base: object
    sigma_d: float
    arm: Arm2Params = ARM2_PARAMS

    def __call__(self, x, u, ud):
        torque = self.sigma_d * mass_matrix_inverse(x[:2], self.arm)
        D = jnp.zeros((x.shape[0], 2), torque.dtype).at[2:4].set(torque)
        return D if self.base is None else jnp.concatenate([self.base(x, u, ud), D], axis=1)


def with_disturbance_model(problem: Problem, sigma_d: float = DISTURBANCE_TORQUE) -> Problem:
    """The design problem of ``problem`` (an arm whose states begin [q, dq], `arm2_muscle6` or
    ``arm2``) whose delayed filter expects external joint torques of density ``sigma_d``
    (N m s^1/2): its noise gets the two columns of `DisturbanceTorqueNoise`. Solve this problem
    and run the policy on ``problem``, whose plant is unchanged: the controller's feedback is the
    same (additive noise), its filter believes an unexpected force sooner."""
    if not (isinstance(sigma_d, (int, float)) and math.isfinite(sigma_d) and sigma_d > 0):
        raise ValueError(f"sigma_d must be a positive density of joint torque (N m s^1/2); got {sigma_d!r}")
    if problem.n_states < 4:
        raise ValueError(f"with_disturbance_model needs an arm whose states begin [q1, q2, dq1, dq2]; got "
                         f"{problem.n_states} states ({problem.name!r})")
    return problem.replace(noise=DisturbanceTorqueNoise(problem.noise, float(sigma_d)))


def force_cv(u, q0=Q0, sigma_u=SIGMA_U, geometry="angle_dependent", t_act=_muscle.T_ACT,
             t_deact=_muscle.T_DEACT) -> np.ndarray:
    """[6] the coefficient of variation of each muscle's force for the excitations u [6] held at
    posture ``q0`` under the excitation noise ``sigma_u`` (the linearised stationary value).

    The activation is then an Ornstein-Uhlenbeck process with time constant t0 = t(u, u) and
    diffusion sigma_u u / t0, so its CV is sigma_u / sqrt(2 t0); the force F_max A(a, l) has
    CV = s sigma_u / sqrt(2 t0) with s = d ln A / d ln a at a = u (N_f z e^-z / (1 - e^-z),
    z = (a / (0.56 N_f))^N_f, about N_f for small activations: the force curve multiplies the
    activation's CV by 1.8-3.2 at the start posture).
    """
    u = jnp.asarray(_common.vector(u, "u", 6))
    l = _geometry(geometry).lengths(jnp.asarray(_common.vector(q0, "q0", 2)))
    t0 = _muscle.activation_time_constant(u, u, t_act, t_deact)
    slope = jax.vmap(jax.grad(lambda a, li: jnp.log(_muscle.activation_force(a, li))))(u, l) * u
    return np.asarray(slope * float(sigma_u) / jnp.sqrt(2.0 * t0))


def center_out_targets(n=8, radius=0.1, q0=Q0, arm: Arm2Params = ARM2_PARAMS, start_angle=0.0):
    """``n`` hand targets [n, 2] (m) on a circle of ``radius`` m around the hand position at posture ``q0``.

    Target k lies in direction start_angle + 2 pi k / n (radians, counter-clockwise from +x).
    """
    n = _common.positive(n, "n")
    if int(n) != n:
        raise ValueError(f"n must be a positive integer; got {n!r}")
    radius = _common.positive(radius, "radius")
    q0 = _common.vector(q0, "q0", 2)
    centre = np.asarray(hand_position(jnp.asarray(q0), _check_params(arm)))
    angles = float(start_angle) + 2 * np.pi * np.arange(int(n)) / int(n)
    return centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)


def arm2_muscle6(delay=PRESET, target=TARGET, noise=True, dt=0.01, horizon=None, final_time=FINAL_TIME,
                 geometry="angle_dependent", x0=None, sigma_u=SIGMA_U, sigma_tau=SIGMA_TAU, r=R_EFFORT,
                 r_f=R_FORCE, w_p=W_POS, w_v=W_VEL, w_a=W_ACT, arm: Arm2Params = ARM2_PARAMS,
                 t_act=_muscle.T_ACT, t_deact=_muscle.T_DEACT, sensory_delay=PRESET,
                 coactivation=COACTIVATION, vision_delay=None, joint_angle_noise=JOINT_ANGLE_DENSITY,
                 joint_velocity_noise=JOINT_VELOCITY_DENSITY) -> Problem:
    """Reaching with the six-muscle arm, delayed excitations and (by default) the human preset.

    Args:
        delay: motor (input) delay tau in seconds (any tau >= 0, a fraction of a step by the zero-order hold): the
            excitation sent at t reaches the muscles' activation dynamics at t + tau. Default
            (`PRESET`): `MOTOR_DELAY` (20 ms) with noise, 0 without.
        target: [2] hand target in metres (shoulder at the origin); see [`center_out_targets`][delayed_ilqr.models.center_out_targets].
        noise: True or ``"human"`` (the human preset: excitation and joint-torque noise, see the
            module docstring) or False (the deterministic arm).
        dt: time step in seconds.
        horizon: K; default ``round(final_time / dt)``.
        final_time: movement time in seconds when ``horizon`` is None.
        geometry: "angle_dependent" (variant B, default), "constant" (variant A) or a geometry object
            from `delayed_ilqr.models.muscle`.
        x0: [10] initial state; default q = Q0, dq = 0 and the rest activations (the static
            equilibrium at Q0 nearest to ``coactivation``, `rest_activations`).
        sigma_u: signal-dependent excitation noise, a diffusion scale (used when ``noise``).
        sigma_tau: signal-independent joint-torque noise in N m s^1/2 (used when ``noise``).
        r: excitation effort weight per unit time (the cost weights are stored in ``cost.params``).
        r_f: active-force effort weight per unit time.
        w_p: final hand position weight.
        w_v: final hand velocity weight.
        w_a: final activation weight.
        arm: rigid-body parameters ([`Arm2Params`][delayed_ilqr.models.Arm2Params]).
        t_act: activation time constant in seconds.
        t_deact: deactivation time constant in seconds.
        sensory_delay: None: the controller sees the state. A delay in seconds (a whole number of
            steps of ``dt``, 0 allowed): proprioception, joint angles and velocities seen that late
            through additive noise (`sensors.joint_sensors`); the activations are not sensed.
            Default (`PRESET`): `SENSORY_DELAY` (40 ms) with noise, None without.
        coactivation: the tonic co-activation level of the rest posture: the rest excitations
            ``cost.params["u_rest"]`` are the activations of the static equilibrium at the start
            posture nearest to it, and the default start. None: Li & Todorov's arm without a
            tonic rest (effort measured from zero, start activations `A_REST`, not an equilibrium).
        vision_delay: None (default): no vision. A delay in seconds: the hand position seen that
            late (`sensors.vision_sensors`), fused with proprioception when ``sensory_delay`` is set.
        joint_angle_noise: the proprioceptive joint-angle noise density in rad s^1/2 (per-sample SD
            density / sqrt(dt); used with ``sensory_delay``); `POSITION_SENSE` has the precision of
            human position sense.
        joint_velocity_noise: the joint-velocity noise density in rad s^-1/2 (likewise).

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"arm2_muscle6"`` with limits 0 <= u <= 1. Solve it
        with ``u_init=rest_commands(problem)``, the warm start its metadata names; the metadata's
        task space is the hand position (target: ``target``).
    """
    final_time = _common.positive(final_time, "final_time")
    preset, sigma_u = _common.noise_setting(noise, sigma_u, NOISE_PRESETS, "human", "arm2_muscle6")
    if isinstance(delay, str) and delay == PRESET:
        delay = 0.0 if preset is None else MOTOR_DELAY
    if isinstance(sensory_delay, str) and sensory_delay == PRESET:
        sensory_delay = None if preset is None else SENSORY_DELAY
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, final_time)
    geometry = _geometry(geometry)
    arm = _check_params(arm)
    x0 = None if x0 is None else _common.vector(x0, "x0", 10)
    if coactivation is None:        # Li & Todorov's arm: effort from zero, the start not at rest
        u_rest, a0 = (0.0,) * 6, (A_REST,) * 6
    else:
        coactivation = _common.positive(coactivation, "coactivation")
        u_rest = a0 = _rest(Q0 if x0 is None else x0[:2], coactivation, geometry, _muscle.F_MAX)
    x0 = Q0 + (0.0, 0.0) + a0 if x0 is None else x0
    if any(v < 0 or v > 1 for v in x0[4:]):
        raise ValueError(f"x0's activations x0[4:] must lie in [0, 1]; got {x0[4:]}")
    target = _common.vector(target, "target", 2)
    t_act, t_deact = _common.positive(t_act, "t_act"), _common.positive(t_deact, "t_deact")
    sigma_tau = _common.non_negative(sigma_tau, "sigma_tau")
    joint_densities = (_common.positive(joint_angle_noise, "joint_angle_noise"),
                       _common.positive(joint_velocity_noise, "joint_velocity_noise"))
    params = {"target": jnp.asarray(target), "u_rest": jnp.asarray(u_rest), "r": _common.positive(r, "r"),
              "r_f": _common.non_negative(r_f, "r_f"), "w_p": _common.non_negative(w_p, "w_p"),
              "w_v": _common.non_negative(w_v, "w_v"), "w_a": _common.non_negative(w_a, "w_a")}
    cost = GeneralCost(MuscleEffort(geometry), ReachFinalCost(arm), params)
    dynamics = Arm2Muscle6Dynamics(arm, geometry, _muscle.F_MAX, t_act, t_deact)
    noise_fn = None if preset is None else Arm2Muscle6Noise(sigma_u, sigma_tau, t_act, t_deact, arm, sigma_tau > 0)
    return Problem(dynamics=dynamics, x0=jnp.asarray(x0), dt=dt, horizon=horizon, delay_steps=delay_steps,
                   cost=cost, noise=noise_fn, u_min=np.zeros(6), u_max=np.ones(6), name="arm2_muscle6",
                   metadata=dataclasses.replace(METADATA if arm == ARM2_PARAMS else _metadata(arm), noise=preset),
                   observation=arm_sensors(10, dt, sensory_delay, vision_delay, arm, joint_densities))
