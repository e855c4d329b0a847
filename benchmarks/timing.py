"""Wall-clock timing shared by the benchmarks: one definition of "the time of a call".

Every call is timed with ``time.perf_counter`` until its result is ready
(``jax.block_until_ready``: JAX dispatches asynchronously; a result that holds no JAX array, such
as crocoddyl's, passes through unchanged). The benchmarks compare times measured in the same run
and print their ratios: the load of a shared machine moves every absolute time, and moves the
calls of one run alike.

|  |  |
|---|---|
| `timed` | (result, seconds) of one call |
| `median_time` | the median of repeated calls, after a first (compiling) call unless told otherwise |
| `first_and_median` | (result, first call's seconds with compilation, median of the calls after it) |
| `interleaved` | (median, min) of several calls taken in turns, so that a change of load hits them alike |
"""
from __future__ import annotations

import statistics
import time
from typing import Callable, Optional

import jax

__all__ = ["timed", "median_time", "first_and_median", "interleaved"]


def timed(fn: Callable, *args):
    """(fn(*args), wall seconds until its result is ready)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def median_time(fn: Callable, *args, repeats: int = 5, warmup: bool = True, slow_repeats: Optional[int] = None,
                slow_s: float = 2.0, fill_s: float = 0.0) -> float:
    """The median wall seconds of calls of ``fn(*args)``.

    Args:
        repeats: the number of timed calls.
        warmup: make one call first, not timed (the compilation).
        slow_repeats: when given, the number of timed calls instead when the first takes over
            ``slow_s`` seconds (one call of a slow solve is enough).
        fill_s: then more calls until they add up to this many seconds (a median of a few
            sub-millisecond calls moves by 20 % between runs on a shared machine).
    """
    if warmup:
        jax.block_until_ready(fn(*args))
    times = []
    while (len(times) < (slow_repeats if slow_repeats is not None and times and times[0] > slow_s else repeats)
           or sum(times) < fill_s):
        times.append(timed(fn, *args)[1])
    return statistics.median(times)


def first_and_median(fn: Callable, *args, repeats: int = 7, slow_repeats: int = 3, slow_s: float = 2.0,
                     fill_s: float = 0.5):
    """(result, first call's seconds (compilation included), `median_time` of the calls after it):
    at least ``repeats`` calls (``slow_repeats`` when one takes over ``slow_s``), and more for fast
    calls until ``fill_s`` seconds are spent."""
    out, first = timed(fn, *args)
    return out, first, median_time(fn, *args, repeats=repeats, warmup=False, slow_repeats=slow_repeats,
                                   slow_s=slow_s, fill_s=fill_s)


def interleaved(fns: dict, repeats: int, warmup: bool = True) -> dict:
    """{name: (median, min) seconds} of ``repeats`` rounds, each calling every function once (after
    a first, compiling call of each with ``warmup``): a change of the machine's load hits them
    alike. The minimum is the call least disturbed by the other processes on a shared machine."""
    if warmup:
        for fn in fns.values():
            jax.block_until_ready(fn())
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            times[name].append(timed(fn)[1])
    return {name: (statistics.median(t), min(t)) for name, t in times.items()}
