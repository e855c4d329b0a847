"""``delayed_ilqr.sweep``: a study over a grid of a model factory's arguments and Monte Carlo seeds,
with results as a labelled xarray Dataset, resumable from its store, locally or on Dask."""
from __future__ import annotations

import collections
import dataclasses
import importlib.metadata
import numbers
import pathlib
from typing import Callable, Mapping, Optional, Sequence

import numpy as np

from .. import Options, _delays, _precision, _validate
from ..experiments import designs
from ..experiments.engine import endpoint_description
from ..problem import delay_key, shared_delay_frame
from ..simulate import check_memory
from .compute import VARIABLES, Settings, compute_batch
from .grid import batches, cells, check_grid

__all__ = ["sweep", "open_sweep", "UNITS"]

#: Units of the factories' arguments that the Dataset's coordinates carry (``units=`` adds others).
#: sigma_u scales the diffusion F (dx = f dt + F dw, w in s^1/2), hence s^1/2.
UNITS = {"delay": "s", "dt": "s", "final_time": "s", "horizon": "steps", "sigma_u": "s^1/2", "radius": "m",
         "target": "m"}


def sweep(model, grid: Mapping[str, Sequence], seeds: Sequence[int] = (0,), trials: int = 100, *,
          fixed: Optional[Mapping] = None, design: str = "aware", options: Optional[Options] = None,
          substeps: int = 1, store=None, overwrite: bool = False, scheduler=None, n_workers: int = 2,
          batch_size: int = 16, cache: bool = True, cache_dir=None, progress: bool = True,
          units: Optional[Mapping[str, str]] = None, delay_frame=None):
    """Solves and runs by Monte Carlo every cell of a grid over a model factory's arguments.

    A cell is one combination of the grid's values: ``problem = factory(**fixed, **cell)`` is the
    plant, the design ``design`` of it is solved (`delayed_ilqr.experiments.designs`), and its
    policy runs ``trials`` times on the plant for each seed. Cells whose problems share a compiled
    solver (equal static structure: same delay, sizes, callables) are solved together by one
    ``vmap``, in batches of at most ``batch_size`` (`grid`). With ``delay_frame`` the delay
    is data (``Problem.delay_frame``): cells of different delays share one compiled solver and
    one batch.

    Args:
        model: a model name (``delayed_ilqr.models.REGISTRY``) or a factory ``(**kwargs) -> Problem``
            (importable by name, e.g. a module-level function, when run on Dask).
        grid: {argument name: values}, e.g. ``{"delay": [0, 0.05, 0.1], "sigma_u": [0.01, 0.02]}``;
            a value may be a vector (a target), which the Dataset indexes by position.
        seeds: the Monte Carlo seeds (the Dataset's ``seed`` dimension); all cells see the same
            noise samples for a seed (common random numbers).
        trials: Monte Carlo trials per cell and seed.
        fixed: the factory's other arguments, the same in every cell (e.g. ``{"noise": True}``).
        design: a design of `delayed_ilqr.experiments.designs.REGISTRY` ("aware": Theorem 1).
        options: solver options (default ``Options()``).
        substeps: Euler-Maruyama sub-steps per control step of the Monte Carlo.
        store: a folder for the results (`store`): each finished batch of cells is written
            there with a completion marker, and a second call with the same arguments resumes,
            computing only the cells that are not finished (identical results). None: in memory.
        overwrite: replace a store that holds another sweep (else that is a ValueError).
        scheduler: None computes here; "local" starts a ``dask.distributed.LocalCluster`` of
            ``n_workers`` processes; an address (``"tcp://host:8786"``) or a ``distributed.Client``
            runs the batches on that cluster (docs/sweeps.md).
        n_workers: workers of the LocalCluster.
        batch_size: at most this many cells per vmapped solve.
        cache: whether the Dask workers keep a persistent compilation cache
            ([`enable_compilation_cache`][delayed_ilqr.enable_compilation_cache]); this process's cache is the caller's.
        cache_dir: the folder of the workers' cache (None: the default folder).
        progress: a progress bar (tqdm) over the cells.
        units: units of further grid arguments, added to [`UNITS`][delayed_ilqr.sweeps.UNITS].
        delay_frame: None (each delay compiles its own solver), an int L (every cell's problem gets
            ``delay_frame=L``), or "auto": L = the longest delay of the grid in steps, when the
            cells' delays differ, no delay has more than `AUTO_FRAME_MAX_CELLS` cells and the
            problems have no delayed sensors (no frame is available with an observation).
            Each solve then costs what one at delay L costs (docs/performance.md), and the
            results equal the unframed ones to round-off.

    Returns:
        An ``xarray.Dataset`` with one dimension per grid argument (coordinates: its values, with
        units) and ``seed``; the variables of `compute.VARIABLES` (status, iterations,
        costs, Monte Carlo means with bootstrap intervals, medians, diverged counts, endpoint
        errors), each with ``long_name`` and ``units``.

    Raises:
        ValueError, TypeError: naming the argument, for a bad grid, a factory that refuses a cell's
            arguments (checked for every cell before anything is solved), bad seeds or counts, or
            a store of another sweep.
    """
    _precision.require_x64("sweep")
    factory, model_name = _factory(model)
    grid = check_grid(grid)
    fixed = dict(fixed or {})
    overlap = set(fixed) & set(grid)
    if overlap:
        raise ValueError(f"fixed and grid must not name the same argument; both name {sorted(overlap)}")
    seeds = _seeds(seeds)
    trials = _validate.positive_int(trials, "trials")
    substeps = _validate.positive_int(substeps, "substeps")
    batch_size = _validate.positive_int(batch_size, "batch_size")
    if design not in designs.REGISTRY:
        raise ValueError(f"design must be one of {sorted(designs.REGISTRY)}; got {design!r}")
    if options is not None and not isinstance(options, Options):
        raise TypeError(f"options must be a delayed_ilqr.Options; got {type(options).__name__}")
    if not (delay_frame is None or delay_frame == "auto"):
        delay_frame = _validate.delay_steps(delay_frame, "delay_frame")
    settings = Settings(factory, tuple(sorted(fixed.items())), design, options, seeds, trials, substeps)
    all_cells = cells(grid)
    problems = {}
    for cell in all_cells:          # every cell's arguments checked by the factory, before any solve
        try:
            problems[cell.index] = settings.problem(cell)
        except (ValueError, TypeError) as exc:
            raise type(exc)(f"grid cell {cell.kwargs}: {exc}") from None
        if problems[cell.index].is_fractional:      # a sweep's cells share whole-step delay frames
            p = problems[cell.index]
            raise ValueError(f"grid cell {cell.kwargs}: delay must be a whole number of steps of dt={p.dt!r} s in a "
                             f"sweep (its cells share one compiled solver over whole-step delays); got "
                             f"{p._delay_repr()} steps")
    _check_delays(grid, all_cells, problems)
    settings, problems = _framed(settings, problems, delay_frame)
    plan = batches(all_cells, lambda c: problems[c.index], batch_size)
    largest = max(plan, key=lambda b: b.size)            # its Monte Carlo holds the most, at once
    check_memory(problems[largest.cells[0].index], trials, substeps, what="trials", runs=largest.size)
    template = _template(grid, seeds, problems[all_cells[0].index], dict(UNITS, **(units or {})))
    template.attrs.update(_attributes(model_name, fixed, settings))

    if store is None:
        todo, target = plan, _InMemory(template)
    else:
        from .store import Store
        target = Store.open(store, template, _store_settings(template, batch_size), overwrite)
        done = target.finished([c.index for c in all_cells])
        target.done, target.known = done, target.markers()
        todo = [b for b in plan if any(c.index not in done for c in b.cells)]
    _run(settings, todo, target, scheduler, n_workers, cache, cache_dir, progress, len(all_cells), problems)
    return target.dataset()


#: ``delay_frame="auto"`` frames a sweep's delays only up to this many cells per delay: a framed
#: solve costs about a millisecond more than an unframed one on the arm and a compilation saved about
#: a second, so beyond about a thousand solves per delay the frame saves nothing. Within a sweep the
#: difference is small either way, a cell's Monte Carlo costing more than its solve
#: (docs/performance.md, "One compilation for many delays" and "sweep throughput").
AUTO_FRAME_MAX_CELLS = 1000


def _framed(settings: Settings, problems: dict, delay_frame):
    """``settings`` and ``problems`` in the delay frame asked for (see [`sweep`][delayed_ilqr.sweeps.sweep])."""
    if delay_frame == "auto":
        counts = collections.Counter(delay_key(p.delay_steps) for p in problems.values())
        few = max(counts.values()) <= AUTO_FRAME_MAX_CELLS
        delay_frame = shared_delay_frame(problems.values()) if few else None
    if delay_frame is None:
        return settings, problems
    try:
        problems = {index: p.replace(delay_frame=delay_frame) for index, p in problems.items()}
    except ValueError as exc:
        raise ValueError(f"delay_frame: {exc}") from None
    return dataclasses.replace(settings, delay_frame=delay_frame), problems


def _check_delays(grid: dict, all_cells, problems: dict) -> None:
    """Two delays of the grid that the factory makes the same number of steps are one cell twice."""
    if "delay" not in grid:
        return
    seen = {}
    for cell in all_cells:
        rest = tuple((k, repr(v)) for k, v in cell.kwargs.items() if k != "delay")
        p = problems[cell.index]
        first = seen.setdefault((rest, delay_key(p.delay_steps)), cell.kwargs["delay"])
        if first != cell.kwargs["delay"]:
            raise ValueError(f"grid['delay']: {first!r} and {cell.kwargs['delay']!r} are the same delay, "
                             f"{_delays.as_json(p.delay_steps)} steps of dt = {p.dt:g} s; give each delay once")


def open_sweep(store):
    """The Dataset of a sweep store, with ``finished`` (1 for the cells whose values are complete
    and verified, 0 for the others, whose values are missing)."""
    from .store import Store
    s = Store(pathlib.Path(store))
    ds = s.dataset()
    grid_dims = [d for d in ds["status"].dims]
    shape = tuple(ds.sizes[d] for d in grid_dims)
    done = s.finished(list(np.ndindex(*shape)))
    finished = np.zeros(shape, np.int8)
    for index in done:
        finished[index] = 1
    return ds.assign(finished=(grid_dims, finished, dict(long_name="1 when the cell is finished and verified")))


class _InMemory:
    """Results collected in memory (no store)."""

    def __init__(self, template):
        self.ds, self.done = template.copy(deep=True), set()

    def write(self, batch_number, results, previous=None):
        for index, values in results:
            for v in VARIABLES:
                self.ds[v.name].values[index] = values[v.name]

    def dataset(self):
        return self.ds


def _run(settings, todo, target, scheduler, n_workers, cache, cache_dir, progress, n_cells, problems):
    from tqdm.auto import tqdm
    bar = tqdm(total=n_cells, initial=n_cells - sum(len(b.cells) for b in todo), unit="cell",
               disable=not progress, desc="sweep")

    def finish(batch, results):
        new = [(i, v) for i, v in results if i not in target.done]
        previous = _previous(target, batch)
        target.write(batch.number, new, previous)
        target.done.update(i for i, _ in new)
        bar.update(len(batch.cells))

    try:
        if scheduler is None:
            for batch in todo:
                finish(batch, compute_batch(settings, batch, [problems[c.index] for c in batch.cells]))
        else:
            from distributed import as_completed
            from .cluster import client_for
            with client_for(scheduler, n_workers, cache, cache_dir) as client:
                futures = {client.submit(compute_batch, settings, batch, pure=False): batch for batch in todo}
                for future in as_completed(futures):
                    finish(futures[future], future.result())
    finally:
        bar.close()


def _previous(target, batch) -> Optional[dict]:
    """Checksums of the batch's cells that were finished before this run (kept in its marker)."""
    if not hasattr(target, "known"):
        return None
    from .store import _key
    marked = target.known
    return {_key(c.index): marked[_key(c.index)] for c in batch.cells
            if c.index in target.done and _key(c.index) in marked}


def _factory(model) -> tuple[Callable, str]:
    if isinstance(model, str):
        from ..models import REGISTRY
        if model not in REGISTRY:
            raise ValueError(f"model must be one of {sorted(REGISTRY)} or a factory; got {model!r}")
        return REGISTRY[model].factory, model
    if callable(model):
        return model, f"{getattr(model, '__module__', '?')}.{getattr(model, '__qualname__', repr(model))}"
    raise TypeError(f"model must be a model name or a factory(**kwargs) -> Problem; got {type(model).__name__}")


def _seeds(seeds) -> tuple[int, ...]:
    if isinstance(seeds, (str, bytes)) or not hasattr(seeds, "__iter__"):
        raise ValueError(f"seeds must be a sequence of non-negative integers; got {seeds!r}")
    out = tuple(_validate.seed(s) for s in seeds)
    if not out or len(set(out)) != len(out):
        raise ValueError(f"seeds must hold at least one seed and no seed twice; got {list(seeds)!r}")
    return out


def _template(grid: dict, seeds: tuple, problem, units: dict):
    """The Dataset of the sweep, every value missing (NaN, or -1 for integers)."""
    import xarray as xr
    coords = {}
    for name, values in grid.items():
        if all(isinstance(v, (numbers.Number, str)) for v in values):
            coords[name] = (name, np.asarray(values), _unit(name, units))
        else:                          # vectors (targets): indexed by position, the values beside
            coords[name] = (name, np.arange(len(values)), dict(long_name=f"position in the grid of {name}"))
            try:
                coords[f"{name}_value"] = ((name, f"{name}_component"), np.asarray(values, np.float64),
                                           _unit(name, units))
            except (ValueError, TypeError):
                coords[f"{name}_value"] = (name, np.asarray([repr(v) for v in values]))
    coords["seed"] = ("seed", np.asarray(seeds, np.int64), dict(long_name="Monte Carlo seed"))
    dims = list(grid)
    shape = [len(grid[d]) for d in dims]
    label, unit = endpoint_description(problem)
    data = {}
    for v in VARIABLES:
        vdims = dims + (["seed"] if v.per_seed else [])
        vshape = shape + ([len(seeds)] if v.per_seed else [])
        fill = np.nan if v.dtype.startswith("float") else -1
        long_name = v.long_name.replace("endpoint error", label)
        data[v.name] = (vdims, np.full(vshape, fill, v.dtype),
                        dict(long_name=long_name, units=unit if v.units == "endpoint" else v.units))
    return xr.Dataset(data, coords=coords)


def _unit(name: str, units: dict) -> dict:
    return dict(units=units[name]) if name in units else {}


def _attributes(model_name: str, fixed: dict, settings: Settings) -> dict:
    import json
    return dict(model=model_name, fixed=json.dumps(fixed, sort_keys=True, default=repr), design=settings.design,
                delay_frame=-1 if settings.delay_frame is None else settings.delay_frame,
                options=repr(settings.options or Options()), trials=settings.trials, substeps=settings.substeps,
                divergence="a trial diverged when its cost is not finite or above 100 times the cost of not "
                           "moving (delayed_ilqr.statistics)",
                delayed_ilqr_version=importlib.metadata.version("delayed-ilqr"))


def _store_settings(template, batch_size: int) -> dict:
    """What must be equal for a store to be resumed: the grid, the seeds, the sweep's attributes."""
    return dict(attrs={k: (v if isinstance(v, (str, int, float)) else repr(v)) for k, v in template.attrs.items()},
                coords={name: np.asarray(c.values).tolist() for name, c in template.coords.items()},
                batch_size=batch_size)
