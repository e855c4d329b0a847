"""The sweep's store: a folder holding the results as a Zarr store (``results.zarr``, one chunk per
cell, read as an xarray Dataset) and a completion marker per batch (``cells/batch-N.json``).

A batch's cells are written first, then its marker, atomically (``delayed_ilqr._files``): the
marker lists each cell with the SHA-256 of its values as written. A cell counts as finished only
when a marker names it and the values read back from the store have that checksum, so a write
that was interrupted (no marker yet), a chunk damaged afterwards (checksum mismatch, or a chunk
that cannot be decoded: all its cells) or a marker without its data is detected, and the cell is
computed again. Only the process that runs the sweep writes (Dask workers return numbers).
The store itself is created atomically (built beside ``path``, then renamed), with the sweep's
settings (``sweep.json``): a store of another sweep is refused, so that cells of two different
sweeps never mix. A store whose metadata (``sweep.json``, the Zarr ``zarr.json`` files) cannot be
read is one ``FileFormatError`` naming the file, with the way out (``overwrite``).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pathlib
import shutil
from typing import Iterable, Optional

import numpy as np

from .._files import FileFormatError, read_json, write_text
from .compute import VARIABLES

__all__ = ["Store", "checksum"]

RESULTS, MARKERS, SETTINGS = "results.zarr", "cells", "sweep.json"

# Cells per Zarr chunk along the last grid dimension (1 along the others): a file per cell and
# variable costs more to create, write and read than the cells' numbers (docs/performance.md,
# "sweep throughput"). A damaged chunk makes its cells unfinished; they are computed again.
CHUNK_CELLS = 256

# what a damaged store file should have been, and the way out
_WHAT = ("a file of a sweep store (delayed_ilqr.sweep writes them); the store is damaged: pass overwrite=True "
         "(--overwrite) to compute it again from the start")


def checksum(values: dict) -> str:
    """SHA-256 of a cell's values, variable by variable in the order of `VARIABLES`, each as
    its dtype's little-endian bytes."""
    h = hashlib.sha256()
    for v in VARIABLES:
        h.update(v.name.encode())
        h.update(np.ascontiguousarray(values[v.name], np.dtype(v.dtype).newbyteorder("<")).tobytes())
    return h.hexdigest()


def _chunks(dims, sizes) -> tuple:
    """One chunk per CHUNK_CELLS cells along the last grid dimension, all seeds in it."""
    grid = [d for d in dims if d != "seed"]
    return tuple(sizes[d] if d == "seed" else (min(sizes[d], CHUNK_CELLS) if d == grid[-1] else 1) for d in dims)


def _key(index) -> str:
    return ",".join(str(int(i)) for i in index)


class Store:
    """A sweep's store folder (see the module docstring). Open it with `open`."""

    def __init__(self, path: pathlib.Path):
        self.path = pathlib.Path(path)
        self._group = None

    @classmethod
    def open(cls, path, template, settings: dict, overwrite: bool = False) -> "Store":
        """The store at ``path``: created from ``template`` (an xarray Dataset of the right shape,
        filled with missing values) when there is none, resumed when it holds the same sweep
        (``settings``), replaced when ``overwrite``; else ValueError."""
        path = pathlib.Path(path)
        settings_text = json.dumps(settings, sort_keys=True, indent=1)
        if path.exists():
            previous = path / SETTINGS
            if not overwrite:
                if not previous.is_file():
                    raise ValueError(f"store {path} exists and is not a sweep store; pass overwrite=True "
                                     "(--overwrite) to replace it")
                if read_json(previous, _WHAT) != json.loads(settings_text):
                    raise ValueError(f"store {path} holds another sweep (its {SETTINGS} differs from these settings); "
                                     "pass overwrite=True (--overwrite) to replace it, or another store")
                return cls(path)
        staging = path.parent / f".{path.name}.creating-{os.getpid()}"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(parents=True)
        try:
            encoding = {name: {"chunks": _chunks(var.dims, template.sizes)} for name, var in template.data_vars.items()}
            template.to_zarr(staging / RESULTS, mode="w", encoding=encoding, consolidated=False)
            (staging / MARKERS).mkdir()
            write_text(staging / SETTINGS, settings_text)
            if path.exists():
                old = path.parent / f".{path.name}.old-{os.getpid()}"
                path.rename(old)
                shutil.rmtree(old)
            staging.rename(path)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return cls(path)

    @property
    def group(self):
        if self._group is None:
            import zarr
            self.check()
            with self._reading():
                self._group = zarr.open_group(self.path / RESULTS, mode="r+")
        return self._group

    def check(self) -> None:
        """The store's metadata readable: results.zarr a folder whose Zarr metadata (``zarr.json``
        of the group and of every variable) are JSON objects; else `FileFormatError`
        naming the file (a damaged chunk is not an error: its cells are computed again)."""
        results = self.path / RESULTS
        if not results.is_dir():
            raise FileFormatError(results, f"is missing or not a folder; expected {_WHAT}")
        for meta in [results / "zarr.json"] + [results / v.name / "zarr.json" for v in VARIABLES]:
            if not isinstance(read_json(meta, _WHAT), dict):
                raise FileFormatError(meta, f"must hold a JSON object; expected {_WHAT}")

    @contextlib.contextmanager
    def _reading(self):
        """Zarr's and xarray's errors on opening a damaged store as one error naming it."""
        try:
            yield
        except FileFormatError:
            raise
        except Exception as exc:
            text = str(exc).strip().splitlines()
            raise FileFormatError(self.path / RESULTS, f"cannot be opened ({type(exc).__name__}: "
                                                       f"{text[0] if text else ''}); expected {_WHAT}") from None

    def markers(self) -> dict[str, str]:
        """{cell key: checksum} of every marker (a marker that cannot be read counts as absent)."""
        out = {}
        for marker in sorted((self.path / MARKERS).glob("batch-*.json")):
            try:
                out.update(json.loads(marker.read_text())["cells"])
            except (OSError, ValueError, KeyError, TypeError):
                continue
        return out

    def finished(self, indices: Iterable[tuple]) -> set[tuple]:
        """The cells among ``indices`` that are finished: named by a marker, with data whose
        checksum matches it."""
        marked = self.markers()
        candidates = [i for i in indices if _key(i) in marked]
        if not candidates:
            return set()
        arrays = {v.name: self._read(v) for v in VARIABLES}
        return {tuple(i) for i in candidates
                if checksum({name: a[tuple(i)] for name, a in arrays.items()}) == marked[_key(i)]}

    def _read(self, variable) -> np.ndarray:
        """A variable's values; a chunk that cannot be read (damaged) reads as missing (NaN or -1),
        which no marker's checksum matches."""
        array = self.group[variable.name]
        try:
            return np.asarray(array[...])
        except Exception:
            fill = np.nan if variable.dtype.startswith("float") else -1
            out = np.full(array.shape, fill, variable.dtype)
            per_seed = 1 if variable.per_seed else 0
            for index in np.ndindex(*array.shape[:array.ndim - per_seed]):
                try:
                    out[index] = array[index]
                except Exception:
                    pass
            return out

    def write(self, batch_number: int, results: list[tuple[tuple, dict]], previous: Optional[dict] = None) -> None:
        """Writes the cells' values, then the batch's marker (atomically). ``previous``: checksums of
        the batch's cells that were already finished and are kept (not written again)."""
        if results:                          # one call per variable: zarr writes the cells' chunks concurrently
            coords = np.array([index for index, _ in results]).T                       # [grid dims, cells]
            for v in VARIABLES:
                array = self.group[v.name]
                data = np.stack([np.asarray(values[v.name], v.dtype) for _, values in results])
                n_seeds = data.shape[1] if v.per_seed else 1
                at = tuple(np.repeat(c, n_seeds) for c in coords)
                if v.per_seed:                    # every (cell, seed) pair
                    at += (np.tile(np.arange(n_seeds), len(results)),)
                try:
                    array.vindex[at] = data.reshape(-1)
                except Exception:                 # a damaged chunk, which a partial write reads first
                    self._rewrite_chunks(array, v, [index for index, _ in results], data)
        cells = dict(previous or {})
        cells.update({_key(index): checksum(values) for index, values in results})
        write_text(self.path / MARKERS / f"batch-{batch_number}.json",
                          json.dumps(dict(batch=batch_number, cells=cells), sort_keys=True))

    @staticmethod
    def _rewrite_chunks(array, variable, indices, data) -> None:
        """Writes whole chunks: what can still be read of each, with the new cells in it (an
        unreadable chunk's other cells become missing; they were unfinished, so this run
        computes them too). A per-seed variable's chunk holds every seed of its cells."""
        grid_ndim = len(indices[0])
        chunks = array.chunks[:grid_ndim]
        regions = {}
        for index, row in zip(indices, data):
            start = tuple(i - i % c for i, c in zip(index, chunks))
            regions.setdefault(start, []).append((index, row))
        for start, cells in regions.items():
            region = tuple(slice(s, min(s + c, n)) for s, c, n in zip(start, chunks, array.shape)) \
                + tuple(slice(0, n) for n in array.shape[grid_ndim:])            # the seed axis, whole
            try:
                block = np.asarray(array[region])
            except Exception:
                block = np.full([r.stop - r.start for r in region],
                                np.nan if variable.dtype.startswith("float") else -1, variable.dtype)
            for index, row in cells:
                block[tuple(i - s for i, s in zip(index, start))] = row
            array[region] = block

    def dataset(self):
        """The results as an xarray Dataset, loaded into memory."""
        import xarray as xr
        self.check()
        with self._reading():
            lazy = xr.open_zarr(self.path / RESULTS, consolidated=False, mask_and_scale=False)
        with lazy:
            coords = lazy.coords.to_dataset().load().coords
            dims = {v.name: lazy[v.name].dims for v in VARIABLES}
            attrs = {v.name: dict(lazy[v.name].attrs) for v in VARIABLES}
            ds = xr.Dataset({v.name: (dims[v.name], self._read(v), attrs[v.name]) for v in VARIABLES},
                            coords=coords, attrs=dict(lazy.attrs))
        for var in ds.variables.values():       # the missing-value markers are this module's, not the data's
            var.attrs.pop("_FillValue", None)
        return ds
