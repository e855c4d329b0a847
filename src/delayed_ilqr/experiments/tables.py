"""Tables of the studies and of single solves, as strings: every row is built here, once.

A table is a header and rows of strings (`delay_study_rows`, `center_out_rows`),
formatted as aligned plain text (`text_table`) or GitHub markdown (`markdown_table`);
the ``solve`` and ``simulate`` commands print two-column summaries (`pairs`).

Every study table reports the Monte Carlo cost as its mean with the bootstrap 95 % interval and its
median (`delayed_ilqr.statistics`), beside the local (linearised) prediction
``Solution.expected_cost``; the ``*_warnings`` functions give the one-line warnings of a study
whose Monte Carlo mean departs from that prediction by more than
`PREDICTION_FACTOR` either way.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .. import Status
from ..statistics import prediction_warning, sample_stats
from .delay_study import ControllerResult
from .delay_text import delay_text
from .designs import REGISTRY

__all__ = ["num", "unit_scale", "PREDICTED", "mc_record", "delay_study_rows", "center_out_rows", "records_table",
           "text_table", "markdown_table", "pairs", "solve_summary", "simulate_summary", "sweep_rows",
           "delay_study_warnings", "center_out_warnings", "sweep_warnings"]

#: The column label of ``Solution.expected_cost`` in every table.
PREDICTED = "local prediction E[J] (linearised)"

Table = tuple[list[str], list[list[str]]]


def num(value: float, digits: int = 4) -> str:
    """``value`` to ``digits`` significant digits; "nan", "inf", "-inf" spelled out."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{value:.{digits}g}"


def unit_scale(unit: str) -> tuple[float, str]:
    """(factor, unit) to print a quantity in: metres as millimetres, anything else as it is."""
    return (1e3, "mm") if unit == "m" else (1.0, unit)


def _mean_ci(st, scale: float = 1.0, digits: int = 4) -> str:
    """Mean over the trials that did not diverge with its bootstrap 95 % interval."""
    if not math.isfinite(st.mean):
        return "none (all diverged)"
    return f"{num(scale * st.mean, digits)} [{num(scale * st.ci95[0], digits)}, {num(scale * st.ci95[1], digits)}]"


def _median_iqr(st, scale: float = 1.0, digits: int = 4) -> str:
    """Median over all trials (diverged as +inf) with the inter-quartile range."""
    return f"{num(scale * st.median, digits)} [{num(scale * st.iqr[0], digits)}, {num(scale * st.iqr[1], digits)}]"


def mc_record(st, prefix: str = "MC J") -> dict:
    """A `SampleStats` as record columns (JSON-ready, None for
    non-finite): ``<prefix> mean``, its bootstrap 95 % interval ``<prefix> mean CI low/high``,
    ``<prefix> median``, and ``diverged``."""
    f = lambda v: None if v is None or not math.isfinite(v) else float(v)          # noqa: E731
    return {f"{prefix} mean": f(st.mean), f"{prefix} mean CI low": f(st.ci95[0]),
            f"{prefix} mean CI high": f(st.ci95[1]), f"{prefix} median": f(st.median),
            "diverged": int(st.n_diverged)}


def delay_study_rows(results: Sequence[ControllerResult]) -> Table:
    """One row per controller and delay: convergence, solve time, predicted and Monte Carlo costs
    (mean over the trials that did not diverge with its bootstrap 95 % interval; median and
    inter-quartile range), diverged trials (one definition, [`delayed_ilqr.statistics`][delayed_ilqr.statistics]) and
    the endpoint error likewise."""
    scale, unit = unit_scale(results[0].endpoint_unit) if results else (1.0, "")
    label = results[0].endpoint_label if results else "endpoint error"
    unit_text = f" [{unit}]" if unit else ""
    header = ["delay", "controller", "converged", "iter", "solve [ms]", PREDICTED,
              "MC mean J [95% CI]", "MC median J [IQR]", "diverged", f"{label}{unit_text}: mean [95% CI]",
              f"{label}{unit_text}: median [IQR]"]
    rows = []
    for r in results:
        c, e = r.cost, r.endpoint_error
        rows.append([delay_text(r.problem), r.controller, "yes" if r.converged else "NO", str(r.iterations),
                     f"{1e3 * r.solve_time:.1f}", num(r.predicted_cost), _mean_ci(c), _median_iqr(c),
                     f"{c.n_diverged}/{c.n}", _mean_ci(e, scale, 3), _median_iqr(e, scale, 3)])
    return header, rows


_CENTER_OUT_HEADER = ["delay", "design", "converged", "iterations median [range]", "solve time per target",
                      "nominal hand error (max)", "nominal final hand speed (max)",
                      f"{PREDICTED} (mean over targets)", "MC mean J [95% CI] (all trials)", "MC median J (all trials)",
                      "diverged", "MC hand error: mean [95% CI]", "MC hand error: median",
                      "MC endpoint spread (1-sigma major axis, mean [range])"]


def _pooled(r, what: str):
    """SampleStats of the per-trial ``what`` ("mc_cost" or "mc_error") pooled over the targets."""
    return sample_stats(np.concatenate([getattr(t, what) for t in r.targets]),
                        np.concatenate([t.diverged for t in r.targets]))


def _center_out_row(r) -> list[str]:
    its = [t.iterations for t in r.targets]
    n = len(r.targets)
    spreads = [1e3 * t.spread for t in r.targets]
    cost, error = _pooled(r, "mc_cost"), _pooled(r, "mc_error")
    return [delay_text(r.delay), r.design, f"{sum(t.converged for t in r.targets)}/{n}",
            f"{int(np.median(its))} [{min(its)}-{max(its)}]", f"{1e3 * r.solve_time / n:.0f} ms",
            f"{1e3 * max(t.hand_error for t in r.targets):.2f} mm",
            f"{1e2 * max(t.hand_speed for t in r.targets):.2f} cm/s",
            f"{np.mean([t.predicted_cost for t in r.targets]):.3g}", _mean_ci(cost, 1.0, 3), num(cost.median, 3),
            f"{cost.n_diverged}/{cost.n}", _mean_ci(error, 1e3, 3) + " mm", f"{num(1e3 * error.median, 3)} mm",
            f"{np.mean(spreads):.2f} mm [{min(spreads):.2f}-{max(spreads):.2f}]"]


def center_out_rows(results: Sequence) -> Table:
    """One row per delay and design of the center-out study ([`center_out.DelayResult`][delayed_ilqr.experiments.center_out.DelayResult]):
    the local (linearised) prediction averaged over the targets; the Monte Carlo cost and hand
    error over all trials of all targets (mean over the trials that did not diverge with its
    bootstrap 95 % interval, median over all); how many diverged; the spread per target."""
    return list(_CENTER_OUT_HEADER), [_center_out_row(r) for r in results]


def records_table(records: Sequence[dict]) -> Table:
    """Records (one dict per row, the same keys; None shown as "-") as a table."""
    header = list(records[0])
    cell = lambda v: "-" if v is None else (num(v) if isinstance(v, float) else str(v))
    return header, [[cell(r[h]) for h in header] for r in records]


def sweep_rows(ds) -> Table:
    """One row per cell of a sweep's Dataset ([`delayed_ilqr.sweep`][delayed_ilqr.sweeps.sweep]): its grid values, the
    solve (status, iterations, the local (linearised) prediction E[J]) and the Monte Carlo over the
    seeds: the mean cost with its 95 % interval (one seed: its bootstrap interval; several: the
    mean of the seeds' means +/- 1.96 standard errors across seeds), the median cost and the median
    endpoint error (means of the seeds' medians), the diverged trials. A delay of the grid (in s) is
    written as `delay_text.delay_text` writes it."""
    dims = list(ds["status"].dims)
    scale, unit = unit_scale(ds.mc_endpoint_error_median.attrs.get("units", ""))
    header = dims + ["status", "iter", PREDICTED, "MC mean J [95% CI]", "MC median J", "diverged",
                     f"median endpoint error [{unit}]" if unit else "median endpoint error"]
    trials = int(ds.attrs.get("trials", 0)) * ds.sizes.get("seed", 1)
    rows = []
    for index in np.ndindex(*(ds.sizes[d] for d in dims)):
        cell = ds.isel(dict(zip(dims, index)))
        values = []
        for d in dims:
            v = np.asarray(cell[f"{d}_value"].values if f"{d}_value" in cell.coords else cell[d].values)
            if _is_delay(ds, d) and np.issubdtype(v.dtype, np.number):
                values.append(delay_text(v))            # "50 ms", "[50, 70] ms", 25.5 ms not rounded
            else:
                values.append(np.array2string(v, precision=3) if v.ndim else
                              (num(float(v)) if np.issubdtype(v.dtype, np.number) else str(v)))
        status = int(cell.status)
        rows.append(values + [Status(status).name if status >= 0 else "missing", str(int(cell.iterations)),
                              num(float(cell.expected_cost)), _seeds_mean_ci(cell),
                              num(float(cell.mc_cost_median.mean("seed"))),
                              f"{int(cell.mc_diverged.sum())}/{trials}",
                              num(scale * float(cell.mc_endpoint_error_median.mean("seed")))])
    return header, rows


def _is_delay(ds, dim: str) -> bool:
    """Whether grid dimension ``dim`` is a delay in seconds (``delay``, ``sensory_delay``, ...)."""
    coord = ds.coords[f"{dim}_value"] if f"{dim}_value" in ds.coords else ds.coords.get(dim)
    return dim.endswith("delay") and coord is not None and coord.attrs.get("units") == "s"


def _seeds_mean_ci(cell) -> str:
    """The mean cost of a sweep cell with its 95 % interval (see `sweep_rows`)."""
    means = np.asarray(cell.mc_cost_mean.values, dtype=np.float64).ravel()
    if means.size == 1:
        lo, hi = float(cell.mc_cost_ci_low.values.ravel()[0]), float(cell.mc_cost_ci_high.values.ravel()[0])
    else:
        half = 1.959963984540054 * np.std(means, ddof=1) / np.sqrt(means.size)
        lo, hi = float(means.mean() - half), float(means.mean() + half)
    return f"{num(float(means.mean()))} [{num(lo)}, {num(hi)}]"


def delay_study_warnings(results: Sequence[ControllerResult]) -> list[str]:
    """One line per controller and delay whose Monte Carlo mean cost departs from its local
    (linearised) prediction by more than the factor of `prediction_warning`."""
    lines = [prediction_warning(f"{r.model}, {r.controller} at {delay_text(r.problem)}", r.cost.mean, r.predicted_cost)
             for r in results]
    return [w for w in lines if w]


def center_out_warnings(results: Sequence) -> list[str]:
    """One line per delay and design of the center-out study where, on some target, the Monte Carlo
    mean cost departs from the target's local prediction by more than the factor (which targets,
    and the range of their ratios)."""
    lines = []
    for r in results:
        bad = [(j, t) for j, t in enumerate(r.targets)
               if prediction_warning("", t.cost_stats.mean, t.predicted_cost) is not None]
        if not bad:
            continue
        ratios = [t.cost_stats.mean / t.predicted_cost if t.predicted_cost > 0 else math.inf for _, t in bad]
        worst = bad[int(np.argmax([abs(math.log(x)) if 0 < x < math.inf else math.inf for x in ratios]))][1]
        line = prediction_warning(f"{r.design} at {delay_text(r.delay)}, targets "
                                  f"{', '.join(str(j + 1) for j, _ in bad)} of {len(r.targets)} (the worst shown)",
                                  worst.cost_stats.mean, worst.predicted_cost)
        lines.append(line + f"; MC / prediction on these targets {num(min(ratios), 3)}-{num(max(ratios), 3)}")
    return lines


def sweep_warnings(ds) -> list[str]:
    """One line when, in some cells of a sweep, the Monte Carlo mean cost (over the seeds) departs
    from the local prediction by more than the factor: how many cells, and the worst."""
    mc = np.asarray(ds.mc_cost_mean.mean("seed").values, dtype=np.float64).ravel()
    predicted = np.asarray(ds.expected_cost.values, dtype=np.float64).ravel()
    bad = [i for i in range(mc.size) if prediction_warning("", mc[i], predicted[i]) is not None]
    if not bad:
        return []
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = mc[bad] / predicted[bad]
    worst = bad[int(np.nanargmax(np.abs(np.log(np.where(ratio > 0, ratio, np.nan))))) if np.any(ratio > 0) else 0]
    return [prediction_warning(f"sweep, {len(bad)} of {mc.size} cells (the worst shown)", mc[worst], predicted[worst])]


def text_table(table: Table) -> str:
    """A plain-text table with aligned columns."""
    header, rows = table
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)),
             "  ".join("-" * w for w in widths)]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in rows]
    return "\n".join(line.rstrip() for line in lines)


def markdown_table(table: Table) -> str:
    """The same table in GitHub markdown."""
    header, rows = table
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def pairs(rows: Sequence[tuple[str, str]]) -> str:
    """Two aligned columns: one ``key  value`` line per row."""
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k.ljust(width)}  {v}" for k, v in rows)


def _problem_rows(problem, description: str, noise: bool) -> list[tuple[str, str]]:
    return [("model", f"{problem.name}: {description}"),
            ("delay", delay_text(problem, steps=True)),
            ("noise", "yes" if noise else "no")]


def solve_summary(problem, description: str, noise: bool, method: str, timed, endpoint) -> list[tuple[str, str]]:
    """The ``solve`` command's summary rows.

    Args:
        problem: the problem solved; description: its model's description; noise: whether noisy.
        method: the backward pass; timed: (solution, seconds, first seconds) of the solve.
        endpoint: (label, unit, value) of the nominal's endpoint error.
    """
    sol, solve_time, first = timed
    status = Status(int(sol.status))
    label, unit, value = endpoint
    scale, unit = unit_scale(unit)
    return _problem_rows(problem, description, noise) + [
        ("method", method),
        ("status", f"{status.name}: {status.message}"),
        ("iterations", str(int(sol.iterations))),
        ("cost (eq. 2, nominal)", num(float(sol.cost))),
        ("expected cost (LQG): the local (linearised) prediction of E[J]", num(float(sol.expected_cost))),
        (f"nominal {label}", f"{num(float(scale * value))} {unit}".rstrip()),
        ("solve time", f"{1e3 * solve_time:.1f} ms (first call with compilation: {first:.2f} s)"),
    ]


def _endpoint_text(result: ControllerResult) -> str:
    scale, unit = unit_scale(result.endpoint_unit)
    e = result.endpoint_error
    return (f"mean {_mean_ci(e, scale)} {unit}, median {_median_iqr(e, scale)} {unit} "
            f"(mean over the {e.n - e.n_diverged} trials that did not diverge)")


def simulate_summary(r: ControllerResult, description: str) -> list[tuple[str, str]]:
    """The ``simulate`` command's summary rows of one evaluated controller."""
    c = r.cost
    return _problem_rows(r.problem, description, r.noise) + [
        ("controller", f"{r.controller}: {REGISTRY[r.controller].description}"),
        ("solve", f"{r.status} after {r.iterations} iterations, {1e3 * r.solve_time:.1f} ms"),
        (PREDICTED, num(r.predicted_cost)),
        ("trials", f"{c.n} (seed {r.seed}, {r.substeps} substep(s) per step)"),
        ("diverged", f"{c.n_diverged} of {c.n} (cost not finite or above {num(r.divergence_bound)})"),
        ("Monte Carlo mean J [95% CI]", _mean_ci(c) + " (trials that did not diverge; bootstrap interval)"),
        ("Monte Carlo median J [IQR]", _median_iqr(c)),
        ("Monte Carlo / prediction", delay_study_warnings([r])[0].removeprefix("warning: ")
         if delay_study_warnings([r]) else "within the factor of 2 either way"),
        (f"final {r.endpoint_label}", _endpoint_text(r)),
        ("mean final state", np.array2string(np.asarray(r.summary.final_state_mean), precision=4)),
    ]
