"""Figures of a delay study: cost and endpoint error against the delay, and the task-space paths."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ..experiments.delay_text import delay_axis, delay_key, delay_text
from ..experiments.tables import unit_scale
from ..models.metadata import task_position, task_space, task_target
from ..statistics import diverged_trials
from ._common import COLORS, controller_label, ellipse, figure, speed_unit, suptitle
from .solution import plot_convergence

__all__ = ["plot_hand_paths", "plot_delay_study", "delay_study_figures", "draws_paths"]


def draws_paths(problem) -> bool:
    """Whether the model's task space gets a paths figure ([`plot_hand_paths`][delayed_ilqr.plot.plot_hand_paths]; the arms)."""
    task = task_space(problem)
    return task is not None and task.paths and task_target(problem) is not None


def _paths_panel(ax, group, n_paths: int):
    """Per controller: its nominal (thick) and ``n_paths`` trials (thin) in the task space, start and
    target, viewed around the nominal paths. Returns (per controller (result, endpoints relative to
    the target in display units, mask of the trials that did not diverge, colour), trials drawn)."""
    zoom, nominals = [], []
    for r in group:
        if not draws_paths(r.problem):
            raise ValueError("plot_hand_paths needs an arm model (a task space with paths, as arm2 and "
                             f"arm2_muscle6 have); got {r.model!r}")
        color = COLORS.get(r.controller, None)
        paths = task_position(r.problem, r.runs.x)                                 # [N, K+1, 2]
        nominal = task_position(r.problem, r.solution.x)
        for j in range(min(n_paths, paths.shape[0])):
            ax.plot(paths[j, :, 0], paths[j, :, 1], color=color, lw=0.6, alpha=0.45)
        ax.plot(nominal[:, 0], nominal[:, 1], color=color, lw=2.2, label=f"{controller_label(r.controller)} nominal")
        nominals.append(nominal)
        target = task_target(r.problem)
        ends = unit_scale(task_space(r.problem).unit)[0] * (paths[:, -1] - target)
        kept = ~diverged_trials(r.runs.cost, r.divergence_bound) & np.all(np.isfinite(ends), axis=1)
        zoom.append((r, ends, kept, color))
    start = task_position(group[0].problem, group[0].runs.x[0, 0])
    ax.scatter([start[0]], [start[1]], marker="o", s=60, color="k", zorder=6, label="start")
    ax.scatter([target[0]], [target[1]], marker="*", s=180, color="tab:orange", zorder=6, label="target")
    # view: the nominal paths, start and target with a margin; trials that leave it are clipped
    box = np.vstack([start, target] + nominals)
    lo, hi = box.min(axis=0), box.max(axis=0)
    centre, half_box = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 0.08
    ax.set_xlim(centre[0] - half_box, centre[0] + half_box)
    ax.set_ylim(centre[1] - half_box, centre[1] + half_box)
    ax.set_aspect("equal")
    return zoom, min(n_paths, paths.shape[0])


def _endpoints_half(zoom) -> float:
    """Half the width of an endpoints view: wide enough for the tightest controller's endpoints
    (99th percentile), at least 5 display units."""
    spans = [np.percentile(np.abs(e[f]), 99) for _, e, f, _ in zoom if np.any(f)]
    return max(5.0, 1.3 * min(spans)) if spans else 5.0


def _endpoints_panel(ax, zoom, unit: str, half: float):
    """Every trial's endpoint relative to the target with the 2-sigma ellipse of the trials that did
    not diverge, in a view of +-``half``; legends count the endpoints outside it (and name only what
    is drawn)."""
    for r, ends, finite, color in zoom:
        inside = finite & np.all(np.abs(ends) <= half, axis=1)
        outside = int(ends.shape[0] - np.count_nonzero(inside))
        name = controller_label(r.controller)
        if np.any(inside):
            label = f"{name} endpoints" + (f" ({outside} outside view)" if outside else "")
            ax.scatter(ends[inside, 0], ends[inside, 1], s=5, color=color, alpha=0.35, label=label)
        else:                               # nothing to draw: said in words, not as a legend entry
            ax.text(0.98, 0.02, f"{name}: all {outside} endpoints outside the view", transform=ax.transAxes,
                    ha="right", va="bottom", fontsize=7, color=color)
        centre_in_view = np.any(finite) and bool(np.all(np.abs(ends[finite].mean(axis=0)) <= half))
        ellipse(ax, ends[finite], color, label=f"{name} 2-sigma ellipse" if centre_in_view else None)
    ax.scatter([0.0], [0.0], marker="*", s=180, color="tab:orange", zorder=6, label="target")
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xlabel(f"endpoint x - target x [{unit}]")
    ax.set_ylabel(f"endpoint y - target y [{unit}]")


def _speed_panel(ax, group, n_paths: int):
    """Per controller: the task-space speed of its nominal (thick) and of ``n_paths`` trials (thin)
    against time, from the displacement of each step (display units per second: cm/s for metres).
    Returns the nominals' largest speed (the caller scales the row to it; wild trials are clipped)."""
    task = task_space(group[0].problem)
    factor, unit = speed_unit(task.unit)
    dt = group[0].problem.dt
    top = 0.0
    for r in group:
        color = COLORS.get(r.controller, None)
        for x, lw, alpha, label in ((r.runs.x[:n_paths], 0.6, 0.45, None),
                                    (r.solution.x[None], 2.2, 1.0, f"{controller_label(r.controller)} nominal")):
            p = task_position(r.problem, x)
            speed = factor * np.linalg.norm(np.diff(p, axis=-2), axis=-1) / dt
            t_axis = dt * np.arange(1, speed.shape[-1] + 1)
            for j in range(speed.shape[0]):
                ax.plot(t_axis, speed[j], color=color, lw=lw, alpha=alpha, label=label if j == 0 else None)
        top = max(top, float(np.nanmax(speed)))                  # the nominal, drawn last
    ax.set_xlabel("time [s]")
    ax.set_ylabel(f"{task.point} speed [{unit}]")
    return top


def plot_hand_paths(results: Sequence, n_paths: int = 10):
    """Hand paths of the arms (task-space paths), their speed profiles and the spread of their
    endpoints, per delay and controller.

    Args:
        results: [`ControllerResult`][delayed_ilqr.experiments.delay_study.ControllerResult] objects of a model
            whose task space draws paths (the arms: from
            [`compare_delays`][delayed_ilqr.experiments.delay_study.compare_delays] or ``evaluate``).
        n_paths: Monte Carlo paths drawn per controller.

    Returns:
        A Figure with three rows and one column per delay. Top: hand paths in the plane (shoulder at
        the origin; per controller its nominal, thick, and ``n_paths`` trials, thin), start and
        target, viewed around the nominal paths (trials that wander off are clipped). Middle: the
        hand speed of the same paths against time (cm/s; y-axis shared across delays). Bottom:
        every trial's endpoint relative to the target (mm) with the 2-sigma covariance ellipse of
        the trials that did not diverge, on one scale for all delays, set by the tightest
        controller's endpoints; legends count the endpoints outside the view.

    Raises:
        ValueError: when the results are not of such a model.
    """
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one ControllerResult; got none")
    keys = [delay_key(r.problem) for r in results]
    positions = delay_axis([r.problem for r in results])[0]
    delays = sorted(set(keys), key=lambda k: positions[keys.index(k)])
    fig = figure(figsize=(5.0 * len(delays), 13.0), layout="constrained")
    axes = fig.subplots(3, len(delays), squeeze=False)
    for ax in axes[1, 1:]:
        ax.sharey(axes[1, 0])
    fastest, zooms = 0.0, []
    for col, tau in enumerate(delays):
        group = [r for r in results if delay_key(r.problem) == tau]
        text = delay_text(group[0].problem)
        top, middle, bottom = axes[:, col]
        zoom, drawn = _paths_panel(top, group, n_paths)
        zooms.append(zoom)
        task = task_space(group[0].problem)
        top.set_xlabel(f"{task.point} x [{task.unit}]")
        top.set_ylabel(f"{task.point} y [{task.unit}]")
        top.set_title(f"{text}: {task.point} paths")
        top.grid(alpha=0.3)
        top.legend(loc="lower left", fontsize=8, framealpha=0.9)
        fastest = max(fastest, _speed_panel(middle, group, n_paths))
        middle.set_title(f"{text}: {task.point} speed")
        middle.grid(alpha=0.3)
        middle.legend(loc="upper right", fontsize=7)
    half = max(_endpoints_half(zoom) for zoom in zooms)          # one endpoint scale for all delays
    for col, zoom in enumerate(zooms):
        bottom = axes[2, col]
        _endpoints_panel(bottom, zoom, unit_scale(task_space(zoom[0][0].problem).unit)[1], half)
        bottom.set_title(f"{delay_text(zoom[0][0].problem)}: endpoints (N = {zoom[0][0].runs.x.shape[0]})")
        bottom.grid(alpha=0.3)
        bottom.legend(loc="upper left", fontsize=7)
    axes[1, 0].set_ylim(0.0, 1.3 * fastest)
    noise = "noisy" if results[0].noise else "deterministic"
    suptitle(fig, f"{results[0].model}: reaching with delayed commands ({noise} plant; thin lines: "
                  f"{drawn} Monte Carlo trials per controller)")
    return fig


def _series(ax, tau, stats, scale, color, c, ci):
    """One controller's values against the delay: the mean over the trials that did not diverge with
    its bootstrap 95 % interval, and the diverged count ([`delayed_ilqr.statistics`][delayed_ilqr.statistics], the same
    trials in both panels) written next to every point that has some."""
    ok = np.array([math.isfinite(st.mean) for st in stats])
    val = np.array([scale * st.mean for st in stats])
    lo = np.array([scale * st.ci95[0] for st in stats])
    hi = np.array([scale * st.ci95[1] for st in stats])
    yerr = np.vstack([np.clip(val - lo, 0, None), np.clip(hi - val, 0, None)])
    yerr = np.where(np.isfinite(yerr), yerr, 0.0)
    ax.plot(tau[ok], val[ok], color=color, lw=1.5, alpha=0.7)
    if np.any(ok):
        ax.errorbar(tau[ok], val[ok], yerr=yerr[:, ok], fmt="o", color=color, capsize=4, ms=7,
                    label=f"{controller_label(c)}: Monte Carlo mean, 95% CI")
    for t, v, st, good in zip(tau, val, stats, ok):
        if st.n_diverged and good:
            ax.annotate(f"{st.n_diverged}/{st.n} diverged", (t, v), textcoords="offset points",
                        xytext=(8, 6 - 14 * ci), fontsize=8, color=color)


def _spread(r) -> float:
    """The 1-sigma major axis of the final task positions of the trials that did not diverge."""
    ends = task_position(r.problem, r.runs.x[:, -1])
    kept = ~diverged_trials(r.runs.cost, r.divergence_bound) & np.all(np.isfinite(ends), axis=1)
    if np.count_nonzero(kept) < 3:
        return math.nan
    return math.sqrt(float(np.max(np.linalg.eigvalsh(np.cov(ends[kept], rowvar=False)))))


def _finish(ax, ylabel: str, title: str, xlabel: str, ticks):
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    if ticks is not None:               # per-channel or jittered delays: one tick per delay, named
        ax.set_xticks(*ticks)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)


def plot_delay_study(results: Sequence):
    """Expected cost and endpoint error against the delay, one series per controller.

    Args:
        results: [`ControllerResult`][delayed_ilqr.experiments.delay_study.ControllerResult] objects (several delays).

    Returns:
        A Figure with two axes. Left: Monte Carlo mean cost over the trials that did not diverge with
        its bootstrap 95 % interval (filled markers, log scale) and the controller's own predicted
        E[J] (open markers, dashed); the number of diverged trials (one definition,
        [`delayed_ilqr.statistics`][delayed_ilqr.statistics]) is written next to a point that has some. Middle: the
        endpoint error (mm for lengths in metres) over the same trials, likewise. Right, for a model
        with a task space (the arms): the endpoint spread, the 1-sigma major axis of the covariance
        of those trials' final task positions.
    """
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one ControllerResult; got none")
    spread = draws_paths(results[0].problem)
    fig = figure(figsize=(18.0 if spread else 12.5, 5.8), layout="constrained")
    axes = fig.subplots(1, 3 if spread else 2)
    ax_cost, ax_err = axes[:2]
    controllers = list(dict.fromkeys(r.controller for r in results))
    scale, unit_text = unit_scale(results[0].endpoint_unit)
    offsets = np.linspace(-1, 1, len(controllers)) * (0.6 if len(controllers) > 1 else 0.0)
    positions, ticks, xlabel = delay_axis([r.problem for r in results])
    where = {id(r): x for r, x in zip(results, positions)}
    distinct = np.unique(positions)
    step = min(np.diff(distinct)) if len(distinct) > 1 else (1.0 if ticks else 50.0)
    for ci, (c, off) in enumerate(zip(controllers, offsets)):
        rows = sorted((r for r in results if r.controller == c), key=lambda r: where[id(r)])
        color = COLORS.get(c, None)
        tau = np.array([where[id(r)] for r in rows]) + off * 0.04 * step
        _series(ax_cost, tau, [r.cost for r in rows], 1.0, color, c, ci)
        _series(ax_err, tau, [r.endpoint_error for r in rows], scale, color, c, ci)
        ax_cost.plot(tau, np.array([r.predicted_cost for r in rows]), ls="--", marker="o", mfc="white", color=color,
                     ms=7, label=f"{controller_label(c)}: its own predicted E[J]")
        if spread:
            axes[2].plot(tau, [scale * _spread(r) for r in rows], marker="o", ms=7, color=color,
                         label=f"{controller_label(c)}: Monte Carlo")
    _finish(ax_cost, "cost J, eq. 2 [-]", "expected cost", xlabel, ticks)
    label = results[0].endpoint_label
    _finish(ax_err, f"{label} [{unit_text or '-'}]", label, xlabel, ticks)
    if spread:
        point = task_space(results[0].problem).point
        _finish(axes[2], f"1-sigma major axis [{unit_text}]", f"spread of the final {point} positions", xlabel, ticks)
    n = results[0].cost.n
    noise = "noisy" if results[0].noise else "deterministic"
    suptitle(fig, f"{results[0].model}: delay-aware vs delay-ignorant control, {n} {noise} trials per point")
    return fig


def delay_study_figures(results: Sequence) -> dict:
    """The figures of a delay study by file name: cost_vs_delay.png, convergence.png (one line per
    solve; the delay-ignorant design problem is the same at every delay, so one line for it unless
    the delay-aware one at 0 ms is drawn) and, for a model whose task space draws paths,
    hand_paths.png."""
    figures = {"cost_vs_delay.png": plot_delay_study(results)}
    sols = {f"{r.controller}, {delay_text(r.problem)}": r.solution for r in results if r.controller != "ignorant"}
    ignorant = [r for r in results if r.controller == "ignorant"]
    zero_aware = any(r.controller == "aware" and r.delay_steps == 0 for r in results)
    if ignorant and not zero_aware:
        sols["ignorant (designed for 0 ms)"] = ignorant[0].solution
    figures["convergence.png"] = plot_convergence(sols)
    if draws_paths(results[0].problem):
        figures["hand_paths.png"] = plot_hand_paths(results)
    return figures
