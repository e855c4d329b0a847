"""The grid of a sweep: cells (one combination of a model factory's keyword arguments), grouped by
the static structure of the problems they build, and cut into the batches that are solved together.

Two problems share one compiled solver when their static parts are equal (callables, sizes, dt,
horizon, delay: ``Problem``'s pytree structure) and their arrays have the same shapes; such cells
form a *group*, and a group is solved in batches of at most ``batch_size`` cells by one ``vmap``.
A batch is padded up to a power of two by repeating its last problem, so that a group compiles its
batched solver for a few sizes only. The batches depend on the whole grid only, never on which
cells are already done, so a resumed sweep computes each batch exactly as an uninterrupted one
(bitwise the same numbers).
"""
from __future__ import annotations

import itertools
import math
import numbers
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import numpy as np

__all__ = ["Cell", "Batch", "cells", "batches", "check_grid", "padded_size"]


class Cell(NamedTuple):
    """One grid point: ``index`` into the grid's dimensions, and the factory's keyword arguments."""
    index: tuple[int, ...]
    kwargs: dict


class Batch(NamedTuple):
    """Cells solved together (equal static structure); ``size`` >= len(cells), the padded batch."""
    number: int
    cells: tuple[Cell, ...]
    size: int


def check_grid(grid: Mapping[str, Sequence]) -> dict[str, list]:
    """The grid as {name: list of values}, checked: non-empty names that are not ``seed``, each
    with at least one value, and no value repeated along a dimension."""
    if not isinstance(grid, Mapping) or not grid:
        raise ValueError(f"grid must be a non-empty mapping of a factory's argument names to lists of values; "
                         f"got {grid!r}")
    out = {}
    for name, values in grid.items():
        if not isinstance(name, str) or not name.isidentifier() or name == "seed":
            raise ValueError(f"grid keys must be the factory's keyword argument names (not 'seed', which "
                             f"is the seeds argument); got {name!r}")
        if isinstance(values, (str, bytes)) or not hasattr(values, "__iter__"):
            raise ValueError(f"grid[{name!r}] must be a sequence of values; got {values!r}")
        values = [_plain(v) for v in values]
        if not values:
            raise ValueError(f"grid[{name!r}] must hold at least one value; got an empty sequence")
        for i, value in enumerate(values):      # by value: 0 and 0.0 are one cell (True and 1 are not)
            twin = next((v for v in values[:i] if _same(v, value)), _NONE)
            if twin is not _NONE:
                raise ValueError(f"grid[{name!r}] must not repeat a value; got {twin!r} and {value!r} in {values!r}")
        out[name] = values
    return out


_NONE = object()


def _same(a, b) -> bool:
    """Two grid values that make the same cell: equal, of the same kind (a bool is not a number)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


def _plain(value):
    """A grid value as plain Python data (floats, ints, bools, strings, tuples of those)."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (numbers.Integral,)):
        return int(value)
    if isinstance(value, (numbers.Real,)):
        return float(value)
    if isinstance(value, (np.ndarray, list, tuple)):
        return tuple(_plain(v) for v in np.asarray(value).tolist()) if np.ndim(value) else _plain(np.asarray(value).item())
    return value


def cells(grid: dict[str, list]) -> list[Cell]:
    """Every grid point in C order (the last dimension fastest)."""
    names = list(grid)
    ranges = [range(len(grid[n])) for n in names]
    return [Cell(index, {n: grid[n][i] for n, i in zip(names, index)}) for index in itertools.product(*ranges)]


def structure_key(problem) -> Any:
    """What must be equal for two problems to share one compiled solver: the pytree structure
    (static fields, hashed by value) and the leaves' shapes and dtypes."""
    leaves, treedef = jax.tree_util.tree_flatten(problem)
    return treedef, tuple((np.shape(x), np.dtype(getattr(x, "dtype", type(x))).str) for x in leaves)


def padded_size(n: int, batch_size: int) -> int:
    """The batch size a chunk of ``n`` cells is padded to: the next power of two, at most batch_size."""
    return min(batch_size, 1 << max(0, math.ceil(math.log2(n)))) if n > 1 else 1


def batches(all_cells: Sequence[Cell], build: Callable[[Cell], Any], batch_size: int) -> list[Batch]:
    """The grid's batches: cells grouped by `structure_key` of their problem (groups in the
    order of their first cell), each group cut in grid order into chunks of ``batch_size``."""
    groups: dict[Any, list[Cell]] = {}
    for cell in all_cells:
        groups.setdefault(structure_key(build(cell)), []).append(cell)
    out = []
    for members in groups.values():
        for start in range(0, len(members), batch_size):
            chunk = tuple(members[start:start + batch_size])
            out.append(Batch(len(out), chunk, padded_size(len(chunk), batch_size)))
    return out
