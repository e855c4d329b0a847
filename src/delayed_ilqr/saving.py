"""Saved solutions and policies: one ``.npz`` file of named arrays with a JSON header.

Format (``FORMAT_VERSION`` 1, documented in docs/guide/saving.md):

- every array of the saved object is an NPZ entry named by its field path: ``x``, ``u``, ``cost``,
  ``status``, ``iterations``, ``policy.x_nominal``, ``policy.state_feedback``, ``trace.cost``, ...
  (a [`Policy`][delayed_ilqr.Policy] saved alone has ``x_nominal``, ``state_feedback``, ...); a field
  that is ``None`` has no entry;
- the entry ``__metadata__`` is the UTF-8 bytes (uint8) of a JSON object: ``format``
  (``"delayed-ilqr"``), ``format_version``, ``library_version``, ``kind`` (``"Solution"`` or
  ``"Policy"``), ``types`` (the class of every nested record by path, ``""`` the top), ``arrays``
  (every entry's shape and dtype), the sizes ``horizon`` K, ``n_states``, ``n_controls``,
  ``delay_steps`` l (the delay the gains were designed for) and, when the problem was given,
  ``dt``, ``delay`` = l dt (s) and ``problem`` (its ``name``, ``delay_steps`` and ``delay``: the
  plant's, which differ from the policy's for a delay-ignorant design), plus the caller's ``info``.

Records are read field by field, by name: a field the file lacks gets the class's default (so a
record that gains an optional field still reads old files), an entry the class does not know is an
error, and a ``format_version`` other than this library's is refused with the versions named.
Everything is read with ``allow_pickle=False``: loading a file runs no code from it.
"""
from __future__ import annotations

import json
import os
from typing import Any, Optional

import jax.numpy as jnp
import numpy as np

from . import _precision
from .solution import Estimator, Policy, Solution, Status, Trace

__all__ = ["FORMAT_VERSION", "save", "load", "load_metadata"]

FORMAT_NAME = "delayed-ilqr"
FORMAT_VERSION = 1
_METADATA = "__metadata__"
# the records a file may contain, by the name the header gives their class (a new record type
# nested in Solution or Policy is added here, with its fields in _fields)
_RECORDS = {cls.__name__: cls for cls in (Solution, Policy, Trace, Estimator)}


def _fields(cls) -> tuple:
    """The field names of a record class: a NamedTuple's, or the Estimator's arrays and its delay."""
    return cls._arrays + ("sensory_delay",) if cls is Estimator else cls._fields


def _flatten(record, prefix: str, arrays: dict, types: dict) -> None:
    types[prefix.rstrip(".")] = type(record).__name__
    for name in _fields(type(record)):
        value = getattr(record, name)
        if value is None:
            continue
        if isinstance(value, tuple(_RECORDS.values())):
            _flatten(value, f"{prefix}{name}.", arrays, types)
        else:
            arrays[prefix + name] = np.asarray(value)


def save(path, obj, problem=None, info: Optional[dict] = None) -> None:
    """Writes a [`Solution`][delayed_ilqr.Solution] or [`Policy`][delayed_ilqr.Policy] to ``path`` (``.npz``).

    Args:
        path: the file; ``.npz`` is appended by NumPy when missing.
        obj: what to save; [`load`][delayed_ilqr.load] returns the same type with bitwise-equal arrays.
        problem: optional, the [`Problem`][delayed_ilqr.Problem] it was solved for: its ``dt``, delay
            and name go into the header (the arrays do not hold the time step).
        info: optional JSON-serialisable dict stored in the header as ``info``.
    """
    if not isinstance(obj, (Solution, Policy)):
        raise TypeError(f"obj must be a delayed_ilqr.Solution or Policy; got {type(obj).__name__}")
    policy = obj.policy if isinstance(obj, Solution) else obj
    K, d, n = np.shape(policy.state_feedback)[-3:]
    arrays, types = {}, {}
    _flatten(obj, "", arrays, types)
    header: dict[str, Any] = dict(
        format=FORMAT_NAME, format_version=FORMAT_VERSION, library_version=_library_version(),
        kind=type(obj).__name__, types=types,
        arrays={k: dict(shape=list(v.shape), dtype=v.dtype.str) for k, v in arrays.items()},
        horizon=int(K), n_states=int(n), n_controls=int(d), delay_steps=int(np.shape(policy.delay_feedback)[-3]))
    if problem is not None:
        if problem.horizon != K or problem.n_states != n or problem.n_controls != d:
            raise ValueError(f"problem must match the saved gains (K={K}, n={n}, d={d}); got {problem!r}")
        l = header["delay_steps"]
        header.update(dt=problem.dt, delay=l * problem.dt,
                      problem=dict(name=problem.name, delay_steps=problem.delay_steps, delay=problem.delay))
    if info is not None:
        header["info"] = info
    try:
        text = json.dumps(header, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"info must be JSON-serialisable (finite numbers, strings, lists, dicts); {exc}") from None
    arrays[_METADATA] = np.frombuffer(text.encode(), np.uint8)
    np.savez(os.fspath(path), **arrays)


def load_metadata(path) -> dict:
    """The JSON header of a file written by [`save`][delayed_ilqr.saving.save] (checked: format and version)."""
    with np.load(os.fspath(path), allow_pickle=False) as npz:
        return _header(npz, path)


def load(path):
    """Reads a file written by [`save`][delayed_ilqr.saving.save] (or ``Solution.save`` / ``Policy.save``) and returns
    what was saved, a [`Solution`][delayed_ilqr.Solution] or [`Policy`][delayed_ilqr.Policy], with
    float64 JAX arrays bitwise equal to the saved ones (a scalar status comes back as a
    [`Status`][delayed_ilqr.Status]). The time step and delay are in [`load_metadata`][delayed_ilqr.load_metadata]."""
    _precision.require_x64("load")
    with np.load(os.fspath(path), allow_pickle=False) as npz:
        header = _header(npz, path)
        arrays = {k: npz[k] for k in npz.files if k != _METADATA}
    types = header["types"]
    unknown = sorted(set(types.values()) - set(_RECORDS))
    if unknown:
        raise ValueError(f"{path}: records of unknown type {unknown}; written by a newer delayed-ilqr "
                         f"({header.get('library_version')})?")
    obj = _build(types, "", arrays, path)
    if arrays:
        raise ValueError(f"{path}: entries {sorted(arrays)} are not fields of {header['kind']}")
    return obj


def _build(types: dict, prefix: str, arrays: dict, path):
    cls = _RECORDS[types[prefix.rstrip(".")]]
    values = {}
    for name in _fields(cls):
        key = prefix + name
        if key in types:
            values[name] = _build(types, key + ".", arrays, path)
        elif key in arrays:
            values[name] = _value(cls, name, arrays.pop(key))
        elif name not in getattr(cls, "_field_defaults", {}):
            raise ValueError(f"{path}: the saved {cls.__name__} has no entry {key!r}, a required field")
    return cls(**values)


def _value(cls, name, array):
    if cls is Solution and name == "status" and array.ndim == 0:
        return Status(int(array))
    if cls is Estimator and name == "sensory_delay":
        return int(array)                        # static: the pytree's auxiliary data
    return jnp.asarray(array)


def _header(npz, path) -> dict:
    if _METADATA not in npz.files:
        raise ValueError(f"{path} is not a delayed-ilqr file (no {_METADATA} entry); write it with "
                         "Solution.save, Policy.save or delayed_ilqr.saving.save")
    header = json.loads(npz[_METADATA].tobytes().decode())
    if header.get("format") != FORMAT_NAME:
        raise ValueError(f"{path} is not a delayed-ilqr file: format {header.get('format')!r}")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise ValueError(f"{path} has format_version {version!r}; this delayed-ilqr "
                         f"({_library_version()}) reads format_version {FORMAT_VERSION} only "
                         f"(the file was written by delayed-ilqr {header.get('library_version')})")
    return header


def _library_version() -> str:
    from . import __version__
    return __version__
