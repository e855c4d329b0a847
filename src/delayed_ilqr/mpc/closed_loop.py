"""The closed loop compiled whole: the controller's tick and the plant's step as one ``lax.scan``
over ticks, ``vmap`` over trials.

Tick k of a trial, with the plant's true delay l_p (``plant.delay_steps``) and s = 1 when the
controller charges its solve time (the command computed at k goes out at k + 1), else 0:

    u_k         = the controller's command from x_k                     (MPC.step)
    ud_k        = u_{k-l_p-s}   (zero before t = 0)                     the command acting on the plant
    x_{k+1}     = x_k + dt f_p(x_k, u_{k-s}, ud_k, t_k) + sqrt(dt) F_p(...) xi_k + W_k

with f_p, F_p the plant's dynamics and noise (Euler-Maruyama, as [`delayed_ilqr.simulate`][delayed_ilqr.simulate]
with one sub-step) and W an optional disturbance the controller does not know. The plant may differ
from the controller's model in its parameters, its delay and its noise, not in n and d.

With sensors (a controller whose problem has an ``observation``) the controller is given, instead
of x_k, the measurement y_k = h(x_{k-l_s}) + G(x_{k-l_s}) v_k of the plant's sensors (the plant's
``observation`` when it has one, else the model's; x0 before time 0), v_k ~ N(0, I).

Several plants (``simulate(ctrl, [plant_1, ..., plant_P])``) that differ only in arrays run in the
same compiled call, mapped over a leading plant axis outside the trials' axis: a mismatch study
(parameters +-20 %, true delays as data through ``delay_frame``) is one run.
"""
from __future__ import annotations

import math
from functools import partial
from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import _precision, _validate
from ..ilqg.batching import one_after_another
from ..problem import Problem
from .controller import FAILED, MPC, tick
from .receding import receding_cost

__all__ = ["ClosedLoop", "simulate"]


class ClosedLoop(NamedTuple):
    """Trials of the receding-horizon controller on a plant (with several plants every array has a
    leading plant axis [P, ...]).

    Attributes:
        x: [N, T+1, n] the plant's states (x[:, 0] = the initial states).
        u: [N, T, d] the commands the controller computed at each tick.
        cost: [N] the plant's cost over the T ticks, sum_k dt running(x_k, u_k, t_k) + final(x_T, t_T),
            with the plant's weights and the controller's reference (``receding``).
        diverged: [N] bool, a state became non-finite or left ``bound``.
        failed: [N] bool, diverged, or ``failure(x_k)`` held at some tick (a fall).
        solver_failures: [N] int, ticks whose solve ended without descent or with a non-finite rollout.
        status: [N, T] int32, the solver's status at each tick ([`Status`][delayed_ilqr.Status] codes).
        estimate: [N, T, n] the state each tick acted on: x_k, or with sensors the filter's x_hat_k.
        reference: [T+1, n] r(t_k), the target the cost measures against.
    """

    x: jax.Array
    u: jax.Array
    cost: jax.Array
    diverged: jax.Array
    failed: jax.Array
    solver_failures: jax.Array
    status: jax.Array
    estimate: jax.Array
    reference: jax.Array

    @property
    def failure_rate(self) -> float:
        """The fraction of trials that failed."""
        return float(np.mean(np.asarray(self.failed)))


def _plant_step(plant: Problem, x, u, ud, xi, t):
    """One Euler-Maruyama step of the plant (t: t_k in s, used by time-dependent dynamics)."""
    x_new = x + plant.dt * plant.dynamics_at(x, u, ud, t)
    if plant.noise is not None:
        x_new = x_new + math.sqrt(plant.dt) * plant.noise_at(x, u, ud, t) @ xi
    return x_new


def _acting(pending, u, lag):
    """u_{k-lag} from the last Q commands ``pending`` [Q, d] (oldest first) and u_k; ``lag`` may be
    traced (a plant whose delay is data, ``Problem.delay_frame``), and one per channel [d]
    (channel j acts with u_{k-lag_j, j})."""
    Q, nd = pending.shape
    if Q == 0:
        return u
    rows = jnp.clip(Q - lag, 0, Q - 1) * jnp.ones(nd, jnp.int32)
    return jnp.where(lag == 0, u, pending[rows, jnp.arange(nd)])


def _sensors(ctrl: MPC, plant: Problem):
    """The sensors that measure the plant for a controller with sensors (None without)."""
    if not ctrl.sensors:
        return None
    return plant.observation if plant.observation is not None else ctrl.problem.observation


def _trial(ctrl: MPC, plant: Problem, ticks: int, failure: Optional[Callable], bound: float, key, x0, disturbance,
           plan=None):
    """One trial: (x [T+1, n], u [T, d], cost, diverged, failed, solver_failures, status [T], estimate [T, n])."""
    nd, p = plant.n_controls, plant.n_noise
    s = int(ctrl.charge_solve_time)
    queue = plant.frame_steps + s                 # the most ticks between computing and acting
    lag = plant.delay_steps + s                   # this plant's (traced with a frame)
    xi = jax.random.normal(key, (ticks, p))
    times = plant.dt * jnp.arange(ticks, dtype=jnp.float64)
    sensors = _sensors(ctrl, plant)
    ls = 0 if sensors is None else sensors.delay_steps
    q = 0 if sensors is None else sensors.noise_matrix(x0).shape[1]
    v = jax.random.normal(jax.random.fold_in(key, 1), (ticks, q))

    def step(carry, data):
        state, past, pending = carry       # past: x_{k-l_s}..x_k; pending: the last `queue` commands computed
        xi_k, v_k, t, w = data
        x, sensed = past[-1], past[0]
        seen = x if sensors is None else sensors.measure(sensed) + sensors.noise_matrix(sensed) @ v_k
        state, out = tick(ctrl, state, seen)
        u = out.command
        # the plant's own u argument: the command it receives now (one tick late when charged)
        received = _acting(pending, u, s) if s else u
        x_new = _plant_step(plant, x, received, _acting(pending, u, lag), xi_k, t) + w
        pending = jnp.concatenate([pending[1:], u[None]]) if queue else pending
        past = jnp.concatenate([past[1:], x_new[None]])
        return (state, past, pending), (x_new, u, out.status, out.estimate)

    start = ctrl.init()
    if plan is not None:
        start = start._replace(plan=plan)
    init = (start, jnp.broadcast_to(x0, (ls + 1, x0.shape[0])), jnp.zeros((queue, nd)))
    _, (xs, us, status, estimate) = jax.lax.scan(step, init, (xi, v, times, disturbance))
    xs = jnp.concatenate([x0[None], xs])
    cost_fn = receding_cost(plant.cost, ctrl.reference)
    running = jax.vmap(cost_fn.running)(xs[:-1], us, times)
    cost = plant.dt * jnp.sum(running) + cost_fn.final(xs[-1], plant.dt * ticks)
    diverged = ~jnp.all(jnp.isfinite(xs)) | jnp.any(jnp.abs(xs) > bound)
    fell = jnp.asarray(False) if failure is None else jnp.any(jax.vmap(failure)(xs))
    solver_failures = jnp.sum(jnp.isin(status, jnp.asarray([int(s) for s in FAILED])))
    return xs, us, cost, diverged, diverged | fell, solver_failures, status, estimate


@partial(jax.jit, static_argnames=("plant_static", "ticks", "failure", "bound", "n_trials", "sequential",
                                   "several"))
def _run(ctrl, plant_static, plant_data, ticks, failure, bound, n_trials, key, x0, disturbance, sequential,
         several=False, plan=None):
    keys = jax.random.split(key, n_trials)

    def trials(data):
        plant = jax.tree_util.tree_unflatten(plant_static, data)
        start = plant.x0 if x0 is None else x0
        in_axes = (0, None if start.ndim == 1 else 0, None if disturbance.ndim == 2 else 0)
        trial = lambda k, x, w: _trial(ctrl, plant, ticks, failure, bound, k, x, w, plan)
        # on CPU the trials run one after another under the vmap (the solver's CPU batching rule): each
        # tick's solve stays a small loop instead of a batched one (docs/performance.md#receding-horizon-control)
        return jax.vmap(one_after_another(trial) if sequential else trial, in_axes=in_axes)(keys, start, disturbance)

    if not several:
        return trials(plant_data)
    return jax.vmap(one_after_another(trials) if sequential else trials)(plant_data)


def _check_plant(ctrl: MPC, plant, name: str = "plant") -> Problem:
    if not isinstance(plant, Problem):
        raise TypeError(f"{name} must be a delayed_ilqr.Problem (the true system); got {type(plant).__name__}")
    model = ctrl.problem
    if (plant.n_states, plant.n_controls) != (model.n_states, model.n_controls):
        raise ValueError(f"{name} must have the controller's state and command sizes (n={model.n_states}, "
                         f"d={model.n_controls}); got n={plant.n_states}, d={plant.n_controls}")
    if not math.isclose(plant.dt, model.dt, rel_tol=1e-12):
        raise ValueError(f"{name}.dt must equal the controller's tick (problem.dt={model.dt}); got {plant.dt}")
    if plant.observation is not None and not ctrl.sensors:
        raise ValueError(f"{name} has sensors (an observation) but the controller is given the state: build the "
                         "controller from a problem with an observation, or drop the plant's; got "
                         f"{name}.observation={plant.observation!r} and problem.observation=None")
    sensors = _sensors(ctrl, plant)
    if sensors is not None:
        m = lambda o: jax.eval_shape(o.measure, jax.ShapeDtypeStruct((model.n_states,), jnp.float64)).shape
        if m(sensors) != m(model.observation):
            raise ValueError(f"{name}.observation must measure as many outputs as the controller's, "
                             f"{m(model.observation)}; got {m(sensors)}")
    return plant


def _stacked(ctrl: MPC, plants) -> tuple:
    """(static, data) of several plants with the data stacked on a leading plant axis."""
    if len(plants) == 0:
        raise ValueError("plant must be a Problem or a non-empty sequence of them; got an empty sequence")
    flat = [jax.tree_util.tree_flatten(_check_plant(ctrl, p, f"plant[{i}]")) for i, p in enumerate(plants)]
    static = flat[0][1]
    for i, (_, other) in enumerate(flat[1:], 1):
        if other != static:
            raise ValueError(f"plant[{i}] must differ from plant[0] only in arrays (data: parameters of a dynamics "
                             "registered as a pytree, x0, weights, the delay with a common delay_frame) to share "
                             f"the compiled run; got another structure: {other} against {static}")
    data = [jnp.stack([jnp.asarray(d[j]) for d, _ in flat]) for j in range(len(flat[0][0]))]
    return static, data


def simulate(ctrl: MPC, plant, ticks: int, n_trials: int = 1, seed: int = 0, disturbance=None,
             x0=None, failure: Optional[Callable] = None, bound: float = math.inf, u_init=None) -> ClosedLoop:
    """Runs ``ctrl`` against ``plant`` for ``ticks`` ticks, ``n_trials`` times, in one compiled loop.

    Args:
        ctrl: the [`MPC`][delayed_ilqr.mpc.MPC].
        plant: the true system, a [`Problem`][delayed_ilqr.Problem] with the controller's n, d and dt;
            its parameters, ``delay_steps`` (the true delay), ``noise``, limits and ``x0`` may differ
            from the controller's model (``plant.horizon`` is not used). Its noise is driven by
            ``jax.random.split(PRNGKey(seed), n_trials)``: two controllers run with the same seed
            see the same noise (common random numbers). Plants that differ only in arrays (a
            dynamics registered as a pytree with its parameters as data; the delay as data with
            ``delay_frame``) share one compiled loop.
        ticks: T, the number of ticks (positive int).
        n_trials: N (positive int).
        seed: non-negative integer.
        disturbance: optional W [T, n] (every trial) or [N, T, n] (one per trial), added to the
            plant's state update and unknown to the controller.
        x0: optional initial states [N, n], one per trial (default ``plant.x0`` for all; the
            controller's filter, with sensors, starts at the model's ``x0`` whatever the plant's).
        failure: optional ``failure(x) -> bool`` on one state (jax-traceable, e.g. the pole past
            horizontal); a trial fails when it holds at any tick.
        bound: a trial diverges when a state component leaves [-bound, bound] (default: only
            non-finite states).
        u_init: optional [K_t, d] the controller's plan before the first tick (its warm start,
            e.g. the solution of the first tick's problem; K_t = ``ctrl.strategy.horizon``);
            default zeros, as ``MPC.init``.

    Returns:
        [`ClosedLoop`][delayed_ilqr.mpc.ClosedLoop] with x [N, T+1, n], u [N, T, d], cost [N] and the failure flags
        ([P, N, ...] for P plants).

    Raises:
        TypeError, ValueError: naming the argument, for a plant of other sizes, another dt, sensors
            the controller does not use, plants that differ in more than arrays, a reference that
            ends before the last tick's horizon, or a malformed disturbance.
    """
    if not isinstance(ctrl, MPC):
        raise TypeError(f"ctrl must be a delayed_ilqr.mpc.MPC; got {type(ctrl).__name__}")
    _precision.require_x64("mpc.simulate")
    several = isinstance(plant, (list, tuple))
    if several:
        static, data = _stacked(ctrl, plant)
        plant = plant[0]
    else:
        data, static = jax.tree_util.tree_flatten(_check_plant(ctrl, plant))
    ticks = _validate.positive_int(ticks, "ticks")
    n_trials = _validate.positive_int(n_trials, "n_trials")
    seed = _validate.seed(seed)
    bound = _validate.positive_float(bound, "bound") if bound != math.inf else bound
    if failure is not None and not callable(failure):
        raise TypeError(f"failure must be None or callable as failure(x); got {type(failure).__name__}")
    ctrl.reference.check_covers(ticks - 1 + ctrl.problem.horizon)     # every horizon ends at t_{k+K}
    nx = plant.n_states
    if disturbance is None:
        disturbance = np.zeros((ticks, nx))
    else:
        shape = (ticks, nx) if np.ndim(disturbance) == 2 else (n_trials, ticks, nx)
        disturbance = _validate.array(disturbance, "disturbance", shape)
    x0 = None if x0 is None else jnp.asarray(_validate.array(x0, "x0", (n_trials, nx)))
    plan = None if u_init is None else ctrl.init(u_init).plan
    out = _run(ctrl, static, data, ticks, failure, float(bound), n_trials, jax.random.PRNGKey(seed), x0,
               jnp.asarray(disturbance), jax.default_backend() == "cpu", several, plan)
    times = plant.dt * jnp.arange(ticks + 1, dtype=jnp.float64)
    reference = jax.vmap(lambda t: ctrl.reference.lookup(ctrl.reference.samples, t))(times)
    return ClosedLoop(*out, reference=reference)
