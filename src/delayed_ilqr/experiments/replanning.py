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
from typing import Any, NamedTuple, Optional

import jax.numpy as jnp
import numpy as np
from scipy.stats import chi2

from .. import Problem, Runs, mpc
from ..models.arm2 import hand_velocity
from ..models.metadata import task_position
from ..models.arm2_muscle6 import with_disturbance_model
from ..problem import GeneralCost
from .engine import Trials, endpoint_error
from .responses import ellipse

__all__ = ["CONTROLLERS", "Stopping", "StoppingCost", "shrinking", "GATE_VELOCITY_SD",
           "gate_covariance", "innovation_gate", "controller", "monte_carlo", "ReachProfile", "reach_profile"]

#: The controllers of the perturbation experiments: the model's, which re-plans at every tick
#: (the default), and the fixed time-varying feedback law of one solve.
CONTROLLERS = ("replanning", "fixed")


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


#: The SD of the unexpected joint-velocity change (rad/s) the filter admits when its innovation
#: gate opens (about 0.3 m/s of the hand), and the same change's effect on the joint angles over
#: the sensory delay [D].
GATE_VELOCITY_SD = 1.0


def gate_covariance(model: Problem) -> np.ndarray:
    """[n, n] what the filter of ``model`` (an arm whose states begin [q1, q2, dq1, dq2], sensed
    l_s steps late) adds to its covariance when its innovation gate opens: a joint-velocity change
    of SD `GATE_VELOCITY_SD` that came up to l_s dt before the sensed state, so the angles moved by
    it times l_s dt (perfectly correlated with it)."""
    tau = model.observation.delay_steps * model.dt
    block = GATE_VELOCITY_SD ** 2 * np.array([[tau * tau, tau], [tau, 1.0]])
    cov = np.zeros((model.n_states, model.n_states))
    for j in range(2):
        idx = np.array([j, 2 + j])
        cov[np.ix_(idx, idx)] = block
    return cov


def innovation_gate(model: Problem, false_alarm: float) -> float:
    """The chi-square quantile of the model's m sensor outputs at 1 - ``false_alarm`` (the
    probability per sample that the gate opens while the model holds)."""
    if not 0 < false_alarm < 1:
        raise ValueError(f"false_alarm must be a probability in (0, 1); got {false_alarm!r}")
    m = int(np.asarray(model.observation.H).shape[0])
    return float(chi2.ppf(1.0 - false_alarm, m))


def controller(model: Problem, disturbance_model: Optional[float] = None, gate: Optional[float] = None) -> "mpc.MPC":
    """The re-planning controller of ``model`` (a reach, `reach_tasks.reach`): the receding-horizon
    controller on `shrinking` (``model``), one solver iteration per tick.

    Args:
        model: the reach (with its sensors, or the state seen).
        disturbance_model: its filter expects external joint torques of this density (N m s^1/2,
            `models.arm2_muscle6.with_disturbance_model`); None: the motor noise alone.
        gate: with sensors, the false-alarm probability per sample of its filter's innovation gate
            (`innovation_gate`, `gate_covariance`); None: no gate.
    """
    design = model if disturbance_model is None else with_disturbance_model(model, disturbance_model)
    extra = ({} if gate is None or model.observation is None
             else dict(innovation_gate=innovation_gate(model, gate), gate_cov=gate_covariance(model)))
    return mpc.MPC(shrinking(design), iterations=1, **extra)


def monte_carlo(ctrl: "mpc.MPC", plant: Problem, first_plan, n_trials: int, seed: int,
                disturbance=None) -> tuple[Trials, int]:
    """``n_trials`` reaches of ``plant`` under ``ctrl`` (`controller`), starting from the plan
    ``first_plan`` [K, d] (the reach's solution, the first tick's problem), with the disturbance
    W [K, n] added to every trial's state update (unknown to the controller). One compiled loop
    ([`mpc.simulate`][delayed_ilqr.mpc.simulate]); trials with the same seed share their noise.

    Returns:
        The `engine.Trials` (its runs: x [N, K+1, n], the commands issued u [N, K, d], the plant's
        cost [N] and with sensors x_hat [N, K, n], the estimates the ticks acted on) and the
        number of ticks whose solve failed (no descent, non-finite rollout), over all trials.
    """
    loop = mpc.simulate(ctrl, plant, ticks=plant.horizon, n_trials=n_trials, seed=seed, disturbance=disturbance,
                        u_init=np.asarray(first_plan))
    runs = Runs(loop.x, loop.u, loop.cost, loop.estimate if ctrl.sensors else None)
    final = np.asarray(loop.x[:, -1], dtype=np.float64)
    return (Trials(runs, task_position(plant, final), endpoint_error(plant, final)),
            int(np.asarray(loop.solver_failures).sum()))


class ReachProfile(NamedTuple):
    """The unperturbed reach of one controller (lengths in metres, times as fractions of the movement).

    Attributes:
        error_median: median final distance to the target.
        sd_major, sd_minor: endpoint SDs along the principal axes (`responses.ellipse`).
        peak_over_mean: peak over mean of the mean hand speed profile.
        time_to_peak: the time of its peak over the movement time.
    """

    error_median: float
    sd_major: float
    sd_minor: float
    peak_over_mean: float
    time_to_peak: float


def reach_profile(trials: Trials, dt: float) -> ReachProfile:
    """The `ReachProfile` of a reach's `engine.Trials` on an arm (states begin [q, dq])."""
    x = np.asarray(trials.runs.x, dtype=np.float64)
    speed = np.linalg.norm(np.asarray(hand_velocity(x[..., :2], x[..., 2:4])), axis=-1).mean(axis=0)
    e = ellipse(np.cov(np.asarray(trials.endpoints).T))
    K = speed.shape[0] - 1
    return ReachProfile(float(np.median(trials.errors)), e.major, e.minor, float(speed.max() / speed.mean()),
                        float(np.argmax(speed) / K))

