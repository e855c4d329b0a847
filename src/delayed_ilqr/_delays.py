"""The input delay as given: one whole number of steps for every command channel, or one per
channel (docs/derivation.md §18). Checks and normalisation shared by [`Problem`][delayed_ilqr.Problem]
and [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG].

One delay ``l`` keeps the single-delay recursion (§3) and, with ``delay_frame``, the frame of §17.
Per-channel delays ``[l_1, ..., l_d]`` are an int32 array [d]; they always run in a frame of
L >= max_j l_j slots (the frame's pass with a vector delay), L = max_j l_j unless a larger
``delay_frame`` is given.
"""
from __future__ import annotations

import numbers

import jax
import numpy as np

from . import _validate

__all__ = ["is_per_channel", "checked", "checked_frame", "check_below_horizon", "longest", "as_json", "fractional",
           "taps_of"]


def is_per_channel(delay_steps) -> bool:
    """Whether ``delay_steps`` gives one delay per channel (an array of one axis, traced or not)."""
    return np.ndim(delay_steps) == 1


def checked(value, n_controls: int, name: str = "delay_steps", taps: bool = False):
    """An int for one delay; an int32 array [d] for a list, tuple or array of per-channel delays.

    Each entry must be a non-negative whole number of steps and there must be one per channel
    (with ``taps``, the LQG layer's, any positive multiple of d: tap i acts on channel i mod d)."""
    if isinstance(value, (list, tuple)) or (isinstance(value, (np.ndarray, jax.Array)) and np.ndim(value) > 0):
        _validate.static(value, name)
        entries = list(np.asarray(value).reshape(-1)) if not isinstance(value, (list, tuple)) else list(value)
        if np.ndim(value) != 1:
            raise ValueError(f"{name} must be one non-negative integer or a list of one per command channel "
                             f"(d = {n_controls}); got an array of shape {np.shape(value)}")
        if len(entries) != n_controls and not (taps and entries and len(entries) % n_controls == 0):
            raise ValueError(f"{name} must give one delay per command channel (d = {n_controls}); got "
                             f"{len(entries)}: {list(value)!r}")
        for j, entry in enumerate(entries):
            if isinstance(entry, (bool, np.bool_)) or not isinstance(entry, (numbers.Real, np.number)) \
                    or not float(entry).is_integer() or entry < 0:
                raise ValueError(f"{name}[{j}] must be a non-negative integer number of steps; got {entry!r} "
                                 f"in {name}={list(value)!r}")
        return np.asarray([int(e) for e in entries], np.int32)
    return _validate.delay_steps(value, name)


def longest(delay_steps) -> int:
    """max_j l_j for per-channel delays, l itself for one delay (concrete values only)."""
    return int(np.max(delay_steps)) if is_per_channel(delay_steps) else int(delay_steps)


def checked_frame(delay_frame, delay_steps, name: str = "delay_frame"):
    """The frame L: as ``_validate.delay_frame`` for one delay; for per-channel delays at least
    max_j l_j, and max_j l_j when not given (per-channel delays always run in a frame)."""
    if not is_per_channel(delay_steps):
        return _validate.delay_frame(delay_frame, delay_steps, name)
    if delay_frame is None:
        return longest(delay_steps)
    value = _validate.delay_steps(delay_frame, name)
    if value < longest(delay_steps):
        raise ValueError(f"{name} must be at least the longest channel delay (the frame holds every channel's "
                         f"pending commands); got {name}={value} with delay_steps={list(delay_steps)!r}")
    return value


def check_below_horizon(delay_steps, horizon: int) -> None:
    """Per-channel delays of a [`Problem`][delayed_ilqr.Problem]: each l_j < K (with l_j >= K, channel
    j's commands would never act within the horizon)."""
    for j, l_j in enumerate(np.asarray(delay_steps)):
        if l_j >= horizon:
            raise ValueError(f"delay_steps[{j}] must be below the horizon: a command sent at step k acts at "
                             f"k + l_j, so with l_j >= K channel {j} never acts; got delay_steps="
                             f"{as_json(delay_steps)}, horizon={horizon}")


def as_json(delay_steps):
    """The delay as a JSON value: an int, or a list of ints per channel (for messages under jit,
    a traced delay as the words that say so)."""
    if isinstance(delay_steps, jax.core.Tracer):
        return f"a traced array of shape {np.shape(delay_steps)}"
    if is_per_channel(delay_steps):
        return [int(l_j) for l_j in np.asarray(delay_steps)]
    return int(delay_steps)


def fractional(value, n_controls: int, name: str = "delay_steps"):
    """A delay in steps that is not whole, as (l [d] int32, phi [d] float64) with value = l + phi,
    0 <= phi < 1 (docs/derivation.md §20); None for a whole delay (`checked`'s). A floating-point
    NumPy or JAX array is taken as fractional even when whole (phi = 0 on the two-tap path, the
    way to keep the delay differentiable). One value is every channel's."""
    is_float_array = isinstance(value, (np.ndarray, jax.Array)) and np.issubdtype(np.asarray(value).dtype,
                                                                                  np.floating)
    if isinstance(value, (bool, np.bool_)) or not (is_float_array or isinstance(value, (numbers.Real, list, tuple))):
        return None
    if isinstance(value, (list, tuple)) and any(isinstance(e, (bool, np.bool_)) or not isinstance(e, numbers.Real)
                                                for e in value):
        return None             # `checked` names the entry
    try:
        entries = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    if np.ndim(value) > 1 or (np.ndim(value) == 1 and len(entries) != n_controls):
        return None             # `checked` says what is wrong
    if not is_float_array and all(np.isfinite(e) and float(e).is_integer() for e in entries):
        return None
    for j, entry in enumerate(entries):
        if not np.isfinite(entry) or entry < 0:
            where = f"{name}[{j}]" if np.ndim(value) else name
            given = list(value) if isinstance(value, (list, tuple)) else np.asarray(value).tolist()
            raise ValueError(f"{where} must be a finite, non-negative number of steps; got {float(entry)!r} in "
                             f"{name}={given!r}")
    entries = np.broadcast_to(entries, (n_controls,))
    whole = np.floor(entries)
    return whole.astype(np.int32), entries - whole


def taps_of(whole, n_controls: int):
    """The two taps of a fractional delay, [l_1..l_d, l_1 + 1..l_d + 1] ([2 d], traced or not)."""
    xp = np if isinstance(whole, np.ndarray) else jax.numpy
    whole = xp.broadcast_to(whole, (n_controls,))
    return xp.concatenate([whole, whole + 1]).astype(xp.int32)
