"""The Li & Todorov six-muscle model of the planar arm: muscle force, activation and geometry.

Pure ``jax.numpy`` functions (elementwise; they broadcast over leading axes) of the averaged
Brown, Cheng & Loeb "virtual muscle" model as used by Li & Todorov (2004) and in Li's 2006 thesis,
as written in ``docs/models.md`` §4.

Force (§4.1, [V2 x6]); l is the fibre length normalised by its optimal length L0, v = dl/dt in
L0 / s, a in [0, 1] the activation:

    T(a, l, v) = A(a, l) (F_L(l) F_V(l, v) + F_P(l))
    A(a, l)    = 1 - exp(-(a / (0.56 N_f(l)))^N_f(l)),     N_f(l) = 2.11 + 4.16 (1/l - 1)
    F_L(l)     = exp(-|(l^1.93 - 1) / 1.03|^1.87)
    F_V(l, v)  = (-5.72 - v) / (-5.72 + (1.38 + 2.09 l) v)                  v <= 0 (shortening)
               = (0.62 - (-3.12 + 4.21 l - 2.67 l^2) v) / (0.62 + v)       v > 0 (lengthening)
    F_P(l)     = -0.02 exp(13.8 - 18.7 l)       (13.8 as in five of six sources, not feedbax's 14.77)

Activation (§4.2, [V2 x4]):

    da/dt = (u - a) / t(u, a),   t = t_deact + u (t_act - t_deact) if u > a else t_deact,
    t_act = 50 ms, t_deact = 66 ms.

Maximal force (§4.3, [V2 x3]): F_max = 31.8 N/cm^2 x PCSA, PCSA = [18, 14, 22, 12, 5, 10] cm^2,
i.e. `F_MAX` = [572.4, 445.2, 699.6, 381.6, 159, 318] N.

Muscle order everywhere (`MUSCLES`): brachialis (elbow flexor), lateral triceps (elbow
extensor), anterior deltoid (shoulder flexor), posterior deltoid (shoulder extensor), biceps
(bi-articular flexor), long triceps (bi-articular extensor). Joint angles q = (shoulder, elbow),
flexion positive (counter-clockwise, as in [`delayed_ilqr.models.arm2`][delayed_ilqr.models.arm2]).

Geometry (§4.4), two variants, each a frozen dataclass (hashable by value) with
``moment_arms(q) -> [..., 2, 6]`` (metres), ``lengths(q) -> [..., 6]`` (normalised) and
``velocities(q, dq) -> [..., 6]`` (L0 / s):

* `AngleDependentGeometry` (variant B, the default, `ANGLE_DEPENDENT`): Van Wouwe et
  al. 2022 / bioptim ``leuven_arm_model.py``, said there to be "from Li & Todorov 2004" [V2]:
  d_ji(q_j) = a_ji + b_ji cos(c_ji q_j),
  l_i = l_base_i + l_mult_i sum_j [a_ji q_j + b_ji sin(c_ji q_j) / c_ji],
  v_i = l_mult_i sum_j d_ji(q_j) dq_j.
* `ConstantGeometry` (variant A, `CONSTANT`): constant moment arms D of Li's 2006 thesis
  (via jeremiedecock/pyarm) [V2], l_i = 1 - sum_j D_ji (q_j - q_ref_j) / L0_i,
  v_i = -sum_j D_ji dq_j / L0_i.

Sign convention (checked, and tested in ``tests/test_muscle.py``): a positive moment arm d_ji means
that muscle i pulling with tension F >= 0 produces a positive (flexing) torque d_ji F on joint j.
By virtual work the muscle then shortens when joint j flexes: d_ji = -L0_i dl_i/dq_j, with L0_i the
optimal fibre length in metres. In variant B dl_i/dq_j = l_mult_i d_ji(q_j) and every l_mult_i < 0,
so the published table is consistent with L0_i = -1 / l_mult_i (brachialis: L0 = 0.192 m; its
length falls from 1.1 at full extension to 0.6 at full flexion, matching the table's "l at 0 -> pi"
column, which ``tests/test_muscle.py`` reproduces for all six muscles). Variant A uses the same L0
(a choice, [D]; pyarm leaves L0 as a TODO) and l = 1 at the reference posture q_ref =
(pi/4, pi/2), the standard start posture of the reaching task (also a choice, [D]).

Where b = 0 in variant B the term b sin(c q) / c is exactly 0 whatever c is (bioptim stores c = 0.01
to avoid 0 / 0; here c = 1 is stored, which gives the same numbers).

Non-smooth points and guards (so that jax derivatives stay finite; document-level deviations from
the formulas, all outside or at the edge of the physiological range):

* ``activation_rate``'s time constant switches from activation to deactivation at u = a; the
  published switch (a kink in the rate) is smoothed by a logistic over `SWITCH_WIDTH` = 1e-2
  in u - a, so that optima with the activation held at the excitation are stationary points and
  the noise amplitude sigma_u u / t(u, a) has no near-kink curvature there (derivation §12). ``t`` uses u clipped to [0, 1] so that an out-of-range command cannot make
  t <= 0 (identical for u in [0, 1]; the clip's derivative at 0 and 1 is the inward one).
* ``force_velocity`` has a continuous value but a kink (different one-sided slopes) at v = 0; each
  branch is evaluated on v clipped to its own side, so the unused branch can never divide by zero.
* ``|x|^1.87`` in F_L is evaluated as ``(x^2)^0.935`` behind a ``where`` (derivative 0 at x = 0).
* ``A(a, l)`` is 0 for a <= `A_EPS` (the value there is below 1e-16), computed through
  ``exp(N_f log(a / (0.56 N_f)))`` with a safe argument, so that derivatives in a and in l (through
  N_f in the exponent) are finite at a = 0.
* N_f(l) uses l clipped to [`L_MIN`, `L_MAX_NF`] (N_f would reach 0 at l = 2.03 and 1/l
  is singular at 0), and F_L uses l >= L_MIN (l^1.93 is undefined for l < 0). Variant B stays in
  l in [0.6, 1.25] over the joint range [0, pi]^2.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize

from .. import _precision
from .._kernels.dense import small_matvec

__all__ = ["MUSCLES", "PCSA", "SPECIFIC_TENSION", "F_MAX", "T_ACT", "T_DEACT", "SWITCH_WIDTH", "A_EPS", "L_MIN", "L_MAX_NF",
           "activation_time_constant", "activation_rate", "n_f", "force_length", "force_velocity",
           "passive_force", "activation_force", "tension", "AngleDependentGeometry", "ConstantGeometry",
           "ANGLE_DEPENDENT", "CONSTANT", "joint_torques", "postural_forces", "rest_activations"]

MUSCLES = ("brachialis", "lateral triceps", "anterior deltoid", "posterior deltoid", "biceps", "long triceps")

# §4.3 [V2 x3]: bioptim Fiso, CasADi MPC Fmax, feedbax comment
SPECIFIC_TENSION = 31.8  # N / cm^2
PCSA = (18.0, 14.0, 22.0, 12.0, 5.0, 10.0)  # cm^2, in MUSCLES order
F_MAX = tuple(SPECIFIC_TENSION * p for p in PCSA)  # N: 572.4, 445.2, 699.6, 381.6, 159, 318

# §4.2 [V2 x4]
T_ACT = 0.05  # s
T_DEACT = 0.066  # s

# §4.1 [V2 x6]: Brown et al. slow/fast-twitch averages (feedbax TODOROV_LI_VIRTUALMUSCLE_PARAMS names)
BETA, OMEGA, RHO = 1.93, 1.03, 1.87  # force-length
V_MAX, CV0, CV1 = -5.72, 1.38, 2.09  # force-velocity, shortening
AV0, AV1, AV2, BV = -3.12, 4.21, -2.67, 0.62  # force-velocity, lengthening
NF0, NF1, AF = 2.11, 4.16, 0.56  # activation-frequency relation
C2, K2, PE_OFFSET = -0.02, -18.7, 13.8  # passive element: C2 exp(13.8 + K2 l)

# domain guards (see the module docstring)
A_EPS = 1e-10
#: Width (in u - a) of the smoothed switch between activation and deactivation time constants.
SWITCH_WIDTH = 1e-2
L_MIN = 0.2
L_MAX_NF = 1.6


# ------------------------------------------------------------------------------------------------
# activation dynamics
# ------------------------------------------------------------------------------------------------
def activation_time_constant(u, a, t_act=T_ACT, t_deact=T_DEACT):
    """t(u, a) = t_deact + u (t_act - t_deact) if u > a else t_deact (u clipped to [0, 1] inside),
    the switch at u = a smoothed over `SWITCH_WIDTH`:
    t = t_deact + s((u - a) / SWITCH_WIDTH) u (t_act - t_deact) with the logistic s.

    Li & Todorov's switch gives the activation rate (u - a) / t a kink at u = a, and optimal
    excitations sit on it (the activation held where the excitation is): a minimum there is not a
    stationary point, no Newton step certifies it, and 28 of 56 delayed noise-aware reaches of
    the center-out grid ended without convergence at such kinks (derivation §12). The width is
    1e-2 rather than the 1e-3 that removes the kink from the rate: the signal-dependent noise
    sigma_u u / t(u, a) inherits the switch, and over 1e-3 its curvature is so large that the
    LQG's model of the noise cost fails for steps above 1e-4 in u, which kept 8 of the grid's
    reaches from converging (derivation §12, cause 4). Smoothed, t differs from the published one
    by less than 0.25 % (relative) for |u - a| >= 0.05 and by less than 1e-12 for |u - a| > 0.3.

    The clip is written with ``where`` so that its derivative at u = 0 and u = 1 is the inward one
    (1): ``jnp.clip`` splits the gradient of a tie in half, and an excitation at its upper bound
    then got half its effect on t in the linearisation. The solver's steps from a bound go inward,
    the LQG planned them with that half derivative, and the line search, measuring the true one,
    rejected them: the noisy six-muscle reaches stalled there (derivation §12).
    """
    uc = jnp.where(u < 0.0, 0.0, jnp.where(u > 1.0, 1.0, u))
    return t_deact + jax.nn.sigmoid((u - a) / SWITCH_WIDTH) * uc * (t_act - t_deact)


def activation_rate(u, a, t_act=T_ACT, t_deact=T_DEACT):
    """da/dt = (u - a) / t(u, a): faster activation (50 ms at u = 1) than deactivation (66 ms).

    The time constant switches smoothly at u = a (`activation_time_constant`).
    """
    return (u - a) / activation_time_constant(u, a, t_act, t_deact)


# ------------------------------------------------------------------------------------------------
# force
# ------------------------------------------------------------------------------------------------
def n_f(l):
    """N_f(l) = 2.11 + 4.16 (1/l - 1), the activation-frequency exponent (l clipped to [L_MIN, L_MAX_NF])."""
    lc = jnp.clip(l, L_MIN, L_MAX_NF)
    return NF0 + NF1 * (1.0 / lc - 1.0)


def _abs_pow(x, p):
    """|x|^p for p > 1 with a finite derivative (0) at x = 0."""
    x2 = x * x
    nonzero = x2 > 0
    return jnp.where(nonzero, jnp.where(nonzero, x2, 1.0) ** (0.5 * p), 0.0)


def force_length(l):
    """F_L(l) = exp(-|(l^1.93 - 1) / 1.03|^1.87); F_L(1) = 1 (l >= L_MIN inside)."""
    lc = jnp.maximum(l, L_MIN)
    return jnp.exp(-_abs_pow((lc ** BETA - 1.0) / OMEGA, RHO))


def force_velocity(l, v):
    """F_V(l, v): Brown's hyperbola for shortening (v <= 0) and lengthening (v > 0); F_V(l, 0) = 1.

    Continuous at v = 0 with different one-sided slopes (a kink).
    """
    vs = jnp.minimum(v, 0.0)  # each branch sees only its own side: no 0 / 0 in the unused one
    vl = jnp.maximum(v, 0.0)
    shortening = (V_MAX - vs) / (V_MAX + (CV0 + CV1 * l) * vs)
    lengthening = (BV - (AV0 + AV1 * l + AV2 * l * l) * vl) / (BV + vl)
    return jnp.where(v <= 0, shortening, lengthening)


def passive_force(l):
    """F_P(l) = -0.02 exp(13.8 - 18.7 l) (Brown's PE2 element, negative: resists compression)."""
    return C2 * jnp.exp(PE_OFFSET + K2 * l)


def activation_force(a, l):
    """A(a, l) = 1 - exp(-(a / (0.56 N_f(l)))^N_f(l)); 0 for a <= A_EPS (finite derivatives at a = 0)."""
    nf = n_f(l)
    pos = a > A_EPS
    a_safe = jnp.where(pos, a, 1.0)
    z = jnp.exp(nf * jnp.log(a_safe / (AF * nf)))
    return jnp.where(pos, -jnp.expm1(-z), 0.0)


def tension(a, l, v):
    """T(a, l, v) = A(a, l) (F_L(l) F_V(l, v) + F_P(l)), the normalised muscle tension (times F_max = N)."""
    return activation_force(a, l) * (force_length(l) * force_velocity(l, v) + passive_force(l))


# ------------------------------------------------------------------------------------------------
# geometry
# ------------------------------------------------------------------------------------------------
def _rows(value, name, shape):
    arr = tuple(tuple(float(v) for v in row) for row in value)
    if (len(arr), len(arr[0])) != shape:
        raise ValueError(f"{name} must have shape {shape}; got {(len(arr), len(arr[0]))}")
    return arr


@dataclass(frozen=True)
class AngleDependentGeometry:
    """Variant B (§4.4, [V2]: Van Wouwe et al. 2022 / bioptim ``leuven_arm_model.py``).

    Attributes (rows: shoulder, elbow; columns: `MUSCLES`):
        a, b: [2][6] moment-arm coefficients in metres, d_ji(q_j) = a_ji + b_ji cos(c_ji q_j).
        c: [2][6] (1/rad); 1.0 is stored where b = 0 (the term is then exactly 0).
        l_base: [6] normalised fibre length at q = 0.
        l_mult: [6] (1 / m): dl_i/dq_j = l_mult_i d_ji(q_j), so L0_i = -1 / l_mult_i.
    """

    a: tuple = ((0.0, 0.0, 0.040, -0.042, 0.030, -0.039),
                (0.030, -0.019, 0.0, 0.0, 0.032, -0.022))
    b: tuple = ((0.0, 0.0, -0.008, 0.0, -0.011, 0.0),
                (-0.011, 0.0, 0.0, 0.0, -0.010, 0.0))
    c: tuple = ((1.0, 1.0, 1.9, 1.0, 1.9, 1.0),
                (1.9, 1.0, 1.0, 1.0, 1.9, 1.0))
    l_base: tuple = (1.1, 0.8, 1.2, 0.7, 1.1, 0.85)
    l_mult: tuple = (-5.2063, -7.5389, -3.9381, -3.0315, -2.5228, -1.8264)

    @property
    def optimal_lengths(self):
        """L0_i = -1 / l_mult_i in metres (the length scale implied by d = -L0 dl/dq)."""
        return tuple(-1.0 / m for m in self.l_mult)

    def moment_arms(self, q):
        """d(q) [..., 2, 6] in metres."""
        a, b, c = jnp.asarray(self.a), jnp.asarray(self.b), jnp.asarray(self.c)
        return a + b * jnp.cos(c * q[..., :, None])

    def lengths(self, q):
        """l(q) [..., 6], normalised by L0."""
        a, b, c = jnp.asarray(self.a), jnp.asarray(self.b), jnp.asarray(self.c)
        qq = q[..., :, None]
        integral = jnp.sum(a * qq + b * jnp.sin(c * qq) / c, axis=-2)
        return jnp.asarray(self.l_base) + jnp.asarray(self.l_mult) * integral

    def velocities(self, q, dq):
        """v = dl/dt [..., 6] in L0 / s."""
        return jnp.asarray(self.l_mult) * jnp.sum(self.moment_arms(q) * dq[..., :, None], axis=-2)


@dataclass(frozen=True)
class ConstantGeometry:
    """Variant A (§4.4, [V2]: Li 2006 thesis via jeremiedecock/pyarm): constant moment arms.

    Attributes (rows: shoulder, elbow; columns: `MUSCLES`):
        D: [2][6] moment arms in metres. The thesis matrix (columns sh.flex, sh.ext, el.flex,
            el.ext, bi.flex, bi.ext; cm) [[4, -4, 0, 0, 2.8, -3.5], [0, 0, 2.5, -2.5, 2.8, -3.5]]
            reordered to `MUSCLES`.
        L0: [6] optimal fibre lengths in metres; default -1 / l_mult of variant B ([D], a choice:
            the thesis value was not retrieved).
        q_ref: [2] posture where every l_i = 1; default the start posture (pi/4, pi/2) ([D]).
    """

    D: tuple = ((0.0, 0.0, 0.040, -0.040, 0.028, -0.035),
                (0.025, -0.025, 0.0, 0.0, 0.028, -0.035))
    L0: tuple = tuple(-1.0 / m for m in AngleDependentGeometry.l_mult)
    q_ref: tuple = (math.pi / 4, math.pi / 2)

    @property
    def optimal_lengths(self):
        return self.L0

    def moment_arms(self, q):
        """D [..., 2, 6] in metres (independent of q)."""
        return jnp.broadcast_to(jnp.asarray(self.D), q.shape[:-1] + (2, 6))

    def lengths(self, q):
        """l_i = 1 - sum_j D_ji (q_j - q_ref_j) / L0_i [..., 6]."""
        dq = q - jnp.asarray(self.q_ref)
        return 1.0 - jnp.sum(jnp.asarray(self.D) * dq[..., :, None], axis=-2) / jnp.asarray(self.L0)

    def velocities(self, q, dq):
        """v_i = -sum_j D_ji dq_j / L0_i [..., 6] in L0 / s."""
        return -jnp.sum(jnp.asarray(self.D) * dq[..., :, None], axis=-2) / jnp.asarray(self.L0)


ANGLE_DEPENDENT = AngleDependentGeometry()
CONSTANT = ConstantGeometry()


def joint_torques(q, dq, a, geometry=ANGLE_DEPENDENT, f_max=F_MAX):
    """tau = d(q) (F_max * T(a, l(q), v(q, dq))) [..., 2] in N m, for q, dq [..., 2] and a [..., 6]."""
    T = tension(a, geometry.lengths(q), geometry.velocities(q, dq))
    force = jnp.asarray(f_max) * T
    return small_matvec(geometry.moment_arms(q), force)


# ------------------------------------------------------------------------------------------------
# posture
# ------------------------------------------------------------------------------------------------
def postural_forces(q, reference, geometry=ANGLE_DEPENDENT, f_max=F_MAX):
    """[..., 6] the active forces A* (fractions of the maximal force, A of §4.1) nearest to
    ``reference`` [..., 6] whose net joint torque at posture q [..., 2] is zero at rest (dq = 0).

    At rest tau = C(q) A with C(q) = d(q) diag(F_max (F_L(l) + F_P(l))) [2, 6] (F_V = 1 at v = 0),
    so the nearest zero-torque forces are the projection A* = A - C' (C C')^{-1} C A: closed form
    and differentiable in q. With ``reference`` the forces of the rest activations at q, A(a_rest,
    l(q)), this is the tonic co-activation that holds posture q still; at the posture where a_rest
    is a static equilibrium (`rest_activations`) A* = A(a_rest, l(q)) exactly.
    """
    l = geometry.lengths(q)
    C = geometry.moment_arms(q) * (jnp.asarray(f_max) * (force_length(l) + passive_force(l)))[..., None, :]
    CCt = C @ jnp.swapaxes(C, -1, -2)
    torque = small_matvec(C, reference)
    return reference - small_matvec(jnp.swapaxes(C, -1, -2), jnp.linalg.solve(CCt, torque[..., None])[..., 0])


def rest_activations(q, level, geometry=ANGLE_DEPENDENT, f_max=F_MAX, tol=1e-12):
    """The activations a [6] nearest to the co-activation ``level`` whose net joint torque at
    posture q [2] (at rest, dq = 0) is zero: min |a - level|^2 subject to tau(q, 0, a) = 0 and
    0 <= a <= 1, solved by SciPy's SLSQP with the exact JAX derivatives.

    Held with the excitations u = a (the activation's own equilibrium), the arm stays at q: a
    static equilibrium with every muscle active, so each can both raise and lower its force.

    Raises:
        ValueError: ``level`` outside (0, 1), or no equilibrium found (the residual torque is
            named).
    """
    _precision.require_x64("models.muscle.rest_activations (the six-muscle arm's rest posture)")
    level = float(level)
    if not 0.0 < level < 1.0:
        raise ValueError(f"level (the co-activation) must lie in (0, 1); got {level!r}")
    q = jnp.asarray(q, dtype=jnp.float64)
    torque = jax.jit(lambda a: joint_torques(q, jnp.zeros(2, q.dtype), a, geometry, f_max))
    jac = jax.jit(jax.jacfwd(torque))
    # scaled: the constraint in N m is O(1), the objective O(0.01); SLSQP's tolerance is on both
    result = minimize(lambda a: float(np.sum((a - level) ** 2)), np.full(6, level),
                      jac=lambda a: 2.0 * (a - level), method="SLSQP", bounds=[(1e-3, 1.0)] * 6,
                      constraints={"type": "eq", "fun": lambda a: np.asarray(torque(jnp.asarray(a))),
                                   "jac": lambda a: np.asarray(jac(jnp.asarray(a)))},
                      options={"ftol": 1e-15, "maxiter": 200})
    a = jnp.asarray(result.x)
    # polish: Newton steps on the torque along the least-norm direction (SLSQP stops near 1e-9 N m)
    for _ in range(3):
        J = jac(a)
        a = a - J.T @ jnp.linalg.solve(J @ J.T, torque(a))
    residual = float(jnp.max(jnp.abs(torque(a))))
    if not result.success and residual > 1e-6 or residual > tol or np.any(np.asarray(a) <= 0):
        raise ValueError(f"no static equilibrium near the co-activation level {level} at q = {np.asarray(q)}: "
                         f"residual torque {residual:.3g} N m ({result.message})")
    return a
