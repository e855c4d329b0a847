"""Shared pieces of the figures: the Figure factory, controller colours, robust limits, ellipses."""
from __future__ import annotations

import math
import warnings

import numpy as np

COLORS = {"aware": "tab:blue", "ignorant": "tab:red", "augmented": "tab:green"}
_LABELS = {
    "aware": "delay-aware",
    "ignorant": "delay-ignorant",
    "augmented": "augmented",
}


def figure(**kwargs):
    """A matplotlib Figure (imported here, so that importing the package does not import matplotlib)."""
    from matplotlib.figure import Figure
    return Figure(**kwargs)


def controller_label(controller: str) -> str:
    """How a controller is named in legends ("delay-aware", ...)."""
    return _LABELS.get(controller, controller)


def robust_limits(ax, nominal, trials, target):
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


def ellipse(ax, points, color, n_sigma=2.0, label=None):
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


# the units every figure uses: a task-space speed in cm/s (lengths in metres), delays in ms
SPEED_UNITS = {"m": (100.0, "cm/s")}


def speed_unit(unit: str) -> tuple[float, str]:
    """(factor, unit) of a speed in a task space measured in ``unit``: cm/s for metres, else unit/s."""
    return SPEED_UNITS.get(unit, (1.0, f"{unit}/s"))


def suptitle(fig, text: str, fontsize: float = 12.0):
    """The figure's title, wrapped to the figure's width so that no line runs off the canvas."""
    import textwrap
    # an average character of the default font is about 0.55 em wide
    width = max(20, int(fig.get_size_inches()[0] * 72.0 / (0.6 * fontsize)))
    return fig.suptitle(textwrap.fill(text, width), fontsize=fontsize)


def command_unit(problem) -> str:
    """The unit of the commands, read from the control labels' brackets ("N m"), when all share
    one; "-" otherwise (dimensionless or mixed)."""
    import re
    from ..models.metadata import labels
    units = {m.group(1) if m else "-" for m in (re.search(r"\[([^\]]+)\]\s*$", s) for s in labels(problem)[1])}
    return units.pop() if len(units) == 1 else "-"
