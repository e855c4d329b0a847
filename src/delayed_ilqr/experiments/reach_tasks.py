"""Reaching problems of the gallery's experiments: a hand target for either arm, a bar target, a
target held from a chosen movement time on, and the target as part of the state (so that it can jump).

Both arms share one cost in hand space (``arm2_muscle6``'s `ReachFinalCost`,
``w_p |e(q) - target|^2 + w_v |de/dt|^2 + w_a |a|^2``, and ``r |u|^2`` per unit time): the
six-muscle arm with its defaults (`arm2_muscle6`), the
torque-driven arm (P2's rigid body, `arm2`) with torque noise at the
human level and the hand-space weights `ARM2_WEIGHTS` below, from the same start posture.

The transforms here change what a controller is asked to do, never the plant's dynamics or noise:

* `bar_target`: only the error along ``normal`` counts (a bar along the other direction);
* `hold_from`: the hand must be on the target, at rest, from the movement time ``T`` (a cost
  parameter) to the horizon, so that problems that differ only in ``T`` share one compiled solver
  (``jax.vmap`` over T, `fitts`);
* `with_target_state`: the target becomes two more states with zero dynamics, so a target jump
  is a disturbance of those states that the feedback policy sees (`target_jump`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import jax.numpy as jnp
import numpy as np

from .. import Options, Problem
from ..models.arm2 import arm2 as _arm2_factory
from ..models.arm2 import ARM2_PARAMS, ARM_STATE_LABELS, hand_position, hand_task, hand_velocity
from ..models.arm2_muscle6 import Q0, ReachFinalCost, arm2_muscle6, center_out_targets
from ..models.metadata import CostParameter, ModelMetadata
from ..problem import GeneralCost

__all__ = ["ARMS", "ARM2_WEIGHTS", "MODEL_DEFAULT", "reach", "loop_latency", "reach_targets", "bar_target",
           "hold_from", "with_target_state", "TorqueEffort", "BarFinalCost", "HoldRunningCost", "HoldFinalCost", "TargetStateDynamics",
           "TargetStateNoise", "TargetStateCost", "TARGET_SENSOR_DENSITY", "TARGET_MOTION_DENSITY",
           "movement_direction", "solver_options"]

#: The arms the gallery runs: the six-muscle arm (its defaults) and the torque-driven arm.
ARMS = ("arm2_muscle6", "arm2")

#: Hand-space cost weights of the torque-driven arm ([D]: r weighs N m torques as P2's Q = 1e-4 I;
#: w_p, w_v as P2's final weights 1e3 rad^-2, 1e1 (rad/s)^-2 scaled by the squared hand Jacobian,
#: about (0.3 m)^2, so that a 1 cm miss costs what P2's 0.03 rad does).
ARM2_WEIGHTS = dict(r=1e-4, w_p=1e4, w_v=1e2, w_a=0.0)


def solver_options(arm: str, options: Optional[Options] = None) -> Options:
    """``options``, or the arm's default: the six-muscle arm's reaches take up to 300 iterations
    (the center-out study's ``DEFAULT_OPTIONS``), the torque arm's ``Options()``."""
    if options is not None:
        return options
    return Options(max_iterations=300) if arm == "arm2_muscle6" else Options()


def reach_targets(n: int = 8, radius: float = 0.1, start_angle: float = 0.0) -> np.ndarray:
    """[n, 2] hand targets (m) on a circle around the start hand position (both arms share it)."""
    return center_out_targets(n, radius, start_angle=start_angle)


@dataclass(frozen=True)
class TorqueEffort:
    """running(x, u, params) = r |u|^2 (per unit time): the torque arm's effort on its joint torques."""

    def __call__(self, x, u, params):
        return params["r"] * (u @ u)


#: The value of ``delay`` / ``sensory_delay`` that keeps the model's own default (its human preset).
MODEL_DEFAULT = "model"


def reach(arm: str = "arm2", target=None, delay=MODEL_DEFAULT, noise: bool = True, final_time: float = 0.5,
          dt: float = 0.01, sensory_delay=MODEL_DEFAULT) -> Problem:
    """A reach of ``arm`` to the hand ``target`` [2] (m; default the 10 cm target straight ahead).

    Every experiment of the gallery builds its plant here, with the models' defaults (no weight
    or noise chosen per experiment): ``delay`` and ``sensory_delay`` are the model's own unless
    given.

    Args:
        arm: "arm2_muscle6" (its defaults) or "arm2" (P2's body with its ``noise=True`` preset and
            the hand-space weights `ARM2_WEIGHTS`), see `ARMS`.
        target: [2] hand target in metres.
        delay: motor (input) delay in seconds, a whole number of ``dt``; `MODEL_DEFAULT`: the model's.
        noise: the model's ``noise=True`` preset in the plant (False: none).
        final_time: movement time (s), the horizon K = final_time / dt.
        dt: the time step (s).
        sensory_delay: the proprioceptive delay in seconds (a whole number of ``dt``), None (the
            state is seen) or `MODEL_DEFAULT` (the model's).

    Returns:
        The `Problem`; its metadata's task space is the hand, its target the
        cost parameter ``target``.
    """
    if arm not in ARMS:
        raise ValueError(f"arm must be one of {ARMS}; got {arm!r}")
    if target is None:
        target = reach_targets(4, 0.1)[1]
    target = tuple(float(v) for v in np.asarray(target, dtype=float).reshape(2))
    given = {k: v for k, v in (("delay", delay), ("sensory_delay", sensory_delay))
             if not (isinstance(v, str) and v == MODEL_DEFAULT)}
    if arm == "arm2_muscle6":
        return arm2_muscle6(target=target, noise=noise, dt=dt, final_time=final_time, **given)
    horizon = int(round(final_time / dt))
    base = _arm2_factory(noise=noise, dt=dt, horizon=horizon, x0=Q0 + (0.0, 0.0), **given)
    params = dict(target=jnp.asarray(target), **{k: jnp.asarray(v) for k, v in ARM2_WEIGHTS.items()})
    cost = GeneralCost(TorqueEffort(), ReachFinalCost(ARM2_PARAMS), params)
    meta = ModelMetadata(state_labels=ARM_STATE_LABELS, control_labels=base.metadata.control_labels,
                         task=hand_task(ARM2_PARAMS, target=CostParameter("target")), noise=base.metadata.noise)
    return base.replace(cost=cost, metadata=meta)


def loop_latency(problem: Problem) -> float:
    """(l_s + l_m) dt in seconds: the sensory delay (0 when the state is seen) plus the motor delay,
    the earliest a response to a disturbance can reach the plant (l_m: the shortest channel's, l + phi
    for a delay between steps, a jitter's shortest delay)."""
    ls = 0 if problem.observation is None else int(problem.observation.delay_steps)
    lm = problem.delay_jitter.shortest if problem.delay_jitter is not None else np.min(problem.delay_in_steps)
    return (ls + float(lm)) * problem.dt


@dataclass(frozen=True)
class BarFinalCost:
    """final(x, params) = w_p (n . (e - target))^2 + w_v |de/dt|^2 + w_a |a|^2: only the hand error
    along the unit ``params["normal"]`` counts (a bar target along the perpendicular)."""

    arm: Any = ARM2_PARAMS

    def __call__(self, x, params):
        q, dq, a = x[:2], x[2:4], x[4:]
        err = params["normal"] @ (hand_position(q, self.arm) - params["target"])
        vel = hand_velocity(q, dq, self.arm)
        return params["w_p"] * err ** 2 + params["w_v"] * (vel @ vel) + params["w_a"] * (a @ a)


def bar_target(problem: Problem, along) -> Problem:
    """``problem`` (a `reach`) with a bar target: the bar lies along the direction ``along`` [2]
    through the target, so the final hand error along ``along`` is free (task-irrelevant) and only
    the error perpendicular to it costs."""
    along = np.asarray(along, dtype=float).reshape(2)
    along = along / np.linalg.norm(along)
    params = dict(problem.cost.params, normal=jnp.asarray([-along[1], along[0]]))
    return problem.replace(cost=GeneralCost(problem.cost.running_fn, BarFinalCost(problem.cost.final_fn.arm), params))


@dataclass(frozen=True)
class HoldRunningCost:
    """running(x, u, params, t) = running_base(x, u, params) + [t >= T] (w_p |e - target|^2 +
    w_v |de/dt|^2) / T_hold: from the movement time T = ``params["T"]`` on, the hand must stay on the
    target at rest (the final cost's weights spread over a hold of ``params["hold"]`` seconds)."""

    base: Any
    arm: Any = ARM2_PARAMS

    def __call__(self, x, u, params, t):
        q, dq = x[:2], x[2:4]
        err = hand_position(q, self.arm) - params["target"]
        vel = hand_velocity(q, dq, self.arm)
        on = (t >= params["T"] - 1e-9).astype(x.dtype)
        hold = on * (params["w_p"] * (err @ err) + params["w_v"] * (vel @ vel)) / params["hold"]
        return self.base(x, u, params) + hold


@dataclass(frozen=True)
class HoldFinalCost:
    """The reach's final cost, time-dependent in form only (the hold's final state)."""

    base: Any

    def __call__(self, x, params, t):
        return self.base(x, params)


def hold_from(problem: Problem, movement_time: float, hold: float) -> Problem:
    """``problem`` (a `reach`) asked to reach its target by ``movement_time`` (s) and hold it
    until the horizon; the horizon must cover ``movement_time + hold`` (hold > 0, seconds)."""
    if not hold > 0:
        raise ValueError(f"hold must be a positive number of seconds; got {hold!r}")
    if movement_time + hold > problem.horizon * problem.dt + 1e-9:
        raise ValueError(f"movement_time + hold must fit in the horizon {problem.horizon * problem.dt:g} s; "
                         f"got {movement_time:g} + {hold:g}")
    params = dict(problem.cost.params, T=jnp.asarray(float(movement_time)), hold=jnp.asarray(float(hold)))
    cost = GeneralCost(HoldRunningCost(problem.cost.running_fn, problem.cost.final_fn.arm),
                       HoldFinalCost(problem.cost.final_fn), params,
                       time_dependent=True)
    return problem.replace(cost=cost)


@dataclass(frozen=True)
class TargetStateDynamics:
    """f([x, g], u, ud) = [f_base(x, u, ud), 0]: the target g [2] is two constant states."""

    base: Any

    def __call__(self, x, u, ud):
        return jnp.concatenate([self.base(x[:-2], u, ud), jnp.zeros(2, x.dtype)])


@dataclass(frozen=True)
class TargetStateNoise:
    """F([x, g], u, ud) = [[F_base(x, u, ud), 0], [0, motion I_2]] (the columns of F_base alone when
    ``motion`` is 0): the target moves as a random walk of density ``motion`` (m / sqrt(s))."""

    base: Any
    n_base: int
    motion: float = 0.0

    def __call__(self, x, u, ud):
        F = (jnp.zeros((self.n_base, 0), x.dtype) if self.base is None else self.base(x[:-2], u, ud))
        F = jnp.concatenate([F, jnp.zeros((2, F.shape[1]), F.dtype)])
        if self.motion == 0.0:
            return F
        walk = jnp.concatenate([jnp.zeros((self.n_base, 2), F.dtype), self.motion * jnp.eye(2, dtype=F.dtype)])
        return jnp.concatenate([F, walk], axis=1)


@dataclass(frozen=True)
class TargetStateCost:
    """final([x, g], params) = final_base(x, params with target = g)."""

    base: Any

    def __call__(self, x, params):
        return self.base(x[:-2], dict(params, target=x[-2:]))


@dataclass(frozen=True)
class _RunningOnBase:
    base: Any

    def __call__(self, x, u, params):
        return self.base(x[:-2], u, params)


#: Vision of the target: per-sample SD 1 mm at dt = 10 ms (a density, m sqrt(s)) [D].
TARGET_SENSOR_DENSITY = 1e-4
#: What the controller expects of a target: a random walk of 2 mm per 10 ms step (m / sqrt(s)) [D];
#: with it the delayed filter believes a seen jump within a step or two (the plant's target moves
#: only when the experiment moves it).
TARGET_MOTION_DENSITY = 0.02


def _target_observation(observation, n_base: int, dt: float):
    """The sensors of [x, g]: ``observation``'s rows on x (arrays H, G), and g seen with the same
    delay through noise of density `TARGET_SENSOR_DENSITY`."""
    from .. import Observation
    if observation.output_fn is not None or observation.noise_fn is not None:
        raise ValueError("with_target_state needs sensors given as arrays H and G (the models' defaults); got "
                         f"{observation!r}")
    H, G = np.asarray(observation.H), np.asarray(observation.G)
    m, q = H.shape[0], G.shape[1]
    H2 = np.zeros((m + 2, n_base + 2))
    H2[:m, :n_base], H2[m:, n_base:] = H, np.eye(2)
    G2 = np.zeros((m + 2, q + 2))
    G2[:m, :q], G2[m:, q:] = G, TARGET_SENSOR_DENSITY / np.sqrt(dt) * np.eye(2)
    return Observation(H2, G2, delay_steps=observation.delay_steps)


def with_target_state(problem: Problem, target_motion: float = 0.0) -> Problem:
    """``problem`` (a `reach`) with its target as the last two states g, which the cost reads
    instead of the parameter: the policy's feedback on them is the optimal response to a target
    displacement (the target-jump model of Liu & Todorov 2007).

    The target has zero dynamics; ``target_motion`` > 0 (m / sqrt(s)) makes it a random walk of that
    density (the design problem: what the controller expects of a target, `TARGET_MOTION_DENSITY`),
    0 keeps it still but for a disturbance (the plant: a jump). With full-state feedback the policy
    sees a jump at once and the motor delay is the loop latency; with the problem's sensors the
    target is seen with the same delay (`TARGET_SENSOR_DENSITY`), and the loop latency is the
    sensory plus the motor delay."""
    if not target_motion >= 0:
        raise ValueError(f"target_motion must be a non-negative density (m / sqrt(s)); got {target_motion!r}")
    n = problem.n_states
    g = jnp.asarray(problem.cost.params["target"])
    meta = problem.metadata
    meta = ModelMetadata(state_labels=meta.state_labels + ("target x [m]", "target y [m]"),
                         control_labels=meta.control_labels, task=meta.task, u_init=meta.u_init, noise=meta.noise)
    cost = GeneralCost(_RunningOnBase(problem.cost.running_fn), TargetStateCost(problem.cost.final_fn),
                       problem.cost.params)
    noise = (None if problem.noise is None and target_motion == 0.0
             else TargetStateNoise(problem.noise, n, float(target_motion)))
    observation = (None if problem.observation is None
                   else _target_observation(problem.observation, n, problem.dt))
    return Problem(dynamics=TargetStateDynamics(problem.dynamics), x0=jnp.concatenate([problem.x0, g]),
                   dt=problem.dt, horizon=problem.horizon, delay_steps=problem.delay_steps, cost=cost,
                   noise=noise, u_min=problem.u_min if problem._has_limits else None,
                   u_max=problem.u_max if problem._has_limits else None, n_controls=problem.n_controls,
                   name=problem.name + "+target", metadata=meta, observation=observation)


def movement_direction(problem: Problem) -> np.ndarray:
    """[2] unit vector from the start hand position to the target."""
    start = np.asarray(hand_position(problem.x0[:2]))
    d = np.asarray(problem.cost.params["target"]) - start
    return d / np.linalg.norm(d)

