"""Figures of the gallery's experiments (`delayed_ilqr.experiments`: kick, target_jump, fitts,
minimal_intervention), each with the published numbers it is compared with in its title or legend.
Lengths in millimetres, times in milliseconds after the perturbation or in seconds of movement."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..experiments.delay_text import delay_text
from ..models.arm2 import hand_position
from ._common import ellipse, figure

__all__ = ["plot_kick", "plot_target_jump", "plot_fitts", "plot_minimal_intervention", "plot_delay_growth"]


def _hand(x):
    return np.asarray(hand_position(np.asarray(x)[..., :2]))


def _command_axis(problem) -> str:
    """The y label of a command response: what the commands are and their unit, from the model's
    control labels (e.g. "excitation u1 [-]": a fraction of the maximal excitation)."""
    labels = getattr(problem.metadata, "control_labels", None) or ("command [-]",)
    name, _, unit = labels[0].rpartition(" [")
    unit = unit.rstrip("]")
    kind = name.split()[0] if name else "command"
    return f"|mean {kind} change| [{'fraction of maximum' if unit == '-' else unit}]"


def _delays(problem) -> str:
    ls = None if problem.observation is None else problem.observation.delay_steps * problem.dt
    sensory = "state seen" if ls is None else f"sensory {1e3 * ls:.0f} ms"
    return f"{problem.name}, motor delay {delay_text(problem)}, {sensory}"


def plot_kick(result):
    """Mean hand paths (kicked, unperturbed) in mm; |mean applied-command response| against the time
    after the kick with the loop latency (dotted) and the published latency bands (reflex 20-50 ms,
    long-latency 50-100 ms, voluntary 100-150 ms; Pruszynski & Scott 2012); final hand errors."""
    a, p = result.analysis, result.problem
    fig = figure(figsize=(15, 4.6), layout="constrained")
    ax_path, ax_u, ax_err = fig.subplots(1, 3)
    calm, kicked = _hand(result.base.runs.x).mean(0), _hand(result.kicked.runs.x).mean(0)
    target = np.asarray(p.cost.params["target"])
    ax_path.plot(1e3 * calm[:, 0], 1e3 * calm[:, 1], "--", color="0.4", label="unperturbed (mean)")
    ax_path.plot(1e3 * kicked[:, 0], 1e3 * kicked[:, 1], color="tab:red", lw=2, label="kicked (mean)")
    ax_path.scatter(*(1e3 * calm[result.pulse_step + 1]), marker="x", color="k", zorder=5, label="kick")
    ax_path.scatter(*(1e3 * target), marker="o", facecolor="none", edgecolor="k", s=80, label="target")
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_path.set_xlabel("hand x [mm]")
    ax_path.set_ylabel("hand y [mm]")
    ax_path.legend(fontsize=8)
    dt, lm = p.dt, p.delay_steps
    resp = np.linalg.norm((np.asarray(result.kicked.runs.u) - np.asarray(result.base.runs.u)).mean(0), axis=1)
    t_after = 1e3 * dt * (np.arange(resp.size) + lm - (result.pulse_step + 1))     # applied command
    for lo, hi, c, name in ((20, 50, "tab:green", "reflex"), (50, 100, "tab:olive", "long-latency"),
                            (100, 150, "tab:orange", "voluntary")):
        ax_u.axvspan(lo, hi, color=c, alpha=0.15, label=f"{name} {lo}-{hi} ms (published)")
    ax_u.plot(t_after, resp, color="tab:red", lw=2, drawstyle="steps-post", label="model (held over each step)")
    ax_u.axvline(1e3 * a.loop_latency, color="k", ls=":", label=f"loop latency {1e3 * a.loop_latency:.0f} ms")
    ax_u.set_xlim(-50, max(300, t_after[-1]))
    ax_u.set_xlabel("time after the kick, applied command [ms]")
    ax_u.set_ylabel(_command_axis(p))
    ax_u.legend(fontsize=7)
    eb, ek = 1e3 * np.asarray(result.base.errors), 1e3 * np.asarray(result.kicked.errors)
    ax_err.boxplot([eb, ek])
    ax_err.set_xticks([1, 2], ["unperturbed", "kicked"])
    ax_err.set_xlabel("trials on the same noise [-]")
    ax_err.set_ylabel("final hand error [mm]")
    ax_err.set_title(f"median ratio {a.error_ratio:.2g} (published: at most about 2)", fontsize=9)
    fig.suptitle(f"A mid-reach kick of {1e3 * float(np.abs(result.kick_speed)):.0f} mm/s ({_delays(p)})")
    return fig


def plot_target_jump(result):
    """Mean hand paths in mm for each jump time (the unjumped path on top); the mean hand
    displacement towards the new target, as a fraction of the jump, against the time after the
    jump, with the loop latency (the earliest a command that sees the jump acts); and the median
    final distance to the new target against the jump time (published: the hand reaches the new
    target when the jump comes early enough, Liu & Todorov 2007), with the jump times too late for
    any correction to act shaded."""
    fig = figure(figsize=(16, 4.6), layout="constrained")
    ax_path, ax_shift, ax_err = fig.subplots(1, 3)
    from matplotlib import colormaps
    p = result.problem
    hand_base = _hand(result.base_x)
    base = hand_base.mean(0)
    n = len(result.analyses)
    unit = np.asarray(result.jump) / np.linalg.norm(result.jump)
    loop = 1e3 * result.analyses[0].loop_latency
    for i, (a, x) in enumerate(zip(result.analyses, result.jumped_x)):
        colour = colormaps["viridis"](0.85 * i / max(n - 1, 1))
        label = f"jump {1e3 * a.time_before_end:.0f} ms before the end"
        hand = _hand(x)
        h = hand.mean(0)
        ax_path.plot(1e3 * h[:, 0], 1e3 * h[:, 1], color=colour, lw=2, label=label)
        start = p.horizon - int(round(a.time_before_end / p.dt))          # the first state the jump moved
        along = (hand - hand_base).mean(0)[start:] @ unit / np.linalg.norm(result.jump)
        ax_shift.plot(1e3 * p.dt * np.arange(along.size), along, color=colour, lw=2, label=label)
    ax_path.plot(1e3 * base[:, 0], 1e3 * base[:, 1], "--", color="k", lw=1.2, zorder=5, label="no jump")
    t0 = np.asarray(p.x0[-2:])
    ax_path.scatter(*(1e3 * t0), marker="o", facecolor="none", edgecolor="k", s=80, label="first target")
    ax_path.scatter(*(1e3 * (t0 + result.jump)), marker="o", color="k", s=40, label="new target")
    ax_path.set_aspect("equal", adjustable="datalim")
    ax_path.set_xlabel("hand x [mm]")
    ax_path.set_ylabel("hand y [mm]")
    ax_path.legend(fontsize=7)
    ax_shift.axvline(loop, color="k", ls=":", label=f"loop latency {loop:.0f} ms")
    ax_shift.axhline(1.0, color="tab:green", ls="--", lw=1, label="the whole jump")
    ax_shift.set_xlabel("time after the jump [ms]")
    ax_shift.set_ylabel("mean hand displacement towards the new target [fraction of the jump]")
    ax_shift.legend(fontsize=7)
    tb = [1e3 * a.time_before_end for a in result.analyses]
    ax_err.axvspan(0, loop, color="0.85", label="too late: no command that sees the jump acts")
    ax_err.plot(tb, [1e3 * a.error_new.median for a in result.analyses], "o-", label="model: median")
    ax_err.axhline(10, color="tab:green", ls="--", label="1 cm (published: reached when >= 200 ms)")
    ax_err.set_xlim(0, max(tb) + 50)
    ax_err.set_xlabel("jump time before the end [ms]")
    ax_err.set_ylabel("final distance to the new target [mm]")
    ax_err.legend(fontsize=7)
    fig.suptitle(f"Target jumps of {1e3 * float(np.linalg.norm(result.jump)):.0f} mm ({_delays(p)}; "
                 f"{getattr(result, 'controller', 'fixed')} controller); Liu & Todorov 2007")
    return fig


def plot_fitts(results: Sequence):
    """Two panels. Left: the chosen movement time (ms) against log2(2D/W) (bit), one colour per
    motor delay: filled where MT lies inside the grid of movement times (the fitted conditions),
    open triangles down at the grid's shortest time where the criterion was met already there
    (MT at most that), triangles up at the longest time where it was never met; each fit drawn
    over the indices it was fitted on, with the published slopes 100-200 ms/bit (shaded, from the
    first delay's fit at its smallest index). Right: the effective width 4.133 SD + 2 |bias| (mm) against the
    time allowed, one line per distance (first delay), beside the grid's widths (dotted) and Fitts
    1954's (dashed): a width below the lines' floor is never met."""
    from ..experiments.fitts import FITTS_1954_WIDTHS
    from ..experiments.responses import EFFECTIVE_WIDTH_SD
    fig = figure(figsize=(11, 4.8), layout="constrained")
    ax, ax_w = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=(1.25, 1)))
    colors = ("tab:blue", "tab:red", "tab:green", "tab:purple")
    for i, r in enumerate(results):
        c = colors[i % len(colors)]
        ts, index, mt = np.asarray(r.movement_times), np.asarray(r.index), np.asarray(r.mt)
        inside = np.isfinite(mt) & (mt > ts[0])
        censored, never = np.isfinite(mt) & ~inside, ~np.isfinite(mt)
        name = f"motor delay {delay_text(r.delay)}"
        ax.scatter(index[inside], 1e3 * mt[inside], color=c, label=f"{name}: MT inside the grid")
        if censored.any():
            ax.scatter(index[censored], np.full(censored.sum(), 1e3 * ts[0]), facecolors="none", edgecolors=c,
                       marker="v", label=f"{name}: met at {1e3 * ts[0]:.0f} ms already (MT <=)")
        if never.any():
            ax.scatter(index[never], np.full(never.sum(), 1e3 * ts[-1]), color=c, marker="^", alpha=0.5,
                       label=f"{name}: not met by {1e3 * ts[-1]:.0f} ms")
        if r.fit is not None:
            x = np.linspace(index[inside].min(), index[inside].max(), 10)
            ax.plot(x, 1e3 * (r.fit.a + r.fit.b * x), color=c,
                    label=f"fit: {1e3 * r.fit.b:.0f} ms/bit, a = {1e3 * r.fit.a:.0f} ms, R$^2$ = {r.fit.r2:.2f}")
            if i == 0:
                y0 = r.fit.a + r.fit.b * x[0]
                ax.fill_between(x, 1e3 * (y0 + 0.1 * (x - x[0])), 1e3 * (y0 + 0.2 * (x - x[0])), color="0.8",
                                alpha=0.5, label="published slopes 100-200 ms/bit (from the fit's first point)")
    ax.set_xlabel("index of difficulty log$_2$(2D/W) [bit]")
    ax.set_ylabel("movement time MT [ms]")
    ax.legend(fontsize=7)
    ax.set_title("MT against the index of difficulty", fontsize=10)
    fig.suptitle("Fitts' law: the movement time the model chooses (Fitts 1954; MacKenzie 1992)")
    r = results[0]
    for d, bias, sd in zip(r.distances, np.asarray(r.bias), np.asarray(r.sd)):
        ax_w.plot(1e3 * np.asarray(r.movement_times), 1e3 * (EFFECTIVE_WIDTH_SD * sd + 2 * np.abs(bias)), marker="o",
                  label=f"D = {1e2 * d:g} cm")
    for w in sorted(set(np.round(np.asarray(r.widths), 6)) | set(FITTS_1954_WIDTHS)):
        fitted = bool(np.any(np.isclose(r.widths, w)))
        ax_w.axhline(1e3 * w, color="0.3" if fitted else "0.6", linestyle=":" if fitted else "--", linewidth=1)
        ax_w.annotate(f"W = {1e3 * w:.3g} mm", (0.99, 1e3 * w), xycoords=("axes fraction", "data"), ha="right",
                      va="bottom", fontsize=7, color="0.3" if fitted else "0.6")
    ax_w.set_yscale("log")
    ax_w.set_xlabel("movement time allowed T [ms]")
    ax_w.set_ylabel("effective width 4.133 SD + 2 |bias| [mm]")
    ax_w.set_title(f"Endpoint spread at T, motor delay {delay_text(r.delay)}\n"
                   "(widths: the grid's dotted, Fitts 1954's others dashed)", fontsize=10)
    ax_w.legend(fontsize=7)
    return fig


def plot_minimal_intervention(scatters: Sequence):
    """Endpoints (mm, relative to the target) with 2-sigma ellipses of the point and the bar target;
    the title gives the SD ratios (published: larger along the task-irrelevant direction, about 2x,
    Todorov & Jordan 2002; Knill et al. 2011)."""
    fig = figure(figsize=(6.5, 5.5), layout="constrained")
    ax = fig.subplots()
    for s, c in zip(scatters, ("tab:blue", "tab:red")):
        e = 1e3 * (s.endpoints - np.asarray(s.problem.cost.params["target"]))
        ax.scatter(e[:, 0], e[:, 1], s=5, color=c, alpha=0.4)
        ellipse(ax, e, c, label=f"{s.name}: irrelevant/relevant SD {s.ratio:.2f}")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("hand x - target [mm]")
    ax.set_ylabel("hand y - target [mm]")
    ax.set_title("Minimal intervention: bar across the movement (published ratio about 2)", fontsize=9)
    ax.legend(fontsize=8)
    return fig


def plot_delay_growth(result):
    """Cost, median endpoint error and endpoint scatter against the motor delay (top row) and the
    sensory delay (bottom row): the Monte Carlo (mean with its 95 % interval for the cost) beside
    the local (linearised) prediction, where there is one."""
    rows = [(name, pts, key) for name, pts, key in (("motor", result.motor, "delay"),
                                                     ("sensory", result.sensory, "sensory_delay")) if pts]
    fig = figure(figsize=(13, 3.6 * len(rows)), layout="constrained")
    axes = np.atleast_2d(fig.subplots(len(rows), 3))
    for (name, pts, key), row in zip(rows, axes):
        d = np.array([1e3 * (getattr(p, key) or 0.0) for p in pts])
        mean = np.array([p.cost.mean for p in pts])
        lo, hi = (np.array([p.cost.ci95[i] for p in pts]) for i in (0, 1))
        row[0].errorbar(d, mean, yerr=[mean - lo, hi - mean], fmt="o-", color="tab:blue", capsize=3,
                        label="Monte Carlo mean, 95 % CI")
        row[0].plot(d, [p.predicted_cost for p in pts], "s--", color="tab:orange", label="linearised prediction")
        row[0].set_yscale("log")
        row[0].set_ylabel("cost [-]")
        row[1].plot(d, [1e3 * p.error_median for p in pts], "o-", color="tab:blue", label="Monte Carlo median")
        row[2].plot(d, [1e3 * p.scatter for p in pts], "o-", color="tab:blue", label="Monte Carlo RMS")
        if all(p.predicted_scatter is not None for p in pts):
            row[1].plot(d, [1e3 * p.predicted_error for p in pts], "s--", color="tab:orange",
                        label="linearised prediction (RMS)")
            row[2].plot(d, [1e3 * p.predicted_scatter for p in pts], "s--", color="tab:orange",
                        label="linearised prediction")
        row[1].set_ylabel("endpoint error [mm]")
        row[2].set_ylabel("endpoint scatter [mm]")
        for ax in row:
            ax.set_xlabel(f"{name} delay [ms]")
            ax.legend(fontsize=8)
    fig.suptitle(f"Cost, endpoint error and scatter against the delay ({result.problem.name})")
    return fig
