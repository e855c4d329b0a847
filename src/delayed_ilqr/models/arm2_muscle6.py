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

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from ..problem import GeneralCost, Problem
from . import _common
from . import muscle as _muscle
from .arm2 import (ARM2_PARAMS, ARM_STATE_LABELS, Arm2Params, _check_params, hand_position, hand_task,
                   hand_velocity, joint_acceleration)
from .metadata import CostParameter, ModelMetadata
from .sensors import arm_sensors

__all__ = ["arm2_muscle6", "center_out_targets", "rest_commands", "default_x0", "Arm2Muscle6Dynamics",
           "Arm2Muscle6Noise",
           "ReachRunningCost", "ReachFinalCost", "FINAL_TIME", "SIGMA_U", "A_REST", "Q0", "TARGET",
           "GEOMETRIES"]

FINAL_TIME = 0.5  # s
SIGMA_U = 0.01  # excitation noise calibrated to human force variability (module docstring)
NOISE_PRESETS = {"human": SIGMA_U}  # noise=True is "human"; another sigma_u is "custom"
A_REST = 0.05
Q0 = (math.pi / 4, math.pi / 2)  # rad, Li 2006 thesis start posture
TARGET = (0.05, 0.5)  # m, Li 2006 thesis hand target
R_EFFORT, W_POS, W_VEL, W_ACT = 1e-4, 1.0, 0.1, 0.0

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
    """F(x, u, ud) [10, 6]: F[4 + i, i] = sigma_u ud_i / t(ud_i, a_i), noise proportional to the excitation."""

    sigma_u: float = SIGMA_U
    t_act: float = _muscle.T_ACT
    t_deact: float = _muscle.T_DEACT

    def __call__(self, x, u, ud):
        a = x[4:]
        gain = self.sigma_u * ud / _muscle.activation_time_constant(ud, a, self.t_act, self.t_deact)
        return jnp.concatenate([jnp.zeros((4, 6), gain.dtype), jnp.diag(gain)], axis=0)


# sigma_u is data (a pytree leaf): derivatives with respect to the noise scale, and problems that
# differ only in it share one compiled solver
jax.tree_util.register_dataclass(Arm2Muscle6Noise, data_fields=["sigma_u"], meta_fields=["t_act", "t_deact"])


@dataclass(frozen=True)
class ReachRunningCost:
    """running(x, u, params) = r |u|^2 (per unit time)."""

    def __call__(self, x, u, params):
        return params["r"] * (u @ u)


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


def default_x0(q0=Q0, a0=A_REST) -> tuple:
    """[q1, q2, 0, 0, a0 x 6]."""
    q0 = _common.vector(q0, "q0", 2)
    return q0 + (0.0, 0.0) + (float(a0),) * 6


def rest_commands(problem: Problem, level=A_REST):
    """A [K, 6] warm start holding every excitation at ``level`` (the activation's equilibrium)."""
    return jnp.full((problem.horizon, problem.n_controls), float(level))


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


def arm2_muscle6(delay=0.0, target=TARGET, noise=True, dt=0.01, horizon=None, final_time=FINAL_TIME,
                 geometry="angle_dependent", x0=None, sigma_u=SIGMA_U, r=R_EFFORT, w_p=W_POS, w_v=W_VEL,
                 w_a=W_ACT, arm: Arm2Params = ARM2_PARAMS, t_act=_muscle.T_ACT, t_deact=_muscle.T_DEACT,
                 sensory_delay=None, vision_delay=None) -> Problem:
    """Energy-optimal reaching with the six-muscle arm and delayed excitations (Li & Todorov 2004).

    Args:
        delay: input delay tau in seconds (a whole number of steps of ``dt``): the excitation sent at
            t reaches the muscles' activation dynamics at t + tau.
        target: [2] hand target in metres (shoulder at the origin); see [`center_out_targets`][delayed_ilqr.models.center_out_targets].
        noise: add signal-dependent excitation noise (F [10, 6], see the module docstring): True
            or ``"human"`` (its one preset, at ``sigma_u``), or False.
        dt: time step in seconds.
        horizon: K; default ``round(final_time / dt)``.
        final_time: movement time in seconds when ``horizon`` is None.
        geometry: "angle_dependent" (variant B, default), "constant" (variant A) or a geometry object
            from `delayed_ilqr.models.muscle`.
        x0: [10] initial state; default q = (pi/4, pi/2), dq = 0, a = A_REST (0.05) for all muscles.
        sigma_u: excitation noise, a diffusion scale (used when ``noise``); default 0.01, calibrated
            to human force variability (module docstring).
        r: effort weight per unit time (the cost weights are stored in ``cost.params``).
        w_p: final hand position weight.
        w_v: final hand velocity weight.
        w_a: final activation weight.
        arm: rigid-body parameters ([`Arm2Params`][delayed_ilqr.models.Arm2Params]).
        t_act: activation time constant in seconds.
        t_deact: deactivation time constant in seconds.
        sensory_delay: None (default): the controller sees the state. A delay in seconds (a
            whole number of steps of ``dt``, 0 allowed): proprioception, joint angles and
            velocities seen that late through additive noise (`sensors.joint_sensors`);
            the activations are not sensed.
        vision_delay: None (default): no vision. A delay in seconds: the hand position seen that
            late (`sensors.vision_sensors`), fused with proprioception when ``sensory_delay`` is set.

    Returns:
        A [`Problem`][delayed_ilqr.Problem] named ``"arm2_muscle6"`` with limits 0 <= u <= 1. Solve it
        with ``u_init=rest_commands(problem)`` (see the module docstring on A_REST), the warm start
        its metadata names; the metadata's task space is the hand position (target: ``target``).
    """
    final_time = _common.positive(final_time, "final_time")
    dt, delay_steps, horizon = _common.time_grid(dt, delay, horizon, final_time)
    preset, sigma_u = _common.noise_setting(noise, sigma_u, NOISE_PRESETS, "human", "arm2_muscle6")
    geometry = _geometry(geometry)
    arm = _check_params(arm)
    x0 = default_x0() if x0 is None else _common.vector(x0, "x0", 10)
    if any(v < 0 or v > 1 for v in x0[4:]):
        raise ValueError(f"x0's activations x0[4:] must lie in [0, 1]; got {x0[4:]}")
    target = _common.vector(target, "target", 2)
    t_act, t_deact = _common.positive(t_act, "t_act"), _common.positive(t_deact, "t_deact")
    params = {"target": jnp.asarray(target), "r": _common.positive(r, "r"), "w_p": _common.non_negative(w_p, "w_p"),
              "w_v": _common.non_negative(w_v, "w_v"), "w_a": _common.non_negative(w_a, "w_a")}
    cost = GeneralCost(ReachRunningCost(), ReachFinalCost(arm), params)
    dynamics = Arm2Muscle6Dynamics(arm, geometry, _muscle.F_MAX, t_act, t_deact)
    noise_fn = None if preset is None else Arm2Muscle6Noise(sigma_u, t_act, t_deact)
    return Problem(dynamics=dynamics, x0=jnp.asarray(x0), dt=dt, horizon=horizon, delay_steps=delay_steps,
                   cost=cost, noise=noise_fn, u_min=np.zeros(6), u_max=np.ones(6), name="arm2_muscle6",
                   metadata=dataclasses.replace(METADATA if arm == ARM2_PARAMS else _metadata(arm), noise=preset),
                   observation=arm_sensors(10, dt, sensory_delay, vision_delay, arm))
