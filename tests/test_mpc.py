"""The receding-horizon controller (delayed_ilqr.mpc) against independent references: a fresh solve
of the shifted problem, ordinary iLQG MPC written as a Python loop, the finite-horizon delayed LQR
law of lqg.backward_pass, and the plant's timing worked out by hand."""
import json
import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import delayed_ilqr as di
from delayed_ilqr import mpc
from delayed_ilqr.lqg import DelayedLQG, DelayedObservation, backward_pass, delayed_kalman, filter_estimates

DT = 0.01
# tight enough that two converged solves of arm2 (flat in u: Q = 1e-4) agree to 1e-7
TIGHT = di.Options(tol_grad=1e-12, tol_cost=1e-15)


def _arm(delay_steps, horizon=15, P=None):
    """arm2 with a short horizon; P (optional) adds a running error weight on the state."""
    problem = di.models.arm2(delay=delay_steps * DT, dt=DT, horizon=horizon)
    if P is None:
        return problem
    c = problem.cost
    return problem.replace(cost=di.QuadraticCost(P=P, Q=c.Q, P_final=c.P_final, x_target=c.x_target))


def _euler(f, x, u, ud):
    return x + DT * np.asarray(f(jnp.asarray(x), jnp.asarray(u), jnp.asarray(ud)))


# -- one tick, iterated to convergence, is a fresh solve of the shifted problem ----------------

@pytest.fixture(scope="module")
def arm_converged():
    """arm2, l = 3, K = 15, and its controller iterated to convergence at every tick (one
    compiled tick for the tests that take it)."""
    problem = _arm(3)
    return problem, mpc.MPC(problem, iterations=100, options=TIGHT)


def test_first_tick_converged_equals_fresh_solve(arm_converged):
    problem, ctrl = arm_converged
    _, tick = ctrl.step(ctrl.init(), problem.x0)
    fresh = di.solve(problem, options=TIGHT)
    assert fresh.converged
    np.testing.assert_allclose(tick.command, fresh.u[0], rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(tick.law.state_feedback, fresh.policy.state_feedback[0], rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(tick.law.delay_feedback, fresh.policy.delay_feedback[0], rtol=1e-6, atol=1e-8)


def test_later_tick_converged_equals_delay_free_solve_from_the_prediction(arm_converged):
    """At tick k with commands b in flight the delayed problem over K steps is, for a cost without
    running state terms, the delay-free problem over K - l steps from the state the model reaches
    under b (the last l commands never act and are zero at the optimum): solved independently."""
    l, K = 3, 15
    problem, ctrl = arm_converged
    state, x = ctrl.init(), np.asarray(problem.x0)
    sent = [np.zeros(2)] * l
    for _ in range(4):        # a few ticks on a perturbed plant, so that the commands in flight differ
        state, tick = ctrl.step(state, x)
        sent.append(np.asarray(tick.command))
        x = _euler(problem.dynamics, x, sent[-1], sent[-1 - l]) + np.array([0.0, 0.0, 0.3, -0.2])
    in_flight = sent[-l:]
    np.testing.assert_allclose(state.in_flight, in_flight)
    state, tick = ctrl.step(state, x)
    x_hat = x
    for b in in_flight:
        x_hat = _euler(problem.dynamics, x_hat, b, b)
    shifted = problem.replace(x0=x_hat, delay_steps=0, horizon=K - l)
    fresh = di.solve(shifted, options=TIGHT)
    assert fresh.converged and tick.status <= 1
    np.testing.assert_allclose(tick.command, fresh.u[0], rtol=1e-6, atol=1e-8)
    assert not np.allclose(tick.command, in_flight[-1], atol=1e-3)       # the comparison can fail


# -- no delay: ordinary iLQG MPC, and every compensation agrees ---------------------------------

def test_undelayed_controller_is_ordinary_ilqg_mpc_with_a_moving_target():
    K, T, iterations = 12, 6, 3
    P = np.diag([50.0, 50.0, 0.5, 0.5])
    problem = _arm(0, horizon=K, P=P)
    Q, P_final = np.asarray(problem.cost.Q), np.asarray(problem.cost.P_final)
    target = np.asarray(problem.cost.x_target)

    def r(t):
        return jnp.asarray(target) + jnp.array([0.3 * jnp.sin(4.0 * t), 0.0, 1.2 * jnp.cos(4.0 * t), 0.0])

    ctrl = mpc.MPC(problem, iterations=iterations, reference=r)
    run = mpc.simulate(ctrl, problem, ticks=T)

    # the same loop in Python, each tick a solve of a problem written here with the time shifted
    def running(x, u, t0, t):
        e = x - r(t0 + t)
        return e @ P @ e + u @ Q @ u

    def final(x, t0, t):
        e = x - r(t0 + t)
        return e @ P_final @ e

    options = di.Options(max_iterations=iterations)
    x, plan, xs, us, cost = np.asarray(problem.x0), np.zeros((K, 2)), [np.asarray(problem.x0)], [], 0.0
    for k in range(T):
        tick_problem = di.Problem(problem.dynamics, x, DT, K, 0, di.GeneralCost(running, final, k * DT, True),
                                  n_controls=2)
        sol = di.solve(tick_problem, u_init=plan, options=options)
        u = np.asarray(sol.u[0])
        cost += DT * float(running(jnp.asarray(x), jnp.asarray(u), 0.0, k * DT))
        x = _euler(problem.dynamics, x, u, u)
        plan = np.concatenate([sol.u[1:], sol.u[-1:]])
        xs.append(x)
        us.append(u)
    cost += float(final(jnp.asarray(x), 0.0, T * DT))
    np.testing.assert_allclose(run.x[0], np.stack(xs), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(run.u[0], np.stack(us), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(run.cost[0], cost, rtol=1e-10)


def test_baselines_agree_without_delay():
    """Without delay every compensation is the same tick problem (the strategies' table): the
    same static shape, and in closed loop the same commands (none against inflight)."""
    from delayed_ilqr.mpc.strategies import Strategy, strategy
    for compensation in mpc.COMPENSATIONS:
        for history in ("sent", "planned"):
            assert strategy(compensation, 0, 10, history) == Strategy(0, 0, 0, 10)
    problem = _arm(0, horizon=10)
    runs = {c: mpc.simulate(mpc.MPC(problem, compensation=c), problem, ticks=8) for c in ("none", "inflight")}
    np.testing.assert_allclose(runs["none"].u, runs["inflight"].u, rtol=1e-12, atol=1e-14)
    assert np.abs(runs["inflight"].u).max() > 1e-3


def test_converged_baselines_agree_with_delay_on_a_deterministic_model():
    """predict, replay of the sent history and inflight solve the same problem at every tick
    (strategies' docstring): converged, they send the same commands; none and replay of the
    planned history do not."""
    problem = _arm(3, horizon=10)
    x0 = np.asarray(problem.x0)[None] + np.array([[0.0, 0.0, 0.5, -0.5]])
    u = {label: np.asarray(mpc.simulate(mpc.MPC(problem, iterations=60, compensation=c, replay_history=h,
                                                options=TIGHT), problem, ticks=6, x0=x0).u[0])
         for label, c, h in (("none", "none", "sent"), ("predict", "predict", "sent"), ("replay", "replay", "sent"),
                             ("planned", "replay", "planned"), ("inflight", "inflight", "sent"))}
    np.testing.assert_allclose(u["predict"], u["inflight"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(u["replay"], u["inflight"], rtol=1e-12, atol=1e-14)
    assert not np.allclose(u["none"], u["inflight"], atol=1e-2)
    assert not np.allclose(u["planned"], u["inflight"], atol=1e-2)


# -- linear plant, quadratic cost: the finite-horizon delayed LQR law ---------------------------

AC, BC = np.array([[0.0, 1.0], [2.0, -0.3]]), np.array([[0.0], [1.0]])


@dataclass(frozen=True)
class LinearPlant:
    """dx/dt = A x + gain B ud: the unstable second-order plant, its actuator gain as data."""

    gain: float = 1.0

    def __call__(self, x, u, ud):
        return jnp.asarray(AC) @ x + self.gain * jnp.asarray(BC) @ ud


jax.tree_util.register_dataclass(LinearPlant, data_fields=["gain"], meta_fields=[])


def _additive_noise(x, u, ud):
    return jnp.diag(jnp.array([0.02, 0.1]))


def _linear(delay_steps, horizon, observation=None, noise=None):
    """x = [position, velocity] of an unstable second-order plant driven by the delayed command."""
    Ac, Bc = AC, BC
    P, Q, P_final = np.diag([3.0, 0.2]), np.array([[0.05]]), np.diag([20.0, 2.0])
    problem = di.Problem(LinearPlant(), x0=np.array([0.4, -0.2]), dt=0.05, horizon=horizon, delay_steps=delay_steps,
                         cost=di.QuadraticCost(P=P, Q=Q, P_final=P_final, x_target=np.zeros(2)),
                         observation=observation, noise=noise)
    K, dt = horizon, 0.05
    lqg = DelayedLQG(A=np.broadcast_to(np.eye(2) + dt * Ac, (K, 2, 2)), B0=np.zeros((K, 2, 1)),
                     B1=np.broadcast_to(dt * Bc, (K, 2, 1)), c=None, C0=None, C1=None,
                     d_tilde=np.zeros(K + 1), d=np.zeros((K + 1, 2)),
                     D=np.concatenate([np.broadcast_to(dt * P, (K, 2, 2)), P_final[None]]),
                     e=np.zeros((K, 1)), E=np.broadcast_to(dt * Q, (K, 1, 1)), delay_steps=delay_steps)
    return problem, lqg


@pytest.fixture(scope="module")
def linear_lqr():
    """(problem, its DelayedLQG, the controller): l = 4, K = 12, 5 iterations per tick; its
    compiled loop (15 ticks) is shared by the tests that take it."""
    problem, lqg = _linear(4, 12)
    return problem, lqg, mpc.MPC(problem, iterations=5)


def test_linear_quadratic_receding_law_is_the_delayed_lqr_law(linear_lqr):
    l, T = 4, 15
    problem, lqg, ctrl = linear_lqr
    gains, _ = backward_pass(lqg)
    L0, M0 = np.asarray(gains.state_feedback[0]), np.asarray(gains.delay_feedback[0])
    run = mpc.simulate(ctrl, problem, ticks=T)
    # the closed loop of the time-invariant law u_k = L_0 x_k + sum_i M_0^i u_{k+i-l}, in NumPy
    x, sent, xs = np.asarray(problem.x0), [np.zeros(1)] * l, []
    for _ in range(T):
        u = L0 @ x + sum(M0[i] @ sent[-l + i] for i in range(l))
        x = x + 0.05 * (np.array([[0.0, 1.0], [2.0, -0.3]]) @ x + np.array([0.0, 1.0]) * sent[-l][0])
        sent.append(u)
        xs.append(x)
    np.testing.assert_allclose(run.u[0], np.stack(sent[l:]), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(run.x[0, 1:], np.stack(xs), rtol=1e-8, atol=1e-10)
    state, tick = ctrl.step(ctrl.init(), problem.x0)
    np.testing.assert_allclose(tick.law.state_feedback, L0, rtol=1e-8)
    np.testing.assert_allclose(tick.law.delay_feedback, M0, rtol=1e-8, atol=1e-12)
    assert np.abs(M0).max() > 1e-2        # the commands in flight are fed back


# -- delayed sensors -------------------------------------------------------------------------------

def _lqg_of_linear(K, delay_steps):
    dt = 0.05
    return DelayedLQG(A=np.broadcast_to(np.eye(2) + dt * AC, (K, 2, 2)), B0=np.zeros((K, 2, 1)),
                      B1=np.broadcast_to(dt * BC, (K, 2, 1)), c=None, C0=None, C1=None, d_tilde=np.zeros(K + 1),
                      d=np.zeros((K + 1, 2)), D=np.zeros((K + 1, 2, 2)), e=np.zeros((K, 1)),
                      E=np.broadcast_to(np.eye(1), (K, 1, 1)), delay_steps=delay_steps)


def test_filter_on_a_linear_plant_is_the_delayed_kalman_filter():
    """The controller's filter, driven tick by tick with measurements made here, against the
    library's linear delayed Kalman filter (lqg.delayed_kalman, lqg.filter_estimates) run on the
    same record, in deviations about the free response from x0."""
    l, ls, T = 4, 3, 16
    H, G, Q = np.array([[1.0, 0.0]]), np.array([[0.02]]), np.diag([1e-4, 4e-4])
    problem, _ = _linear(l, 12, observation=di.Observation(H, G, delay_steps=ls))
    ctrl = mpc.MPC(problem, process_cov=Q)
    rng = np.random.default_rng(0)
    state, xs, us, ys, estimates = ctrl.init(), [np.asarray(problem.x0)], [], [], []
    for k in range(T):
        y = H @ xs[max(k - ls, 0)] + G @ rng.standard_normal(1)
        state, tick = ctrl.step(state, y)
        us.append(np.asarray(tick.command))
        ys.append(y)
        estimates.append(np.asarray(tick.estimate))
        ud = us[k - l] if k >= l else np.zeros(1)
        xs.append(xs[-1] + 0.05 * (AC @ xs[-1] + BC @ ud) + np.sqrt(np.diag(Q)) * rng.standard_normal(2))
    lqg = _lqg_of_linear(T, l)
    obs = DelayedObservation(np.broadcast_to(H, (T, 1, 2)), np.broadcast_to(G, (T, 1, 1)), ls)
    fgains, _ = delayed_kalman(lqg, obs, process_cov=np.broadcast_to(Q, (T, 2, 2)))
    x_bar = [np.asarray(problem.x0)]
    for _ in range(T):
        x_bar.append(np.asarray(lqg.A[0]) @ x_bar[-1])
    dy = np.stack(ys) - np.stack([H @ x_bar[max(k - ls, 0)] for k in range(T)])
    x_hat, _ = filter_estimates(lqg, obs, fgains, np.stack(us), dy)
    np.testing.assert_allclose(np.stack(estimates), np.stack(x_bar[:-1]) + np.asarray(x_hat), rtol=1e-10, atol=1e-12)
    assert np.abs(np.stack(estimates) - np.stack(xs[:-1])).max() > 1e-3        # an estimate, not the state


def test_exact_undelayed_sensors_give_the_full_state_controller(linear_lqr):
    """Sensors of the whole state without delay, with a noise of 1e-9 and a filter that trusts
    them (process covariance >> sensory), make the state-feedback controller."""
    problem, _, ctrl = linear_lqr
    sensed, _ = _linear(4, 12, observation=di.Observation(np.eye(2), 1e-9 * np.eye(2)))
    with_sensors = mpc.MPC(sensed, iterations=5, process_cov=1e-2 * np.eye(2), initial_cov=np.eye(2))
    full, seen = mpc.simulate(ctrl, problem, ticks=15), mpc.simulate(with_sensors, sensed, ticks=15)
    np.testing.assert_allclose(seen.u, full.u, rtol=0, atol=1e-6)
    np.testing.assert_allclose(seen.x, full.x, rtol=0, atol=1e-7)
    np.testing.assert_allclose(seen.estimate, full.x[:, :-1], rtol=0, atol=1e-7)


def test_compensating_the_sensory_delay_beats_ignoring_it():
    """Monte Carlo (under vmap) of the noisy unstable plant seen through its position 0.3 s late:
    the controller with the delayed filter against one built for undelayed sensors (it takes
    y_k for h(x_k)); common random numbers."""
    H, G, Q = np.array([[1.0, 0.0]]), np.array([[0.01]]), np.diag([4e-4, 1e-2]) * 0.05
    model, _ = _linear(2, 20, observation=di.Observation(H, G, delay_steps=6))
    naive_model, _ = _linear(2, 20, observation=di.Observation(H, G, delay_steps=0))
    plant = model.replace(noise=_additive_noise)
    runs = {name: mpc.simulate(mpc.MPC(m, process_cov=Q), plant, ticks=40, n_trials=8, seed=3)
            for name, m in (("delayed", model), ("naive", naive_model))}
    ours, naive = runs["delayed"], runs["naive"]
    assert ours.x.shape == (8, 41, 2) and np.abs(ours.x[0, -1] - ours.x[1, -1]).max() > 1e-6
    error = {name: float(np.sqrt(np.mean((np.asarray(r.estimate) - np.asarray(r.x[:, :-1])) ** 2)))
             for name, r in runs.items()}
    assert error["delayed"] < 0.5 * error["naive"]
    assert np.median(ours.cost) < 0.7 * np.median(naive.cost)
    assert not np.any(ours.failed)


def test_a_noisy_models_real_time_tick_takes_its_step(linear_lqr):
    """The noisy solver returns the best nominal it has evaluated; the tick runs one more
    iteration so that its step counts. With additive noise the step is the deterministic one
    (the noise changes neither gains nor feedforward), and on a linear-quadratic problem one
    step is the optimum: the first command is the delayed LQR law's L_0 x_0 (nothing in flight)."""
    problem, lqg, _ = linear_lqr
    noisy = problem.replace(noise=_additive_noise)
    ctrl = mpc.MPC(noisy, iterations=1)
    _, tick = ctrl.step(ctrl.init(), problem.x0)
    gains, _ = backward_pass(lqg)
    expected = np.asarray(gains.state_feedback[0]) @ np.asarray(problem.x0)
    np.testing.assert_allclose(tick.command, expected, rtol=1e-8)
    assert abs(float(expected[0])) > 0.1


# -- several plants in one compiled run -----------------------------------------------------------

def test_several_plants_in_one_run_equal_the_runs_one_by_one(linear_lqr):
    """Plants of actuator gain 0.8 and 1.2, another x0 and a true delay one step off (data through
    a common delay_frame), with motor noise: one call, against one call per plant."""
    problem, _, ctrl = linear_lqr
    base = problem.replace(noise=_additive_noise)
    plants = [base.replace(dynamics=LinearPlant(gain), x0=np.asarray(x0)).replace(delay_steps=lp, delay_frame=6)
              for gain, x0, lp in ((0.8, (0.4, -0.2), 4), (1.2, (0.1, 0.3), 5), (1.0, (0.4, -0.2), 3))]
    together = mpc.simulate(ctrl, plants, ticks=15, n_trials=2, seed=5)
    assert together.x.shape == (3, 2, 16, 2) and together.cost.shape == (3, 2)
    for i, plant in enumerate(plants):
        alone = mpc.simulate(ctrl, plant, ticks=15, n_trials=2, seed=5)
        np.testing.assert_allclose(together.x[i], alone.x, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(together.cost[i], alone.cost, rtol=1e-12)
    assert np.abs(together.x[0] - together.x[1]).max() > 1e-3
    with pytest.raises(ValueError) as e:
        mpc.simulate(ctrl, [plants[0], problem], ticks=15)
    assert str(e.value).startswith("plant[1] must differ from plant[0] only in arrays")


def test_bad_sensor_configuration_is_refused_word_for_word(linear_lqr):
    problem, _, ctrl = linear_lqr
    with pytest.raises(ValueError) as e:
        mpc.MPC(problem, process_cov=np.eye(2))
    assert str(e.value) == ("process_cov is the delayed filter's: give it only for a problem with an observation "
                            "(sensors); got process_cov for a problem without one")
    sensed, _ = _linear(4, 12, observation=di.Observation(np.eye(2)[:1], np.eye(1), delay_steps=2))
    with pytest.raises(ValueError) as e:
        mpc.MPC(sensed, initial_cov=-np.eye(2))
    assert str(e.value) == "initial_cov must be positive semi-definite; got a smallest eigenvalue of -1"
    with pytest.raises(ValueError) as e:
        mpc.simulate(ctrl, sensed, ticks=3)
    assert str(e.value).startswith("plant has sensors (an observation) but the controller is given the state")


# -- timing of the loop -------------------------------------------------------------------------

@pytest.mark.parametrize("charge", [False, True])
def test_the_first_command_acts_after_the_true_delay(charge):
    """arm2 has no gravity: at rest it stays at x0 until the first command acts, at tick
    l_true + 1 (+ 1 when the solve time is charged), whatever the model's delay."""
    model, plant = _arm(2), _arm(4)
    run = mpc.simulate(mpc.MPC(model, charge_solve_time=charge), plant, ticks=9)
    first = 4 + int(charge)
    np.testing.assert_array_equal(run.x[0, :first + 1], np.broadcast_to(plant.x0, (first + 1, 4)))
    assert np.abs(run.x[0, first + 1] - plant.x0).max() > 1e-6


def test_trials_under_noise_are_reproducible_and_differ_and_failures_are_flagged():
    problem = _arm(2, horizon=10)
    plant = di.models.arm2(delay=0.02, dt=DT, horizon=10, noise=True, sigma_u=0.05)
    ctrl = mpc.MPC(problem)
    w = np.zeros((3, 5, 4))
    w[2, 2, 2] = 1e300            # a kick that overflows the state of trial 2
    args = dict(ticks=5, n_trials=3, seed=1, disturbance=w, bound=1e3, failure=_q1_positive)
    a, b = mpc.simulate(ctrl, plant, **args), mpc.simulate(ctrl, plant, **args)
    assert a.x.shape == (3, 6, 4) and a.u.shape == (3, 5, 2) and a.cost.shape == (3,)
    np.testing.assert_array_equal(a.x, b.x)
    assert np.abs(a.x[0, -1] - a.x[1, -1]).max() > 1e-8
    np.testing.assert_array_equal(a.diverged, [False, False, True])
    np.testing.assert_array_equal(a.failed, [True, True, True])        # q1 starts at pi / 4 > 0
    assert np.all(np.isfinite(a.x[:2]))


def _q1_positive(x):
    return x[0] > 0.0


# -- bad input ----------------------------------------------------------------------------------

def test_bad_configuration_is_refused_word_for_word():
    problem = _arm(3, horizon=10)
    with pytest.raises(ValueError) as e:
        mpc.MPC(problem, compensation="smith")
    assert str(e.value) == "compensation must be one of 'inflight', 'none', 'predict', 'replay'; got 'smith'"
    with pytest.raises(ValueError) as e:
        mpc.MPC(problem, iterations=0)
    assert str(e.value) == "iterations must be a positive integer; got 0"
    with pytest.raises(ValueError) as e:
        mpc.MPC(_arm(9, horizon=10), charge_solve_time=True)
    assert str(e.value) == ("problem.horizon must be longer than the controller's delay (delay_steps, plus one tick "
                            "with charge_solve_time): a command must act within the horizon; got horizon=10, "
                            "controller delay=10")
    ctrl = mpc.MPC(problem)
    with pytest.raises(AttributeError) as e:
        ctrl.iterations = 3
    assert str(e.value) == "MPC is immutable: make a new one instead of setting 'iterations'"


def test_bad_plant_and_reference_are_refused_word_for_word():
    ctrl = mpc.MPC(_arm(2, horizon=10))
    with pytest.raises(ValueError) as e:
        mpc.simulate(ctrl, di.models.cart_pole(dt=DT), ticks=3)
    assert str(e.value) == ("plant must have the controller's state and command sizes (n=4, d=2); "
                            "got n=4, d=1")
    reference = np.tile(np.asarray(ctrl.problem.cost.x_target), (20, 1))
    ctrl = mpc.MPC(_arm(2, horizon=10), reference=reference)
    mpc.simulate(ctrl, ctrl.problem, ticks=10)          # reads up to step 10 - 1 + 10 = 19
    with pytest.raises(ValueError) as e:
        mpc.simulate(ctrl, ctrl.problem, ticks=11)
    assert str(e.value) == ("reference must cover every step a tick's horizon reads: up to step 20 (the tick + "
                            "horizon); got 20 samples (steps 0..19); lengthen the reference or run fewer ticks")
    state = ctrl.init()._replace(tick=jnp.asarray(9, jnp.int32))
    ctrl.step(state, ctrl.problem.x0)                   # tick 9 reads up to step 19
    with pytest.raises(ValueError) as e:
        ctrl.step(state._replace(tick=jnp.asarray(10, jnp.int32)), ctrl.problem.x0)
    assert str(e.value).startswith("reference must cover every step a tick's horizon reads: up to step 20")
    with pytest.raises(ValueError) as e:
        mpc.MPC(_arm(2, horizon=10), reference=np.zeros((5, 3)))
    assert str(e.value) == "reference must have shape (*, 4); got shape (5, 3)"


# -- the planar quadrotor -------------------------------------------------------------------------

def test_planar_quadrotor_hovers_and_its_accelerations_follow_the_equations():
    problem = di.models.planar_quadrotor()
    f = problem.dynamics
    np.testing.assert_allclose(f(jnp.zeros(6), jnp.zeros(2), jnp.zeros(2)), np.zeros(6), atol=1e-15)
    m, r, inertia, g = 0.486, 0.25, 0.00383, 9.81
    x = np.array([0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    ud = np.array([0.5, -0.2])
    total = m * g + 0.3
    expected = [-math.sin(0.3) * total / m, math.cos(0.3) * total / m - g, r * 0.7 / inertia]
    np.testing.assert_allclose(f(jnp.asarray(x), jnp.zeros(2), jnp.asarray(ud))[3:], expected, rtol=1e-12)
    F = di.models.planar_quadrotor(noise=True).noise(jnp.asarray(x), jnp.zeros(2), jnp.asarray(ud))
    # each noise column is sigma_u T_i times the response to one newton on rotor i
    one = np.asarray(f(jnp.asarray(x), jnp.zeros(2), jnp.array([1.0, 0.0])) - f(jnp.asarray(x), jnp.zeros(2),
                                                                                jnp.zeros(2)))
    np.testing.assert_allclose(F[:, 0], 0.05 * (m * g / 2 + 0.5) * one, rtol=1e-12)


# -- the command line -----------------------------------------------------------------------------

def test_mpc_command_writes_its_table_figure_and_manifest(tmp_path):
    from click.testing import CliRunner

    from delayed_ilqr import cli
    out = tmp_path / "run"
    result = CliRunner().invoke(cli.main, ["--no-cache", "mpc", "arm2", "--delay", "0.03", "--true-delay", "0.05",
                                           "--mismatch", "0.2", "--horizon", "10", "--ticks", "12",
                                           "--compensation", "none", "--compensation", "inflight", "--out", str(out)],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert "model delay 30 ms, plant delay 50 ms, actuator gain 1.2" in result.output
    assert "| delay | plant | none | inflight |" in result.output
    table = json.loads((out / "mpc.json").read_text(), parse_constant=_refuse)        # strict JSON
    assert [row["strategy"] for row in table] == ["none", "inflight"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert set(manifest["files"]) == {"closed_loop.png", "mpc.json", "runs.npz"}
    assert manifest["settings"]["true_delay"] == pytest.approx(0.05)
    assert manifest["settings"]["noise"] is True            # the plant's motor noise is on by default
    runs = np.load(out / "runs.npz")
    assert runs["x_inflight"].shape == (1, 13, 4) and runs["u_none"].shape == (1, 12, 2)
    bad = CliRunner().invoke(cli.main, ["--no-cache", "mpc", "arm2", "--delay", "0.03", "--true-delay", "0.025"])
    assert bad.exit_code == 2
    assert "arm2: the delay must be a whole number of steps of dt=0.01 s on the command line" in bad.output
    bad = CliRunner().invoke(cli.main, ["--no-cache", "mpc", "arm2", "--delay", "0.03", "--true-delay", "0.1",
                                        "--horizon", "10"])
    assert bad.exit_code == 2
    assert ("arm2: the horizon must be longer than the delay (a command must act within it); got --horizon 10 "
            "steps and --true-delay 0.1 s = 10 steps") in " ".join(bad.output.split())


def _refuse(constant):
    raise ValueError(f"not strict JSON: {constant}")


# -- the full-size baseline study (make bench; its key assertion, the converged agreement, is above) --

@pytest.mark.full
def test_baseline_study_of_the_tracking_arm():
    """The tracking arm at 100 ms (experiments.mpc_baselines, 4 trials): ignoring the delay fails
    in every trial on every plant, replay of the sent history is inflight's tick problem (the
    same cells), and the three delay-aware controllers keep every trial on the model."""
    from delayed_ilqr.experiments import mpc_baselines
    rows = mpc_baselines.run_scenario(mpc_baselines.SCENARIOS["arm2"], n_trials=4, delays=(0.1,))
    cells = {(r.condition, r.strategy): r for r in rows}
    for condition, _, _ in mpc_baselines.CONDITIONS:
        assert cells[(condition, "none")].failure_rate == 1.0
        sent, ours = cells[(condition, "replay (sent)")], cells[(condition, "inflight")]
        assert sent.median_cost == pytest.approx(ours.median_cost, rel=1e-9)
    for label in ("predict", "replay (sent)", "inflight"):
        assert cells[("model", label)].failure_rate == 0.0


# -- one delay per command channel (Nav2's per-axis model_delay_vx / vy) --------------------------

def test_per_channel_delays_on_decoupled_axes_equal_one_delay_per_axis():
    """The point mass's x and y axes are independent (f, the cost's weights and the plant are
    diagonal), so the controller with channel delays [2, 4] must send on channel j the commands of
    the controller with the single delay l_j: each channel's commands in flight, kept per channel,
    are fed back by its own delay; the plant acts on each channel l_j + 1 ticks late (the solve
    time charged: one more command in flight on each channel)."""
    model = di.models.point_mass(dt=DT, horizon=12)
    T = 10
    run = mpc.simulate(mpc.MPC(model.replace(delay_steps=[2, 4]), iterations=3, charge_solve_time=True),
                       model.replace(delay_steps=[2, 4]), ticks=T)
    for j, l in enumerate((2, 4)):
        one = mpc.simulate(mpc.MPC(model.replace(delay_steps=l), iterations=3, charge_solve_time=True),
                           model.replace(delay_steps=l), ticks=T)
        np.testing.assert_allclose(run.u[0, :, j], one.u[0, :, j], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(run.x[0, :, [j, 2 + j]], one.x[0, :, [j, 2 + j]], rtol=1e-9, atol=1e-12)
    assert np.abs(run.u[0, :, 1]).max() > 1e-3
    with pytest.raises(ValueError) as e:
        mpc.MPC(model.replace(delay_steps=[2, 4]), compensation="predict")
    assert str(e.value) == ("compensation must be 'inflight' with per-channel delay_steps (the delayed law feeds "
                            "back each channel's commands in flight; 'none', 'predict' and 'replay' take one delay); "
                            "got compensation='predict' with delay_steps=[2, 4]")


def test_sensors_of_different_delays_or_periods_are_refused_by_name():
    """The controller's filter measures every tick with one delay: a list of sensors of different
    delays, or a sensor sampled every other tick, would be read wrongly, so they are refused."""
    model = di.models.point_mass(delay=0.02, horizon=12)
    eye = np.eye(4)
    late = di.Observation(eye[:2], 0.004 * np.eye(2), delay_steps=6)
    early = di.Observation(eye[2:], 0.03 * np.eye(2), delay_steps=2)
    with pytest.raises(ValueError) as e:
        mpc.MPC(model.replace(observation=[late, early]))
    assert str(e.value) == ("problem.observation must have one sensory delay for mpc.MPC (its delayed filter measures "
                            "every tick with one delay; sensors of different delays are fused only by solve and "
                            "simulate); got sensors with delay_steps [6, 2]")
    with pytest.raises(ValueError) as e:
        mpc.MPC(model.replace(observation=di.Observation(eye[:2], 0.004 * np.eye(2), delay_steps=6, period=3)))
    assert str(e.value) == ("problem.observation must measure every tick for mpc.MPC (its delayed filter updates at "
                            "every tick); got period [3]")
