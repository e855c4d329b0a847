"""Center-out reaching with the six-muscle arm and delayed excitations (Li & Todorov 2004).

For each delay and design: the reaches to ``n_targets`` hand targets on a circle around the start
hand position are solved in one compiled, vectorised call (``jax.vmap`` of
[`solve`][delayed_ilqr.solve] over the targets, which are cost parameters,
`engine.timed_batched_solve`), then each target's delayed feedback policy runs ``n_trials``
times on the noisy plant (signal-dependent excitation noise). The arm is Li & Todorov's as
published (``arm2_muscle6(**LI_TODOROV)``: no tonic rest, effort on the excitations, excitation
noise only), whose delay study this is; the center-out reaches of the model's human preset are
measured in ``docs/results/center_out_human.md``.

Three designs of the same plant (`designs`; all three by default, the first two with
sensors):

* ``"noise-aware"`` (iLQG): designed on the noisy arm itself, so the signal-dependent
  noise enters the backward pass (Todorov & Li 2005): the nominal trades accuracy for smaller,
  less noisy excitations and the feedback is the LQG optimum for the multiplicative noise.
* ``"deterministic"`` (iLQR): designed on the noise-free arm, then run in the noise.
* ``"statistical"``: the noise-aware design's nominal and feedforward with its feedback
  re-designed by statistical linearisation around the closed loop's predicted distribution
  ([`statistical_feedback`][delayed_ilqr.statistical.statistical_feedback] with its defaults, vmapped over the
  targets; ``docs/results/noise_calibration.md`` §5.5), for the delays where the noise-aware
  design's trials leave its linearisation. Full-state feedback only (not with
  ``sensory_delay``). Its solver statistics are the noise-aware solve's (the same solve, done
  once when both designs run); its predicted cost is the Gaussian closure's E[J] of the SL policy
  (the solver has no LQG prediction for SL gains).

Per delay and design the study reports iterations, solve time, the final hand error of the
nominal, the predicted expected cost (J(0) of the last LQG) against the Monte Carlo mean, and the
endpoint spread (mean hand error and the 2-sigma ellipse of the final hand positions); the hand is
the task space of the model's metadata.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple, Optional, Sequence

import jax
import numpy as np

from .. import Options, Policy, Problem, Solution, Status
from ..statistics import SampleStats, divergence_bound, diverged_trials, sample_stats
from ..models.arm2 import hand_velocity
from ..models.arm2_muscle6 import LI_TODOROV, SIGMA_U, arm2_muscle6, center_out_targets
from ..models.metadata import task_position, task_target
from . import designs
from ..statistical import statistical_feedback
from .delay_text import delay_text
from .engine import Timed, monte_carlo, stack, take, timed_batched_solve
from .progress import progress_bar

__all__ = ["TargetResult", "DelayResult", "ReachShape", "center_out", "reach_shape", "DEFAULT_OPTIONS", "DESIGNS",
           "SENSING_DESIGNS", "designs_for",
           "SIGMA_U", "PEAK_PROMINENCE"]

#: Muscle reaches take 30-200 iterations (the excitations saturate at 0 and 1 on long stretches,
#: where the box-QP's active set changes slowly); 300 leaves a margin.
DEFAULT_OPTIONS = Options(max_iterations=300)

#: Every design the study offers, by name (module docstring); its default with full-state feedback.
DESIGNS = ("noise-aware", "deterministic", "statistical")

#: The default with ``sensory_delay`` (the statistical design needs full-state feedback).
SENSING_DESIGNS = ("noise-aware", "deterministic")

#: Designs that re-design the feedback of another design's solve: name -> the design solved.
_SOLVED_AS = {"statistical": "noise-aware"}


@dataclass(frozen=True)
class TargetResult:
    """One reach of the study (lengths in metres).

    Attributes:
        target: [2] hand target.
        status: the solver's [`Status`][delayed_ilqr.Status] name; iterations: its iteration count.
        cost: eq. (2) of the noise-free nominal.
        predicted_cost: the design's expected cost J(0) of its last LQG (for the deterministic
            design, the noise-free cost: it does not know the noise; for the statistical design,
            the Gaussian closure's E[J] of its policy, ``StatisticalFeedback.predicted_cost``).
        hand_error: distance of the nominal's final hand position from the target.
        hand_speed: the nominal's final hand speed (m/s).
        endpoints: [N, 2] final hand positions of the noisy trials.
        mc_error: [N] their distances from the target.
        mc_cost: [N] eq. (2) of each noisy trial.
        diverged: [N] bool, the trials that diverged ([`diverged_trials`][delayed_ilqr.statistics.diverged_trials]
            with the plant's [`divergence_bound`][delayed_ilqr.statistics.divergence_bound]); every statistic
            below leaves them out of its mean and spread.
        sl_change: the statistical design's last relative feedback change
            (``StatisticalFeedback.change``, near 0 at a fixed point); None for the other designs.
    """

    target: np.ndarray
    status: str
    iterations: int
    cost: float
    predicted_cost: float
    hand_error: float
    hand_speed: float
    endpoints: np.ndarray
    mc_error: np.ndarray
    mc_cost: np.ndarray
    diverged: np.ndarray
    sl_change: Optional[float] = None

    @property
    def converged(self) -> bool:
        return Status[self.status].converged

    @property
    def cost_stats(self) -> SampleStats:
        """Statistics of the Monte Carlo cost (mean over the trials that did not diverge)."""
        return sample_stats(self.mc_cost, self.diverged)

    @property
    def error_stats(self) -> SampleStats:
        """Statistics of the hand error over the same trials."""
        return sample_stats(self.mc_error, self.diverged)

    @property
    def endpoint_cov(self) -> np.ndarray:
        """[2, 2] covariance of the final hand positions of the trials that did not diverge."""
        return np.cov(self.endpoints[~self.diverged], rowvar=False)

    @property
    def spread(self) -> float:
        """Endpoint spread: sqrt of the largest eigenvalue of the covariance (1-sigma major axis)."""
        return float(np.sqrt(np.max(np.linalg.eigvalsh(self.endpoint_cov))))


@dataclass(frozen=True)
class DelayResult:
    """All reaches at one delay with one design.

    Attributes:
        delay: tau in seconds; delay_steps: l; dt: the time step (s).
        design: one of `DESIGNS` (see the module docstring).
        solve_time: seconds of the compiled batched solve of all targets (second call); for the
            statistical design, the noise-aware solve's plus the batched SL re-design's.
        first_call: seconds of the first call (compilation included), summed likewise.
        targets: one [`TargetResult`][delayed_ilqr.experiments.center_out.TargetResult] per target.
        solutions: the batched [`Solution`][delayed_ilqr.Solution] (leading axis: target).
        runs: the Monte Carlo [`Runs`][delayed_ilqr.Runs] per target.
        plants: the plant of each target (its metadata maps states to hand positions).
    """

    delay: float
    delay_steps: int
    dt: float
    design: str
    solve_time: float
    first_call: float
    targets: list
    solutions: Solution
    runs: list
    plants: list = field(repr=False, compare=False)

    def policy(self, j: int) -> Policy:
        """The delayed feedback policy of target j."""
        return take(self.solutions.policy, j)


#: A speed maximum counts as a peak of [`reach_shape`][delayed_ilqr.experiments.center_out.reach_shape] when it rises this fraction of the
#: peak speed above the lower of the two minima around it (SciPy's prominence): ripples smaller
#: than 2 % of the peak are not peaks.
PEAK_PROMINENCE = 0.02


class ReachShape(NamedTuple):
    """The shape of one reach, the two properties human reaches are known for (Morasso 1981;
    Flash & Hogan 1985): straight hand paths and single-peaked, bell-shaped speed.

    Attributes:
        speed: [K] hand speed (m/s), the hand displacement per step over dt (as plotted).
        peaks: number of speed peaks (maxima of prominence `PEAK_PROMINENCE` x the peak).
        deviation: largest distance of the hand from the straight start-target line, over the
            start-target distance (0 for a straight path).
        peak_to_mean: peak speed over mean speed; 15/8 for the minimum-jerk profile of Flash &
            Hogan 1985 (bell-shaped), 1 for constant speed (flat-topped).
    """

    speed: np.ndarray
    peaks: int
    deviation: float
    peak_to_mean: float


def reach_shape(plant: Problem, x) -> ReachShape:
    """Path deviation and speed peaks of the states x [K+1, n] of a reach of ``plant``, whose
    metadata names the hand (task) space and its target (the start is x[0]'s hand position)."""
    from scipy.signal import find_peaks  # lazy: the study itself does not need SciPy

    target = task_target(plant)
    if target is None or np.shape(target) != (2,):
        raise ValueError("plant must name a planar task space with a target in its metadata (as arm2_muscle6 "
                         f"does); got {getattr(plant, 'name', type(plant).__name__)!r} with target {target!r}")
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 3 or x.shape[1] != plant.n_states:
        raise ValueError(f"x must be states [K+1, {plant.n_states}] of one reach, K >= 2; got shape {x.shape}")
    hand = np.asarray(task_position(plant, x))
    speed = np.linalg.norm(np.diff(hand, axis=0), axis=1) / plant.dt
    chord, rel = target - hand[0], hand - hand[0]
    deviation = np.max(np.abs(rel[:, 0] * chord[1] - rel[:, 1] * chord[0])) / (chord @ chord)
    # zeros around the profile, so that a maximum at either end is a peak too
    peaks, _ = find_peaks(np.concatenate([[0.0], speed, [0.0]]), prominence=PEAK_PROMINENCE * speed.max())
    return ReachShape(speed=speed, peaks=len(peaks), deviation=float(deviation),
                      peak_to_mean=float(speed.max() / speed.mean()))


def designs_for(names: Optional[Sequence[str]], sensory_delay: Optional[float]) -> tuple:
    """The designs [`center_out`][delayed_ilqr.experiments.center_out.center_out] runs: ``names`` (a non-empty selection of `DESIGNS`),
    in their order, each once, checked against ``sensory_delay``; for None the default,
    `DESIGNS` with the state seen and `SENSING_DESIGNS` with a ``sensory_delay``.
    ``ValueError`` names the rule broken."""
    if names is None:
        return DESIGNS if sensory_delay is None else SENSING_DESIGNS
    names = tuple(dict.fromkeys(names))           # a design named twice runs once
    if not names or any(d not in DESIGNS for d in names):
        raise ValueError(f"designs must be a non-empty selection of {DESIGNS}; got {names!r}")
    if sensory_delay is not None and "statistical" in names:
        # statistical_feedback re-designs full-state feedback gains; it refuses an observation
        raise ValueError("the statistical design needs full-state feedback: run it without sensory_delay "
                         f"(got sensory_delay={sensory_delay!r})")
    return names


def center_out(delays: Sequence[float] = (0.0, 0.05, 0.1), n_targets: int = 8, radius: float = 0.1,
               n_trials: int = 200, seed: int = 0, options: Optional[Options] = None,
               geometry: str = "angle_dependent", sigma_u: float = SIGMA_U,
               designs: Optional[Sequence[str]] = None, sensory_delay: Optional[float] = None,
               progress: bool = False) -> list[DelayResult]:
    """Runs the center-out study; one [`DelayResult`][delayed_ilqr.experiments.center_out.DelayResult] per delay and design (delay-major).

    Args:
        delays: input delays in seconds (whole multiples of the 10 ms step).
        n_targets: targets on the circle (8 in the classic task), the first one to the right.
        radius: circle radius in metres (start hand position at the centre).
        n_trials: noisy trials per target; seed: their seed (target j uses seed + j, so every
            design meets the same noise).
        options: solver options (default `DEFAULT_OPTIONS`).
        geometry: muscle moment arms, "angle_dependent" (default) or "constant".
        sigma_u: excitation noise of the plant (the model's default 0.01, calibrated to human force
            variability, ``docs/models.md`` §4.5); the noise-aware design
            is made for it.
        designs: a non-empty selection of `DESIGNS` (default: all of them, or
            `SENSING_DESIGNS` with a ``sensory_delay``).
        sensory_delay: None (default): the controllers see the state. A delay in seconds (0
            allowed): they see the arm's proprioception that late through its sensory noise
            (``arm2_muscle6``'s ``sensory_delay``; each design gets the delayed Kalman filter of
            its own problem, the noise-aware one with Todorov's alternation), the sensorimotor
            loop whose noise and delay make human endpoint scatter (``docs/results/noise_calibration.md``).
        progress: a progress bar on stderr over the solves and the Monte Carlo runs (when stderr is
            a terminal, `progress`).

    Raises:
        ValueError: an unknown design, or ``"statistical"`` with a ``sensory_delay``.
    """
    options = DEFAULT_OPTIONS if options is None else options
    if not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    names = designs_for(designs, sensory_delay)
    targets = center_out_targets(n_targets, radius)
    results = []
    # per delay and design: its solve (or re-design), then one Monte Carlo run per target
    with progress_bar(len(delays) * len(names) * (1 + len(targets)), "center-out", "step", progress) as bar:
        for delay in delays:
            plants = [arm2_muscle6(**dict(LI_TODOROV, sensory_delay=sensory_delay), delay=delay, target=tuple(t),
                                   noise=True, geometry=geometry, sigma_u=sigma_u) for t in targets]
            solved = {}                 # design solved -> Timed, shared by the designs built on it
            for name in names:
                bar.set_postfix_str(f"{delay_text(delay)}, {name}")
                results.append(_reaches(float(delay), name, plants, options, n_trials, seed, solved, bar))
    return results


# module level, so that a second study with the same shapes reuses the compiled filter design
_filter_on_plants = jax.jit(jax.vmap(designs.filter_on_plant))

# statistical_feedback of every target's plant and policy (leading axis: target)
_statistical_on_plants = jax.jit(jax.vmap(statistical_feedback, in_axes=(0, 0, None)))



def _solve(name: str, plants: list[Problem], options: Options) -> Timed:
    """The batched solve of design ``name`` for all plants (with the plant's filter if it has one)."""
    problems = [designs.design(plant, name, options)[0] for plant in plants]
    timed = timed_batched_solve(problems, designs.design(plants[0], name, options)[1])
    if plants[0].observation is not None and designs.REGISTRY[name].filter_on_plant:
        timed = timed._replace(solution=_filter_on_plants(stack(plants), timed.solution))
    return timed


def _statistical(plants: list[Problem], base: Timed, options: Options):
    """The SL re-design of the batched noise-aware solution ``base`` on every plant: (solution with
    the SL policies and the closure's E[J] as expected_cost, [targets] SL change, seconds, first-call
    seconds); the times include ``base``'s.

    Compiled ahead and run once (seconds: the run; first: compilation and run), not called twice
    as the solves are: an SL run costs several times the solve it starts from (the README's
    center-out table gives both).
    """
    args = (stack(plants), base.solution.policy, options)
    start = time.perf_counter()
    compiled = _statistical_on_plants.lower(*args).compile()
    compile_seconds = time.perf_counter() - start
    start = time.perf_counter()
    sl = jax.block_until_ready(compiled(*args))
    seconds = time.perf_counter() - start
    first = compile_seconds + seconds
    sols = base.solution._replace(policy=sl.policy, expected_cost=sl.predicted_cost)
    return sols, np.asarray(sl.change), base.seconds + seconds, base.first_seconds + first


def _reaches(delay: float, name: str, plants: list[Problem], options: Options, n_trials: int,
             seed: int, solved: dict, bar) -> DelayResult:
    """One delay and design: the batched solve of all targets (taken from ``solved`` when another
    design of this delay made it, stored there otherwise), for the statistical design its batched
    SL re-design, then the Monte Carlo of each policy; ``bar`` counts the solve and each run."""
    base = _SOLVED_AS.get(name, name)
    if base not in solved:
        solved[base] = _solve(base, plants, options)
    sols, solve_time, first = solved[base]
    sl_change = None
    if name == "statistical":
        sols, sl_change, solve_time, first = _statistical(plants, solved[base], options)
    bar.update()
    per_target, runs = [], []
    for j, plant in enumerate(plants):
        trials = monte_carlo(plant, take(sols.policy, j), n_trials, seed + j)
        target = task_target(plant)
        nominal_end = task_position(plant, sols.x[j, -1])
        mc_cost = np.asarray(trials.runs.cost)
        per_target.append(TargetResult(
            target=target, status=Status(int(sols.status[j])).name, iterations=int(sols.iterations[j]),
            cost=float(sols.cost[j]), predicted_cost=float(sols.expected_cost[j]),
            hand_error=float(np.linalg.norm(nominal_end - target)),
            hand_speed=float(np.linalg.norm(hand_velocity(sols.x[j, -1, :2], sols.x[j, -1, 2:4]))), endpoints=trials.endpoints,
            mc_error=trials.errors, mc_cost=mc_cost,
            diverged=diverged_trials(mc_cost, divergence_bound(plant)),
            sl_change=None if sl_change is None else float(sl_change[j])))
        runs.append(trials.runs)
        bar.update()
    return DelayResult(delay=delay, delay_steps=plants[0].delay_steps, dt=plants[0].dt, design=name,
                       solve_time=solve_time, first_call=first, targets=per_target, solutions=sols, runs=runs,
                       plants=plants)
