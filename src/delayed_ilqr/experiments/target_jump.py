"""Target jumps (Liu & Todorov 2007): the target is displaced at a given time before the end of the
reach; when does the correction start, and does the hand reach the new target?

Published (what the experiment is compared with), Liu & Todorov 2007 (J Neurosci 27:9354): the hand
reaches the displaced target when the jump comes early enough; when it comes late, the corrections
are stronger near the end of the movement but incomplete (timing-dependent feedback gains, as
optimal feedback control predicts). Visual corrections start 100-150 ms after the jump
(Pruszynski & Scott 2012; Scott 2016).

The model: the reach's target is part of the state (`reach_tasks.with_target_state`), so the
delayed feedback policy's gains on it are the optimal response to a displaced target, and a jump of
``jump`` metres perpendicular to the movement at step kp is a disturbance of those states. With the
model's default sensors the target is seen through them, as late as the arm (the library has one
sensory delay; human vision is slower, 100-150 ms), and the design expects targets to move
(`reach_tasks.TARGET_MOTION_DENSITY`) so that its delayed filter believes a seen jump; the plant's
target moves only by the jump. The loop latency is the sensory plus the motor delay (the motor delay
alone when the state is seen). The same trials run with and without each jump on the same noise.

Measured per jump time (`analyse`, rules in `responses`): the first change of the
applied command and the onset of the mean hand response (10 % of its peak lateral displacement),
both after the jump; the median final distance to the new target, the fraction of the jump the
hand made up, the peak speed of the mean correction (its vigour: Liu & Todorov found later
jumps corrected more vigorously) and, with sensors, how much of the hand's correction the delayed
filter believes at the last step (`responses.believed_fraction`).

The controller (``controller``) is the model's re-planning controller (`replanning`, the default:
it re-solves the reach from its delayed filter's estimate, the target's included, at every tick)
or the fixed time-varying feedback law of one solve ("fixed").

``disturbance_model`` (N m s^1/2, default none) designs the controller and its filter for external
joint torques of that density (`models.arm2_muscle6.with_disturbance_model`); the plant is unchanged.
"""
from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import numpy as np

from .. import Options, Problem, Solution, solve
from ..models.arm2 import hand_position
from ..models.arm2_muscle6 import with_disturbance_model
from ..models.metadata import default_u_init
from ..statistics import SampleStats, sample_stats
from .engine import monte_carlo
from . import replanning
from .reach_tasks import (MODEL_DEFAULT, TARGET_MOTION_DENSITY, movement_direction, reach, solver_options,
                          with_target_state)
from .responses import believed_fraction, first_change, onset

__all__ = ["PUBLISHED", "JumpAnalysis", "JumpResult", "analyse", "target_jump_experiment", "comparison"]

PUBLISHED = (
    ("correction of an early jump", "Liu & Todorov 2007", "the hand reaches the displaced target"),
    ("correction of a late jump", "Liu & Todorov 2007", "stronger corrections near the end, incomplete"),
    ("onset of the visual correction", "Pruszynski & Scott 2012; Scott 2016", "100-150 ms after the jump"),
)


class JumpAnalysis(NamedTuple):
    """One jump time (seconds after the jump; metres).

    Attributes:
        time_before_end: when the jump came, seconds before the end of the movement.
        first_change: first change of the applied command (any trial), None if none.
        onset: onset of the mean hand displacement from the unjumped reach (10 % of its peak).
        loop_latency: the motor delay, the causal bound on ``first_change``.
        error_new: SampleStats of the final distance to the new target.
        corrected: the mean final displacement along the jump over the jump size (1: all of it).
        peak_speed: the peak speed (m/s) of the mean correction, the hand's velocity along the jump
            relative to the unjumped reach (the vigour of the correction).
        believed: at the last step, the fraction of the mean hand displacement that the filter's
            estimate holds (None with the state seen).
    """

    time_before_end: float
    first_change: Optional[float]
    onset: Optional[float]
    loop_latency: float
    error_new: SampleStats
    corrected: float
    peak_speed: float
    believed: Optional[float] = None


class JumpResult(NamedTuple):
    """The experiment: the plant with its target states, its solution (the fixed law, the
    re-planning controller's first plan), the jump vector [2], the unjumped trials (x [N, K+1, n])
    and per jump time the jumped trials' states and the analysis; ``base_cost`` [N] the unjumped
    trials' costs, the ``controller`` (`replanning.CONTROLLERS`) and the re-planning ticks whose
    solve failed (``solver_failures``, over every run)."""

    problem: Problem
    solution: Solution
    jump: np.ndarray
    base_x: np.ndarray
    jumped_x: list
    analyses: list
    base_cost: Optional[np.ndarray] = None
    controller: str = "fixed"
    solver_failures: int = 0


def analyse(base_u, jumped_u, hand_base, hand_jumped, jump, new_target, jump_step: int, dt: float,
            motor_steps: int, time_before_end: float, sensory_steps: int = 0, estimate_base=None,
            estimate_jumped=None) -> JumpAnalysis:
    """The `JumpAnalysis` of runs on common noise: commands ``base_u``, ``jumped_u`` [N, K, d]
    (issued), hand positions ``hand_base``, ``hand_jumped`` [N, K+1, 2], the ``jump`` vector [2], the
    ``new_target`` [2]; the jump enters x_{jump_step+1}; ``motor_steps`` l_m, ``sensory_steps`` l_s
    (0: the state is seen); ``estimate_base``, ``estimate_jumped`` [N, K, 2] the filter's
    estimates of the hand position (None with the state seen)."""
    start = jump_step + 1
    first = first_change(np.asarray(jumped_u) - np.asarray(base_u))
    shift = np.asarray(hand_jumped) - np.asarray(hand_base)                  # [N, K+1, 2]
    unit = np.asarray(jump) / np.linalg.norm(jump)
    along = shift.mean(axis=0) @ unit
    on = onset(along, start=start)
    final = np.asarray(hand_jumped)[:, -1]
    believed = None
    if estimate_base is not None:
        seen = (np.asarray(estimate_jumped) - np.asarray(estimate_base)).mean(axis=0)
        believed = believed_fraction(shift.mean(axis=0)[:-1], seen, seen.shape[0] - 1)
    return JumpAnalysis(float(time_before_end), None if first is None else dt * (first + motor_steps - start),
                        None if on is None else dt * (on - start), dt * (motor_steps + sensory_steps),
                        sample_stats(np.linalg.norm(final - new_target, axis=1)),
                        float(along[-1] / np.linalg.norm(jump)), float(np.abs(np.diff(along)).max() / dt), believed)


def target_jump_experiment(arm: str = "arm2_muscle6", delay=MODEL_DEFAULT, sensory_delay=MODEL_DEFAULT,
                           jump: float = 0.02, times_before_end: Sequence[float] = (0.1, 0.2, 0.3, 0.4),
                           trials: int = 100, seed: int = 0, target=None, final_time: float = 0.6,
                           options: Optional[Options] = None, disturbance_model: Optional[float] = None,
                           controller: str = "replanning") -> JumpResult:
    """Runs the experiment of the module docstring.

    Args:
        arm: "arm2" or "arm2_muscle6".
        delay: the motor delay (s); default the model's.
        sensory_delay: the sensory delay (s), None (the state and the target are seen at once) or the
            model's default.
        jump: the target displacement (m), perpendicular (counter-clockwise) to the movement.
        times_before_end: when the target jumps, seconds before the end of the movement.
        trials: Monte Carlo trials per condition (same noise in each).
        seed: their seed.
        target: [2] the first target (default 10 cm ahead).
        final_time: the movement time (s).
        options: solver options (default `reach_tasks.solver_options`).
        disturbance_model: the filter's expected external torques (N m s^1/2, `with_disturbance_model`;
            None: the plant's noise alone).
        controller: "replanning" (the model's, `replanning.controller`) or "fixed" (the feedback
            law of one solve).
    """
    if controller not in replanning.CONTROLLERS:
        raise ValueError(f"controller must be one of {replanning.CONTROLLERS}; got {controller!r}")
    base = reach(arm, target, delay=delay, final_time=final_time, sensory_delay=sensory_delay)
    design = with_target_state(base if disturbance_model is None else with_disturbance_model(base, disturbance_model),
                               TARGET_MOTION_DENSITY)
    problem = with_target_state(base)
    sol = solve(design, u_init=default_u_init(design), options=solver_options(arm, options))
    d = movement_direction(base)
    vec = jump * np.array([-d[1], d[0]])
    new_target = np.asarray(base.cost.params["target"]) + vec
    steps = [problem.horizon - int(round(t / problem.dt)) - 1 for t in times_before_end]
    if any(not 0 <= kp < problem.horizon - 1 for kp in steps):
        raise ValueError(f"times_before_end must lie within the movement, 0 < t < {final_time:g} s; "
                         f"got {tuple(times_before_end)!r}")
    failures = 0
    if controller == "fixed":
        trials_of = lambda W: monte_carlo(problem, sol.policy, trials, seed, disturbance=W)      # noqa: E731
    else:
        ctrl = replanning.controller(with_target_state(base, TARGET_MOTION_DENSITY), disturbance_model)

        def trials_of(W):
            nonlocal failures
            out, failed = replanning.monte_carlo(ctrl, problem, sol.u, trials, seed, disturbance=W)
            failures += failed
            return out
    calm = trials_of(None)
    hand = lambda x: None if x is None else np.asarray(hand_position(np.asarray(x)[..., :2]))    # noqa: E731
    ls = 0 if problem.observation is None else problem.observation.delay_steps
    jumped_x, analyses = [], []
    for t, kp in zip(times_before_end, steps):
        W = np.zeros((problem.horizon, problem.n_states))
        W[kp, -2:] = vec
        runs = trials_of(W).runs
        jumped_x.append(np.asarray(runs.x))
        analyses.append(analyse(calm.runs.u, runs.u, hand(calm.runs.x), hand(runs.x), vec, new_target, kp,
                                problem.dt, problem.delay_steps, float(t), ls, hand(calm.runs.x_hat), hand(runs.x_hat)))
    return JumpResult(problem, sol, vec, np.asarray(calm.runs.x), jumped_x, analyses, np.asarray(calm.runs.cost),
                      controller, failures)


def comparison(result: JumpResult) -> list[dict]:
    """Rows (finding, source, published, measured) of the docs' table: one per jump time, then the
    onset."""
    rows = []
    for a in result.analyses:
        rows.append(dict(finding=f"jump {1e3 * a.time_before_end:.0f} ms before the end", source="Liu & Todorov 2007",
                         published="reaches the new target if early enough; incomplete if late",
                         measured=f"median final distance to the new target {1e3 * a.error_new.median:.1f} mm, "
                                  f"{100 * a.corrected:.0f} % of the jump made up"
                                  + ("" if a.believed is None else
                                     f"; the filter believes {100 * a.believed:.0f} % of the hand's correction")))
    first = next((a for a in result.analyses if a.first_change is not None), None)
    rows.append(dict(finding=PUBLISHED[2][0], source=PUBLISHED[2][1], published=PUBLISHED[2][2],
                     measured="no response" if first is None else
                     f"first command change {1e3 * first.first_change:.0f} ms, hand onset "
                     f"{'none' if first.onset is None else f'{1e3 * first.onset:.0f} ms'} "
                     f"(loop latency {1e3 * first.loop_latency:.0f} ms)"))
    return rows
