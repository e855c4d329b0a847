"""The shape of the six-muscle arm's reaches at no delay (docs/results/reach_shape.md).

The energy-optimal reach of Li & Todorov's arm under effort and final-state cost is not the human
one (straight, bell-shaped): it pushes, coasts and brakes (flat-topped speed), and along the x
axis it moves one joint after the other (curved path, a second speed peak). These tests hold what
was established about it: that the plotted speed is the hand's speed, that the curved, two-peaked
reach is the optimum of the model (an optimiser sharing nothing with iLQG but the rollout finds the
same cost), and that the force-activation curve causes it (with a force linear in the activation
the same reach is straight and single-peaked)."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr.experiments import designs
from delayed_ilqr.experiments.center_out import DEFAULT_OPTIONS, reach_shape
from delayed_ilqr.models.arm2 import ARM2_PARAMS, hand_position, hand_velocity
from delayed_ilqr.models.arm2_muscle6 import LI_TODOROV, arm2_muscle6, center_out_targets, rest_commands

from direct import direct_optimum
from linear_force import linear_force

TARGETS = center_out_targets(8, 0.1)


def _reach(target: int):
    """The center-out study's deterministic design of its 0 ms reach to ``target`` (1-based)."""
    plant = arm2_muscle6(delay=0.0, target=tuple(TARGETS[target - 1]), noise=True, **LI_TODOROV)
    return designs.design(plant, "deterministic", DEFAULT_OPTIONS)[0]


@pytest.fixture(scope="module")
def reach_1():
    problem = _reach(1)
    return problem, di.solve(problem, rest_commands(problem), DEFAULT_OPTIONS)


def test_reach_shape_of_constructed_paths():
    # straight, minimum-jerk reach (Flash & Hogan 1985): one peak, no deviation, peak/mean 15/8
    problem = _reach(2)
    start = np.asarray(hand_position(problem.x0[:2]))
    s = np.linspace(0.0, 1.0, 401)
    fraction = 10 * s**3 - 15 * s**4 + 6 * s**5
    path = start + fraction[:, None] * (TARGETS[1] - start)
    shape = reach_shape(problem.replace(dt=1.0 / 400), _states_through(problem, path))
    assert shape.peaks == 1 and shape.deviation < 1e-9
    assert shape.peak_to_mean == pytest.approx(15 / 8, rel=1e-3)
    # a detour of 3 cm at right angles and a pause half-way: deviation 0.3, two peaks
    bump = 0.03 * np.sin(np.pi * s)[:, None] * np.array([-1.0, 1.0]) / np.sqrt(2)
    def half(t):  # 0 -> 0.5 over t in [0, 0.5], at rest at both ends
        return 0.25 * (1 - np.cos(2 * np.pi * np.clip(t, 0.0, 0.5)))
    halting = half(s) + half(s - 0.5)
    path = start + halting[:, None] * (TARGETS[1] - start) + bump
    shape = reach_shape(problem.replace(dt=1.0 / 400), _states_through(problem, path))
    assert shape.peaks == 2 and shape.deviation == pytest.approx(0.3, rel=1e-3)


def test_reach_shape_refuses_a_plant_without_a_target_and_wrong_states():
    problem = _reach(2)
    with pytest.raises(ValueError, match="x must be states"):
        reach_shape(problem, np.zeros((51, 4)))
    with pytest.raises(ValueError, match="plant must name a planar task space"):
        reach_shape(di.models.pendulum(), np.zeros((51, 2)))


def _states_through(problem, hand):
    """States [N, 10] whose hand positions are ``hand`` [N, 2] (inverse kinematics of the elbow-down
    arm: the hand metadata only reads q)."""
    arm = ARM2_PARAMS
    l1, l2 = float(arm.l1), float(arm.l2)
    r2 = np.sum(hand**2, axis=1)
    q2 = np.arccos((r2 - l1**2 - l2**2) / (2 * l1 * l2))
    q1 = np.arctan2(hand[:, 1], hand[:, 0]) - np.arctan2(l2 * np.sin(q2), l1 + l2 * np.cos(q2))
    x = np.zeros((len(hand), 10))
    x[:, 0], x[:, 1] = q1, q2
    np.testing.assert_allclose(np.asarray(jax.vmap(hand_position)(jnp.asarray(x[:, :2]))), hand,
                               atol=1e-12)
    return x


def test_curved_two_peaked_reach_is_the_optimum_of_the_model(reach_1):
    problem, sol = reach_1
    assert di.Status(int(sol.status)).converged
    # bounded L-BFGS-B from the same rest commands finds the same minimum (5.678e-6 both)
    reference = direct_optimum(problem, u_init=rest_commands(problem))
    assert float(sol.cost) == pytest.approx(reference, rel=1e-5)
    shape = reach_shape(problem, sol.x)
    assert shape.peaks == 2 and shape.deviation > 0.25   # measured: 0.333 of the 10 cm
    # the plotted speed (hand displacement per step over dt) is |J(q) dq| up to the Euler step's
    # second-order term, dt/2 |d(J dq)/dt| <= 0.005 s x 10 m/s^2 = 5 cm/s at most, 0.04 measured
    x = np.asarray(sol.x)
    v = np.asarray(jax.vmap(hand_velocity)(jnp.asarray(x[:-1, :2]), jnp.asarray(x[:-1, 2:4])))
    np.testing.assert_allclose(shape.speed, np.linalg.norm(v, axis=1), atol=5e-3)


def test_force_linear_in_activation_makes_the_reach_straight_and_single_peaked(reach_1):
    problem = linear_force(_reach(1))
    sol = di.solve(problem, jnp.zeros((problem.horizon, 6)), dataclasses.replace(DEFAULT_OPTIONS, max_iterations=40))
    # the solve's cost stops changing within 20 iterations (5.6624e-8 at 20, 40 and 300) though it
    # ends MAX_ITERATIONS; the reach arrives (its final hand error below 1 mm)
    hand_end = np.asarray(hand_position(sol.x[-1, :2]))
    assert np.linalg.norm(hand_end - TARGETS[0]) < 1e-3
    shape, published = reach_shape(problem, sol.x), reach_shape(*reach_1[:1], reach_1[1].x)
    assert shape.peaks == 1 and published.peaks == 2                 # measured: 1 and 2
    assert shape.deviation < 0.02 and published.deviation > 0.25     # measured: 0.004 and 0.333
