"""Figures of the center-out study: hand paths, hand speed profiles, endpoint ellipses in mm, cost and
endpoint spread against the delay, and the excitation patterns.

Each figure is compared with a finding of the reaching literature in the report's caption
(`CAPTIONS`): nearly straight hand paths (Morasso 1981), single-peaked, bell-shaped speed
profiles (Flash & Hogan 1985), endpoint ellipses of a few millimetres elongated along the movement
(Gordon, Ghilardi & Ghez 1994; van Beers, Haggard & Wolpert 2004).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..experiments.delay_text import delay_tag, delay_text
from ..models.metadata import task_position, task_space
from ..statistics import sample_stats
from ._common import ellipse, figure, suptitle

__all__ = ["plot_center_out", "plot_speed_profiles", "plot_endpoints", "plot_center_out_vs_delay",
           "plot_excitations", "center_out_figures", "CAPTIONS"]

#: Per figure file (the excitation figures by prefix): what it shows and the human finding it is
#: compared with. The report writes it under the figure.
CAPTIONS = {
    "center_out_hand_paths.png":
        "Nominal hand paths (thick), five noisy trials per target (thin) and the 2-sigma ellipses of the "
        "endpoints. Compared with: human point-to-point reaches in the horizontal plane run along "
        "nearly straight hand paths (Morasso 1981, Exp Brain Res 42:223; Flash & Hogan 1985, J Neurosci 5:1688).",
    "center_out_speed.png":
        "Hand speed of the nominal reaches against time (one line per target). Compared with: human reaches "
        "have single-peaked, bell-shaped speed profiles (Morasso 1981; Flash & Hogan 1985). The model's "
        "energy optimum at no delay is flat-topped instead (push, coast, brake), a consequence of its "
        "force-activation curve (docs/results/reach_shape.md).",
    "center_out_endpoints.png":
        "Endpoints of the noisy trials relative to each target, in mm, with their 2-sigma ellipses (one "
        "colour per target; all panels on one scale). Compared with: human endpoints of unseen 10 "
        "cm reaches scatter by millimetres, in ellipses elongated along the movement (Gordon, Ghilardi & Ghez "
        "1994, Exp Brain Res 99:97), and execution noise explains that scatter (van Beers, Haggard & "
        "Wolpert 2004, J Neurophysiol 91:1050).",
    "center_out_vs_delay.png":
        "Monte Carlo mean cost (over the trials of all targets that did not diverge, bootstrap 95 % "
        "interval; open markers: the designs' predicted E[J]) and endpoint spread (1-sigma major "
        "axis: mean over targets, bars from the smallest to the largest) against the input delay. "
        "Compared with: human endpoint spread of a few mm at short feedback delays (Gordon et al. "
        "1994); the cost of the delay is this library's prediction.",
    "center_out_excitations":
        "Nominal muscle excitations against the time they are sent (they act one delay later). "
        "Compared with: human EMG of point-to-point movements, an agonist burst that accelerates "
        "and an antagonist burst that brakes (the triphasic pattern of fast movements; Hallett, "
        "Shahani & Young 1975, J Neurol Neurosurg Psychiatry 38:1154).",
}

_DESIGN_COLORS = {"noise-aware": "tab:blue", "deterministic": "tab:red", "statistical": "tab:green"}

#: Titles and legends name a design in words where its CLI name does not say what it is.
_DESIGN_LABELS = {"statistical": "noise-aware + SL"}


def _label(design: str) -> str:
    return _DESIGN_LABELS.get(design, design)


def _grid(results, width: float, height: float, **kwargs):
    """A figure with one panel per (design row, delay column); returns (figure, axes, place)."""
    designs = list(dict.fromkeys(r.design for r in results))
    delays = list(dict.fromkeys(r.delay for r in results))
    fig = figure(figsize=(width * len(delays), height * len(designs)), layout="constrained")
    grid = fig.subplots(len(designs), len(delays), squeeze=False, **kwargs)
    return fig, grid, lambda r: grid[designs.index(r.design), delays.index(r.delay)]


def _target_colors(n: int):
    from matplotlib import colormaps
    return [colormaps["tab10"](j % 10) for j in range(n)]


def _reaches_panel(ax, r, n_paths: int, colors):
    """One delay and design: per target its nominal path (thick), ``n_paths`` trials (thin), the
    target (star) and the 2-sigma ellipse of the trials' final positions; the start is the black dot."""
    plant = r.plants[0]
    nominal = task_position(plant, r.solutions.x)                                  # [targets, K+1, 2]
    for j, t in enumerate(r.targets):
        color = colors[j]
        for path in task_position(plant, r.runs[j].x[:n_paths]):
            ax.plot(path[:, 0], path[:, 1], color=color, lw=0.5, alpha=0.5)
        ax.plot(nominal[j, :, 0], nominal[j, :, 1], color=color, lw=2.0, label=f"target {j + 1}")
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
    ax.set_title(f"{_label(r.design)}, {delay_text(r.delay)} (converged {converged}/{len(r.targets)})")
    ax.grid(alpha=0.3)


def plot_center_out(results: Sequence, n_paths: int = 5):
    """Center-out reaches of the six-muscle arm: hand paths and endpoint ellipses, one panel per
    delay (columns) and design (rows).

    Args:
        results: [`DelayResult`][delayed_ilqr.experiments.center_out.DelayResult] objects.
        n_paths: Monte Carlo hand paths drawn per target.

    Returns:
        A Figure: per delay and design, each target's nominal hand path (thick), ``n_paths`` noisy
        trials (thin), the target (star) and the 2-sigma covariance ellipse of the trials' final
        hand positions; the start hand position is the black dot. The legend below the panels
        names the targets by number, as the other center-out figures do.
    """
    results = _nonempty(results)
    fig, grid, place = _grid(results, 4.6, 4.8)
    colors = _target_colors(len(results[0].targets))
    for r in results:
        _reaches_panel(place(r), r, n_paths, colors)
    handles, labels = grid[0, 0].get_legend_handles_labels()
    # as many columns as the figure's width holds (about an inch per entry)
    columns = max(1, min(len(labels), int(fig.get_size_inches()[0] / 1.05)))
    fig.legend(handles, labels, loc="outside lower center", fontsize=8, ncol=columns)
    suptitle(fig, f"six-muscle arm, center-out: hand paths ({n_paths} of N = {results[0].runs[0].x.shape[0]} "
                  "trials per target) and 2-sigma endpoint ellipses")
    return fig


def _nonempty(results) -> list:
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one DelayResult; got none")
    return results


def _hand_speed(plant, x, dt: float) -> np.ndarray:
    """Hand speed [..., K] (m/s) of states x [..., K+1, n]: the hand displacement per step over dt."""
    p = task_position(plant, x)
    return np.linalg.norm(np.diff(p, axis=-2), axis=-1) / dt


def plot_speed_profiles(results: Sequence):
    """Hand speed of every nominal reach against time, one panel per delay (columns) and design (rows).

    Args:
        results: [`DelayResult`][delayed_ilqr.experiments.center_out.DelayResult] objects.

    Returns:
        A Figure: per target (colour) the nominal's hand speed in cm/s, from the hand displacement of
        each step, against the time at the end of the step; all panels share the axes.
    """
    results = _nonempty(results)
    fig, grid, place = _grid(results, 4.2, 3.4, sharex=True, sharey=True)
    colors = _target_colors(len(results[0].targets))
    for r in results:
        ax = place(r)
        speed = 100.0 * _hand_speed(r.plants[0], np.asarray(r.solutions.x), r.dt)          # [targets, K]
        t_axis = r.dt * np.arange(1, speed.shape[1] + 1)
        for j in range(speed.shape[0]):
            ax.plot(t_axis, speed[j], color=colors[j], lw=1.5, label=f"target {j + 1}")
        ax.set_title(f"{_label(r.design)}, {delay_text(r.delay)}")
        ax.grid(alpha=0.3)
    for ax in grid[-1]:
        ax.set_xlabel("time [s]")
    for ax in grid[:, 0]:
        ax.set_ylabel("hand speed [cm/s]")
    grid[0, -1].legend(fontsize=7, loc="upper right", ncol=2)
    suptitle(fig, "six-muscle arm, center-out: hand speed of the nominal reaches")
    return fig


def plot_endpoints(results: Sequence):
    """Endpoints of the noisy trials relative to their targets, in mm, one panel per delay and design.

    Args:
        results: [`DelayResult`][delayed_ilqr.experiments.center_out.DelayResult] objects.

    Returns:
        A Figure: per target (colour) the endpoints of the trials that did not diverge minus the
        target (dots), their mean (cross) and 2-sigma ellipse, equal axes; all panels share one
        scale, that of the largest ellipse, so that panels compare at a glance (a spread orders of
        magnitude smaller than the largest shows as a point; each panel writes its spread, the
        mean over targets of the 1-sigma major axis).
    """
    results = _nonempty(results)
    fig, grid, place = _grid(results, 4.2, 4.2, sharex=True, sharey=True)
    colors = _target_colors(len(results[0].targets))
    half = 0.5
    for r in results:
        ax = place(r)
        for j, t in enumerate(r.targets):
            kept = ~t.diverged & np.all(np.isfinite(t.endpoints), axis=1)
            rel = 1e3 * (t.endpoints[kept] - t.target)                                    # mm
            if rel.shape[0] < 3:
                continue
            ax.scatter(rel[:, 0], rel[:, 1], s=3, color=colors[j], alpha=0.25)
            mean = rel.mean(axis=0)
            ax.scatter([mean[0]], [mean[1]], marker="x", s=40, color=colors[j], zorder=5)
            ellipse(ax, rel, colors[j], label=f"target {j + 1}")
            half = max(half, float(np.max(np.abs(mean)) + 2.4 * np.sqrt(np.max(np.linalg.eigvalsh(
                np.cov(rel, rowvar=False))))))
        ax.scatter([0.0], [0.0], marker="+", s=80, color="k", zorder=6)
        # on the shared scale a small spread is a dot: its size in words
        ax.text(0.98, 0.02, f"spread {np.mean([1e3 * t.spread for t in r.targets]):.3g} mm", transform=ax.transAxes,
                ha="right", va="bottom", fontsize=8)
    for r in results:
        ax = place(r)
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.set_xlabel("endpoint x - target x [mm]")
        ax.set_ylabel("endpoint y - target y [mm]")
        ax.set_title(f"{_label(r.design)}, {delay_text(r.delay)}")
        ax.grid(alpha=0.3)
    grid[0, 0].legend(fontsize=7, loc="upper left", ncol=2)
    suptitle(fig, f"six-muscle arm, center-out: endpoints relative to the target (N = "
                  f"{results[0].runs[0].x.shape[0]} per target), 2-sigma ellipses, mean as a cross")
    return fig


def plot_center_out_vs_delay(results: Sequence):
    """Cost and endpoint spread against the delay, one series per design.

    Args:
        results: [`DelayResult`][delayed_ilqr.experiments.center_out.DelayResult] objects (several delays).

    Returns:
        A Figure with two axes. Left: the Monte Carlo mean cost over all targets' trials that did
        not diverge, with its bootstrap 95 % interval ([`sample_stats`][delayed_ilqr.statistics.sample_stats],
        log scale), and the mean over targets of the design's predicted E[J] (open markers,
        dashed). Right: the endpoint spread (1-sigma major axis of each target's endpoint
        covariance) in mm: mean over targets, bars from the smallest to the largest target.
    """
    results = _nonempty(results)
    fig = figure(figsize=(11.5, 5.8), layout="constrained")
    ax_cost, ax_spread = fig.subplots(1, 2)
    designs = list(dict.fromkeys(r.design for r in results))
    for i, design in enumerate(designs):
        rows = sorted((r for r in results if r.design == design), key=lambda r: r.delay)
        color = _DESIGN_COLORS.get(design, f"C{i}")
        tau = np.array([1e3 * r.delay for r in rows]) + (i - (len(designs) - 1) / 2) * 1.5
        stats = [sample_stats(np.concatenate([t.mc_cost for t in r.targets]),
                              np.concatenate([t.diverged for t in r.targets])) for r in rows]
        mean = np.array([s.mean for s in stats])
        ci = np.array([s.ci95 for s in stats]).T
        ax_cost.errorbar(tau, mean, yerr=np.abs(ci - mean), fmt="o-", color=color, capsize=4,
                         label=f"{_label(design)}: Monte Carlo mean, 95 % CI")
        ax_cost.plot(tau, [np.mean([t.predicted_cost for t in r.targets]) for r in rows], ls="--", marker="o",
                     mfc="white", color=color, label=f"{_label(design)}: predicted E[J]")
        spread = np.array([[1e3 * t.spread for t in r.targets] for r in rows])          # [delays, targets] mm
        mid = spread.mean(axis=1)
        ax_spread.errorbar(tau, mid, yerr=[mid - spread.min(axis=1), spread.max(axis=1) - mid], fmt="o-",
                           color=color, capsize=4, label=f"{_label(design)}: mean over targets [range]")
    for ax, label, title in ((ax_cost, "cost J, eq. 2 [-]", "expected cost"),
                             (ax_spread, "endpoint spread, 1-sigma major axis [mm]", "endpoint spread")):
        ax.set_yscale("log")
        ax.set_xlabel("input delay [ms]")
        ax.set_ylabel(label)
        ax.set_title(title)
        ax.grid(alpha=0.3, which="both")
        # below the axes: inside, two entries per design cover the low predicted costs
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)
    suptitle(fig, "six-muscle arm, center-out: what the delay costs")
    return fig


def plot_excitations(result):
    """Nominal muscle excitations u_k of every target at one delay and design (one panel per target).

    Args:
        result: a [`DelayResult`][delayed_ilqr.experiments.center_out.DelayResult].

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
        ax.set_title(f"target {j + 1}: nominal misses by {1e3 * target.hand_error:.2f} mm", fontsize=9)
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    for ax in axes[n:]:
        ax.set_visible(False)
    axes[0].legend(fontsize=7, loc="upper right")
    for ax in axes[-cols:]:
        ax.set_xlabel("time sent [s]")
    for ax in axes[::cols]:
        ax.set_ylabel("excitation [-]")
    suptitle(fig, f"six-muscle arm: nominal excitations per target, {_label(result.design)} design, "
                  f"delay {delay_text(result.delay)}")
    return fig


def center_out_figures(results: Sequence) -> dict:
    """The center-out figures by file name: center_out_hand_paths.png, center_out_speed.png,
    center_out_endpoints.png, center_out_vs_delay.png (with more than one delay) and, per delay and
    design, center_out_excitations_<design>_<delay>ms.png (captions: `CAPTIONS`), except for
    a design whose nominal excitations are another's at that delay (the statistical design keeps
    the noise-aware nominal): that figure would repeat the other but for its title."""
    results = _nonempty(results)
    figures = {"center_out_hand_paths.png": plot_center_out(results),
               "center_out_speed.png": plot_speed_profiles(results),
               "center_out_endpoints.png": plot_endpoints(results)}
    if len({r.delay for r in results}) > 1:
        figures["center_out_vs_delay.png"] = plot_center_out_vs_delay(results)
    drawn = []
    for r in results:
        u = np.asarray(r.solutions.u)
        if any(d == r.delay and np.array_equal(u, v) for d, v in drawn):
            continue
        drawn.append((r.delay, u))
        figures[f"center_out_excitations_{r.design}_{delay_tag(r.delay)}.png"] = plot_excitations(r)
    return figures
