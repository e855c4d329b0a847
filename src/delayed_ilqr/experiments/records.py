"""The record of a problem that every output file carries: `problem_record`.

A result is only reproducible with the full problem it came from, so the command line writes this
record into its ``manifest.json``, the JSON of each study and the header of every saved solution
(``delayed_ilqr.load_metadata(path)["info"]["problem"]``): the time grid, the delays, the noise
(its preset's name, ``ModelMetadata.noise``, and its level), and the parameters of the dynamics,
the noise, the cost and the sensors, read from their fields, so that a user's own plant is
recorded as well as a built-in one.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

__all__ = ["problem_record", "delay_values"]

# arrays larger than this are recorded by shape only (a record is metadata, not data)
_MAX_ARRAY_SIZE = 1000
_MAX_DEPTH = 6


def problem_record(problem) -> dict:
    """A JSON-ready dict of everything that defines ``problem`` ([`Problem`][delayed_ilqr.Problem]).

    Keys: ``name``; ``dt`` (s), ``horizon`` K and ``final_time`` = K dt (s); ``delay`` (s) and
    ``delay_steps`` (lists per channel, and for a delay that is not whole steps, its l + phi); ``delay_jitter`` (None, or the
    jitter's ``{"steps", "probabilities"}``); ``sensory_delay`` (s) and ``sensory_delay_steps`` (None without sensors);
    ``n_states``, ``n_controls``; ``x0``; ``u_min``, ``u_max`` (None where unlimited);
    ``noise``: None without noise, else ``{"preset": name or None, "type": class, <its fields>}``
    (e.g. ``sigma_u``); ``dynamics``, ``cost``, ``observation``: ``{"type": class, <fields>}``
    with nested parameters (e.g. the arm's ``Arm2Params``) as dicts. Non-finite numbers are None.
    """
    meta = getattr(problem, "metadata", None)
    observation = getattr(problem, "observation", None)
    ls = None if observation is None else int(observation.delay_steps)
    delay, delay_steps = delay_values(problem)
    noise = None
    if problem.noise is not None:
        noise = {"preset": None if meta is None else getattr(meta, "noise", None), **_describe(problem.noise)}
    return dict(
        name=problem.name, dt=problem.dt, horizon=int(problem.horizon), final_time=problem.horizon * problem.dt,
        delay=delay, delay_steps=delay_steps,
        delay_jitter=None if getattr(problem, "delay_jitter", None) is None else problem.delay_jitter.as_json(),
        sensory_delay=None if ls is None else ls * problem.dt, sensory_delay_steps=ls,
        n_states=int(problem.n_states), n_controls=int(problem.n_controls), x0=_value(problem.x0),
        u_min=_value(problem.u_min), u_max=_value(problem.u_max), noise=noise,
        dynamics=_describe(problem.dynamics), cost=_describe(problem.cost),
        observation=None if observation is None else _describe(observation))


def delay_values(problem) -> tuple:
    """(delay in s, delay in steps) of ``problem`` as JSON values: for one whole delay a float and
    an int; per channel, or not whole steps (docs/derivation.md §20), lists of one per channel (l_j + phi_j
    steps); a jittered problem's are its longest delay (``delay_jitter`` is recorded beside them)."""
    # one delay: an int of steps; per channel, or not whole steps: a list
    steps = np.asarray(getattr(problem, "delay_in_steps", problem.delay_steps))
    steps = steps if steps.ndim or getattr(problem, "is_fractional", False) else steps.astype(int)
    return (steps * problem.dt).tolist(), steps.tolist()


def _describe(obj, depth: int = 0) -> Any:
    """``{"type": class name, field: value, ...}`` of a dataclass, NamedTuple or plain object."""
    if depth > _MAX_DEPTH:
        return repr(obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        fields = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    elif isinstance(obj, tuple) and hasattr(obj, "_fields"):
        fields = obj._asdict()
    elif hasattr(obj, "__dict__") and not callable(getattr(obj, "__func__", None)) and not _is_function(obj):
        fields = {k: v for k, v in vars(obj).items() if not k.startswith("_")}
    else:
        return _value(obj, depth)
    return {"type": type(obj).__name__, **{k: _value(v, depth + 1) for k, v in fields.items()}}


def _is_function(obj) -> bool:
    return hasattr(obj, "__code__") or type(obj).__name__ in ("builtin_function_or_method", "PjitFunction")


def _value(value, depth: int = 0) -> Any:
    """A JSON value: numbers (non-finite as None), strings, lists, dicts, or a description."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _value(v, depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):
        return [_value(v, depth + 1) for v in value]
    if hasattr(value, "shape") and hasattr(value, "dtype"):        # NumPy and JAX arrays
        array = np.asarray(value)
        if array.size > _MAX_ARRAY_SIZE:
            return {"shape": list(array.shape), "dtype": array.dtype.str}
        if array.dtype.kind in "biuf":
            return _value(array.tolist(), depth + 1) if array.ndim else _value(array.item())
        return repr(array)
    if _is_function(value):
        return f"{getattr(value, '__module__', '')}.{getattr(value, '__qualname__', repr(value))}"
    return _describe(value, depth + 1)
