"""The receding-horizon controller: an immutable configuration ([`MPC`][delayed_ilqr.mpc.MPC]), its state
([`ControllerState`][delayed_ilqr.mpc.ControllerState]) and a pure tick ([`MPC.step`][delayed_ilqr.mpc.MPC.step]).

One tick k, given the newest state x_k (time t_k = k dt), or with sensors (a problem with an
``observation``) the newest measurement y_k = h(x_{k-l_s}) + G v_k:

0. with sensors, the delayed filter (``estimation``) takes y_k and carries its estimate of
   x_{k-l_s} to the present with the commands already sent: the tick acts on x_hat_k = E[x_k | I_k];
1. the strategy (``strategies``) makes the tick problem: the problem restarted at t_k from x_k
   (or from the model's prediction x_hat_{k+l_c}) with the commands in flight acting first;
2. the warm start is the last tick's plan shifted by one tick;
3. the solver's own iteration (linearise, backward pass, line search, regularisation; the
   compiled body of [`solve`][delayed_ilqr.solve]) runs at most ``iterations`` times: one is the
   real-time iteration, more converge the tick towards a fresh solve of the shifted problem;
4. the plan's command is sent (and joins the commands in flight), the plan shifts, and the tick
   returns the command together with its feedback law ([`TickLaw`][delayed_ilqr.mpc.TickLaw]);
   with sensors the filter predicts the next sensed state under the commands actually sent.

With ``charge_solve_time=True`` the solve takes one tick: the command computed at tick k from x_k
is sent at tick k + 1, so the controller's delay is l_c = l + 1 (the model's l steps plus the
tick), and [`simulate`][delayed_ilqr.mpc.simulate] holds it one tick before the plant's queue.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import _delays, _precision, _validate
from ..ilqg.solver import _solve_body
from ..options import Options
from ..problem import Problem
from ..sensor_list import SensorList
from ..solution import Status
from .estimation import FilterState, filter_init, filter_predict, filter_update, present_estimate
from .receding import at_tick, tick_problem
from .reference import Reference, reference as make_reference
from .strategies import COMPENSATIONS, REPLAY_HISTORIES, Strategy, strategy

__all__ = ["MPC", "ControllerState", "TickLaw", "Tick"]

#: The solver statuses that make a tick count as failed (an iteration limit is how a real-time
#: iteration ends, not a failure).
FAILED = (Status.REGULARIZATION_LIMIT, Status.NON_FINITE_ROLLOUT, Status.NON_FINITE_INITIAL)


class ControllerState(NamedTuple):
    """What the controller remembers between ticks.

    Attributes:
        plan: [K_t, d] the nominal commands, warm start of the next tick (already shifted); K_t is
            the tick problem's horizon (K, or K - l_c for ``predict``).
        in_flight: [l_c, d] the commands sent and not yet acting, oldest first (u_{k-l_c}..u_{k-1}).
        tick: [] int32, k.
        estimate: with sensors, the delayed filter's `FilterState` (None without).
    """

    plan: jax.Array
    in_flight: jax.Array
    tick: jax.Array
    estimate: Optional[FilterState] = None


class TickLaw(NamedTuple):
    """The feedback law of the tick's solve at the command sent (eq. 6 in absolute terms):

        u = u_nominal + feedforward + L (x - x_nominal) + sum_i M^i (u_{k+i-l_c} - u_nominal_{k+i-l_c})

    With per-channel delays l_m is the longest channel's, and channel j's entries i < l_m - l_c,j
    are zero (those commands have acted).

    Attributes:
        x_nominal: [n]; u_nominal: [d] (the command sent); feedforward: [d] (the solver's next step);
        state_feedback: [d, n] L; delay_feedback: [l_m, d, d] M^i on the commands in flight
        (l_m the tick problem's delay: l_c for inflight, 0 for the delay-free strategies).
    """

    x_nominal: jax.Array
    u_nominal: jax.Array
    feedforward: jax.Array
    state_feedback: jax.Array
    delay_feedback: jax.Array


class Tick(NamedTuple):
    """The output of one tick: the command to send [d], its [`TickLaw`][delayed_ilqr.mpc.TickLaw], the solver's status
    (int32) and iterations, the predicted cost of the tick problem, and the state the tick acted on
    [n] (x_k; with sensors the filter's estimate x_hat_k)."""

    command: jax.Array
    law: TickLaw
    status: jax.Array
    iterations: jax.Array
    cost: jax.Array
    estimate: jax.Array


def _check_compensation(value) -> str:
    if not isinstance(value, str) or value not in COMPENSATIONS:
        raise ValueError(f"compensation must be one of {', '.join(repr(c) for c in COMPENSATIONS)}; got {value!r}")
    return value


class MPC:
    """A delay-aware receding-horizon (model-predictive) controller for a [`Problem`][delayed_ilqr.Problem].

    ``problem.horizon`` is the receding horizon K, ``problem.delay_steps`` the model's input delay
    l, ``problem.dt`` the tick. Immutable; validated when built.

    Args:
        problem: the model the controller plans with (dynamics, cost, limits, noise). With a
            [`QuadraticCost`][delayed_ilqr.QuadraticCost] the cost recedes as the tracking cost
            (x - r(t))'P(x - r(t)) + u'Qu with the terminal cost (x - r)'P_final(x - r) at the
            horizon's end (``receding``); a GeneralCost is used as written. With an
            ``observation`` the controller is given measurements, not states, and estimates the
            state with its delayed filter (``estimation``).
        iterations: the most solver iterations per tick (positive int; 1: real-time iteration).
            With a noisy model the solver returns the nominal of lowest merit it has evaluated
            (derivation §12), and a step's merit is evaluated by the next iteration: its ticks run
            ``iterations + 1``, so that the last step counts.
        compensation: how the delay is handled: "inflight" (this library's delayed law, the
            default), "none" (ignore it), "predict" (roll the model forward over the latency, then
            solve delay-free), "replay" (Nav2's command-history replay); ``strategies`` has the table.
        charge_solve_time: if True, the command computed at tick k is sent at tick k + 1 (the solve
            takes one tick), and the controller's delay is l + 1.
        reference: None (track the problem's ``x_target``), an array [T_ref, n] sampled at dt from
            t = 0 (a trajectory), or a callable r(t) -> [n] (a moving target; jax-traceable).
        replay_history: for "replay": "sent" (the commands sent, Nav2's command-history replay) or
            "planned" (the plan's own values for the ticks in flight, re-planned every tick).
        options: [`Options`][delayed_ilqr.Options] for the solver's tolerances and line search
            (``max_iterations`` is replaced by ``iterations``).
        process_cov: with sensors, the delayed filter's process covariance per step [n, n]
            (symmetric PSD); default dt F F' of the model's noise at the estimate (``estimation``).
            Give one for a model without noise, or the filter never corrects its model.
        initial_cov: with sensors, the covariance of the filter's initial estimate ``problem.x0``
            [n, n] (symmetric PSD); default zeros (x0 known exactly, as in the problem).
        innovation_gate: with sensors, an optional threshold on the normalised squared innovation
            (chi-square with m degrees of freedom while the model holds): above it the filter adds
            ``gate_cov`` to its prior covariance before the update, believing an unexpected push at
            once (``estimation.filter_update``). Default None: no gate.
        gate_cov: [n, n] (symmetric PSD) the covariance added when the gate opens; required with
            ``innovation_gate``.

    Raises:
        ValueError, TypeError: naming the argument, for an unknown compensation, a non-positive
            ``iterations``, a horizon not longer than the controller's delay, a reference of the
            wrong shape, or filter covariances of the wrong shape, not PSD, or given without sensors.
    """

    __slots__ = ("problem", "iterations", "compensation", "charge_solve_time", "reference", "replay_history",
                 "options", "strategy", "template", "process_cov", "initial_cov",
                 "innovation_gate", "gate_cov")

    def __init__(self, problem: Problem, iterations: int = 1, compensation: str = "inflight",
                 charge_solve_time: bool = False, reference=None, replay_history: str = "sent",
                 options: Options | None = None, process_cov=None, initial_cov=None,
                 innovation_gate=None, gate_cov=None):
        if not isinstance(problem, Problem):
            raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
        _precision.require_x64("mpc.MPC")
        iterations = _validate.positive_int(iterations, "iterations")
        compensation = _check_compensation(compensation)
        if not isinstance(charge_solve_time, (bool, np.bool_)):
            raise TypeError(f"charge_solve_time must be True or False; got {charge_solve_time!r}")
        if replay_history not in REPLAY_HISTORIES:
            raise ValueError(f"replay_history must be 'sent' or 'planned'; got {replay_history!r}")
        _check_sensors(problem.observation)
        process_cov, initial_cov = _filter_covariances(problem, process_cov, initial_cov)
        innovation_gate, gate_cov = _gate(problem, innovation_gate, gate_cov)
        if problem.delay_jitter is not None:
            raise ValueError("mpc.MPC takes a fixed input delay: its tick problems and replay assume the command sent "
                             f"l steps ago acts now; got a problem with delay_jitter={problem.delay_jitter!r}")
        per_channel = _delays.is_per_channel(problem.delay_steps)
        if per_channel and compensation != "inflight":
            raise ValueError(f"compensation must be 'inflight' with per-channel delay_steps (the delayed law feeds "
                             f"back each channel's commands in flight; 'none', 'predict' and 'replay' take one "
                             f"delay); got compensation={compensation!r} with delay_steps="
                             f"{_delays.as_json(problem.delay_steps)}")
        if problem.delay_frame is not None:     # per-channel delays keep the frame of their longest
            problem = problem.replace(delay_frame=None) if per_channel else problem.without_frame("mpc.MPC")
        options = Options() if options is None else options
        if not isinstance(options, Options):
            raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
        l_c = _delays.longest(problem.delay_steps) + int(charge_solve_time)
        if l_c >= problem.horizon:
            raise ValueError("problem.horizon must be longer than the controller's delay (delay_steps, plus one "
                             "tick with charge_solve_time): a command must act within the horizon; got horizon="
                             f"{problem.horizon}, controller delay={l_c}")
        ref = make_reference(reference, problem)
        strat = strategy(compensation, l_c, problem.horizon, replay_history)
        values = dict(problem=problem, iterations=iterations, compensation=compensation,
                      charge_solve_time=bool(charge_solve_time), reference=ref, replay_history=replay_history,
                      options=dataclasses.replace(options, max_iterations=iterations + _noisy(problem)),
                      strategy=strat,
                      template=tick_problem(problem, ref, _channel_delays(problem, charge_solve_time)
                                            if per_channel else strat.model_delay, strat.horizon),
                      process_cov=process_cov, initial_cov=initial_cov, innovation_gate=innovation_gate,
                      gate_cov=gate_cov)
        for name, value in values.items():
            object.__setattr__(self, name, value)

    def __setattr__(self, name, value):
        raise AttributeError(f"MPC is immutable: make a new one instead of setting {name!r}")

    @property
    def controller_delay(self) -> int:
        """l_c: the model's delay in ticks, plus one when the solve time is charged (with
        per-channel delays the longest channel's: the commands the controller keeps in flight)."""
        problem = self.problem           # per-channel: its frame is the longest delay (static under jit)
        l = problem.frame_steps if _delays.is_per_channel(problem.delay_steps) else problem.delay_steps
        return l + int(self.charge_solve_time)

    @property
    def sensors(self) -> bool:
        """Whether the controller sees delayed, noisy measurements (its problem's ``observation``)."""
        return self.problem.observation is not None

    def init(self, u_init=None) -> ControllerState:
        """The state before the first tick: the plan ``u_init`` [K_t, d] (default zeros; K_t the
        tick problem's horizon, ``strategy.horizon``), nothing in flight (commands before t = 0
        are zero, as in the problem), tick 0; with sensors the filter at ``problem.x0`` with
        covariance ``initial_cov``."""
        K, nd = self.strategy.horizon, self.problem.n_controls
        plan = np.zeros((K, nd)) if u_init is None else _validate.array(u_init, "u_init", (K, nd))
        estimate = None
        if self.sensors:
            estimate = filter_init(self.problem.x0, self.initial_cov, self.problem.observation.delay_steps, nd)
        return ControllerState(jnp.asarray(plan), jnp.zeros((self.controller_delay, nd)), jnp.asarray(0, jnp.int32),
                               estimate)

    def step(self, state: ControllerState, x) -> tuple[ControllerState, Tick]:
        """One compiled tick from the newest state x [n], or with sensors the newest measurement
        y_k [m] (see the module docstring).

        Raises:
            ValueError: for a sampled reference that ends before the step this tick's horizon
                reads last (tick k + horizon)."""
        if self.reference.sampled:
            self.reference.check_covers(int(state.tick) + self.problem.horizon)
        return _tick(self, state, jnp.asarray(x, jnp.float64))

    def __repr__(self):
        return (f"MPC({self.problem.name!r}, K={self.problem.horizon}, l={_delays.as_json(self.problem.delay_steps)}, "
                f"compensation={self.compensation!r}, iterations={self.iterations}"
                + (", charge_solve_time=True" if self.charge_solve_time else "") + ")")


# An MPC is a JAX pytree: its problems' arrays and the reference's samples are data, the rest static,
# so controllers that differ only in arrays (x0, weights, a reference trajectory) share one
# compiled tick and one compiled closed loop.
_STATIC = ("iterations", "compensation", "charge_solve_time", "replay_history", "options", "strategy",
           "innovation_gate")


def _flatten(ctrl: MPC):
    return ((ctrl.problem, ctrl.template, ctrl.reference.samples, ctrl.process_cov, ctrl.initial_cov, ctrl.gate_cov),
            tuple(getattr(ctrl, name) for name in _STATIC) + (ctrl.reference.lookup,))


def _unflatten(aux, data):
    new = object.__new__(MPC)
    problem, template, samples, process_cov, initial_cov, gate_cov = data
    for name, value in zip(_STATIC, aux):
        object.__setattr__(new, name, value)
    for name, value in (("problem", problem), ("template", template), ("reference", Reference(aux[-1], samples)),
                        ("process_cov", process_cov), ("initial_cov", initial_cov), ("gate_cov", gate_cov)):
        object.__setattr__(new, name, value)
    return new


def _check_sensors(observation) -> None:
    """The controller's filter measures every tick with one sensory delay: several sensors of
    different delays, and sensors sampled less often than every tick, are refused by name."""
    if observation is None:
        return
    periods = set(observation.period) if isinstance(observation.period, tuple) else {observation.period}
    if isinstance(observation, SensorList) and not observation.equal_delays:
        raise ValueError("problem.observation must have one sensory delay for mpc.MPC (its delayed filter "
                         "measures every tick with one delay; sensors of different delays are fused only by "
                         f"solve and simulate); got sensors with delay_steps {list(observation.delays)}")
    if periods != {1}:
        raise ValueError("problem.observation must measure every tick for mpc.MPC (its delayed filter updates "
                         f"at every tick); got period {sorted(periods)}")


def _channel_delays(problem: Problem, charge_solve_time: bool) -> tuple:
    """(l_1 + s, ..., l_d + s): each channel's controller delay (s = 1 when the solve time is charged)."""
    return tuple(int(l_j) + int(charge_solve_time) for l_j in np.asarray(problem.delay_steps))


def _noisy(problem: Problem) -> int:
    """1 for a model with motor noise (its ticks run one more solver iteration), else 0."""
    return int(problem.noise is not None)


def _filter_covariances(problem: Problem, process_cov, initial_cov):
    """The filter's (process_cov, initial_cov), checked: None without sensors."""
    if problem.observation is None:
        for name, value in (("process_cov", process_cov), ("initial_cov", initial_cov)):
            if value is not None:
                raise ValueError(f"{name} is the delayed filter's: give it only for a problem with an observation "
                                 f"(sensors); got {name} for a problem without one")
        return None, None
    n = problem.n_states
    checked = []
    for name, value in (("process_cov", process_cov), ("initial_cov", initial_cov)):
        if value is None:
            checked.append(None if name == "process_cov" else jnp.zeros((n, n)))
            continue
        value = _validate.array(value, name, (n, n))
        checked.append(jnp.asarray(_validate.symmetric_psd(np.asarray(value), name, definite=False), jnp.float64))
    return tuple(checked)


def _gate(problem: Problem, innovation_gate, gate_cov):
    """The filter's (innovation_gate, gate_cov), checked: both None, or a positive number and a
    symmetric PSD [n, n], with sensors."""
    if innovation_gate is None and gate_cov is None:
        return None, None
    if problem.observation is None:
        raise ValueError("innovation_gate and gate_cov belong to the delayed filter: give them only for a problem "
                         "with an observation (sensors); got them for a problem without one")
    if innovation_gate is None or gate_cov is None:
        raise ValueError("innovation_gate and gate_cov go together (the threshold and the covariance added when "
                         f"it is crossed); got innovation_gate={innovation_gate!r} and gate_cov "
                         f"{'None' if gate_cov is None else 'given'}")
    gate = _validate.positive_float(innovation_gate, "innovation_gate")
    n = problem.n_states
    cov = _validate.array(gate_cov, "gate_cov", (n, n))
    return gate, jnp.asarray(_validate.symmetric_psd(np.asarray(cov), "gate_cov", definite=False), jnp.float64)


jax.tree_util.register_pytree_node(MPC, _flatten, _unflatten)


def predicted_state(ctrl: MPC, x, in_flight, plan, t0):
    """x_hat_{k+l_c}: the model from x [n] over the latency under the commands in flight
    [l_c, d] (the commands sent during it are the plan's, which a delayed plant does not feel)."""
    problem = ctrl.problem

    def one(x, row):
        ud, u, t = row
        return x + problem.dt * problem.dynamics_at(x, u, ud, t), None

    l = in_flight.shape[0]
    times = t0 + problem.dt * jnp.arange(l, dtype=x.dtype)
    sent = plan[jnp.minimum(jnp.arange(l), plan.shape[0] - 1)]
    return jax.lax.scan(one, x, (in_flight, sent, times))[0]


def tick(ctrl: MPC, state: ControllerState, x) -> tuple[ControllerState, Tick]:
    """One tick of ``ctrl`` (pure; [`MPC.step`][delayed_ilqr.mpc.MPC.step] is it compiled) from the newest state x [n]
    (with sensors the newest measurement y [m]): returns the next state and the [`Tick`][delayed_ilqr.mpc.Tick]."""
    s: Strategy = ctrl.strategy
    dt = ctrl.problem.dt
    if ctrl.sensors:
        x_del, P_post = filter_update(ctrl.problem, state.estimate, x, ctrl.innovation_gate, ctrl.gate_cov)
        commands = jnp.concatenate([state.estimate.earlier, state.in_flight])
        x = present_estimate(ctrl.problem, x_del, commands, state.tick, ctrl.controller_delay)
    t0 = dt * state.tick.astype(x.dtype)
    start, t_start = x, t0
    if s.predict_steps:
        start, t_start = predicted_state(ctrl, x, state.in_flight, state.plan, t0), t0 + s.predict_steps * dt
    in_flight = state.in_flight if s.model_delay else state.in_flight[:0]
    problem = at_tick(ctrl.template, start, in_flight, t_start)
    sol = _solve_body(problem, state.plan, ctrl.options)
    j, policy = s.send_index, sol.policy
    command = sol.u[j]
    law = TickLaw(sol.x[j], command, policy.feedforward[j], policy.state_feedback[j], policy.delay_feedback[j])
    plan = jnp.concatenate([sol.u[1:], sol.u[-1:]])          # the last command held for the new last tick
    sent = jnp.concatenate([state.in_flight[1:], command[None]]) if state.in_flight.shape[0] else state.in_flight
    estimate = None
    if ctrl.sensors:
        estimate = filter_predict(ctrl.problem, x_del, P_post, jnp.concatenate([commands, command[None]]), state.tick,
                                  ctrl.controller_delay, ctrl.process_cov)
    new = ControllerState(plan, sent, state.tick + 1, estimate)
    return new, Tick(command, law, sol.status, sol.iterations, sol.cost, x)


_tick = jax.jit(tick)
