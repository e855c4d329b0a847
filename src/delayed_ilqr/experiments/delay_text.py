"""An input delay as reports, figures and file names write it, from one place.

A delay is given as a [`Problem`][delayed_ilqr.Problem] (its ``delay_in_steps`` times ``dt``, and
its ``delay_jitter``) or as seconds (a number, or a sequence of one per command channel). It reads:

|  |  |
|---|---|
| one delay | ``50 ms`` |
| one per channel | ``[50, 70] ms`` (channels with equal delays: one value) |
| between steps (fractional) | ``25 ms``, ``[25, 33.333333] ms``: the value, not rounded to a step or a millisecond |
| jittered | ``20/30/40 ms jittered (p = 0.25/0.5/0.25)``: the distribution of the delay |

Values are milliseconds rounded to 1 ns (``1e3 * 0.07`` is 70.00000000000001 in floating point).
`delay_tag` is the same delay in a file name or an array key (``50ms``, ``50,70ms``,
``jitter20,30,40ms``); `delay_key` a hashable value that tells delays apart (grouping results);
`delay_axis` places delays on a figure's x-axis (in ms when each is one number; otherwise by
rank, each tick labelled with its delay).
"""
from __future__ import annotations

import numbers
from typing import Optional, Sequence, Union

import numpy as np

__all__ = ["milliseconds", "seconds", "ms_text", "delay_text", "delay_tag", "delay_key", "delay_axis"]

#: Milliseconds are rounded to this many decimals (1 ns): enough for any fraction of a step that
#: a user gives, and it hides the round-off of tau = (l + phi) dt.
DECIMALS = 6

Milliseconds = Union[float, tuple]


def _jitter(delay):
    return getattr(delay, "delay_jitter", None)


def milliseconds(delay) -> Milliseconds:
    """The delay in ms (rounded to 1 ns): one float when every channel has the same delay, else a
    tuple of one per channel. A jittered problem's is its longest delay (see `delay_text`).

    Args:
        delay: a [`Problem`][delayed_ilqr.Problem], or seconds (a number or a sequence [d]).
    """
    if hasattr(delay, "delay_in_steps"):
        seconds = np.asarray(delay.delay_in_steps, np.float64) * delay.dt
    elif isinstance(delay, numbers.Real) or (np.ndim(delay) <= 1 and np.size(delay) > 0
                                             and np.issubdtype(np.asarray(delay).dtype, np.number)):
        seconds = np.asarray(delay, np.float64)
    else:
        raise TypeError(f"delay must be a delayed_ilqr.Problem or seconds (a number or one per channel); "
                        f"got {delay!r}")
    ms = np.round(1e3 * np.atleast_1d(seconds), DECIMALS) + 0.0      # + 0.0: no "-0"
    return float(ms[0]) if np.all(ms == ms[0]) else tuple(float(v) for v in ms)


def seconds(delay) -> Milliseconds:
    """`milliseconds` in seconds (one float, or a tuple per channel): a study's delay axis."""
    ms = milliseconds(delay)
    return tuple(v / 1e3 for v in ms) if isinstance(ms, tuple) else ms / 1e3


def _number(value: float) -> str:
    return np.format_float_positional(value, trim="-")


def ms_text(ms: Milliseconds) -> str:
    """A `milliseconds` value as text: ``50 ms`` or ``[50, 70] ms``."""
    if isinstance(ms, tuple):
        return "[" + ", ".join(_number(v) for v in ms) + "] ms"
    return f"{_number(ms)} ms"


def _support_ms(delay) -> list[str]:
    jitter = _jitter(delay)
    return [_number(round(1e3 * s * delay.dt, DECIMALS) + 0.0) for s in jitter.steps]


def delay_text(delay, *, steps: bool = False) -> str:
    """The delay as a reader reads it (the module's table); with ``steps``, followed by its value
    in steps of dt, e.g. ``50 ms (5 steps of dt = 10 ms)``, ``25 ms (2.5 steps of dt = 10 ms)``.

    Args:
        delay: a [`Problem`][delayed_ilqr.Problem], or seconds (a number or a sequence [d]);
            ``steps`` needs a Problem.
    """
    jitter = _jitter(delay)
    if jitter is not None:
        text = (f"{'/'.join(_support_ms(delay))} ms jittered "
                f"(p = {'/'.join(f'{p:.4g}' for p in np.asarray(jitter.probabilities, np.float64))})")
    else:
        text = ms_text(milliseconds(delay))
    if not steps:
        return text
    if not hasattr(delay, "dt"):
        raise TypeError(f"delay_text(..., steps=True) needs a delayed_ilqr.Problem (its dt); got {delay!r}")
    if jitter is not None:
        in_steps = "/".join(str(s) for s in jitter.steps)
    else:
        values = np.round(np.atleast_1d(np.asarray(delay.delay_in_steps, np.float64)), DECIMALS) + 0.0
        in_steps = _number(values[0]) if np.all(values == values[0]) else \
            "[" + ", ".join(_number(v) for v in values) + "]"
    return f"{text} ({in_steps} steps of dt = {ms_text(milliseconds(delay.dt))})"


def delay_tag(delay) -> str:
    """The delay in a file name or an array key: ``50ms``, ``25.5ms``, ``50,70ms`` per channel,
    ``jitter20,30,40ms`` for a jittered problem (its support)."""
    if _jitter(delay) is not None:
        return f"jitter{','.join(_support_ms(delay))}ms"
    ms = milliseconds(delay)
    return (",".join(_number(v) for v in ms) if isinstance(ms, tuple) else _number(ms)) + "ms"


def delay_key(delay):
    """A hashable value equal for equal delays: the `milliseconds` and, for a jittered problem,
    its support and probabilities."""
    jitter = _jitter(delay)
    return milliseconds(delay), None if jitter is None else (jitter.steps, tuple(jitter.probabilities))


def _order(key):
    """Delays in order: by their longest channel (a jitter by its longest delay), then the rest."""
    ms, jitter = key
    values = ms if isinstance(ms, tuple) else (ms,)
    return max(values), values, jitter is not None, jitter or ()


def delay_axis(delays: Sequence) -> tuple[np.ndarray, Optional[tuple[list, list]], str]:
    """Where each delay stands on a figure's x-axis: (positions [n], ticks, x-axis label).

    When every delay is one number (no per-channel delays, no jitter), the positions are the delays
    in ms, ``ticks`` is None and the label ``input delay [ms]``. Otherwise a delay has no single
    place on such an axis: the distinct delays stand at 0, 1, ... in order (`_order`: by the
    longest channel), ``ticks`` = (those positions, their `delay_text`) and the label
    ``input delay``.

    Args:
        delays: [`Problem`][delayed_ilqr.Problem]s or seconds, one per point.
    """
    keys = [delay_key(d) for d in delays]
    if all(jitter is None and not isinstance(ms, tuple) for ms, jitter in keys):
        return np.array([ms for ms, _ in keys], np.float64), None, "input delay [ms]"
    distinct = sorted(dict.fromkeys(keys), key=_order)
    first = {}                                  # each distinct delay's first occurrence, for its text
    for k, d in zip(keys, delays):
        first.setdefault(k, d)
    return (np.array([distinct.index(k) for k in keys], np.float64),
            (list(range(len(distinct))), [delay_text(first[k]) for k in distinct]), "input delay")
