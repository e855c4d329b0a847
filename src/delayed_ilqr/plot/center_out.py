"""Figures of the center-out study: hand paths with endpoint ellipses, and the excitation patterns."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..models.metadata import task_position, task_space
from ._common import ellipse, figure

__all__ = ["plot_center_out", "plot_excitations", "center_out_figures"]


def _reaches_panel(ax, r, n_paths: int, colors):
    """One delay and design: per target its nominal path (thick), ``n_paths`` trials (thin), the
    target (star) and the 2-sigma ellipse of the trials' final positions; the start is the black dot."""
    plant = r.plants[0]
    nominal = task_position(plant, r.solutions.x)                                  # [targets, K+1, 2]
    for j, t in enumerate(r.targets):
        color = colors[j]
        for path in task_position(plant, r.runs[j].x[:n_paths]):
            ax.plot(path[:, 0], path[:, 1], color=color, lw=0.5, alpha=0.5)
        ax.plot(nominal[j, :, 0], nominal[j, :, 1], color=color, lw=2.0)
        ax.scatter([t.target[0]], [t.target[1]], marker="*", s=120, color=color, edgecolor="k", zorder=6)
        ellipse(ax, t.endpoints[~t.diverged & np.all(np.isfinite(t.endpoints), axis=1)], color)
    start = nominal[0, 0]
    ax.scatter([start[0]], [start[1]], marker="o", s=50, color="k", zorder=7, label="start")
    radius = float(np.max(np.linalg.norm(np.stack([t.target for t in r.targets]) - start, axis=1)))
    half = 1.8 * radius
    ax.set_xlim(start[0] - half, start[0] + half)
    ax.set_ylim(start[1] - half, start[1] + half)
    ax.set_aspect("equal")
    task = task_space(plant)
    ax.set_xlabel(f"{task.point} x [{task.unit}]")
    ax.set_ylabel(f"{task.point} y [{task.unit}]")
    converged = sum(t.converged for t in r.targets)
    ax.set_title(f"{r.design}, delay {1e3 * r.delay:g} ms ({converged}/{len(r.targets)} converged)")
    ax.grid(alpha=0.3)


def plot_center_out(results: Sequence, n_paths: int = 5):
    """Center-out reaches of the six-muscle arm: hand paths and endpoint ellipses, one panel per
    delay (columns) and design (rows).

    Args:
        results: :class:`~delayed_ilqr.experiments.center_out.DelayResult` objects.
        n_paths: Monte Carlo hand paths drawn per target.

    Returns:
        A Figure: per delay and design, each target's nominal hand path (thick), ``n_paths`` noisy
        trials (thin), the target (star) and the 2-sigma covariance ellipse of the trials' final
        hand positions; the start hand position is the black dot.
    """
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one DelayResult; got none")
    designs = list(dict.fromkeys(r.design for r in results))
    delays = list(dict.fromkeys(r.delay for r in results))
    fig = figure(figsize=(4.6 * len(delays), 4.8 * len(designs)), layout="constrained")
    grid = fig.subplots(len(designs), len(delays), squeeze=False)
    from matplotlib import colormaps
    colors = [colormaps["tab10"](j % 10) for j in range(len(results[0].targets))]
    for r in results:
        _reaches_panel(grid[designs.index(r.design), delays.index(r.delay)], r, n_paths, colors)
    fig.suptitle(f"six-muscle arm, center-out: nominal paths, {n_paths} noisy trials per target, "
                 f"2-sigma endpoint ellipses (N = {results[0].runs[0].x.shape[0]})")
    return fig


def plot_excitations(result):
    """Nominal muscle excitations u_k of every target at one delay and design (one panel per target).

    Args:
        result: a :class:`~delayed_ilqr.experiments.center_out.DelayResult`.

    Returns:
        A Figure with one panel per target (2 rows), the six excitations against time (the command
        sent at t reaches the muscles at t + delay).
    """
    from ..models.muscle import MUSCLES
    n = len(result.targets)
    cols = (n + 1) // 2
    fig = figure(figsize=(3.2 * cols, 5.6), layout="constrained")
    axes = fig.subplots(2, cols, squeeze=False, sharex=True, sharey=True).ravel()
    u = np.asarray(result.solutions.u)                                     # [targets, K, 6]
    t_axis = result.dt * np.arange(u.shape[1])
    for j, (ax, target) in enumerate(zip(axes, result.targets)):
        for m, name in enumerate(MUSCLES):
            ax.step(t_axis, u[j, :, m], where="post", lw=1.2, label=name)
        ax.set_title(f"target {j + 1} ({1e3 * target.hand_error:.2f} mm)", fontsize=9)
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    for ax in axes[n:]:
        ax.set_visible(False)
    axes[0].legend(fontsize=7, loc="upper right")
    for ax in axes[-cols:]:
        ax.set_xlabel("time sent [s]")
    fig.suptitle(f"six-muscle arm: nominal excitations per target, {result.design} design, "
                 f"delay {1e3 * result.delay:g} ms")
    return fig


def center_out_figures(results: Sequence) -> dict:
    """The center-out figures by file name: center_out_hand_paths.png and, per delay and design,
    center_out_excitations_<design>_<delay>ms.png."""
    figures = {"center_out_hand_paths.png": plot_center_out(results)}
    for r in results:
        figures[f"center_out_excitations_{r.design}_{1e3 * r.delay:g}ms.png"] = plot_excitations(r)
    return figures
