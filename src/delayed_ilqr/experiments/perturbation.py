"""Perturbation experiments: a lateral kick of the hand during a reach, and the
mean corrective response against the sensory delay.

Per sensory delay l_s the model gets its default sensors (``sensory_delay=``), the controller and
the delayed filter are designed ([`solve`][delayed_ilqr.solve]), and the same trials are run twice
with the same seed (common motor and sensory noise): without and with the disturbance W, a change
``kick`` (m/s) of the task point's velocity at ``pulse_time``, perpendicular to the nominal movement
there (``simulate(..., disturbance=W)``). The mean of (perturbed - unperturbed) over the trials is
the corrective response: it starts with the command u_{kp+1+l_s} (the first that can see the kick,
``latency_steps``) and reaches the plant l_m steps later.

The kick is made in the velocity states x[2:4] of a model whose task map reads x[0:2] (the point
mass, both arms): dx[2:4] = pinv(d map / d x[0:2]) dv at the nominal (the arms' hand Jacobian).
"""
from __future__ import annotations

from typing import NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .. import Problem, Runs, Solution, simulate, solve
from ..models import REGISTRY
from ..models.metadata import default_u_init, task_space
from .progress import progress_bar

__all__ = ["PerturbationResult", "lateral_kick", "perturbation_study", "first_response", "PERTURB_MODELS"]


class PerturbationResult(NamedTuple):
    """One sensory delay of a perturbation study.

    Attributes:
        problem: the plant with its sensors; sensory_delay: l_s dt in seconds; solution: the
        observed solve; disturbance: W [K, n];
        pulse_step: kp (W_kp enters x_{kp+1}); base, perturbed: [`Runs`][delayed_ilqr.Runs] with
        the same seed; latency_steps: first k at which some trial's command differs (None if none);
        half_steps: first k at which the mean command response reaches half its peak (None if none).
    """

    problem: Problem
    sensory_delay: float
    solution: Solution
    disturbance: np.ndarray
    pulse_step: int
    base: Runs
    perturbed: Runs
    latency_steps: Optional[int]
    half_steps: Optional[int]

    @property
    def converged(self) -> bool:
        return bool(self.solution.converged)


def lateral_kick(problem: Problem, x_nominal, pulse_step: int, kick: float) -> np.ndarray:
    """W [K, n]: row ``pulse_step`` changes the task point's velocity by ``kick`` (m/s) perpendicular
    (counter-clockwise) to its nominal velocity there; zero elsewhere."""
    task = task_space(problem)
    if task is None or problem.n_states < 4:
        raise ValueError(f"a perturbation needs a model whose task map reads x[0:2] and whose velocities are "
                         f"x[2:4] (point_mass, arm2, arm2_muscle6); got {problem.name!r}")
    x = jnp.asarray(x_nominal[pulse_step])
    J = np.asarray(jax.jacfwd(task.map)(x))[:, :2]                   # d task / d x[0:2]
    velocity = J @ np.asarray(x[2:4])
    speed = float(np.linalg.norm(velocity))
    direction = np.array([-velocity[1], velocity[0]]) / speed if speed > 1e-9 else np.array([1.0, 0.0])
    W = np.zeros((problem.horizon, problem.n_states))
    W[pulse_step, 2:4] = np.linalg.pinv(J) @ (kick * direction)
    return W


def first_response(base: Runs, perturbed: Runs):
    """(first k at which some trial's command differs, first k at which |mean command response|
    reaches half its peak); None where there is none."""
    diff = np.asarray(perturbed.u) - np.asarray(base.u)
    changed = np.flatnonzero(np.any(diff != 0, axis=(0, 2)))
    mean = np.linalg.norm(diff.mean(axis=0), axis=1)
    peak = float(mean.max()) if mean.size else 0.0
    half = np.flatnonzero(mean >= 0.5 * peak) if peak > 0 else np.array([], int)
    return (int(changed[0]) if changed.size else None), (int(half[0]) if half.size else None)


def perturbation_study(model: str, sensory_delays: Sequence[float], delay: float, pulse_time: float, kick: float,
                       trials: int, seed: int, noise=True, model_kwargs=None,
                       progress: bool = False) -> list[PerturbationResult]:
    """The study of the module docstring for ``model`` (a registry name) with input delay ``delay``
    (s), at each sensory delay (s); ``noise`` is the factory's (True, False or a preset's name);
    ``progress``: a bar on stderr over the sensory delays (when it is a terminal)."""
    results = []
    with progress_bar(len(sensory_delays), "perturb", "sensory delay", progress) as bar:
        for ls in sensory_delays:
            problem = REGISTRY[model].factory(delay=delay, noise=noise, sensory_delay=ls, **(model_kwargs or {}))
            sol = solve(problem, u_init=default_u_init(problem))
            kp = int(round(pulse_time / problem.dt))
            if not 0 <= kp < problem.horizon:
                raise ValueError(f"pulse_time must lie within the movement, 0 <= t < "
                                 f"{problem.horizon * problem.dt:g} s; got {pulse_time!r}")
            W = lateral_kick(problem, np.asarray(sol.x), kp, kick)
            base = simulate(problem, sol.policy, trials, seed=seed)
            perturbed = simulate(problem, sol.policy, trials, seed=seed, disturbance=W)
            results.append(PerturbationResult(problem, float(ls), sol, W, kp, base, perturbed,
                                              *first_response(base, perturbed)))
            bar.update()
    return results


PERTURB_MODELS = ("point_mass", "arm2", "arm2_muscle6")
"""The models `lateral_kick` can perturb (a task map on x[0:2], velocities x[2:4]) and whose
factories accept ``sensory_delay``."""
