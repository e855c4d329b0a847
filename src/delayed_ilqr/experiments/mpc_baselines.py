"""The compensations of actuation delay in receding-horizon control, compared in closed loop.

Each scenario runs one controller per compensation ([`delayed_ilqr.mpc.strategies`][delayed_ilqr.mpc.strategies]) against
plants that match the model, differ from it by +-20 % in their inertial parameters, or have a true
delay two steps off the model's. Trials start from random perturbations of the initial state (the
same for every controller: common random numbers), and every controller runs the real-time
iteration (``iterations``, default one solver iteration per tick). Measured per condition and
compensation: the median closed-loop cost, the failure rate (a fall or divergence) and the RMS
tracking error in the model's task space (over the trials that did not fail).

|  |  |
|---|---|
| cart_pole | balancing the pole upright (Florian's cart-pole, &#124;u&#124; <= 10 N), dt = 25 ms, horizon 1 s, from tilts of sd 0.1 rad; a fall: the pole past 45 degrees |
| cart_pole_swing_up | swinging the pole up from hanging and holding it, dt = 50 ms, horizon 2 s, 8 s of ticks; a failure: the pole more than 0.5 rad off upright in the last 2 s |
| arm2 | the two-link arm (Li & Todorov 2004) tracking a target moving on a circle in joint space (0.5 Hz), dt = 10 ms, horizon 0.3 s; a failure: the hand more than 10 cm from the target's after the first 0.5 s |
| planar_quadrotor | the planar quadrotor flying to a waypoint 1 m away and holding it, dt = 10 ms, horizon 0.5 s; a fall: a roll past 90 degrees |

The five plants of a controller run in one compiled call (``mpc.simulate`` of a list of plants):
the mismatched dynamics are pytrees whose scale is data, and the true delay is data through
``delay_frame``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, NamedTuple, Optional, Union

import jax
import jax.numpy as jnp
import numpy as np

from .. import mpc
from ..models import arm2, cart_pole, planar_quadrotor
from ..models.arm2 import ARM2_PARAMS, Arm2Dynamics
from ..models.cart_pole import CartPoleDynamics
from ..models.planar_quadrotor import INERTIA, MASS
from ..problem import QuadraticCost
from .delay_text import milliseconds, ms_text

__all__ = ["Scenario", "SCENARIOS", "CONDITIONS", "STRATEGIES", "Row", "run_scenario", "markdown", "InputGain",
           "compare"]

#: The controllers compared: (label, compensation, replay_history).
STRATEGIES = (("none", "none", "sent"), ("predict", "predict", "sent"), ("replay (planned)", "replay", "planned"),
              ("replay (sent)", "replay", "sent"), ("inflight", "inflight", "sent"))

#: The plants: (label, scale of the inertial parameters, true delay minus the model's, in steps).
CONDITIONS = (("model", 1.0, 0), ("inertia -20 %", 0.8, 0), ("inertia +20 %", 1.2, 0), ("delay -2 steps", 1.0, -2),
              ("delay +2 steps", 1.0, 2))


@dataclass(frozen=True)
class ScaledCartPole:
    """The cart-pole with its masses and pole length scaled by ``scale`` (data)."""

    scale: float = 1.0

    def __call__(self, x, u, ud):
        s = self.scale
        return CartPoleDynamics(cart_mass=1.0 * s, pole_mass=0.1 * s, half_length=1.0 * s)(x, u, ud)


@dataclass(frozen=True)
class ScaledArm:
    """The two-link arm with the forearm's mass and both inertias scaled by ``scale`` (data)."""

    scale: float = 1.0

    def __call__(self, x, u, ud):
        p, s = ARM2_PARAMS, self.scale
        return Arm2Dynamics(p._replace(m2=p.m2 * s, I1=p.I1 * s, I2=p.I2 * s))(x, u, ud)


for _cls in (ScaledCartPole, ScaledArm):
    jax.tree_util.register_dataclass(_cls, data_fields=["scale"], meta_fields=[])


def _scaled_quadrotor(scale):
    return planar_quadrotor().dynamics.__class__(mass=MASS * scale, inertia=INERTIA * scale)


@dataclass(frozen=True)
class ArmTarget:
    """The arm's moving target: joint angles on a circle of radius 0.3 rad at 0.5 Hz, with their rates."""

    centre: tuple = (math.pi / 3, math.pi / 2)
    radius: float = 0.3
    frequency: float = 0.5

    def __call__(self, t):
        w = 2 * math.pi * self.frequency
        q = jnp.asarray(self.centre) + self.radius * jnp.stack([jnp.sin(w * t), jnp.cos(w * t)])
        dq = self.radius * w * jnp.stack([jnp.cos(w * t), -jnp.sin(w * t)])
        return jnp.concatenate([q, dq])


class Scenario(NamedTuple):
    """One task: its model at a delay (seconds), a plant of scaled parameters, the ticks, the
    initial state's spread (sd per component), the reference, the fall test and the error map."""

    name: str
    model: Callable            # delay (s) -> Problem
    plant_dynamics: Callable   # scale -> dynamics (a pytree whose scale is data)
    delays: tuple              # seconds
    ticks: int
    spread: tuple              # [n] sd of the initial perturbation
    reference: Optional[Callable]
    failure: Optional[Callable]
    bound: float
    failure_from: int = 0      # the first tick at which ``failure`` counts (a swing-up may pass through it)
    max_error: float = math.inf    # a failure: the task-space error above this from tick failure_from on


def _cart_pole(delay):
    problem = cart_pole(delay=delay, dt=0.025, horizon=40, x0=(0.0, math.pi, 0.0, 0.0))
    return problem.replace(cost=QuadraticCost(P=np.diag([1.0, 20.0, 0.1, 0.5]), Q=1e-2 * np.eye(1),
                                              P_final=np.diag([10.0, 100.0, 10.0, 10.0]),
                                              x_target=np.array([0.0, math.pi, 0.0, 0.0])))


def _swing_up(delay):
    problem = cart_pole(delay=delay, dt=0.05, horizon=40)
    return problem.replace(cost=QuadraticCost(P=np.diag([0.5, 5.0, 0.05, 0.05]), Q=1e-2 * np.eye(1),
                                              P_final=np.diag([10.0, 100.0, 10.0, 10.0]),
                                              x_target=np.array([0.0, math.pi, 0.0, 0.0])))


def _arm(delay):
    # P / Q = 100 (rad^-2 / (N m)^-2): a closed loop of a few hertz. The benchmark's Q = 1e-4 with
    # these P makes a loop so fast that 20 ms of delay error destabilises every compensation.
    target = ArmTarget()
    problem = arm2(delay=delay, dt=0.01, horizon=30, x0=tuple(float(v) for v in target(0.0)))
    return problem.replace(cost=QuadraticCost(P=np.diag([100.0, 100.0, 1.0, 1.0]), Q=np.eye(2),
                                              P_final=np.diag([10.0, 10.0, 1.0, 1.0]),
                                              x_target=problem.cost.x_target))


def _quadrotor(delay):
    return planar_quadrotor(delay=delay, dt=0.01, horizon=50, x_target=(1.0, 0.5, 0.0, 0.0, 0.0, 0.0))


SCENARIOS = {
    "cart_pole": Scenario("cart_pole", _cart_pole, ScaledCartPole, (0.05, 0.1, 0.2), 120, (0.0, 0.1, 0.0, 0.1),
                          None, lambda x: jnp.abs(x[1] - jnp.pi) > jnp.pi / 4, 1e3),
    "cart_pole_swing_up": Scenario("cart_pole_swing_up", _swing_up, ScaledCartPole, (0.1, 0.2), 160,
                                   (0.0, 0.05, 0.0, 0.05), None, lambda x: jnp.abs(x[1] - jnp.pi) > 0.5, 1e3,
                                   failure_from=120),
    "arm2": Scenario("arm2", _arm, ScaledArm, (0.05, 0.1, 0.15), 200, (0.05, 0.05, 0.1, 0.1), ArmTarget(), None,
                     1e3, failure_from=50, max_error=0.1),
    "planar_quadrotor": Scenario("planar_quadrotor", _quadrotor, _scaled_quadrotor, (0.02, 0.05, 0.1), 200,
                                 (0.05, 0.05, 0.05, 0.05, 0.05, 0.1), None, lambda x: jnp.abs(x[2]) > jnp.pi / 2,
                                 1e3),
}


class Row(NamedTuple):
    """One cell of the study: a scenario at a model delay, a plant condition and a controller."""

    scenario: str
    delay_ms: Union[float, tuple]       # the model's delay: one value, or one per command channel
    condition: str
    strategy: str
    median_cost: float
    failure_rate: float
    tracking_rms: float         # in the task space's unit, over the trials that did not fail (NaN: none)
    unit: str


def _tracking_errors(problem, run: mpc.ClosedLoop) -> np.ndarray:
    """[N, T+1] the task-space distance to the reference at every tick."""
    task = problem.metadata.task
    err = np.asarray(task.map(jnp.asarray(run.x))) - np.asarray(task.map(jnp.asarray(run.reference)))[None]
    return np.sqrt(np.sum(err ** 2, axis=-1))


def _tracking_rms(problem, run: mpc.ClosedLoop) -> np.ndarray:
    """[N] RMS over the ticks of the task-space distance to the reference."""
    return np.sqrt(np.mean(_tracking_errors(problem, run) ** 2, axis=-1))


def run_scenario(scenario: Scenario, n_trials: int = 16, seed: int = 0, iterations: int = 1,
                 delays=None) -> list[Row]:
    """Every controller of `STRATEGIES` against every plant of `CONDITIONS`, at each
    model delay of the scenario (or ``delays``, seconds): the `Row` of each."""
    rows = []
    for delay in scenario.delays if delays is None else delays:
        model = scenario.model(delay)
        l = model.delay_steps
        frame = l + 2
        rng = np.random.default_rng(seed)
        x0 = np.asarray(model.x0) + rng.standard_normal((n_trials, model.n_states)) * np.asarray(scenario.spread)
        labels = [label for label, _, _ in CONDITIONS]
        plants = [model.replace(dynamics=scenario.plant_dynamics(scale)).replace(delay_steps=max(l + offset, 0),
                                                                                  delay_frame=frame)
                  for _, scale, offset in CONDITIONS]
        for label, compensation, history in STRATEGIES:
            ctrl = mpc.MPC(model, iterations=iterations, compensation=compensation, replay_history=history,
                           reference=scenario.reference)
            late = scenario.failure_from > 0
            # every plant in one compiled run: outputs [P, N, ...]
            runs = mpc.simulate(ctrl, plants, ticks=scenario.ticks, n_trials=n_trials, seed=seed, x0=x0,
                                failure=None if late else scenario.failure, bound=scenario.bound)
            for i, condition in enumerate(labels):
                run = mpc.ClosedLoop(*(a[i] for a in runs[:-1]), reference=runs.reference)
                failed = np.asarray(run.failed)
                if late and scenario.failure is not None:
                    tail = jax.vmap(jax.vmap(scenario.failure))(run.x[:, scenario.failure_from:])
                    failed = failed | np.asarray(jnp.any(tail, axis=1))
                with np.errstate(invalid="ignore"):
                    far = _tracking_errors(model, run)[:, scenario.failure_from:] > scenario.max_error
                failed = failed | np.any(far, axis=1)
                rms = _tracking_rms(model, run)
                rows.append(Row(scenario.name, milliseconds(model), condition, label,
                                float(np.median(np.asarray(run.cost))), float(np.mean(failed)),
                                float(np.mean(rms[~failed])) if np.any(~failed) else math.nan,
                                model.metadata.task.unit))
    return rows


def _cell(row: Row) -> str:
    scale = 100.0 if row.unit == "m" else 1.0
    unit = "cm" if row.unit == "m" else row.unit
    err = "-" if math.isnan(row.tracking_rms) else f"{scale * row.tracking_rms:.3g} {unit}"
    cost = f"{row.median_cost:.3g}" if math.isfinite(row.median_cost) else "inf"
    return f"{cost} / {100 * row.failure_rate:.0f} % / {err}"


def markdown(rows: list[Row], labels=None) -> str:
    """One markdown table per scenario: a row per (model delay, plant), a column per controller
    (``labels``, default all of `STRATEGIES`), each cell "median cost / failure rate / RMS
    tracking error"."""
    labels = [label for label, _, _ in STRATEGIES] if labels is None else list(labels)
    out = []
    for name in dict.fromkeys(r.scenario for r in rows):
        mine = [r for r in rows if r.scenario == name]
        out += [f"### {name}", "", "| delay | plant | " + " | ".join(labels) + " |",
                "|---|---|" + "---|" * len(labels)]
        for key in dict.fromkeys((r.delay_ms, r.condition) for r in mine):
            cells = {r.strategy: _cell(r) for r in mine if (r.delay_ms, r.condition) == key}
            out.append(f"| {ms_text(key[0])} | {key[1]} | " + " | ".join(cells.get(s, "") for s in labels) + " |")
        out.append("")
    return "\n".join(out)


@dataclass(frozen=True)
class InputGain:
    """A plant whose actuators deliver ``gain`` times the acting command: f(x, u, gain ud) (the
    model-agnostic mismatch of the command line's ``--mismatch``: a motor constant or a supply
    voltage off by a fraction). ``gain`` is data; ``fn`` the model's dynamics (static)."""

    fn: Callable
    gain: float = 1.0

    def __call__(self, x, u, ud):
        return self.fn(x, u, self.gain * ud)


jax.tree_util.register_dataclass(InputGain, data_fields=["gain"], meta_fields=["fn"])


def compare(model, plant, ticks: int, n_trials: int = 1, seed: int = 0, iterations: int = 1,
            strategies=STRATEGIES, x0=None, failure=None, bound: float = 1e6):
    """Each controller of ``strategies`` on ``plant``: ({label: ClosedLoop}, [Row]) with the same
    noise and initial states for all (common random numbers)."""
    runs, rows = {}, []
    for label, compensation, history in strategies:
        ctrl = mpc.MPC(model, iterations=iterations, compensation=compensation, replay_history=history)
        run = mpc.simulate(ctrl, plant, ticks=ticks, n_trials=n_trials, seed=seed, x0=x0, failure=failure,
                           bound=bound)
        runs[label] = run
        failed = np.asarray(run.failed)
        task = getattr(model.metadata, "task", None)
        rms = _tracking_rms(model, run) if task is not None else np.full(n_trials, math.nan)
        rows.append(Row(model.name, milliseconds(model), plant.name, label,
                        float(np.median(np.asarray(run.cost))), float(np.mean(failed)),
                        float(np.mean(rms[~failed])) if np.any(~failed) else math.nan,
                        task.unit if task is not None else ""))
    return runs, rows
