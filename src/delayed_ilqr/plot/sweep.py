"""Figures straight from a sweep's Dataset ([`delayed_ilqr.sweep`][delayed_ilqr.sweeps.sweep]): the Monte Carlo cost and
the endpoint error against one grid dimension, one line per value of another."""
from __future__ import annotations

from typing import Mapping, Optional

import numpy as np

from ..experiments.tables import unit_scale
from ._common import figure, suptitle

__all__ = ["plot_sweep"]


def _label(da, unit: Optional[str] = None, extra: str = "") -> str:
    """Axis label from ``da``'s long name (and ``extra``) and unit (``unit`` overrides its own; "-"
    when it has none)."""
    name = da.attrs.get("long_name", da.name).split(" (")[0] + extra
    unit = da.attrs.get("units", "") if unit is None else unit
    return f"{name} [{unit if unit and unit != '1' else '-'}]"


def _axis_scale(da) -> tuple[float, Optional[str]]:
    """(factor, unit) of a grid axis on the figure: times in seconds (the delays) as ms, as every
    figure of the package draws delays; anything else as it is (unit None: its own)."""
    return (1e3, "ms") if da.attrs.get("units") == "s" else (1.0, None)


def plot_sweep(ds, x: Optional[str] = None, hue: Optional[str] = None, select: Optional[Mapping] = None):
    """Two panels against grid dimension ``x``: the Monte Carlo mean cost with its bootstrap 95 %
    interval (log scale), and the median endpoint error (in mm when the Dataset's unit is m); one
    line per value of ``hue``.

    Args:
        ds: the Dataset of [`delayed_ilqr.sweep`][delayed_ilqr.sweeps.sweep] (or [`delayed_ilqr.open_sweep`][delayed_ilqr.sweeps.open_sweep]).
        x: the dimension on the horizontal axis (default: the first grid dimension).
        hue: a dimension drawn as one line per value (default: the second grid dimension, if any).
        select: {dimension: index} for the other grid dimensions (default: their first value, named
            in the title). Seeds are pooled: the mean over seeds, the band from the lowest to the
            highest interval bound of any seed.

    Returns:
        A matplotlib Figure.
    """
    grid_dims = [d for d in ds["status"].dims]
    if not grid_dims:
        raise ValueError("ds must be a sweep Dataset with at least one grid dimension")
    x = grid_dims[0] if x is None else x
    if x not in grid_dims:
        raise ValueError(f"x must be one of the grid dimensions {grid_dims}; got {x!r}")
    if hue is None:
        hue = next((d for d in grid_dims if d != x), None)
    if hue is not None and (hue not in grid_dims or hue == x):
        raise ValueError(f"hue must be another of the grid dimensions {grid_dims}; got {hue!r}")
    select = dict(select or {})
    fixed = {d: select.get(d, 0) for d in grid_dims if d not in (x, hue)}
    sub = ds.isel(fixed)
    fig = figure(figsize=(10, 4), layout="constrained")
    cost_ax, error_ax = fig.subplots(1, 2)
    hues = [None] if hue is None else list(range(sub.sizes[hue]))
    x_factor, x_unit = _axis_scale(ds[x])
    xs = x_factor * np.asarray(sub[x].values)
    # endpoint errors in mm, as the sweep's table prints them (metres read badly at this scale)
    scale, error_unit = unit_scale(ds.mc_endpoint_error_median.attrs.get("units", ""))
    for j in hues:
        line = sub if j is None else sub.isel({hue: j})
        label = None if j is None else f"{hue} = {_value(line, hue)}"
        mean = line.mc_cost_mean.mean("seed").values
        low, high = line.mc_cost_ci_low.min("seed").values, line.mc_cost_ci_high.max("seed").values
        drawn = cost_ax.plot(xs, mean, marker="o", label=label)[0]
        cost_ax.fill_between(xs, low, high, color=drawn.get_color(), alpha=0.2)
        error_ax.plot(xs, scale * line.mc_endpoint_error_median.mean("seed").values, marker="o", label=label)
    cost_ax.set_yscale("log")
    cost_ax.set_ylabel(_label(ds.mc_cost_mean, extra=", 95 % CI"))
    error_ax.set_ylabel(_label(ds.mc_endpoint_error_median, error_unit))
    for ax in (cost_ax, error_ax):
        ax.set_xlabel(_label(ds[x], x_unit))
        ax.grid(alpha=0.3)
    if hue is not None:
        cost_ax.legend(fontsize=8)
    trials, seeds = ds.attrs.get("trials", "?"), ds.sizes.get("seed", 1)
    where = ", ".join(f"{d} = {_value(sub, d)}" for d in fixed)
    suptitle(fig, f"{ds.attrs.get('model', 'sweep')}: {trials} trials x {seeds} seed(s) per cell"
                  + (f"; {where}" if where else ""), fontsize=10)
    return fig


def _value(ds, dim):
    value_coord = f"{dim}_value"
    v = ds[value_coord].values if value_coord in ds.coords else ds[dim].values
    v = np.asarray(v)
    return np.array2string(v, precision=3) if v.ndim else f"{v.item():g}" if np.issubdtype(v.dtype, np.number) \
        else str(v.item())
