"""Eager input checks shared by the public constructors.

Every message names the argument, the rule it broke and what was received, so that a user can fix
the call without reading the source. Checks run on concrete (NumPy) values before any tracing.
"""
from __future__ import annotations

import numbers

import jax
import numpy as np


def static(value, name: str):
    """Refuses a traced value for a field that fixes the compiled program (sizes, dt, callables)."""
    if isinstance(value, jax.core.Tracer):
        raise ValueError(f"{name} cannot be traced (it is static: it fixes the compiled solver); under jit or vmap "
                         "pass it as a Python number and batch only the arrays (x0, cost arrays or params, "
                         "limits); got a traced value")


def delay_steps(value, name: str = "delay_steps") -> int:
    """A non-negative whole number of steps (bools and non-integral floats are refused)."""
    static(value, name)
    if isinstance(value, bool) or not isinstance(value, (numbers.Integral, np.integer)):
        if isinstance(value, (numbers.Real, np.floating)) and float(value).is_integer() and not isinstance(value, bool):
            value = int(value)
        else:
            raise ValueError(f"{name} must be a non-negative integer number of steps; got {value!r}")
    if value < 0:
        raise ValueError(f"{name} must be a non-negative integer number of steps; got {value}")
    return int(value)


def delay_frame(value, delay: int, name: str = "delay_frame"):
    """None, or a whole number of pending slots L >= the delay l (the frame of docs/derivation.md §17)."""
    if value is None:
        return None
    value = delay_steps(value, name)
    if value < delay:
        raise ValueError(f"{name} must be at least delay_steps (the frame holds the l pending commands); "
                         f"got {name}={value} with delay_steps={delay}")
    return value


def non_negative_int(value, name: str) -> int:
    static(value, name)
    if isinstance(value, bool) or not isinstance(value, (numbers.Integral, np.integer)) or value < 0:
        raise ValueError(f"{name} must be a non-negative integer; got {value!r}")
    return int(value)


def positive_int(value, name: str) -> int:
    static(value, name)
    if isinstance(value, bool) or not isinstance(value, (numbers.Integral, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer; got {value!r}")
    return int(value)


def real(value, name: str, rule: str) -> float:
    """A real number as a Python float: ints, floats, NumPy scalars and 0-d arrays of them. Bools
    and strings are refused (``dt=True`` would be 1.0, ``tol_cost='1e-3'`` would fail later)."""
    static(value, name)
    if isinstance(value, (np.ndarray, jax.Array)) and not isinstance(value, jax.core.Tracer) and value.ndim == 0:
        value = np.asarray(value)[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.integer, np.floating)):
        raise ValueError(f"{name} must be {rule}; got {value!r}")
    try:
        return float(value)
    except OverflowError:           # an int beyond the float range
        raise ValueError(f"{name} must be {rule}; got {value!r}") from None


def positive_float(value, name: str) -> float:
    v = real(value, name, "a positive finite number")
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number; got {value!r}")
    return v


def non_negative_float(value, name: str) -> float:
    v = real(value, name, "a finite number >= 0")
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be a finite number >= 0; got {value!r}")
    return v


def seed(value, name: str = "seed") -> int:
    """A seed for ``jax.random.PRNGKey``: an integer in [0, 2**63)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise TypeError(f"{name} must be a non-negative integer; got {value!r}")
    if not 0 <= value < 2 ** 63:
        raise ValueError(f"{name} must be a non-negative integer below 2**63; got {value!r}")
    return int(value)


def reg(value, name: str = "reg"):
    """A regularisation lambda >= 0 (checked when concrete; a traced lambda passes as it is)."""
    if isinstance(value, jax.core.Tracer):
        return value
    return non_negative_float(value, name)


def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def array(value, name: str, shape: tuple, *, finite: bool = True):
    """Converts to a float64 array of the given shape; ``None`` entries of ``shape`` match anything.

    Traced values (under ``jit`` / ``vmap``) are checked for shape only and returned as they are.
    """
    if isinstance(value, jax.core.Tracer):
        if value.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, value.shape)):
            raise ValueError(f"{name} must have shape {_shape_text(shape)}; got shape {value.shape}")
        return value
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of numbers; got {type(value).__name__}") from None
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        raise ValueError(f"{name} must have shape {_shape_text(shape)}; got shape {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name} must be finite; got a non-finite value at index {tuple(int(i) for i in bad)}")
    return arr


def symmetric_psd(mat: np.ndarray, name: str, *, definite: bool, tol: float = 1e-10) -> np.ndarray:
    """Checks that the trailing two axes hold symmetric positive (semi-)definite matrices (not traced ones)."""
    if isinstance(mat, jax.core.Tracer):
        return mat
    asym = np.max(np.abs(mat - np.swapaxes(mat, -1, -2)), initial=0.0)
    scale = max(1.0, float(np.max(np.abs(mat), initial=0.0)))
    if asym > tol * scale:
        raise ValueError(f"{name} must be symmetric; got an asymmetry of {asym:.3g}")
    if mat.shape[-1] == 0:
        return mat
    eig = np.linalg.eigvalsh(0.5 * (mat + np.swapaxes(mat, -1, -2)))
    low = float(np.min(eig))
    if definite and low <= 0:
        raise ValueError(f"{name} must be positive definite; got a smallest eigenvalue of {low:.3g}")
    if not definite and low < -tol * scale:
        raise ValueError(f"{name} must be positive semi-definite; got a smallest eigenvalue of {low:.3g}")
    return mat
