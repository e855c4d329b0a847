"""The six-muscle arm's human preset (``arm2_muscle6()``, docs/models.md §4.7) against the classic
findings of center-out reaching (docs/results/center_out_human.md has the full-size study).

Measured by Monte Carlo on a fixed seed list: two of the eight 10 cm targets (0 and 90 deg) and
one the tests never use otherwise (15 cm at 112.5 deg), solved in one batch (one compilation),
100 trials each. The full eight targets, with unseen distances and directions, are under the ``full``
marker. Published ranges (Morasso 1981; Flash & Hogan 1985; Gordon, Ghilardi & Ghez 1994; van
Beers, Haggard & Wolpert 2004): single-peaked hand speed with peak/mean 1.6-2.0, lateral path
deviation <= 10 % of the length, endpoint SD 2-8 mm with the ellipse's major axis within 30 deg of
the movement direction.
"""
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from delayed_ilqr.models import muscle
from delayed_ilqr.models.arm2 import hand_velocity
from delayed_ilqr.models.arm2_muscle6 import (A_REST, COACTIVATION, MOTOR_DELAY, POSITION_SENSE, Q0,
                                              SENSORY_DELAY, SIGMA_U, arm2_muscle6, center_out_targets, default_x0,
                                              force_cv, rest_activations)
from delayed_ilqr.models.sensors import JOINT_ANGLE_DENSITY, JOINT_VELOCITY_DENSITY

from human_reaches import center_out_reaches, reaches

EIGHT = center_out_targets(8, 0.1)
UNSEEN = center_out_targets(16, 0.15)[5]          # 15 cm at 112.5 deg


def _hand_speeds(x0, u, steps=100):
    """Hand speed [steps] (m/s) of the noise-free arm from x0 with the excitations u held (Euler, dt)."""
    p = arm2_muscle6(noise=False, x0=tuple(np.asarray(x0)))

    def step(x, _):
        x = x + p.dt * p.dynamics(x, u, u)
        return x, jnp.linalg.norm(hand_velocity(x[:2], x[2:4]))
    return np.asarray(jax.lax.scan(step, p.x0, None, length=steps)[1])


def test_the_rest_posture_is_an_equilibrium():
    """Holding the rest excitations keeps the hand still for 1 s (< 1 mm/s); the former uniform
    start activation (0.05, not an equilibrium) drifts by centimetres per second."""
    rest = jnp.asarray(rest_activations())
    assert np.max(_hand_speeds(default_x0(), rest)) < 1e-3
    assert np.max(_hand_speeds(default_x0(a0=A_REST), jnp.full(6, A_REST))) > 5e-3
    # every muscle active, near the co-activation level, and the net torque zero
    assert np.all(np.asarray(rest) > 0.02) and abs(float(np.mean(rest)) - COACTIVATION) < 0.05
    tau = muscle.joint_torques(jnp.asarray(Q0), jnp.zeros(2), rest)
    np.testing.assert_allclose(tau, 0.0, atol=1e-10)


def test_the_effort_is_measured_from_the_tonic_forces_that_hold_the_current_posture():
    """postural_forces: at the start posture the rest's own forces (the rest is a static
    equilibrium found by SLSQP); at other postures forces whose activations, found by bisection on
    A(a, l) and put through joint_torques, hold the arm still, and the nearest such forces (the
    change is orthogonal to every zero-torque direction: the projection's optimality condition)."""
    rest = jnp.asarray(rest_activations())
    geo = muscle.ANGLE_DEPENDENT
    l0 = geo.lengths(jnp.asarray(Q0))
    np.testing.assert_allclose(muscle.postural_forces(jnp.asarray(Q0), muscle.activation_force(rest, l0)),
                               muscle.activation_force(rest, l0), atol=1e-14)
    for q in ((0.5, 1.9), (1.2, 1.2), (0.3, 2.2)):
        q = jnp.asarray(q)
        l = geo.lengths(q)
        ref = muscle.activation_force(rest, l)
        target = muscle.postural_forces(q, ref)
        lo, hi = jnp.zeros(6), jnp.ones(6)
        for _ in range(60):                                       # A(a, l) is increasing in a
            mid = 0.5 * (lo + hi)
            low = muscle.activation_force(mid, l) < target
            lo, hi = jnp.where(low, mid, lo), jnp.where(low, hi, mid)
        tau = muscle.joint_torques(q, jnp.zeros(2), 0.5 * (lo + hi))
        assert float(jnp.max(jnp.abs(tau))) < 1e-8
        assert float(jnp.max(jnp.abs(muscle.joint_torques(q, jnp.zeros(2), rest)))) > 0.05   # the rest alone does not hold q
        C = jax.jacfwd(lambda f: geo.moment_arms(q) @ (jnp.asarray(muscle.F_MAX) * f * (muscle.force_length(l) + muscle.passive_force(l))))(target)
        null = np.linalg.svd(np.asarray(C))[2][2:]                # [4, 6] zero-torque directions
        np.testing.assert_allclose(null @ np.asarray(target - ref), 0.0, atol=1e-14)


def test_the_human_preset_has_delays_sensors_and_both_motor_noises():
    p = arm2_muscle6()
    assert p.delay_steps * p.dt == pytest.approx(MOTOR_DELAY)
    assert p.observation is not None and p.observation.delay_steps * p.dt == pytest.approx(SENSORY_DELAY)
    assert 0.05 <= MOTOR_DELAY + SENSORY_DELAY <= 0.1          # long-latency loop (Pruszynski & Scott 2012)
    F = np.asarray(p.noise(p.x0, jnp.asarray(p.cost.params["u_rest"]), jnp.asarray(p.cost.params["u_rest"])))
    assert F.shape == (10, 8) and np.all(F[2:4, 6:] != 0) and np.all(F[4:, :6].diagonal() > 0)
    ideal = arm2_muscle6(noise=False)
    assert ideal.noise is None and ideal.observation is None and ideal.delay_steps == 0


def test_the_force_cv_is_the_stated_one():
    """force_cv (the linearised stationary CV) against a Monte Carlo of the model's own activation
    rows (its dynamics and noise, Euler steps of 1 ms, 3000 trials) at the start posture; the
    stated range at the default noise, 4-9 % of the force for held excitations of 0.2-0.6."""
    p = arm2_muscle6(dt=0.001, sensory_delay=None)
    u = jnp.asarray([0.2, 0.3, 0.4, 0.5, 0.6, 0.3])
    x = p.x0.at[4:].set(u)
    l = muscle.ANGLE_DEPENDENT.lengths(x[:2])
    rng = np.random.default_rng(0)
    a = np.tile(np.asarray(u), (3000, 1))
    f_rows = jax.jit(jax.vmap(lambda ai: p.dynamics(x.at[4:].set(ai), u, u)[4:]))
    F_rows = jax.jit(jax.vmap(lambda ai: p.noise(x.at[4:].set(ai), u, u)[4:, :6]))
    for _ in range(700):                                           # > 10 time constants
        xi = rng.standard_normal(a.shape)
        a = a + p.dt * np.asarray(f_rows(a)) + math.sqrt(p.dt) * np.einsum("nij,nj->ni", np.asarray(F_rows(a)), xi)
    force = np.asarray(jax.vmap(lambda ai: muscle.activation_force(ai, l))(jnp.asarray(a)))
    cv = force.std(axis=0) / force.mean(axis=0)
    stated = force_cv(u)
    np.testing.assert_allclose(cv, stated, rtol=0.08)
    assert SIGMA_U == 0.01 and np.all((stated > 0.04) & (stated < 0.09))


def test_position_sense_has_the_precision_of_human_position_sense():
    """POSITION_SENSE: a posture held for 1 s is known to 0.6-1.1 deg through it (van Beers, Sittig &
    Denier van der Gon 1998), the preset's sensors know it to about 0.1 deg; the option reaches the
    observation, the default's is unchanged, and a non-positive density is refused by name."""
    assert 0.6 <= math.degrees(POSITION_SENSE["joint_angle_noise"] / math.sqrt(1.0)) <= 1.1
    assert math.degrees(JOINT_ANGLE_DENSITY) < 0.2
    dt = 0.01
    for model, (angle, velocity) in (({}, (JOINT_ANGLE_DENSITY, JOINT_VELOCITY_DENSITY)),
                                     (POSITION_SENSE, tuple(POSITION_SENSE.values()))):
        G = np.asarray(arm2_muscle6(dt=dt, **model).observation.G)
        np.testing.assert_allclose(G, np.diag([angle, angle, velocity, velocity]) / math.sqrt(dt), rtol=1e-15)
    with pytest.raises(ValueError, match="joint_angle_noise must be a positive finite number; got 0"):
        arm2_muscle6(joint_angle_noise=0)


@pytest.fixture(scope="module")
def measured():
    return reaches(np.vstack([EIGHT[[0, 2]], UNSEEN]), n_trials=100, seed=0)


def _straight_and_bell_shaped(r):
    assert r.status.startswith("CONVERGED"), r
    assert r.peaks == 1 and 1.6 <= r.peak_to_mean <= 2.0, r
    assert r.deviation <= 0.10, r          # the mean path


def test_reaches_are_straight_and_bell_shaped(measured):
    for r in measured[:2]:
        _straight_and_bell_shaped(r)


@pytest.mark.xfail(strict=True, reason="measured (docs/results/center_out_human.md, 300 trials): a mean path "
                   "deviation of 10.5 % at 15 cm, 112.5 deg (peak/mean 1.61); a longer movement time curves it more")
def test_an_unseen_reach_is_straight_and_bell_shaped(measured):
    _straight_and_bell_shaped(measured[2])


def test_endpoints_scatter_by_millimetres(measured):
    for r in measured:
        assert 2e-3 <= r.sd_major <= 8e-3, r


def test_muscles_can_respond_in_both_directions(measured):
    """Most excitations are interior (the rest is co-activated): few sit at a bound and far fewer
    feedback rows are zero than with Li & Todorov's effort from zero (57-64 % at a bound, 49-63 %
    zero rows; measured now 0-8 % and 6-24 %, the rows of the last motor-delay steps, whose
    commands act after the horizon, included)."""
    for r in measured:
        assert r.at_bound < 0.15 and r.zero_rows < 0.35, r


def _axis_difference(a, b) -> float:
    """The angle in [0, 90] deg between two axes given by their orientations in degrees."""
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


def test_the_endpoint_scatter_is_the_filters_final_error(measured):
    """Why the ellipses keep the posture's orientation: the hand ends where the delayed Kalman filter
    believes the target is, so the endpoint scatter is, for the most part, the filter's own error at
    the last command (its hand error e(x) - e(x_hat)). Its ellipse has the endpoints' orientation
    and it explains most of their variance (measured 2026-12-06, 8 targets, 300 trials: axes within
    7 deg, 55-68 % of the variance; docs/results/center_out_human.md). A noise whose
    uncorrected part set the endpoints instead (the movement-aligned scatter that is published)
    would break this."""
    for r in measured:
        assert _axis_difference(r.orientation, r.estimate_orientation) <= 20, r
        assert r.estimate_share >= 0.4, r


@pytest.mark.xfail(strict=True, reason="the endpoint ellipses keep the orientation of the filter's final error "
                   "(8-44 deg from +x), whichever noise source dominates, so they align with the movement only "
                   "near that axis: docs/results/center_out_human.md, 'Why the ellipses keep the posture's orientation'")
def test_endpoint_ellipses_lie_along_the_movement(measured):
    assert sum(r.angle <= 30 for r in measured) >= 2


@functools.lru_cache(maxsize=1)
def _eight():
    return tuple(center_out_reaches(8, 0.1, n_trials=300))


@pytest.mark.full
def test_the_eight_targets_full():
    for r in _eight():
        _straight_and_bell_shaped(r)
        assert 2e-3 <= r.sd_major <= 8e-3, r


@pytest.mark.full
@pytest.mark.xfail(strict=True, reason="3 of 8 ellipses within 30 deg of the movement (docs/results/center_out_human.md)")
def test_endpoint_ellipses_lie_along_the_movement_full():
    assert sum(r.angle <= 30 for r in _eight()) >= 6


@pytest.mark.full
@pytest.mark.xfail(strict=True, reason="at 15 cm, 112.5 deg: deviation 10.5 %; at -67.5 deg MAX_ITERATIONS (docs/results/center_out_human.md)")
def test_unseen_distances_and_directions_full():
    for radius in (0.15, 0.06):
        for r in center_out_reaches(8, radius, start_angle=math.pi / 8, n_trials=300):
            _straight_and_bell_shaped(r)
            assert 2e-3 <= r.sd_major <= 8e-3, r


@functools.lru_cache(maxsize=1)
def _eight_position_sense():
    return tuple(center_out_reaches(8, 0.1, n_trials=300, **POSITION_SENSE))


@pytest.mark.full
def test_position_sense_full():
    """docs/results/center_out_human.md: with proprioception at the precision of human position
    sense the 8 reaches keep their shape, scatter by 4.5-6.8 mm, and the filter's final error is
    86-97 % of the endpoint variance (it sees little of the execution noise)."""
    for r in _eight_position_sense():
        _straight_and_bell_shaped(r)
        assert 2e-3 <= r.sd_major <= 8e-3, r
        assert r.estimate_share >= 0.8, r


@pytest.mark.full
@pytest.mark.xfail(strict=True, reason="5 of 8 ellipses within 30 deg of the movement with POSITION_SENSE "
                   "(docs/results/center_out_human.md)")
def test_position_sense_ellipses_lie_along_the_movement_full():
    assert sum(r.angle <= 30 for r in _eight_position_sense()) >= 6
