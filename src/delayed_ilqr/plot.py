"""Figures for solutions, Monte Carlo runs and delay studies.

Every function builds a :class:`matplotlib.figure.Figure` directly (no ``pyplot``: no global
state, no backend switch in the caller's session, never ``show()``) and returns it; save it with
``fig.savefig("name.png")`` (rendered by Agg). matplotlib is imported inside the functions, so
importing :mod:`delayed_ilqr` does not import it.
"""
from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from typing import Optional, Sequence

import numpy as np

__all__ = ["plot_trajectories", "plot_hand_paths", "plot_delay_study", "plot_convergence", "state_labels",
           "COLORS"]

COLORS = {"aware": "tab:blue", "ignorant": "tab:red", "augmented": "tab:green"}
_LABELS = {
    "aware": "delay-aware",
    "ignorant": "delay-ignorant",
    "augmented": "augmented",
}

_STATE_LABELS = {
    "arm2": (["shoulder angle q1 [rad]", "elbow angle q2 [rad]", "shoulder velocity dq1 [rad/s]",
              "elbow velocity dq2 [rad/s]"], ["shoulder torque u1 [N m]", "elbow torque u2 [N m]"]),
    "point_mass": (["position x [m]", "position y [m]", "velocity vx [m/s]", "velocity vy [m/s]"],
                   ["force fx [N]", "force fy [N]"]),
    "pendulum": (["angle theta [rad]", "angular velocity [rad/s]"], ["torque u [N m]"]),
    "cart_pole": (["cart position x [m]", "pole angle theta [rad]", "cart velocity [m/s]",
                   "pole angular velocity [rad/s]"], ["force on cart u [N]"]),
    "arm2_muscle6": (["shoulder angle q1 [rad]", "elbow angle q2 [rad]", "shoulder velocity dq1 [rad/s]",
                      "elbow velocity dq2 [rad/s]"] + [f"activation a{i}" for i in range(1, 7)],
                     [f"excitation u{i}" for i in range(1, 7)]),
}


def _figure(**kwargs):
    from matplotlib.figure import Figure
    return Figure(**kwargs)


def state_labels(problem) -> tuple[list[str], list[str]]:
    """(state labels [n], control labels [d]) with units for the built-in models, else x[i] / u[j]."""
    known = _STATE_LABELS.get(problem.name)
    if known is not None and len(known[0]) == problem.n_states and len(known[1]) == problem.n_controls:
        return list(known[0]), list(known[1])
    return [f"x[{i}]" for i in range(problem.n_states)], [f"u[{j}]" for j in range(problem.n_controls)]


def _label(controller: str) -> str:
    return _LABELS.get(controller, controller)


def plot_trajectories(problem, policy, runs=None, n_trials: int = 5, title: Optional[str] = None):
    """States and commands against time: the policy's nominal and a few Monte Carlo trials.

    Args:
        problem: the :class:`~delayed_ilqr.Problem` (for dt, names and the target).
        policy: a :class:`~delayed_ilqr.Policy` or :class:`~delayed_ilqr.Solution` (its nominal is drawn).
        runs: optional :class:`~delayed_ilqr.Runs`; its first ``n_trials`` trials are drawn thin.
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
    t_x, t_u = dt * np.arange(K + 1), dt * np.arange(K)
    s_labels, u_labels = state_labels(problem)
    total = nx + nd
    ncols = min(total, 3)
    nrows = math.ceil(total / ncols)
    fig = _figure(figsize=(4.2 * ncols, 2.9 * nrows), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax in axes[total:]:
        fig.delaxes(ax)
    show = 0 if runs is None else min(int(n_trials), int(np.shape(runs.x)[0]))
    xs = np.asarray(runs.x[:show]) if show else None
    us = np.asarray(runs.u[:show]) if show else None
    target = getattr(problem.cost, "x_target", None)
    all_x = None if runs is None else np.asarray(runs.x)
    all_u = None if runs is None else np.asarray(runs.u)
    for i in range(nx):
        ax = axes[i]
        for j in range(show):
            ax.plot(t_x, xs[j, :, i], color="0.55", lw=0.8, alpha=0.8,
                    label="Monte Carlo trials" if j == 0 else None)
        ax.plot(t_x, x_nom[:, i], color="tab:blue", lw=2.0, label="nominal")
        if target is not None:
            ax.scatter([t_x[-1]], [float(np.asarray(target)[i])], marker="*", s=120, color="tab:orange",
                       zorder=5, label="target")
        _robust_limits(ax, x_nom[:, i], None if all_x is None else all_x[:, :, i],
                       None if target is None else float(np.asarray(target)[i]))
        ax.set_ylabel(s_labels[i])
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
    for k in range(nd):
        ax = axes[nx + k]
        for j in range(show):
            ax.step(t_u, us[j, :, k], where="post", color="0.55", lw=0.8, alpha=0.8)
        ax.step(t_u, u_nom[:, k], where="post", color="tab:blue", lw=2.0)
        _robust_limits(ax, u_nom[:, k], None if all_u is None else all_u[:, :, k], None)
        ax.set_ylabel(u_labels[k])
        ax.set_xlabel("time sent [s]")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    if title is None:
        title = (f"{problem.name}: states and commands sent (acting {problem.delay:g} s later), "
                 + ("noisy plant" if problem.noise is not None else "deterministic plant"))
    fig.suptitle(title)
    return fig


def _robust_limits(ax, nominal, trials, target):
    """y-limits around the nominal and the 5-95 % band of all trials at each time (plus a quarter
    of the range), so that a few diverging trials do not flatten the rest (they are clipped)."""
    values = [np.asarray(nominal, dtype=float)]
    if target is not None:
        values.append(np.array([target]))
    if trials is not None and trials.shape[0]:
        finite = np.where(np.isfinite(trials), trials, np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)        # all-NaN columns of blown-up runs
            band = np.nanpercentile(finite, [5.0, 95.0], axis=0)
        values.append(band[np.isfinite(band)])
    v = np.concatenate([np.ravel(a) for a in values])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return
    lo, hi = float(v.min()), float(v.max())
    pad = (0.25 if trials is not None else 0.08) * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.1
    ax.set_ylim(lo - pad, hi + pad)


def _ellipse(ax, points, color, n_sigma=2.0, label=None):
    """Draws the n_sigma covariance ellipse of points [N, 2]; returns the patch (None if degenerate)."""
    from matplotlib.patches import Ellipse
    if points.shape[0] < 3:
        return None
    cov = np.cov(points, rowvar=False)
    if not np.all(np.isfinite(cov)):
        return None
    vals, vecs = np.linalg.eigh(cov)
    vals = np.clip(vals, 0.0, None)
    angle = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
    patch = Ellipse(points.mean(axis=0), 2 * n_sigma * math.sqrt(vals[1]), 2 * n_sigma * math.sqrt(vals[0]),
                    angle=angle, fill=False, edgecolor=color, lw=2.0, label=label)
    ax.add_patch(patch)
    return patch


def plot_hand_paths(results: Sequence, n_paths: int = 10):
    """Hand paths of the two-link arms and the spread of their endpoints, per delay and controller.

    Args:
        results: :class:`~delayed_ilqr.study.ControllerResult` objects of an arm model (from
            :func:`~delayed_ilqr.study.compare_delays` or :func:`~delayed_ilqr.study.evaluate`).
        n_paths: Monte Carlo hand paths drawn per controller.

    Returns:
        A Figure with two rows and one column per delay. Top: hand paths in the plane (shoulder at
        the origin; per controller its nominal, thick, and ``n_paths`` trials, thin), start and
        target, viewed around the nominal paths (trials that wander off are clipped). Bottom: every trial's endpoint relative to the target (mm) with the 2-sigma
        covariance ellipse of the finite endpoints; the view is set by the tightest controller and
        legends count the endpoints outside it.

    Raises:
        ValueError: when the results are not of an arm model.
    """
    from .models.arm2 import hand_position
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one ControllerResult; got none")
    delays = sorted({r.delay for r in results})
    fig = _figure(figsize=(5.0 * len(delays), 9.0), layout="constrained")
    axes = fig.subplots(2, len(delays), squeeze=False)
    for col, tau in enumerate(delays):
        group = [r for r in results if r.delay == tau]
        top, bottom = axes[0, col], axes[1, col]
        zoom, nominals = [], []
        for r in group:
            kin = _arm_of(r)
            if kin is None:
                raise ValueError(f"plot_hand_paths needs an arm model (arm2, arm2_muscle6); got {r.model!r}")
            params, target = kin
            color = COLORS.get(r.controller, None)
            x = np.asarray(r.runs.x)
            with np.errstate(invalid="ignore"):
                hands = np.asarray(hand_position(np.asarray(x[:, :, :2]), params))   # [N, K+1, 2]
                nominal = np.asarray(hand_position(np.asarray(r.solution.x[:, :2]), params))
            for j in range(min(n_paths, hands.shape[0])):
                top.plot(hands[j, :, 0], hands[j, :, 1], color=color, lw=0.6, alpha=0.45)
            top.plot(nominal[:, 0], nominal[:, 1], color=color, lw=2.2, label=f"{_label(r.controller)} nominal")
            nominals.append(nominal)
            ends = 1e3 * (hands[:, -1] - target)
            finite = np.all(np.isfinite(ends), axis=1)
            zoom.append((r, ends, finite, color))
        start = np.asarray(hand_position(np.asarray(group[0].runs.x[0, 0, :2]), params))
        top.scatter([start[0]], [start[1]], marker="o", s=60, color="k", zorder=6, label="start")
        top.scatter([target[0]], [target[1]], marker="*", s=180, color="tab:orange", zorder=6, label="target")
        # view: the nominal paths, start and target with a margin; trials that leave it are clipped
        box = np.vstack([start, target] + [n for n in nominals])
        lo, hi = box.min(axis=0), box.max(axis=0)
        centre, half_box = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 0.08
        top.set_xlim(centre[0] - half_box, centre[0] + half_box)
        top.set_ylim(centre[1] - half_box, centre[1] + half_box)
        top.set_aspect("equal")
        top.set_xlabel("hand x [m]")
        top.set_ylabel("hand y [m]")
        top.set_title(f"delay {1e3 * tau:g} ms: hand paths ({min(n_paths, hands.shape[0])} trials each)")
        top.grid(alpha=0.3)
        top.legend(loc="lower left", fontsize=8, framealpha=0.9)
        # the zoom: wide enough for the tightest controller's endpoints (99th percentile), at least 5 mm
        spans = [np.percentile(np.abs(e[f]), 99) for _, e, f, _ in zoom if np.any(f)]
        half = max(5.0, 1.3 * min(spans)) if spans else 5.0
        for r, ends, finite, color in zoom:
            inside = finite & np.all(np.abs(ends) <= half, axis=1)
            outside = int(ends.shape[0] - np.count_nonzero(inside))
            label = f"{_label(r.controller)} endpoints" + (f" ({outside} outside view)" if outside else "")
            bottom.scatter(ends[inside, 0], ends[inside, 1], s=5, color=color, alpha=0.35, label=label)
            _ellipse(bottom, ends[finite], color, label=f"{_label(r.controller)} 2-sigma ellipse")
        bottom.scatter([0.0], [0.0], marker="*", s=180, color="tab:orange", zorder=6, label="target")
        bottom.set_xlim(-half, half)
        bottom.set_ylim(-half, half)
        bottom.set_aspect("equal")
        bottom.set_xlabel("endpoint x - target x [mm]")
        bottom.set_ylabel("endpoint y - target y [mm]")
        bottom.set_title(f"delay {1e3 * tau:g} ms: final hand positions (N = {group[0].runs.x.shape[0]})")
        bottom.grid(alpha=0.3)
        bottom.legend(loc="upper left", fontsize=7)
    noise = "noisy" if results[0].noise else "deterministic"
    fig.suptitle(f"{results[0].model}: reaching with delayed commands ({noise} plant)")
    return fig


def _arm_of(result):
    """(params, hand target) of a result's arm (see :func:`~delayed_ilqr.study.arm_kinematics`), or None."""
    from .study import arm_kinematics
    problem = getattr(result, "problem", None)
    if problem is not None:
        return arm_kinematics(problem)
    return None


def plot_delay_study(results: Sequence):
    """Expected cost and endpoint error against the delay, one series per controller.

    Args:
        results: :class:`~delayed_ilqr.study.ControllerResult` objects (several delays).

    Returns:
        A Figure with two axes. Left: Monte Carlo mean cost with 95 % confidence intervals (filled
        markers, log scale) and the controller's own predicted E[J] (open markers, dashed). Where a
        mean is infinite (some trials diverged) the median and its 95 % interval are drawn instead
        with a triangle marker and the diverged count is written next to it. Right: the endpoint
        error (mm for the arm and the point mass), mean with 95 % interval, or median likewise.
    """
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one ControllerResult; got none")
    fig = _figure(figsize=(12.5, 5.8), layout="constrained")
    ax_cost, ax_err = fig.subplots(1, 2)
    controllers = list(dict.fromkeys(r.controller for r in results))
    unit = results[0].endpoint_unit
    scale, unit_text = (1e3, "mm") if unit == "m" else (1.0, unit)
    offsets = np.linspace(-1, 1, len(controllers)) * (0.6 if len(controllers) > 1 else 0.0)
    delays = sorted({r.delay for r in results})
    step = 1e3 * (min(np.diff(delays)) if len(delays) > 1 else 0.05)
    for ci, (c, off) in enumerate(zip(controllers, offsets)):
        rows = sorted((r for r in results if r.controller == c), key=lambda r: r.delay)
        color = COLORS.get(c, None)
        tau = np.array([1e3 * r.delay for r in rows]) + off * 0.04 * step
        for ax, get, s in ((ax_cost, lambda r: r.cost, 1.0), (ax_err, lambda r: r.endpoint_error, scale)):
            stats = [get(r) for r in rows]
            mean_ok = np.array([math.isfinite(st.mean) and math.isfinite(st.ci95[0]) for st in stats])
            val = np.array([s * (st.mean if ok else st.median) for st, ok in zip(stats, mean_ok)])
            lo = np.array([s * (st.ci95[0] if ok else st.median_ci95[0]) for st, ok in zip(stats, mean_ok)])
            hi = np.array([s * (st.ci95[1] if ok else st.median_ci95[1]) for st, ok in zip(stats, mean_ok)])
            yerr = np.vstack([np.clip(val - lo, 0, None), np.clip(hi - val, 0, None)])
            yerr = np.where(np.isfinite(yerr), yerr, 0.0)
            ax.plot(tau, val, color=color, lw=1.5, alpha=0.7)
            if np.any(mean_ok):
                ax.errorbar(tau[mean_ok], val[mean_ok], yerr=yerr[:, mean_ok], fmt="o", color=color, capsize=4,
                            ms=7, label=f"{_label(c)}: Monte Carlo mean, 95% CI")
            if np.any(~mean_ok):
                ax.errorbar(tau[~mean_ok], val[~mean_ok], yerr=yerr[:, ~mean_ok], fmt="^", color=color, capsize=4,
                            ms=8, label=f"{_label(c)}: median, 95% CI (mean infinite)")
                for t, v, st, ok in zip(tau, val, stats, mean_ok):
                    if not ok and st.n_diverged and math.isfinite(v):
                        ax.annotate(f"{st.n_diverged}/{st.n} diverged", (t, v), textcoords="offset points",
                                    xytext=(8, 6 - 14 * ci), fontsize=8, color=color)
        pred = np.array([r.predicted_cost for r in rows])
        ax_cost.plot(tau, pred, ls="--", marker="o", mfc="white", color=color, ms=7,
                     label=f"{_label(c)}: its own predicted E[J]")
    ax_cost.set_yscale("log")
    ax_cost.set_xlabel("input delay [ms]")
    ax_cost.set_ylabel("cost J (eq. 2)")
    ax_cost.set_title("expected cost")
    ax_cost.grid(alpha=0.3, which="both")
    ax_cost.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    ax_err.set_yscale("log")
    ax_err.set_xlabel("input delay [ms]")
    ax_err.set_ylabel(f"{results[0].endpoint_label}" + (f" [{unit_text}]" if unit_text else ""))
    ax_err.set_title(f"final {results[0].endpoint_label}")
    ax_err.grid(alpha=0.3, which="both")
    ax_err.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2)
    n = results[0].cost.n
    noise = "noisy" if results[0].noise else "deterministic"
    fig.suptitle(f"{results[0].model}: delay-aware vs delay-ignorant control, {n} {noise} trials per point")
    return fig


def plot_convergence(solutions, title: Optional[str] = None):
    """Cost against iteration (log scale) for one solution or a ``{label: Solution}`` mapping.

    Returns:
        A Figure with one axis: per solution one line of ``trace.cost`` (eq. 2 on the nominal) and,
        when the problem is noisy (the trace's merit differs from its cost), a dashed line of the
        noise-aware merit the line search minimises. Open markers are rejected iterations.
    """
    if not isinstance(solutions, Mapping):
        solutions = {"iLQG": solutions}
    fig = _figure(figsize=(7.5, 5.0), layout="constrained")
    ax = fig.subplots()
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
            ax.scatter(it[rejected], cost[rejected], facecolors="white", edgecolors=color, s=18, zorder=3)
        if not np.allclose(merit, cost, rtol=1e-12, equal_nan=True):
            ax.plot(it, merit, color=color, ls="--", label=f"{label}: merit (cost + noise terms)")
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    ax.set_title(title or "iLQG convergence (open markers: rejected steps)")
    return fig


def plot_center_out(results: Sequence, n_paths: int = 5):
    """Center-out reaches of the six-muscle arm: hand paths and endpoint ellipses, one panel per
    delay (columns) and design (rows).

    Args:
        results: :class:`~delayed_ilqr.center_out.DelayResult` objects.
        n_paths: Monte Carlo hand paths drawn per target.

    Returns:
        A Figure: per delay and design, each target's nominal hand path (thick), ``n_paths`` noisy
        trials (thin), the target (star) and the 2-sigma covariance ellipse of the trials' final
        hand positions; the start hand position is the black dot.
    """
    from .center_out import _hand
    results = list(results)
    if not results:
        raise ValueError("results must hold at least one DelayResult; got none")
    designs = list(dict.fromkeys(r.design for r in results))
    delays = list(dict.fromkeys(r.delay for r in results))
    fig = _figure(figsize=(4.6 * len(delays), 4.8 * len(designs)), layout="constrained")
    grid = fig.subplots(len(designs), len(delays), squeeze=False)
    axes = [grid[designs.index(r.design), delays.index(r.delay)] for r in results]
    from matplotlib import colormaps
    cmap = [colormaps["tab10"](j % 10) for j in range(len(results[0].targets))]
    for ax, r in zip(axes, results):
        nominal = _hand(r.solutions.x)                                      # [targets, K+1, 2]
        for j, t in enumerate(r.targets):
            color = cmap[j]
            trials = _hand(r.runs[j].x[:n_paths])
            for path in trials:
                ax.plot(path[:, 0], path[:, 1], color=color, lw=0.5, alpha=0.5)
            ax.plot(nominal[j, :, 0], nominal[j, :, 1], color=color, lw=2.0)
            ax.scatter([t.target[0]], [t.target[1]], marker="*", s=120, color=color, edgecolor="k", zorder=6)
            _ellipse(ax, t.endpoints[np.all(np.isfinite(t.endpoints), axis=1)], color)
        start = nominal[0, 0]
        ax.scatter([start[0]], [start[1]], marker="o", s=50, color="k", zorder=7, label="start")
        radius = float(np.max(np.linalg.norm(np.stack([t.target for t in r.targets]) - start, axis=1)))
        half = 1.8 * radius
        ax.set_xlim(start[0] - half, start[0] + half)
        ax.set_ylim(start[1] - half, start[1] + half)
        ax.set_aspect("equal")
        ax.set_xlabel("hand x [m]")
        ax.set_ylabel("hand y [m]")
        converged = sum(t.converged for t in r.targets)
        ax.set_title(f"{r.design}, delay {1e3 * r.delay:g} ms ({converged}/{len(r.targets)} converged)")
        ax.grid(alpha=0.3)
    fig.suptitle(f"six-muscle arm, center-out: nominal paths, {n_paths} noisy trials per target, "
                 f"2-sigma endpoint ellipses (N = {results[0].runs[0].x.shape[0]})")
    return fig


def plot_excitations(result):
    """Nominal muscle excitations u_k of every target at one delay and design (one panel per target).

    Args:
        result: a :class:`~delayed_ilqr.center_out.DelayResult`.

    Returns:
        A Figure with one panel per target (2 rows), the six excitations against time (the command
        sent at t reaches the muscles at t + delay).
    """
    from .models.muscle import MUSCLES
    n = len(result.targets)
    cols = (n + 1) // 2
    fig = _figure(figsize=(3.2 * cols, 5.6), layout="constrained")
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
