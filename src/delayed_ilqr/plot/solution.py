"""Figures of one solution: states and commands against time, and the solver's convergence."""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Optional

import numpy as np

from ..experiments.delay_text import delay_text
from ..models.metadata import labels
from ._common import figure, robust_limits, suptitle

__all__ = ["plot_trajectories", "plot_convergence", "state_labels"]


def state_labels(problem) -> tuple[list[str], list[str]]:
    """(state labels [n], control labels [d]) with units from the model's metadata, else x[i] / u[j]."""
    return labels(problem)


def _grid(total: int):
    """A figure with ``total`` axes, up to three per row (the spare ones removed)."""
    ncols = min(total, 3)
    nrows = math.ceil(total / ncols)
    fig = figure(figsize=(4.2 * ncols, 2.9 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[total:]:
        fig.delaxes(ax)
    return fig, axes


def _state_axis(ax, t_x, trials, nominal, target, all_trials, label):
    for j in range(0 if trials is None else trials.shape[0]):
        ax.plot(t_x, trials[j], color="0.55", lw=0.8, alpha=0.8, label="Monte Carlo trials" if j == 0 else None)
    ax.plot(t_x, nominal, color="tab:blue", lw=2.0, label="nominal")
    if target is not None:
        ax.scatter([t_x[-1]], [target], marker="*", s=120, color="tab:orange", zorder=5, label="target")
    robust_limits(ax, nominal, all_trials, target)
    ax.set_ylabel(label)
    ax.set_xlabel("time [s]")
    ax.grid(alpha=0.3)


def _command_axis(ax, t_u, trials, nominal, all_trials, label):
    for j in range(0 if trials is None else trials.shape[0]):
        ax.step(t_u, trials[j], where="post", color="0.55", lw=0.8, alpha=0.8)
    ax.step(t_u, nominal, where="post", color="tab:blue", lw=2.0)
    robust_limits(ax, nominal, all_trials, None)
    ax.set_ylabel(label)
    ax.set_xlabel("time sent [s]")
    ax.grid(alpha=0.3)


def plot_trajectories(problem, policy, runs=None, n_trials: int = 5, title: Optional[str] = None):
    """States and commands against time: the policy's nominal and a few Monte Carlo trials.

    Args:
        problem: the [`Problem`][delayed_ilqr.Problem] (for dt, labels and the target).
        policy: a [`Policy`][delayed_ilqr.Policy] or [`Solution`][delayed_ilqr.Solution] (its nominal is drawn).
        runs: optional [`Runs`][delayed_ilqr.Runs]; its first ``n_trials`` trials are drawn thin.
        n_trials: how many trials to draw.
        title: the figure title (default: model, delay and noise).

    Returns:
        A Figure with one axis per state and per command (n + d axes). Each axis holds
        min(n_trials, N) trial lines and one nominal line; state axes also mark the target x_K.
        The vertical range covers the nominal and the 5-95 % band of all N trials with a margin, so
        a trial that diverges is clipped at the frame instead of flattening the others.
    """
    policy = getattr(policy, "policy", policy)
    x_nom, u_nom = np.asarray(policy.x_nominal), np.asarray(policy.u_nominal)
    nx, nd, K, dt = problem.n_states, problem.n_controls, problem.horizon, problem.dt
    s_labels, u_labels = state_labels(problem)
    fig, axes = _grid(nx + nd)
    show = 0 if runs is None else min(int(n_trials), int(np.shape(runs.x)[0]))
    xs = np.asarray(runs.x[:show]) if show else None
    us = np.asarray(runs.u[:show]) if show else None
    target = getattr(problem.cost, "x_target", None)
    all_x = None if runs is None else np.asarray(runs.x)
    all_u = None if runs is None else np.asarray(runs.u)
    for i in range(nx):
        _state_axis(axes[i], dt * np.arange(K + 1), None if xs is None else xs[:, :, i], x_nom[:, i],
                    None if target is None else float(np.asarray(target)[i]),
                    None if all_x is None else all_x[:, :, i], s_labels[i])
    for k in range(nd):
        _command_axis(axes[nx + k], dt * np.arange(K), None if us is None else us[:, :, k], u_nom[:, k],
                      None if all_u is None else all_u[:, :, k], u_labels[k])
    axes[0].legend(loc="best", fontsize=8)
    if title is None:
        title = (f"{problem.name}: states and commands sent (acting {delay_text(problem)} later), "
                 + ("noisy plant" if problem.noise is not None else "deterministic plant"))
    suptitle(fig, title)
    return fig


def plot_convergence(solutions, title: Optional[str] = None):
    """Cost against iteration (log scale) for one solution or a ``{label: Solution}`` mapping.

    Returns:
        A Figure with one axis: per solution one line of ``trace.cost`` (eq. 2 on the nominal) and,
        when the problem is noisy (the trace's merit differs from its cost), a dashed line of the
        noise-aware merit the line search minimises. Open markers are rejected iterations (with a
        legend entry only when there are some).
    """
    if not isinstance(solutions, Mapping):
        solutions = {"iLQG": solutions}
    fig = figure(figsize=(7.5, 5.0), layout="constrained")
    ax = fig.subplots()
    any_rejected = False
    for i, (label, sol) in enumerate(solutions.items()):
        n = int(sol.iterations) + 1
        it = np.arange(n)
        cost = np.asarray(sol.trace.cost[:n])
        merit = np.asarray(sol.trace.merit[:n])
        step = np.asarray(sol.trace.step_size[:n])
        color = f"C{i}"
        status = "converged" if sol.converged else "not converged"
        (line,) = ax.plot(it, cost, color=color, marker="o", ms=4, label=f"{label}: cost ({status})")
        rejected = np.zeros(n, bool)
        rejected[1:] = ~(step[1:] > 0)
        if np.any(rejected):
            line.set_markevery(list(np.flatnonzero(~rejected)))
            ax.scatter(it[rejected], cost[rejected], facecolors="white", edgecolors=color, s=18, zorder=3,
                       label=None if any_rejected else "rejected step (open marker)")
            any_rejected = True
        if not np.allclose(merit, cost, rtol=1e-12, equal_nan=True):
            ax.plot(it, merit, color=color, ls="--", label=f"{label}: merit (cost + noise terms)")
    ax.set_yscale("log")
    from matplotlib.ticker import MaxNLocator
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("iteration [-]")
    ax.set_ylabel("cost J, eq. 2 [-]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(title or "iLQG convergence")
    return fig
