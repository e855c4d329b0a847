"""Figures of a perturbation study: the mean corrective responses against the sensory delay."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..experiments.delay_text import delay_text
from ..models.metadata import task_position, task_space
from ._common import command_unit, figure, speed_unit, suptitle

__all__ = ["plot_perturbation", "perturbation_figures"]


def _color(i: int, n: int):
    from matplotlib import colormaps
    return colormaps["viridis"](0.85 * i / max(n - 1, 1))


def plot_perturbation(results: Sequence):
    """Three panels, one colour per sensory delay: the mean task-space paths (solid: kicked,
    dashed: unperturbed), the mean task-point speed against time (cm/s for a task in metres), and
    the norm of the mean command response |E[u_perturbed - u]| against time (in the commands'
    unit), with the kick (grey line) and the first command that responds (dotted, per colour)."""
    first = results[0]
    fig = figure(figsize=(15, 4.6), layout="constrained")
    ax_path, ax_speed, ax_u = fig.subplots(1, 3)
    task = task_space(first.problem)
    factor, speed_label = speed_unit(task.unit if task is not None else "")
    for i, r in enumerate(results):
        color = _color(i, len(results))
        problem = r.problem
        dt = problem.dt
        label = f"sensory delay {1000 * r.sensory_delay:.0f} ms"
        kicked = task_position(problem, np.asarray(r.perturbed.x)).mean(axis=0)
        calm = task_position(problem, np.asarray(r.base.x)).mean(axis=0)
        ax_path.plot(calm[:, 0], calm[:, 1], color=color, lw=1.0, ls="--")
        ax_path.plot(kicked[:, 0], kicked[:, 1], color=color, lw=2.0, label=label)
        if i == 0:
            ax_path.scatter(*calm[r.pulse_step + 1], color="k", marker="x", zorder=5, label="kick")
        t = dt * np.arange(kicked.shape[0])
        speed = factor * np.linalg.norm(np.diff(kicked, axis=0), axis=1) / dt
        ax_speed.plot(t[1:], speed, color=color, lw=1.8, label=label)
        response = np.linalg.norm((np.asarray(r.perturbed.u) - np.asarray(r.base.u)).mean(axis=0), axis=1)
        ax_u.plot(t[:-1], response, color=color, lw=1.8, label=label)
        if r.latency_steps is not None:
            ax_u.axvline(r.latency_steps * dt, color=color, ls=":", lw=1.0)
    for ax in (ax_speed, ax_u):
        ax.axvline((first.pulse_step + 1) * first.problem.dt, color="0.5", lw=1.0)
        ax.set_xlabel("time [s]")
    unit = task.unit if task is not None else ""
    name = task.point if task is not None else "task point"
    ax_path.set_xlabel(f"{name} x [{unit}]")
    ax_path.set_ylabel(f"{name} y [{unit}]")
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_path.set_title("mean paths (dashed: unperturbed)")
    ax_speed.set_ylabel(f"{name} speed [{speed_label}]")
    ax_speed.set_title("mean speed, kicked trials")
    ax_u.set_ylabel(f"|mean command response| [{command_unit(first.problem)}]")
    ax_u.set_title("corrective command (dotted: first response)")
    ax_path.legend(fontsize=8)
    noise = "noisy" if first.problem.noise is not None else "deterministic"
    suptitle(fig, f"{first.problem.name}: correction of a kick at {1e3 * (first.pulse_step + 1) * first.problem.dt:g} "
                  f"ms against the sensory delay (input delay {delay_text(first.problem)}, {noise} plant, "
                  f"means over {np.shape(first.base.x)[0]} trials)")
    return fig


def perturbation_figures(results: Sequence) -> dict:
    """The study's figures by file name."""
    return {"perturbation.png": plot_perturbation(results)}
