"""XLA's CPU backend, configured for loops of many small operations: [`configure_cpu`][delayed_ilqr.configure_cpu].

XLA on CPU runs each operation of a loop body as a separate thunk, at about 0.1 to 0.2 us each,
and the time steps of motor-control problems are small (P1's backward step is 29 such operations
on [4, 20] matrices). XLA compiles a ``while`` loop whose body reads and writes less than
``xla_cpu_small_while_loop_byte_threshold`` bytes per iteration (1024 by default) into one
function instead, with no thunk per operation, unless the loop holds a library call. Two flags
make that cover the solver's scans, about halving the time of a small solve (measurements:
docs/performance.md#configure_cpu):

* ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000``
  (`SMALL_LOOP_BYTES`): trades the thunk runtime's multi-threaded library kernels, which
  only large per-step products need, for no per-operation cost in every smaller loop; see
  docs/performance.md#xla_cpu_small_while_loop_byte_threshold.
* ``--xla_cpu_experimental_ynn_fusion_type=-individual_dot``: trades YNNPACK's single dots, fast
  on large products, for loops that can be compiled as one function (a loop that holds one
  never is); ``ilqg.solver.compiled_solver`` turns them back on for long delays
  (`LIBRARY_DOTS`); see docs/performance.md#xla_cpu_experimental_ynn_fusion_type.

Both are process-wide, and only ``XLA_FLAGS`` sets the threshold (``jax.jit``'s
``compiler_options`` take no map-valued options); XLA reads it once, when JAX starts its
backend. Importing ``delayed_ilqr`` sets nothing (a process-wide setting is the program's to
choose, and a flag that another jaxlib does not know aborts every process that inherits it): a
program that wants the speed calls [`configure_cpu`][delayed_ilqr.configure_cpu] before its first JAX computation, as the
``delayed-ilqr`` command line, the tests and the benchmarks do.
"""
from __future__ import annotations

import functools
import importlib.util
import mmap
import os
import pathlib
import string
import sys
import warnings
from typing import NamedTuple

__all__ = ["configure_cpu"]

SMALL_LOOP_BYTES = 1_000_000


class _Flag(NamedTuple):
    """One of the flags: added unless ``XLA_FLAGS`` already mentions ``setting``, and only when
    the installed jaxlib knows every name in ``requires``."""
    flag: str
    setting: str
    requires: tuple[str, ...]


_EXTRA_OPTIONS = "--xla_backend_extra_options="   # a map, key=value,...; a second one replaces the first
_FLAGS = (
    _Flag(f"{_EXTRA_OPTIONS}xla_cpu_small_while_loop_byte_threshold={SMALL_LOOP_BYTES}",
          "xla_cpu_small_while_loop_byte_threshold",
          ("xla_backend_extra_options", "xla_cpu_small_while_loop_byte_threshold")),
    _Flag("--xla_cpu_experimental_ynn_fusion_type=-individual_dot", "xla_cpu_experimental_ynn_fusion_type",
          ("xla_cpu_experimental_ynn_fusion_type",)),
)
# YNNPACK's single dots back, for one compilation (``jax.jit``'s compiler_options name the whole list)
LIBRARY_DOTS = {"xla_cpu_experimental_ynn_fusion_type": "LIBRARY_FUSION_TYPE_INDIVIDUAL_DOT"}
_LIBRARY_SUFFIXES = (".so", ".dylib", ".pyd", ".dll")
_IDENTIFIER_BYTES = frozenset(string.ascii_letters.encode() + string.digits.encode() + b"_")


def configure_cpu() -> tuple[str, ...]:
    """Adds XLA's two CPU flags for small loops to ``XLA_FLAGS``, for this process and its children.

    Call it once, before the first JAX computation of the program (XLA reads ``XLA_FLAGS`` when
    JAX starts its backend); small solves then run about twice as fast. What ``XLA_FLAGS``
    already sets is kept: a flag that sets the same option is left as it is (so
    ``--xla_cpu_experimental_ynn_fusion_type=+individual_dot`` or
    ``--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1024`` restore XLA's
    defaults), and the threshold joins the options of an existing ``--xla_backend_extra_options``.
    A flag that the installed jaxlib does not know is left out with a warning (XLA aborts the
    process on an unknown flag). Calling it again adds nothing.

    Returns:
        The flags this call added to ``XLA_FLAGS`` (empty when there was nothing to add, or when
        it came too late).

    Warns:
        UserWarning: when JAX's backend has already started, so that the flags could not take
            effect (nothing is changed then), and for each flag the installed jaxlib lacks.
    """
    current = os.environ.get("XLA_FLAGS", "")
    missing = [f for f in _FLAGS if f.setting not in current]
    if not missing:
        return ()
    if _backend_started():
        warnings.warn("delayed_ilqr.configure_cpu() came after JAX's first computation, when XLA had "
                      "already read XLA_FLAGS; nothing was changed. Call it at the top of the program, "
                      "before any JAX computation, for the faster compilation of small loops.",
                      UserWarning, stacklevel=2)
        return ()
    known = _known_names(tuple(sorted({name for f in missing for name in f.requires})))
    added = []
    for f in missing:
        if all(known[name] for name in f.requires):
            current = _with_flag(current, f.flag)
            added.append(f.flag)
        else:
            warnings.warn(f"the installed jaxlib does not know {f.flag}; it was left out of XLA_FLAGS "
                          "(solves stay correct, small ones run slower)", UserWarning, stacklevel=2)
    if added:
        os.environ["XLA_FLAGS"] = current
    return tuple(added)


def _with_flag(flags: str, flag: str) -> str:
    """``flags`` with ``flag`` appended, or for the extra options joined to the last one there."""
    tokens = flags.split()
    if flag.startswith(_EXTRA_OPTIONS):
        for i in reversed(range(len(tokens))):
            if tokens[i].startswith(_EXTRA_OPTIONS):
                separator = "," if tokens[i] != _EXTRA_OPTIONS else ""
                tokens[i] = f"{tokens[i]}{separator}{flag[len(_EXTRA_OPTIONS):]}"
                return " ".join(tokens)
    return " ".join([*tokens, flag])


def _backend_started() -> bool:
    """Whether JAX has started a backend (and so read ``XLA_FLAGS``) in this process."""
    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge   # no public query that does not itself start the backend
    return xla_bridge.backends_are_initialized()


@functools.cache
def _known_names(names: tuple[str, ...]) -> dict[str, bool]:
    """For each name, whether a shared library of the installed jaxlib holds it as a C string.

    XLA parses ``XLA_FLAGS`` against flag names compiled into jaxlib (and reads backend options
    by name), so a name it knows is stored NUL-terminated, not continuing a longer identifier.
    Reading the files leaves JAX's backend unstarted, which a trial compilation would not.
    """
    found = dict.fromkeys(names, False)
    for library in _jaxlib_libraries():
        with open(library, "rb") as file, mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as data:
            for name in names:
                found[name] = found[name] or _holds_c_string(data, name.encode())
        if all(found.values()):
            break
    return found


def _holds_c_string(data, name: bytes) -> bool:
    """Whether ``data`` holds ``name`` NUL-terminated, not preceded by an identifier character."""
    start = data.find(name + b"\0")
    while start >= 0:
        if start == 0 or data[start - 1] not in _IDENTIFIER_BYTES:
            return True
        start = data.find(name + b"\0", start + 1)
    return False


def _jaxlib_libraries() -> list[pathlib.Path]:
    """The shared libraries of the installed jaxlib, largest (XLA itself) first."""
    spec = importlib.util.find_spec("jaxlib")
    roots = [pathlib.Path(p) for p in (spec.submodule_search_locations or ())] if spec else []
    libraries = [p for root in roots for p in root.rglob("*") if p.suffix in _LIBRARY_SUFFIXES and p.is_file()]
    return sorted(libraries, key=lambda p: p.stat().st_size, reverse=True)
