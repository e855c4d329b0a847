"""A mid-reach mechanical kick of the hand: when does the motor command first respond, and does the
hand still end on the target?

Published (what the experiment is compared with):

* Pruszynski & Scott 2012 (Exp Brain Res 218:341) and Scott 2016 (Trends Neurosci 39:512): after a
  mechanical perturbation of the arm the short-latency stretch reflex starts at 20-50 ms, the
  long-latency, goal-directed response at 50-100 ms, voluntary corrections at 100-150 ms and later.
* Nashed, Crevecoeur & Scott 2012 (J Neurophysiol 108:999): the corrections bring the hand to the
  target (final errors of perturbed reaches close to those of unperturbed ones).

The model: a reach (`reach_tasks.reach`) with a motor delay l_m and, optionally,
proprioception l_s late through the delayed Kalman filter. The same trials run twice on the same
noise (common random numbers), without and with a change ``kick`` (m/s) of the hand's velocity
perpendicular to the movement at ``pulse_time`` (`perturbation.lateral_kick`). The state
after the kick is x_{kp+1}; the first command that can see it is issued at kp + 1 + l_s and acts
on the muscles (or joints) l_m steps later: **the loop latency (l_s + l_m) dt is a hard causal
bound** on the first change of the applied command, measured from the kick.

Measured (`analyse`, rules in `responses`): the first change of the applied command
(any trial, exact with common noise), the onset of the mean command response (10 % of its peak),
the largest mean lateral displacement of the hand, the median final hand error kicked against
unperturbed, and, with sensors, how much of the kick the delayed filter believes: the fraction
of the mean hand displacement that the estimate holds one and two loop latencies after the kick
(`responses.believed_fraction`).

The controller (``controller``) is the model's re-planning controller (`replanning`, the default:
it re-solves the reach from its delayed filter's estimate at every tick, and its filter's
innovation gate believes an unexpected push) or the fixed time-varying feedback law of one solve
("fixed"). With the re-planning controller the fixed law's unperturbed trials run too, so that
the two unperturbed reaches can be compared (`replanning.reach_profile`).

``gate`` (a false-alarm probability per sample, default none) gives the re-planning controller's
filter an innovation gate: when a measurement surprises it, it believes a sudden push
(`replanning.controller`).

``disturbance_model`` (N m s^1/2, default none) designs the controller and its filter for external joint
torques of that density (`models.arm2_muscle6.with_disturbance_model`); the plant is unchanged.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

from .. import Options, Problem, Runs, Solution, solve
from ..models.arm2 import hand_position
from ..models.arm2_muscle6 import with_disturbance_model
from ..models.metadata import default_u_init
from ..statistics import SampleStats, sample_stats
from .engine import Trials, monte_carlo
from .perturbation import lateral_kick
from . import replanning
from .reach_tasks import MODEL_DEFAULT, reach, solver_options
from .responses import believed_fraction, first_change, onset

__all__ = ["PUBLISHED", "KickAnalysis", "KickResult", "analyse", "kick_experiment", "comparison"]

#: Published numbers, (finding, source, value) rows of the docs' table.
PUBLISHED = (
    ("short-latency (reflex) response", "Pruszynski & Scott 2012", "20-50 ms after the perturbation"),
    ("long-latency (goal-directed) response", "Pruszynski & Scott 2012; Scott 2016", "50-100 ms"),
    ("voluntary correction", "Pruszynski & Scott 2012; Scott 2016", "100-150 ms and later"),
    ("final error after the correction", "Nashed, Crevecoeur & Scott 2012",
     "the hand reaches the target (median final error within about twice the unperturbed)"),
)


class KickAnalysis(NamedTuple):
    """What `analyse` measures (times in seconds after the kick, lengths in metres).

    Attributes:
        first_change: the first change of the applied command (any trial); None if none.
        onset: the onset of the mean applied-command response (10 % of its peak); None if none.
        loop_latency: (l_s + l_m) dt, the causal bound on both.
        peak_displacement: the largest mean hand displacement from the unperturbed path.
        error_base, error_kicked: `SampleStats` of the final hand
            error without and with the kick.
        error_ratio: median kicked error over median unperturbed error.
        believed: (one, two) loop latencies after the kick, the fraction of the mean hand
            displacement that the filter's estimate holds (None with the state seen).
    """

    first_change: Optional[float]
    onset: Optional[float]
    loop_latency: float
    peak_displacement: float
    error_base: SampleStats
    error_kicked: SampleStats
    error_ratio: float
    believed: Optional[tuple] = None


class KickResult(NamedTuple):
    """The experiment: ``problem`` (the plant), ``solution`` (the reach's solve: the fixed law, the
    re-planning controller's first plan), ``disturbance`` W [K, n], ``pulse_step`` kp (W_kp enters
    x_{kp+1}), ``base`` and ``kicked`` `engine.Trials`, the `KickAnalysis`, the ``kick_speed`` (m/s),
    the ``controller`` (`replanning.CONTROLLERS`), the re-planning ticks whose solve failed
    (``solver_failures``, over both runs) and, with the re-planning controller, the fixed law's
    unperturbed trials on the same seed (``fixed_base``)."""

    problem: Problem
    solution: Solution
    disturbance: np.ndarray
    pulse_step: int
    base: Trials
    kicked: Trials
    analysis: KickAnalysis
    kick_speed: float = float("nan")
    controller: str = "fixed"
    solver_failures: int = 0
    fixed_base: Optional[Trials] = None


def analyse(base: Runs, kicked: Runs, pulse_step: int, dt: float, motor_steps: int, sensory_steps: int,
            base_errors, kicked_errors, hand_base, hand_kicked, estimate_base=None,
            estimate_kicked=None) -> KickAnalysis:
    """The `KickAnalysis` of runs on common noise.

    Args:
        base: the unperturbed `Runs` (u [N, K, d] the issued commands).
        kicked: the kicked `Runs`, on the same noise.
        pulse_step: kp (W_kp enters x_{kp+1}).
        dt: the step (s).
        motor_steps: l_m.
        sensory_steps: l_s (0 when the state is seen).
        base_errors: [N] final hand errors (m) without the kick.
        kicked_errors: [N] final hand errors (m) with it.
        hand_base: [N, K+1, 2] hand positions without the kick.
        hand_kicked: [N, K+1, 2] hand positions with it.
        estimate_base: [N, K, 2] the filter's estimates of the hand position at each step without
            the kick (None with the state seen).
        estimate_kicked: [N, K, 2] the same with the kick.
    """
    diff = np.asarray(kicked.u) - np.asarray(base.u)
    kick_state = pulse_step + 1                     # the first state the kick moved
    first = first_change(diff, start=0)
    on = onset(diff.mean(axis=0), start=0)
    after = lambda k: None if k is None else dt * (k + motor_steps - kick_state)      # noqa: E731  applied
    displacement = np.linalg.norm(np.mean(np.asarray(hand_kicked) - np.asarray(hand_base), axis=0), axis=1)
    eb, ek = sample_stats(base_errors), sample_stats(kicked_errors)
    believed = None
    if estimate_base is not None:
        loop = motor_steps + sensory_steps
        true = np.asarray(hand_kicked)[:, :-1] - np.asarray(hand_base)[:, :-1]
        seen = np.asarray(estimate_kicked) - np.asarray(estimate_base)
        believed = tuple(believed_fraction(true.mean(axis=0), seen.mean(axis=0), k)
                         for k in (kick_state + loop, kick_state + 2 * loop) if k < true.shape[1])
    return KickAnalysis(after(first), after(on), dt * (motor_steps + sensory_steps), float(displacement.max()),
                        eb, ek, float(ek.median / eb.median) if eb.median > 0 else float("inf"), believed)


def kick_experiment(arm: str = "arm2_muscle6", delay=MODEL_DEFAULT, sensory_delay=MODEL_DEFAULT,
                    kick: float = 0.15, pulse_time: Optional[float] = None, trials: int = 200, seed: int = 0,
                    target=None, final_time: float = 0.5, options: Optional[Options] = None,
                    disturbance_model: Optional[float] = None, controller: str = "replanning",
                    gate: Optional[float] = None) -> KickResult:
    """Runs the experiment of the module docstring.

    Args:
        arm: "arm2" or "arm2_muscle6" (`reach_tasks.reach`).
        delay: motor delay l_m dt (s); default the model's.
        sensory_delay: proprioceptive delay l_s dt (s), None (the state is seen, l_s = 0) or the
            model's default.
        kick: the change of the hand's speed (m/s), perpendicular (counter-clockwise) to the movement.
        pulse_time: when (s); default mid-movement.
        trials: Monte Carlo trials (each runs without and with the kick on the same noise).
        seed: their seed.
        target: [2] hand target (default 10 cm straight ahead).
        final_time: movement time (s).
        options: solver options.
        disturbance_model: the filter's expected external torques (N m s^1/2, `with_disturbance_model`;
            None: the plant's noise alone).
        controller: "replanning" (the model's, `replanning.controller`) or "fixed" (the feedback
            law of one solve).
        gate: the re-planning controller's innovation gate, its false-alarm probability per sample
            (`replanning.controller`); None: no gate.
    """
    if controller not in replanning.CONTROLLERS:
        raise ValueError(f"controller must be one of {replanning.CONTROLLERS}; got {controller!r}")
    problem = reach(arm, target, delay=delay, final_time=final_time, sensory_delay=sensory_delay)
    design = problem if disturbance_model is None else with_disturbance_model(problem, disturbance_model)
    sol = solve(design, u_init=default_u_init(design), options=solver_options(arm, options))
    kp = int(round((0.5 * final_time if pulse_time is None else pulse_time) / problem.dt))
    if not 0 <= kp < problem.horizon - 1:
        raise ValueError(f"pulse_time must lie within the movement, 0 <= t < {final_time - problem.dt:g} s; "
                         f"got {pulse_time!r}")
    W = lateral_kick(problem, np.asarray(sol.x), kp, kick)
    fixed_base, failures = monte_carlo(problem, sol.policy, trials, seed), 0
    if controller == "fixed":
        base, kicked = fixed_base, monte_carlo(problem, sol.policy, trials, seed, disturbance=W)
    else:
        ctrl = replanning.controller(problem, disturbance_model, gate)
        (base, f_base), (kicked, f_kicked) = (replanning.monte_carlo(ctrl, problem, sol.u, trials, seed, disturbance=w)
                                              for w in (None, W))
        failures = f_base + f_kicked
    ls = 0 if problem.observation is None else problem.observation.delay_steps
    hand = lambda x: None if x is None else np.asarray(hand_position(np.asarray(x)[..., :2]))    # noqa: E731
    analysis = analyse(base.runs, kicked.runs, kp, problem.dt, problem.delay_steps, ls, base.errors, kicked.errors,
                       hand(base.runs.x), hand(kicked.runs.x), hand(base.runs.x_hat), hand(kicked.runs.x_hat))
    return KickResult(problem, sol, W, kp, base, kicked, analysis, float(kick), controller, failures,
                      None if controller == "fixed" else fixed_base)


def _ms(v) -> str:
    return "none" if v is None else f"{1e3 * v:.0f} ms"


def comparison(result: KickResult) -> list[dict]:
    """Rows (finding, source, published, measured) of the docs' table."""
    a = result.analysis
    measured = (f"first change of the applied command {_ms(a.first_change)} after the kick "
                f"(loop latency {_ms(a.loop_latency)})",
                f"onset of the mean command response {_ms(a.onset)}",
                f"the model has one loop latency, {_ms(a.loop_latency)}",
                f"median final error {1e3 * a.error_kicked.median:.1f} mm kicked vs {1e3 * a.error_base.median:.1f} mm "
                f"unperturbed ({a.error_ratio:.2g}x); peak mean displacement {1e3 * a.peak_displacement:.1f} mm"
                + ("" if not a.believed else "; the filter believes " + " and ".join(
                    f"{100 * b:.0f} %" for b in a.believed) + " of it one and two loop latencies after the kick"))
    return [dict(finding=f, source=s, published=pub, measured=m) for (f, s, pub), m in zip(PUBLISHED, measured)]
