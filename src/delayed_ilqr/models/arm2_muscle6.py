"""The two-link arm driven by six muscles through delayed neural excitations (Li & Todorov 2004).

``docs/models.md`` §4 (the muscle model is in `delayed_ilqr.models.muscle`), rigid body of §3
([`delayed_ilqr.models.arm2`][delayed_ilqr.models.arm2], P2's parameters [`ARM2_PARAMS`][delayed_ilqr.models.ARM2_PARAMS]):

    x = [q1, q2, dq1, dq2, a1..a6] (10),   u = neural excitations in [0, 1]^6 (6)
    f(x, u, ud) = [dq,  M(q)^{-1} (tau - C(q, dq) - B dq),  (ud - a) / t(ud, a)]
    tau = d(q) (F_max * T(a, l(q), v(q, dq)))

The command sent at step k reaches the muscles after the input delay: the *delayed* excitation
``ud`` = u_{k-l} drives the activation dynamics; ``u`` itself does not enter the plant.

Noise (``noise=True``; §4.5): signal-dependent (multiplicative) noise on the excitations, the form
Todorov & Li (2005) describe for their 6-muscle arm ([V] abstract: dx = f dt + F(x, u) dw with
control-dependent F; "acts multiplicatively on the muscle excitations" is [R]). The excitation
acting on muscle i is ud_i (1 + sigma_u w_i) with white w_i, filtered by the activation dynamics at
the time constant of the noise-free command, so F [10, 6] is zero except
F[4 + i, i] = sigma_u ud_i / t(ud_i, a_i). F is a continuous-time diffusion
(`delayed_ilqr.models.noise`; a per-step sigma of Todorov's convention is
``per_step_noise_to_diffusion(sigma, dt)``).

Noise level, calibrated to human data (``docs/models.md`` §4.5): a held excitation gives an
activation whose stationary coefficient of variation is sigma_u / sqrt(2 t) = 2.8 to 3.2 sigma_u
(t = 66 to 50 ms). The default `SIGMA_U` = 0.01 makes it 2.8-3.2 %, the few per cent of
isometric force variability in humans, whose standard deviation grows in proportion to the mean
force (signal-dependent noise: Jones, Hamilton & Wolpert 2002 [V abstract]; the per-cent size [R];
the coefficient of variation of joint torque falls with strength, Hamilton, Jones & Wolpert 2004
[V abstract]). Measured with it (``docs/models.md`` §4.5 has the table): 10 cm center-out reaches
of the noise-aware design have a 1-sigma endpoint spread of 0.05 mm at no delay and 9 mm at
100 ms. Human reaches without vision of the hand scatter by millimetres (endpoint ellipses
elongated along the movement, Gordon, Ghilardi & Ghez 1994; van Beers, Haggard & Wolpert 2004
[V abstract]; the millimetre size [R]); the model reaches that only with a feedback delay, because
at no delay its feedback sees the exact state at once (no sensory noise, no sensory delay), and
motor noise alone large enough for millimetres at no delay (sigma_u >= 0.05) lies outside the
range where the linearisation holds (Monte Carlo mean 150x the prediction, half the noise-aware
reaches unconverged). The former default 0.1 (Li's torque-arm value, §4.5 [V2]) gave activations a
28-32 % coefficient of variation. Other levels: the ``sigma_u`` argument.

Cost (a [`GeneralCost`][delayed_ilqr.GeneralCost]; the running cost is multiplied by dt, the final cost
is not, as in Todorov's ``ilqg_det.m``, §4.6 [V]):

    running(x, u) = r |u|^2
    final(x)      = w_p |e(q) - e*|^2 + w_v |de/dt(q, dq)|^2 + w_a |a|^2

with e the hand position. ``cost.params = {"target", "w_p", "w_v", "w_a", "r"}`` (arrays): problems
with different targets or weights share one compiled solver (``jax.vmap`` over targets works).

| parameter | default | source |
|---|---|---|
| arm | ARM2_PARAMS | §3 Li & Todorov 2004 / Li 2006 thesis [V2] (m2 = 1.1 kg, B = [[0.05, 0.025], [0.025, 0.05]]), as P2 |
| muscles | muscle.py | §4.1-4.3 [V2]; geometry variant B (default) or A |
| t_act/t_deact | 50 / 66 ms | §4.2 [V2 x4] |
| dt | 0.01 s | §4.6 Li 2006 thesis reaching task [V2] |
| final time | 0.5 s (K = 50) | §4.6 [R] "T ~ 0.5 s"; Ueyama uses 0.4 s |
| x0 | q = (pi/4, pi/2), dq = 0, a = A_REST | §4.6 Li 2006 thesis x0 [V2]; the rest activation is [D], see below |
| target | (0.05, 0.5) m | §4.6 Li 2006 thesis hand target e* [V2] (9.0 cm from the start hand position (-0.021, 0.446) m) |
| r | 1e-4 | [D] within §4.6's range (1e-3 thesis torque arm, 1e-4 [R] Li & Todorov 2004); excitations are O(0.1-1) |
| w_p | 1 (1/m^2) | §4.6 Li 2006 thesis final position weight [V2] |
| w_v | 0.1 (s^2/m^2) | [D] (thesis: 1e-2 on a torque arm); 0.1 stops the hand |
| w_a | 0 | [D] optional final activation penalty |
| sigma_u | 0.01 | §4.5, calibrated to human force variability (see above) |

Rest activation (`A_REST` = 0.05, [D]): the force A(a, l) ~ (a / (0.56 N_f))^N_f has zero
slope at a = 0 (N_f > 1 over the joint range), so at a = u = 0 the linearised dynamics have no path
from the commands to the arm and iLQG's first step is zero. Starting from a small activation level
(and warm-starting the solver with ``u_init = A_REST`` everywhere, [`rest_commands`][delayed_ilqr.models.rest_commands], the
equilibrium of the activation dynamics; Ueyama's replication starts from u0 = 0.1, §4.6) avoids this.
At a = A_REST the muscles' net torques at the start posture are not exactly zero, so the arm drifts
slightly if the command is held; the reach cost corrects this.

What this cost predicts (``docs/models.md`` §4.6, ``docs/results/reach_shape.md``): at no delay the
optimal reach pushes, coasts and brakes (flat-topped hand speed), and along the x axis it curves
with two speed peaks, unlike human reaches (straight, bell-shaped; Morasso 1981, Flash & Hogan
1985). The reason is the force A ~ (a / (0.56 N_f))^N_f with N_f >= 2.11 (§4.1): an effort
r |u|^2 on the excitations then grows about as force^(2 / N_f), concave, which favours short
bursts. Bounded L-BFGS-B finds the same optima. With a delay, the noise-aware design's reaches are
single-peaked.
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
from .sensors import joint_sensors

__all__ = ["arm2_muscle6", "center_out_targets", "rest_commands", "rest_activations", "default_x0",
           "Arm2Muscle6Dynamics", "Arm2Muscle6Noise", "ReachRunningCost", "ReachFinalCost", "FINAL_TIME",
           "SIGMA_U", "SIGMA_TAU", "COACTIVATION", "MOTOR_DELAY", "SENSORY_DELAY", "PRESET", "Q0", "TARGET",
           "GEOMETRIES"]

FINAL_TIME = 0.5  # s
SIGMA_U = 0.01  # signal-dependent excitation noise (module docstring)
SIGMA_TAU = 0.004  # N m s^1/2, signal-independent joint-torque noise (module docstring)
NOISE_PRESETS = {"human": SIGMA_U}  # noise=True is "human"; another sigma_u is "custom"
COACTIVATION = 0.15  # tonic co-activation of the rest posture (module docstring)
MOTOR_DELAY = 0.02  # s, efferent + electromechanical delay of the human preset
SENSORY_DELAY = 0.04  # s, proprioceptive (afferent) delay of the human preset
PRESET = "preset"  # the default of ``delay`` and ``sensory_delay``: the human preset's values
Q0 = (math.pi / 4, math.pi / 2)  # rad, Li 2006 thesis start posture
TARGET = (0.05, 0.5)  # m, Li 2006 thesis hand target
R_EFFORT, R_FORCE, W_POS, W_VEL, W_ACT = 1e-4, 1e-2, 1.0, 0.1, 0.0

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
    F[2:4, 6:8] = sigma_tau M(q)^{-1}."""

    sigma_u: float = SIGMA_U
    sigma_tau: float = SIGMA_TAU
    t_act: float = _muscle.T_ACT
    t_deact: float = _muscle.T_DEACT
    arm: Arm2Params = ARM2_PARAMS

    def __call__(self, x, u, ud):
        q, a = x[:2], x[4:]
        gain = self.sigma_u * ud / _muscle.activation_time_constant(ud, a, self.t_act, self.t_deact)
        torque = self.sigma_tau * mass_matrix_inverse(q, self.arm)
        zeros = jnp.zeros((2, 6), gain.dtype)
        excitation = jnp.concatenate([zeros, zeros, jnp.diag(gain)], axis=0)
        additive = jnp.concatenate([jnp.zeros((2, 2), gain.dtype), torque, jnp.zeros((6, 2), gain.dtype)], axis=0)
        return jnp.concatenate([excitation, additive], axis=1)


# the noise scales are data (pytree leaves): derivatives with respect to them, and problems that
# differ only in them share one compiled solver
jax.tree_util.register_dataclass(Arm2Muscle6Noise, data_fields=["sigma_u", "sigma_tau"],
                                 meta_fields=["t_act", "t_deact", "arm"])


@dataclass(frozen=True)
class ReachRunningCost:
    """running(x, u, params) = r |u - u_rest|^2 + r_f |A(a, l(q)) - A(u_rest, l(q))|^2 (per unit time):
    the excitations' and the muscles' active forces' (fractions of the maximal force) departures
    from the tonic rest."""

    geometry: object = _muscle.ANGLE_DEPENDENT

    def __call__(self, x, u, params):
        q, a, rest = x[:2], x[4:], params["u_rest"]
        l = self.geometry.lengths(q)
        du = u - rest
        df = _muscle.activation_force(a, l) - _muscle.activation_force(rest, l)
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
    """A [K, 6] warm start holding the excitations at the problem's rest (``cost.params["u_rest"]``,
    where the activations of the rest posture are in equilibrium), or at a scalar ``level``."""
    rest = problem.cost.params["u_rest"] if level is None else jnp.full(problem.n_controls, float(level))
    return jnp.broadcast_to(jnp.asarray(rest, jnp.float64), (problem.horizon, problem.n_controls))


METADATA = _metadata(ARM2_PARAMS)


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
                 coactivation=COACTIVATION) -> Problem:
    """Reaching with the six-muscle arm, delayed excitations and (by default) the human preset.

    Args:
        delay: motor (input) delay tau in seconds (a whole number of steps of ``dt``): the
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
        coactivation: the tonic co-activation level of the rest posture (the rest excitations
            ``cost.params["u_rest"]`` are the equilibrium activations nearest to it).

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
    coactivation = _common.positive(coactivation, "coactivation")
    x0 = None if x0 is None else _common.vector(x0, "x0", 10)
    u_rest = _rest(Q0 if x0 is None else x0[:2], coactivation, geometry, _muscle.F_MAX)
    x0 = Q0 + (0.0, 0.0) + u_rest if x0 is None else x0
    if any(v < 0 or v > 1 for v in x0[4:]):
        raise ValueError(f"x0's activations x0[4:] must lie in [0, 1]; got {x0[4:]}")
    target = _common.vector(target, "target", 2)
    t_act, t_deact = _common.positive(t_act, "t_act"), _common.positive(t_deact, "t_deact")
    sigma_tau = _common.non_negative(sigma_tau, "sigma_tau")
    params = {"target": jnp.asarray(target), "u_rest": jnp.asarray(u_rest), "r": _common.positive(r, "r"),
              "r_f": _common.non_negative(r_f, "r_f"), "w_p": _common.non_negative(w_p, "w_p"),
              "w_v": _common.non_negative(w_v, "w_v"), "w_a": _common.non_negative(w_a, "w_a")}
    cost = GeneralCost(ReachRunningCost(geometry), ReachFinalCost(arm), params)
    dynamics = Arm2Muscle6Dynamics(arm, geometry, _muscle.F_MAX, t_act, t_deact)
    noise_fn = None if preset is None else Arm2Muscle6Noise(sigma_u, sigma_tau, t_act, t_deact, arm)
    return Problem(dynamics=dynamics, x0=jnp.asarray(x0), dt=dt, horizon=horizon, delay_steps=delay_steps,
                   cost=cost, noise=noise_fn, u_min=np.zeros(6), u_max=np.ones(6), name="arm2_muscle6",
                   metadata=dataclasses.replace(METADATA if arm == ARM2_PARAMS else _metadata(arm), noise=preset),
                   observation=None if sensory_delay is None else joint_sensors(10, sensory_delay, dt))
