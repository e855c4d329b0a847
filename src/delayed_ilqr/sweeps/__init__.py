"""Sweeps: studies over a grid of a model factory's arguments and seeds (``delayed_ilqr.sweep``).

| module | its job |
|---|---|
| run.py | ``sweep`` and ``open_sweep``: the grid, the Dataset, local or Dask execution |
| grid.py | cells, grouped by the problems' static structure, cut into padded batches |
| compute.py | one batch: vmapped solve, Monte Carlo per seed, statistics (what a worker returns) |
| store.py | the resumable store: Zarr results, per-batch completion markers with checksums |
| cluster.py | ``dask.distributed``: LocalCluster or a scheduler address, the worker set-up |

Needs the ``sweep`` extra (xarray, zarr, dask[distributed]); ``import delayed_ilqr`` does not
import this package.
"""
from .run import UNITS, open_sweep, sweep

__all__ = ["sweep", "open_sweep", "UNITS"]
