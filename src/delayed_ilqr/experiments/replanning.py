"""The re-planning controller of the gallery: a reach whose plan is re-solved at every step from
the delayed filter's estimate, over the time that remains (shrinking horizon).

The fixed time-varying feedback law of one solve is the optimal response to small departures from
its nominal. A kick or a target jump moves the arm far from it, and the law's corrections (and
its filter's predictions) then leave the linearisation. The model's controller instead re-plans:
at every tick k it takes the newest proprioceptive measurement into its extended delayed filter
(re-linearised about its own estimate, `delayed_ilqr.mpc.estimation`), carries the estimate to the
present with the commands already sent, and re-solves the reach from there, with the commands in
flight acting first, warm-started with its last plan ([`mpc.MPC`][delayed_ilqr.mpc.MPC],
compensation "inflight", one solver iteration per tick: the real-time iteration).

A reach ends at a fixed time T while the receding controller's tick problems span a fixed number
of steps K. `shrinking` makes them the same problem: from T on the model's dynamics and noise
stop and the running cost keeps only the effort on the excitations (so that the commands after T
stay well posed), hence the tick problem at t_k over [t_k, t_k + K dt] is the reach from t_k to T
padded with steps that change nothing. The first tick's problem is the reach itself, and the
controller starts from its solution.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import Options, Problem, solve
from ..models.metadata import default_u_init
from ..problem import GeneralCost

__all__ = ["Stopping", "StoppingCost", "shrinking", "controller", "run"]


@dataclass(frozen=True)
class Stopping:
    """f(x, u, ud, t) (or F): the model's own before ``end`` (s), zero from it on."""

    fn: Any
    end: float

    def __call__(self, x, u, ud, t):
        value = self.fn(x, u, ud)
        return jnp.where(t < self.end - 1e-9, value, jnp.zeros_like(value))


@dataclass(frozen=True)
class StoppingCost:
    """running(x, u, params, t) = the reach's running cost before ``end`` (s), r |u - u_rest|^2
    from it on (or r |u|^2 when the cost has no ``u_rest``); final(x, params, t) = the reach's."""

    running_fn: Any
    final_fn: Any
    end: float

    def running(self, x, u, params, t):
        rest = params.get("u_rest", jnp.zeros_like(u))
        idle = params["r"] * ((u - rest) @ (u - rest))
        return jnp.where(t < self.end - 1e-9, self.running_fn(x, u, params), idle)

    def final(self, x, params, t):
        return self.final_fn(x, params)


def shrinking(problem: Problem) -> Problem:
    """The model of the re-planning controller for ``problem`` (a reach of horizon K ending at
    T = K dt, time-invariant): dynamics and noise stop at T and the running cost keeps only the
    effort on the commands from T on (module docstring)."""
    if problem.time_dependent or getattr(problem.cost, "time_dependent", False):
        raise ValueError(f"shrinking takes a time-invariant reach; got {problem.name!r} with time-dependent "
                         "dynamics or cost")
    end = problem.horizon * problem.dt
    cost = StoppingCost(problem.cost.running_fn, problem.cost.final_fn, end)
    return problem.replace(dynamics=Stopping(problem.dynamics, end),
                           noise=None if problem.noise is None else Stopping(problem.noise, end),
                           cost=GeneralCost(cost.running, cost.final, problem.cost.params, time_dependent=True),
                           time_dependent=True, name=problem.name + " (re-planned)")
