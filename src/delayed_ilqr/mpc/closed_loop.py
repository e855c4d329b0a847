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
    """Trials of the receding-horizon controller on a plant.

    Attributes:
        x: [N, T+1, n] the plant's states (x[:, 0] = the initial states).
        u: [N, T, d] the commands the controller computed at each tick.
        cost: [N] the plant's cost over the T ticks, sum_k dt running(x_k, u_k, t_k) + final(x_T, t_T),
            with the plant's weights and the controller's reference (``receding``).
        diverged: [N] bool, a state became non-finite or left ``bound``.
        failed: [N] bool, diverged, or ``failure(x_k)`` held at some tick (a fall).
        solver_failures: [N] int, ticks whose solve ended without descent or with a non-finite rollout.
        status: [N, T] int32, the solver's status at each tick ([`Status`][delayed_ilqr.Status] codes).
        reference: [T+1, n] r(t_k), the target the cost measures against.
    """

    x: jax.Array
    u: jax.Array
    cost: jax.Array
    diverged: jax.Array
    failed: jax.Array
    solver_failures: jax.Array
    status: jax.Array
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
    traced (a plant whose delay is data, ``Problem.delay_frame``)."""
    Q = pending.shape[0]
    if Q == 0:
        return u
    return jnp.where(lag == 0, u, pending[jnp.clip(Q - lag, 0, Q - 1)])


def _trial(ctrl: MPC, plant: Problem, ticks: int, failure: Optional[Callable], bound: float, key, x0, disturbance):
    """One trial: (x [T+1, n], u [T, d], cost, diverged, failed, solver_failures, status [T])."""
    nd, p = plant.n_controls, plant.n_noise
    s = int(ctrl.charge_solve_time)
    queue = plant.frame_steps + s                 # the most ticks between computing and acting
    lag = plant.delay_steps + s                   # this plant's (traced with a frame)
    xi = jax.random.normal(key, (ticks, p))
    times = plant.dt * jnp.arange(ticks, dtype=jnp.float64)

    def step(carry, data):
        state, x, pending = carry          # pending: the last `queue` commands computed, oldest first
        xi_k, t, w = data
        state, out = tick(ctrl, state, x)
        u = out.command
        # the plant's own u argument: the command it receives now (one tick late when charged)
        received = _acting(pending, u, s) if s else u
        x_new = _plant_step(plant, x, received, _acting(pending, u, lag), xi_k, t) + w
        pending = jnp.concatenate([pending[1:], u[None]]) if queue else pending
        return (state, x_new, pending), (x_new, u, out.status)

    init = (ctrl.init(), x0, jnp.zeros((queue, nd)))
    _, (xs, us, status) = jax.lax.scan(step, init, (xi, times, disturbance))
    xs = jnp.concatenate([x0[None], xs])
    cost_fn = receding_cost(plant.cost, ctrl.reference)
    running = jax.vmap(cost_fn.running)(xs[:-1], us, times)
    cost = plant.dt * jnp.sum(running) + cost_fn.final(xs[-1], plant.dt * ticks)
    diverged = ~jnp.all(jnp.isfinite(xs)) | jnp.any(jnp.abs(xs) > bound)
    fell = jnp.asarray(False) if failure is None else jnp.any(jax.vmap(failure)(xs))
    solver_failures = jnp.sum(jnp.isin(status, jnp.asarray([int(s) for s in FAILED])))
    return xs, us, cost, diverged, diverged | fell, solver_failures, status


@partial(jax.jit, static_argnames=("plant_static", "ticks", "failure", "bound", "n_trials", "sequential"))
def _run(ctrl, plant_static, plant_data, ticks, failure, bound, n_trials, key, x0, disturbance, sequential):
    plant = jax.tree_util.tree_unflatten(plant_static, plant_data)
    keys = jax.random.split(key, n_trials)
    in_axes = (0, None if x0.ndim == 1 else 0, None if disturbance.ndim == 2 else 0)
    trial = lambda k, x, w: _trial(ctrl, plant, ticks, failure, bound, k, x, w)
    # on CPU the trials run one after another under the vmap (the solver's CPU batching rule): each
    # tick's solve stays a small loop instead of a batched one (docs/performance.md#receding-horizon-control)
    return jax.vmap(one_after_another(trial) if sequential else trial, in_axes=in_axes)(keys, x0, disturbance)


def _check_plant(ctrl: MPC, plant) -> Problem:
    if not isinstance(plant, Problem):
        raise TypeError(f"plant must be a delayed_ilqr.Problem (the true system); got {type(plant).__name__}")
    model = ctrl.problem
    if (plant.n_states, plant.n_controls) != (model.n_states, model.n_controls):
        raise ValueError(f"plant must have the controller's state and command sizes (n={model.n_states}, "
                         f"d={model.n_controls}); got n={plant.n_states}, d={plant.n_controls}")
    if not math.isclose(plant.dt, model.dt, rel_tol=1e-12):
        raise ValueError(f"plant.dt must equal the controller's tick (problem.dt={model.dt}); got {plant.dt}")
    return plant


def simulate(ctrl: MPC, plant: Problem, ticks: int, n_trials: int = 1, seed: int = 0, disturbance=None,
             x0=None, failure: Optional[Callable] = None, bound: float = math.inf) -> ClosedLoop:
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
        x0: optional initial states [N, n], one per trial (default ``plant.x0`` for all).
        failure: optional ``failure(x) -> bool`` on one state (jax-traceable, e.g. the pole past
            horizontal); a trial fails when it holds at any tick.
        bound: a trial diverges when a state component leaves [-bound, bound] (default: only
            non-finite states).

    Returns:
        [`ClosedLoop`][delayed_ilqr.mpc.ClosedLoop] with x [N, T+1, n], u [N, T, d], cost [N] and the failure flags.

    Raises:
        TypeError, ValueError: naming the argument, for a plant of other sizes or another dt, a
            reference that ends before the last tick's horizon, or a malformed disturbance.
    """
    if not isinstance(ctrl, MPC):
        raise TypeError(f"ctrl must be a delayed_ilqr.mpc.MPC; got {type(ctrl).__name__}")
    _precision.require_x64("mpc.simulate")
    plant = _check_plant(ctrl, plant)
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
    x0 = plant.x0 if x0 is None else jnp.asarray(_validate.array(x0, "x0", (n_trials, nx)))
    data, static = jax.tree_util.tree_flatten(plant)
    out = _run(ctrl, static, data, ticks, failure, float(bound), n_trials, jax.random.PRNGKey(seed), x0,
               jnp.asarray(disturbance), jax.default_backend() == "cpu")
    times = plant.dt * jnp.arange(ticks + 1, dtype=jnp.float64)
    reference = jax.vmap(lambda t: ctrl.reference.lookup(ctrl.reference.samples, t))(times)
    return ClosedLoop(*out, reference=reference)
