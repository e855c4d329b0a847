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
  ``dt``, ``delay`` = l dt (s) and ``problem`` (its ``name``, ``delay_steps`` and ``delay``, a
  fractional delay's as l_j + phi_j steps: the plant's, which differ from the policy's for a
  delay-ignorant design; and ``delay_jitter``: None or the jitter's ``{"steps", "probabilities"}``),
  plus the caller's ``info``.

Files are written atomically (``delayed_ilqr._files``: an interrupted save leaves the old file).
Records are read field by field, by name: a field the file lacks gets the class's default (so a
record that gains an optional field still reads old files), an entry the class does not know is an
error, and a ``format_version`` other than this library's is refused with the versions named.
Everything is read with ``allow_pickle=False``: loading a file runs no code from it. A file that
is not one of these (damaged, truncated, foreign) or whose header contradicts its arrays is one
`FileFormatError` (a ``ValueError``) naming the file and what is wrong; float arrays come
back as float64.
"""
from __future__ import annotations

import json
import math
import os
import pathlib
import warnings
from typing import Any, Optional

import jax.numpy as jnp
import numpy as np

from . import _delays, _files, _precision
from ._files import FileFormatError
from .delay_jitter import DelayJitter
from .fused_estimator import FusedEstimator
from .solution import Estimator, Policy, Solution, Status, Trace

__all__ = ["FORMAT_VERSION", "FileFormatError", "save", "load", "load_metadata", "load_delay_jitter"]

FORMAT_NAME = "delayed-ilqr"
FORMAT_VERSION = 1
_METADATA = "__metadata__"
# the records a file may contain, by the name the header gives their class (a new record type
# nested in Solution or Policy is added here, with its fields in _fields)
_RECORDS = {cls.__name__: cls for cls in (Solution, Policy, Trace, Estimator, FusedEstimator)}
# the static (pytree auxiliary) fields of the estimators, saved as integer arrays
_STATIC = {Estimator: ("sensory_delay",), FusedEstimator: ("lags",)}


def _fields(cls) -> tuple:
    """The field names of a record class: a NamedTuple's, or an estimator's arrays and its delays."""
    return cls._arrays + _STATIC[cls] if cls in _STATIC else cls._fields


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
    """Writes a [`Solution`][delayed_ilqr.Solution] or [`Policy`][delayed_ilqr.Policy] to ``path`` (``.npz``),
    atomically: an interrupted save leaves the old file (or none), never a truncated one.

    Args:
        path: the file; ``.npz`` is appended when missing (as NumPy does; [`load`][delayed_ilqr.load] finds it
            under the same name).
        obj: what to save; [`load`][delayed_ilqr.load] returns the same type with bitwise-equal arrays.
        problem: optional, the [`Problem`][delayed_ilqr.Problem] it was solved for: its ``dt``, delay,
            delay jitter and name go into the header (the arrays do not hold them), and
            ``load(path, problem=...)`` checks a plant against them.
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
        # a fractional delay as its value in steps, l_j + phi_j (its taps are l_j and l_j + 1)
        steps = np.asarray(problem.delay_in_steps, np.float64).tolist() if problem.is_fractional \
            else _delays.as_json(problem.delay_steps)
        header.update(dt=problem.dt, delay=l * problem.dt,
                      problem=dict(name=problem.name, delay_steps=steps, delay=(np.asarray(steps) * problem.dt).tolist(),
                                   delay_jitter=None if problem.delay_jitter is None
                                   else problem.delay_jitter.as_json()))
    if info is not None:
        header["info"] = info
    try:
        text = json.dumps(header, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"info must be JSON-serialisable (finite numbers, strings, lists, dicts); {exc}") from None
    arrays[_METADATA] = np.frombuffer(text.encode(), np.uint8)
    _files.savez(_with_suffix(path), arrays)


def _with_suffix(path) -> pathlib.Path:
    path = pathlib.Path(os.fspath(path))
    return path if path.suffix == ".npz" else path.with_name(path.name + ".npz")


def _existing(path) -> pathlib.Path:
    """The file [`save`][delayed_ilqr.saving.save] wrote for ``path``: ``path`` itself, or ``path.npz`` when ``path``
    does not exist (save appended the suffix)."""
    path = pathlib.Path(os.fspath(path))
    return path if path.exists() or path.suffix == ".npz" else _with_suffix(path)


def load_metadata(path) -> dict:
    """The JSON header of a file written by [`save`][delayed_ilqr.saving.save] (checked: format and version).

    Raises:
        FileFormatError: a ``ValueError`` naming the file and what is wrong with it.
    """
    path = _existing(path)
    with _files.open_npz(path, _WHAT) as npz:
        return _header(npz, path)


def load_delay_jitter(path) -> Optional[DelayJitter]:
    """The [`DelayJitter`][delayed_ilqr.DelayJitter] of the plant a file was saved for
    (``save(..., problem=)`` with ``delay_jitter``), None for a plant without jitter.

    Raises:
        FileFormatError: also when the file records no problem (saved without ``problem=``, or by
            a delayed-ilqr that did not record the jitter), so that a missing record is never read
            as "no jitter", and when the recorded jitter is not a valid one.
    """
    path = _existing(path)
    header = load_metadata(path)
    if "delay_jitter" not in _problem_record(header):
        raise _files.FileFormatError(path, "records no delay jitter: it was saved without problem= (or by an older "
                                           "delayed-ilqr), so the plant's jitter is unknown")
    return _recorded_jitter(header, path)


def _problem_record(header: dict) -> dict:
    record = header.get("problem")
    return record if isinstance(record, dict) else {}


def _recorded_jitter(header: dict, path) -> Optional[DelayJitter]:
    """The header's ``problem.delay_jitter`` as a DelayJitter (None when absent or null), checked
    against the recorded problem's delay_steps (the jitter's longest delay)."""
    record = _problem_record(header).get("delay_jitter")
    if record is None:
        return None
    try:
        jitter = DelayJitter.from_json(record)
    except (TypeError, ValueError) as exc:
        raise _files.FileFormatError(path, f"its header's problem.delay_jitter is not a valid DelayJitter: {exc}") \
            from None
    if header["problem"].get("delay_steps") != jitter.longest:
        raise _files.FileFormatError(path, f"its header's problem.delay_jitter {jitter!r} contradicts its "
                                           f"problem.delay_steps {header['problem'].get('delay_steps')!r} (a "
                                           f"jittered plant's delay_steps is the jitter's longest delay)")
    return jitter


def load(path, problem=None):
    """Reads a file written by [`save`][delayed_ilqr.saving.save] (or ``Solution.save`` / ``Policy.save``) and returns
    what was saved, a [`Solution`][delayed_ilqr.Solution] or [`Policy`][delayed_ilqr.Policy], with
    float64 JAX arrays equal to the saved ones (bitwise for float64 files; a float32 file's arrays
    are converted exactly; a scalar status comes back as a [`Status`][delayed_ilqr.Status]). The
    time step and delay are in [`load_metadata`][delayed_ilqr.load_metadata].

    Args:
        path: the file (``path.npz`` when ``path`` does not exist, as [`save`][delayed_ilqr.saving.save] names it).
        problem: optional, the plant the loaded policy is for: its horizon, states and controls
            must be the saved ones and its ``dt`` the one recorded by ``save(..., problem=)``
            (the gains are per step, so on another time step they are another controller) and its
            ``delay_jitter`` the recorded one (None included); a file that records no time step
            gives a ``UserWarning`` that it cannot be checked.

    Raises:
        FileFormatError: a ``ValueError`` naming the file and what is wrong: not a file of
            [`save`][delayed_ilqr.saving.save] (missing, empty, truncated, damaged, a single ``.npy`` array, text, a
            pickle, another NPZ), an unknown format version or record type, a header whose kind,
            sizes or array shapes contradict the arrays, arrays whose shapes disagree, or a
            recorded delay jitter that is invalid or contradicts the recorded delay.
        ValueError: a ``problem`` that does not match the file.
    """
    _precision.require_x64("load")
    path = _existing(path)
    with _files.open_npz(path, _WHAT) as npz:
        header = _header(npz, path)
        arrays = {k: _files.read_entry(npz, k, path, _WHAT) for k in npz.files if k != _METADATA}
    _check_arrays(header, arrays, path)
    obj = _build(header["types"], "", arrays, path)         # takes the entries it uses out of arrays
    if arrays:
        raise _files.FileFormatError(path, f"entries {sorted(arrays)} are not fields of {header['kind']}")
    _check_sizes(header, obj, path)
    _recorded_jitter(header, path)
    if problem is not None:
        _check_problem(header, problem, path)
    return obj


def _build(types: dict, prefix: str, arrays: dict, path):
    cls = _RECORDS[types[prefix.rstrip(".")]]
    values = {}
    for name in _fields(cls):
        key = prefix + name
        if key in types:
            values[name] = _build(types, key + ".", arrays, path)
        elif key in arrays:
            values[name] = _value(cls, name, arrays.pop(key), path, key)
        elif name not in getattr(cls, "_field_defaults", {}):
            raise _files.FileFormatError(path, f"the saved {cls.__name__} has no entry {key!r}, a required field")
    return cls(**values)


def _value(cls, name, array, path, key):
    if cls is Solution and name == "status" and array.ndim == 0:
        try:
            return Status(int(array))
        except ValueError:
            raise _files.FileFormatError(path, f"status {int(array)} is not a delayed_ilqr.Status code "
                                               f"({[int(s) for s in Status]})") from None
    if cls is Estimator and name == "sensory_delay":
        if array.ndim or array.dtype.kind not in "iu" or int(array) < 0:
            raise _files.FileFormatError(path, f"{key} must be a non-negative integer scalar; got {array!r}")
        return int(array)                        # static: the pytree's auxiliary data
    if cls is FusedEstimator and name == "lags":
        if array.ndim != 1 or array.dtype.kind not in "iu" or np.any(array < 0):
            raise _files.FileFormatError(path, f"{key} must be a vector of non-negative integers; got {array!r}")
        return tuple(int(v) for v in array)
    if array.dtype.kind == "f":                  # the library computes in float64, whatever the writer did
        return jnp.asarray(array, jnp.float64)
    if array.dtype.kind not in "biu":
        raise _files.FileFormatError(path, f"entry {key!r} must hold numbers; got dtype {array.dtype}")
    return jnp.asarray(array)


_WHAT = "a delayed-ilqr file (Solution.save, Policy.save or delayed_ilqr.saving.save write one)"
# the header's keys that load relies on, with their JSON types
_HEADER_KEYS = dict(kind=str, types=dict, arrays=dict, horizon=int, n_states=int, n_controls=int, delay_steps=int)


def _header(npz, path) -> dict:
    if _METADATA not in npz.files:
        raise _files.FileFormatError(path, f"is not a delayed-ilqr file (no {_METADATA} entry); write it with "
                                           "Solution.save, Policy.save or delayed_ilqr.saving.save")
    raw = _files.read_entry(npz, _METADATA, path, _WHAT)
    try:
        text = raw.tobytes().decode()
    except UnicodeError as exc:
        raise _files.FileFormatError(path, f"its header is not UTF-8 text ({exc}); expected {_WHAT}") from None
    header = _files.parse_json(text, path, _WHAT, "its header")
    if not isinstance(header, dict):
        raise _files.FileFormatError(path, f"its header must be a JSON object; got a {type(header).__name__}; "
                                           f"expected {_WHAT}")
    if header.get("format") != FORMAT_NAME:
        raise _files.FileFormatError(path, f"is not a delayed-ilqr file: format {header.get('format')!r}")
    version = header.get("format_version")
    if version != FORMAT_VERSION:
        raise _files.FileFormatError(path, f"has format_version {version!r}; this delayed-ilqr "
                                           f"({_library_version()}) reads format_version {FORMAT_VERSION} only "
                                           f"(the file was written by delayed-ilqr {header.get('library_version')})")
    for key, kind in _HEADER_KEYS.items():
        if not isinstance(header.get(key), kind) or isinstance(header.get(key), bool):
            raise _files.FileFormatError(path, f"its header's {key!r} must be a JSON {kind.__name__}; got "
                                               f"{header.get(key)!r}; expected {_WHAT}")
    return header


def _check_arrays(header: dict, arrays: dict, path) -> None:
    """The header's kind and record types known, and its list of arrays the archive's."""
    if header["kind"] not in ("Solution", "Policy"):
        raise _files.FileFormatError(path, f"the header's kind must be 'Solution' or 'Policy'; got {header['kind']!r}")
    types = header["types"]
    if types.get("") != header["kind"]:
        raise _files.FileFormatError(path, f"the header's kind {header['kind']!r} contradicts its record types "
                                           f"(the top record is {types.get('')!r})")
    unknown = sorted(set(map(str, types.values())) - set(_RECORDS))
    if unknown:
        raise _files.FileFormatError(path, f"records of unknown type {unknown}; written by a newer delayed-ilqr "
                                           f"({header.get('library_version')})?")
    listed = header["arrays"]
    extra, missing = sorted(set(arrays) - set(listed)), sorted(set(listed) - set(arrays))
    if extra:
        raise _files.FileFormatError(path, f"entries {extra} are not fields of {header['kind']} (nor in the header)")
    if missing:
        raise _files.FileFormatError(path, f"the header lists entries {missing} that the archive lacks")
    for key, array in arrays.items():
        said = listed[key] if isinstance(listed[key], dict) else {}
        if said.get("shape") != list(array.shape) or said.get("dtype") != array.dtype.str:
            raise _files.FileFormatError(path, f"entry {key!r} has shape {list(array.shape)} and dtype "
                                               f"{array.dtype.str}; the header says {said.get('shape')} and "
                                               f"{said.get('dtype')}")


def _check_sizes(header: dict, obj, path) -> None:
    """Every array's trailing shape that of the header's sizes K, n, d, l (leading axes: a batch)."""
    policy = obj.policy if isinstance(obj, Solution) else obj
    feedback, delayed = np.shape(policy.state_feedback), np.shape(policy.delay_feedback)
    if len(feedback) < 3 or len(delayed) < 4:
        raise _files.FileFormatError(path, f"state_feedback must be [K, d, n] and delay_feedback [K, l, d, d]; got "
                                           f"shapes {list(feedback)} and {list(delayed)}")
    K, d, n = feedback[-3:]
    found = dict(horizon=K, n_controls=d, n_states=n, delay_steps=delayed[-3])
    for key, value in found.items():
        if header[key] != value:
            raise _files.FileFormatError(path, f"the header's {key} {header[key]} contradicts the arrays "
                                               f"(K={K}, n={n}, d={d}, l={delayed[-3]})")
    batch, l = list(feedback[:-3]), delayed[-3]
    sizes = dict(K=K, n=n, d=d, l=l)
    checked = [(policy, dict(x_nominal="K+1, n", u_nominal="K, d", feedforward="K, d"))]
    if isinstance(obj, Solution):
        checked.append((obj, dict(x="K+1, n", u="K, d", cost="", expected_cost="", iterations="")))
    for record, shapes in checked:
        for name, dims in shapes.items():
            trailing = [sizes[dim[0]] + (1 if dim.endswith("+1") else 0) for dim in dims.split(", ") if dim]
            shape = list(np.shape(getattr(record, name)))
            if shape != batch + trailing:
                said = ", ".join(f"{dim}={sizes[dim]}" for dim in "Knd" if dim in dims)
                raise _files.FileFormatError(path, f"{name} must be [{dims}] ({said}{', batch ' + str(batch) if batch else ''}"
                                                   f"); got shape {shape}")


def _check_problem(header: dict, problem, path) -> None:
    """``problem`` the plant the file's gains were made for: sizes and, when recorded, dt."""
    sizes = dict(horizon=problem.horizon, n_states=problem.n_states, n_controls=problem.n_controls)
    for key, value in sizes.items():
        if header[key] != value:
            raise ValueError(f"{path}: saved for {key} = {header[key]}, but the problem has {key} = {value}; the "
                             "problem argument must be the plant the file's gains were made for")
    if "dt" not in header:
        warnings.warn(f"{path} records no time step (saved without problem=), so the problem's dt = "
                      f"{problem.dt:g} s cannot be checked against the gains'", UserWarning, stacklevel=3)
    elif not math.isclose(header["dt"], problem.dt, rel_tol=1e-9, abs_tol=0.0):
        raise ValueError(f"{path}: saved for dt = {header['dt']:g} s, but the problem has dt = {problem.dt:g} s; the "
                         "problem argument must have the saved time step (per-step gains are another controller "
                         "at another step)")
    if "delay_jitter" in _problem_record(header):
        saved = _recorded_jitter(header, path)
        if saved != problem.delay_jitter:
            raise ValueError(f"{path}: saved for a plant with delay_jitter={saved!r}, but the problem has "
                             f"delay_jitter={problem.delay_jitter!r}; the problem argument must be the plant the "
                             "file's gains were designed for")


def _library_version() -> str:
    from . import __version__
    return __version__
