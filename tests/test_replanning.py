"""The re-planning controller of the gallery (`experiments.replanning`): its shrinking-horizon tick
problem against the principle of optimality, and the delayed filter's innovation gate against the
closed-form Kalman update."""
from types import SimpleNamespace

import jax
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import mpc
from delayed_ilqr.experiments import replanning
from delayed_ilqr.experiments.reach_tasks import reach
from delayed_ilqr.mpc.estimation import FilterState, filter_update


def _scalar_update(x, P, y, R):
    """The Kalman update of a position sensor y = x[0] + noise of variance R, in closed form."""
    gain = P[:, 0] / (P[0, 0] + R)
    return x + gain * (y - x[0]), P - np.outer(gain, P[0])


def test_innovation_gate_adds_its_covariance_exactly_when_the_innovation_surprises():
    R = 0.01
    obs = di.Observation(np.array([[1.0, 0.0]]), np.array([[np.sqrt(R)]]), delay_steps=1)
    problem = SimpleNamespace(observation=obs)
    P, jump = np.diag([1e-4, 2e-4]), np.array([[1.0, 0.5], [0.5, 1.0]])
    state = FilterState(np.zeros(2), P, np.zeros((1, 1)))
    gate = 9.0                                              # chi-square, one output
    for y, opens in ((0.05, False), (1.0, True)):           # normalised squares 0.25 and 99
        assert (y * y / (P[0, 0] + R) > gate) == opens
        x_del, P_post = filter_update(problem, state, np.array([y]), gate, jax.numpy.asarray(jump))
        x_ref, P_ref = _scalar_update(np.zeros(2), P + jump if opens else P, y, R)
        np.testing.assert_allclose(x_del, x_ref, rtol=1e-12)
        np.testing.assert_allclose(P_post, P_ref, rtol=1e-10, atol=1e-15)
    x_open, _ = filter_update(problem, state, np.array([1.0]), gate, jax.numpy.asarray(jump))
    x_shut, _ = filter_update(problem, state, np.array([1.0]))
    assert x_open[0] > 0.9 > 0.1 > x_shut[0]                # believed at once vs explained as noise


def test_gate_arguments_are_checked_by_name():
    problem = reach("arm2", noise=False, final_time=0.1, sensory_delay=0.05)
    with pytest.raises(ValueError) as e:
        mpc.MPC(problem.replace(observation=None), innovation_gate=9.0, gate_cov=np.eye(problem.n_states))
    assert str(e.value).startswith("innovation_gate and gate_cov belong to the delayed filter")
    with pytest.raises(ValueError) as e:
        mpc.MPC(problem, innovation_gate=9.0)
    assert str(e.value) == ("innovation_gate and gate_cov go together (the threshold and the covariance added when "
                            "it is crossed); got innovation_gate=9.0 and gate_cov None")
    with pytest.raises(ValueError) as e:
        mpc.MPC(problem, innovation_gate=-1.0, gate_cov=np.eye(problem.n_states))
    assert str(e.value) == "innovation_gate must be a positive finite number; got -1.0"


def test_a_shrinking_tick_from_the_optimal_state_continues_the_optimal_plan():
    """Principle of optimality: re-solved from scratch at tick k, from the optimal trajectory's state
    with its commands in flight, the shrinking-horizon problem sends the reach's own u_k; the plain
    receding problem (its horizon running past the end) sends another command."""
    problem = reach("arm2", delay=0.03, noise=False, sensory_delay=None, final_time=0.2)
    sol = di.solve(problem)
    assert sol.converged
    K, l, k = problem.horizon, problem.delay_steps, 8
    assert 0 < l < k
    plan = np.zeros((K, problem.n_controls))
    state = lambda: mpc.ControllerState(jax.numpy.asarray(plan), jax.numpy.asarray(sol.u[k - l:k]),  # noqa: E731
                                        jax.numpy.asarray(k, jax.numpy.int32))
    shrinking = mpc.MPC(replanning.shrinking(problem), iterations=200)
    _, tick = shrinking.step(state(), sol.x[k])
    # both solves stop at a relative cost change of 1e-10 (Options()), so the commands agree to about 1e-5
    np.testing.assert_allclose(tick.command, sol.u[k], rtol=0, atol=1e-4 * np.abs(sol.u).max())
    _, plain = mpc.MPC(problem, iterations=200).step(state(), sol.x[k])
    assert np.abs(plain.command - sol.u[k]).max() > 1e-2 * np.abs(sol.u[k]).max()
