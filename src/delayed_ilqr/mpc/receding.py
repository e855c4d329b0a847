"""The problem one tick of the receding-horizon controller solves: the user's problem started at
tick k, from a given state, with the commands already in flight acting first.

At tick k the controller solves, over its horizon K (``problem.horizon``) and with the model's
delay l_c (the tick problem's ``delay_steps``):

    x_{j+1} = x_j + dt f(x_j, u_j, ud_j, t_k + j dt),   ud_j = b_j (j < l_c),  u_{j-l_c} (j >= l_c)
    J = sum_{j<K} dt running(x_j, u_j, t_k + j dt) + final(x_K, t_k + K dt)

with b = [u_{k-l_c}, ..., u_{k-1}] the commands in flight. The solver knows only "commands before
time 0 are zero" (``linearize.delayed_commands``), so `InFlightDynamics` adds the in-flight
commands to the zeros it sees for j < l_c: ud = ud_solver + b_j. Its derivative in ud is then
f_ud at the command that really acts, so the backward pass (Theorem 1) computes the gains M_j^i
on the in-flight commands too. Both the in-flight commands b and the start time t_k are data
(pytree leaves): every tick shares one compiled solver.

A [`QuadraticCost`][delayed_ilqr.QuadraticCost] recedes as a tracking cost of a reference r(t) (the
problem's ``x_target`` when no reference is given):

    running = (x - r(t))' P (x - r(t)) + u' Q u,     final = (x - r(t_end))' P_final (x - r(t_end))

so that P weighs the error along the whole horizon and P_final is the terminal cost that keeps a
short receding horizon meaningful. A [`GeneralCost`][delayed_ilqr.GeneralCost] is kept as written, with
its time (if it declares one) shifted to t_k + j dt.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp

from ..problem import GeneralCost, Problem, QuadraticCost
from .reference import Lookup, Reference

__all__ = ["InFlightDynamics", "receding_cost", "tick_problem", "at_tick"]


class InFlightDynamics:
    """f(x, u, ud, t) of a tick problem: the model's f at time t0 + t, with the in-flight command
    b_j added to the acting command at the steps j = round(t / dt) < l (module docstring). With
    per-channel delays (``lags`` = (l_1, ..., l_d), the longest L = len(in_flight)) channel i's
    acting command gets b_{L - l_i + j, i} at the steps j < l_i: the command it sent j - l_i ticks ago.

    Attributes:
        fn: the model's f (or F for the noise), called with its time when ``time_dependent``.
        dt: the step (s); ``in_flight`` [l, d], b in time order; ``t0`` [] the tick's time (s).
        lags: None (one delay, l = len(in_flight)) or one delay per channel (a tuple, static).
    """

    def __init__(self, fn: Callable, time_dependent: bool, dt: float, in_flight, t0, lags=None):
        self.fn, self.time_dependent, self.dt = fn, time_dependent, dt
        self.in_flight, self.t0, self.lags = in_flight, t0, lags

    def __call__(self, x, u, ud, t):
        L = self.in_flight.shape[0]
        if L:
            j = jnp.round(t / self.dt).astype(jnp.int32)
            lags = L if self.lags is None else jnp.asarray(self.lags)
            rows = jnp.clip(L - lags + j, 0, L - 1) * jnp.ones(ud.shape[-1], jnp.int32)
            ud = ud + jnp.where(j < lags, self.in_flight[rows, jnp.arange(ud.shape[-1])], 0.0)
        return self.fn(x, u, ud, self.t0 + t) if self.time_dependent else self.fn(x, u, ud)


def _flatten(f: InFlightDynamics):
    # the model's callable is data when it is itself a pytree (a registered dataclass), else static
    fn_data = None if jax.tree_util.treedef_is_leaf(jax.tree_util.tree_structure(f.fn)) else f.fn
    return (f.in_flight, f.t0, fn_data), (None if fn_data is not None else f.fn, f.time_dependent, f.dt, f.lags)


def _unflatten(aux, data):
    fn_static, time_dependent, dt, lags = aux
    in_flight, t0, fn_data = data
    return InFlightDynamics(fn_static if fn_data is None else fn_data, time_dependent, dt, in_flight, t0, lags)


jax.tree_util.register_pytree_node(InFlightDynamics, _flatten, _unflatten)


@dataclass(frozen=True)
class _Tracking:
    """The receding tracking cost of a QuadraticCost (module docstring): running and final in one
    static object; params = (P, Q, P_final, reference samples, t0)."""

    lookup: Lookup

    def running(self, x, u, params, t):
        P, Q, _, samples, t0 = params
        err = x - self.lookup(samples, t0 + t)
        return err @ P @ err + u @ Q @ u

    def final(self, x, params, t):
        _, _, P_final, samples, t0 = params
        err = x - self.lookup(samples, t0 + t)
        return err @ P_final @ err


@dataclass(frozen=True)
class _Shifted:
    """A GeneralCost's running and final, their time (if any) shifted by t0; params = (inner, t0)."""

    running_fn: Callable
    final_fn: Callable
    time_dependent: bool

    def running(self, x, u, params, t):
        inner, t0 = params
        return self.running_fn(x, u, inner, t0 + t) if self.time_dependent else self.running_fn(x, u, inner)

    def final(self, x, params, t):
        inner, t0 = params
        return self.final_fn(x, inner, t0 + t) if self.time_dependent else self.final_fn(x, inner)


def receding_cost(cost, reference: Reference, t0=0.0) -> GeneralCost:
    """The problem's cost as a time-dependent [`GeneralCost`][delayed_ilqr.GeneralCost] of a tick starting
    at t0 (s): tracking of ``reference`` for a QuadraticCost, the cost shifted in time otherwise."""
    t0 = jnp.asarray(t0, jnp.float64)
    if isinstance(cost, QuadraticCost):
        track = _Tracking(reference.lookup)
        return GeneralCost(track.running, track.final, (cost.P, cost.Q, cost.P_final, reference.samples, t0),
                           time_dependent=True)
    shifted = _Shifted(cost.running_fn, cost.final_fn, cost.time_dependent)
    return GeneralCost(shifted.running, shifted.final, (cost.params, t0), time_dependent=True)


def tick_problem(problem: Problem, reference: Reference, delay_steps, horizon: int) -> Problem:
    """The template of the tick problem (module docstring) with model delay ``delay_steps`` (0 for
    the delay-free strategies; a tuple for one delay per channel) over ``horizon`` steps, nothing
    in flight and t0 = 0; validated once, here.

    The sensors are not part of the tick problem (the controller is given the state)."""
    nd = problem.n_controls
    per_channel = isinstance(delay_steps, tuple)
    longest = max(delay_steps) if per_channel else delay_steps
    zeros, t0 = jnp.zeros((longest, nd)), jnp.asarray(0.0)
    lags = delay_steps if per_channel else None
    wrap = lambda fn: None if fn is None else InFlightDynamics(fn, problem.time_dependent, problem.dt, zeros, t0,
                                                               lags)
    delay_steps = list(delay_steps) if per_channel else delay_steps
    return problem.replace(dynamics=wrap(problem.dynamics), noise=wrap(problem.noise), delay_steps=delay_steps,
                           horizon=horizon,
                           cost=receding_cost(problem.cost, reference), time_dependent=True, observation=None,
                           delay_frame=None, name=f"{problem.name} (receding)")


def at_tick(template: Problem, x0, in_flight, t0) -> Problem:
    """The template started at state x0 [n] and time t0 (s) with the commands ``in_flight``
    [l, d] (traceable: no validation, every tick shares the template's compiled solver)."""
    new = copy.copy(template)
    new.x0 = x0
    retime = lambda f: None if f is None else InFlightDynamics(f.fn, f.time_dependent, f.dt, in_flight, t0, f.lags)
    new.dynamics, new.noise = retime(template.dynamics), retime(template.noise)
    new.cost = copy.copy(template.cost)
    new.cost.params = (*template.cost.params[:-1], jnp.asarray(t0, jnp.float64))     # t0 is the last param
    return new
