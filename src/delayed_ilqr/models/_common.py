"""Argument checks shared by the model factories (delays in seconds, step sizes, horizons)."""
from __future__ import annotations

import math
import numbers

import jax.numpy as jnp
import numpy as np

from .. import _validate
from ..problem import QuadraticCost

# A delay is accepted when tau / dt is within this relative distance of an integer: 0.03 / 0.01 is
# 2.9999999999999996 in floating point and must give 3, while 0.025 / 0.01 = 2.5 must be refused.
_STEP_RTOL = 1e-9


def _real(value, name: str) -> float:
    """A real scalar as a Python float (bools, strings, arrays are refused)."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, np.integer, np.floating)):
        raise ValueError(f"{name} must be a non-negative finite number of seconds; got {value!r}")
    return float(value)


def delay_to_steps(delay, dt, name: str = "delay") -> int:
    """Converts an input delay tau in seconds into l = tau / dt steps.

    Args:
        delay: tau >= 0 in seconds; it must be a whole number of steps of ``dt`` (up to a relative
            rounding tolerance of 1e-9, so that ``delay_to_steps(0.03, 0.01) == 3``).
        dt: the time step in seconds (positive, finite).
        name: the argument's name used in error messages.

    Returns:
        l, a non-negative Python int.

    Raises:
        ValueError: naming ``name`` (or ``dt``), the rule and the value received, e.g.
            ``delay must be a whole number of steps of dt=0.01 s; got 0.025 s (2.5 steps)``.
    """
    dt = _validate.positive_float(dt, "dt")
    tau = _real(delay, name)
    if not math.isfinite(tau) or tau < 0:
        raise ValueError(f"{name} must be a non-negative finite number of seconds; got {delay!r}")
    steps = tau / dt
    if not math.isfinite(steps):
        raise ValueError(f"{name} must be a finite number of steps of dt={dt!r} s; got {tau!r} s")
    whole = round(steps)
    # a float32 delay carries its own rounding: 0.03 in float32 is 0.029999999329 (3 steps)
    rtol = max(_STEP_RTOL, 4 * float(np.finfo(delay.dtype).eps)) if isinstance(delay, np.floating) else _STEP_RTOL
    if abs(steps - whole) > rtol * max(1.0, abs(steps)):
        raise ValueError(f"{name} must be a whole number of steps of dt={dt!r} s; "
                         f"got {tau!r} s ({steps:.10g} steps)")
    return int(whole)


def delay_in_steps(delay, dt, name: str = "delay"):
    """An input delay tau in seconds as tau / dt steps: an int when it is a whole number of steps
    (`delay_to_steps`'s rounding tolerance), else the float tau / dt, whose fraction the solver
    treats by the zero-order hold (docs/derivation.md §20). The checks and messages are
    `delay_to_steps`'s."""
    try:
        return delay_to_steps(delay, dt, name)
    except ValueError as exc:
        if "whole number of steps" not in str(exc):
            raise
    return _real(delay, name) / float(dt)


def horizon_steps(horizon, final_time: float, dt: float) -> int:
    """``horizon`` checked as a positive int, or, when None, the number of steps nearest tf / dt."""
    if horizon is None:
        return max(1, int(round(final_time / dt)))
    return _validate.positive_int(horizon, "horizon")


def time_grid(dt, delay, horizon, final_time: float) -> tuple[float, int, int]:
    """(dt, delay_steps, horizon) of a model factory, each checked: dt > 0, the delay any
    non-negative number of seconds (argument name "delay"; in steps an int when whole, else a float,
    `delay_in_steps`), the horizon given or round(final_time / dt)."""
    dt = positive(dt, "dt")
    return dt, delay_in_steps(delay, dt, "delay"), horizon_steps(horizon, final_time, dt)


def benchmark_cost(x_target):
    """The cost P1 and P2 share (``docs/models.md`` §2): P = 0, Q = 1e-4 I_2,
    P_f = diag(1e3, 1e3, 1e1, 1e1), and the final target [4]."""
    return QuadraticCost(P=jnp.zeros((4, 4)), Q=1e-4 * jnp.eye(2),
                         P_final=jnp.diag(jnp.array([1e3, 1e3, 1e1, 1e1])), x_target=jnp.array(x_target))


def vector(value, name: str, size: int) -> tuple:
    """A length-``size`` finite vector, as a tuple of Python floats (hashable, readable in reprs)."""
    arr = _validate.array(value, name, (size,))
    return tuple(float(v) for v in arr)


def positive(value, name: str) -> float:
    return _validate.positive_float(value, name)


def non_negative(value, name: str) -> float:
    return _validate.non_negative_float(value, name)


def flag(value, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False; got {value!r}")
    return bool(value)


def noise_setting(noise, sigma_u, presets: dict, default: str, model: str) -> tuple:
    """(preset, sigma_u) of a factory's ``noise`` and ``sigma_u`` arguments, or (None, None) for no noise.

    Args:
        noise: False (no noise), True (the model's ``default`` preset) or a preset's name.
        sigma_u: None (the preset's level) or a non-negative level: with ``noise=True`` it
            replaces the default preset's (reported as ``"custom"`` unless it equals it); with a
            preset named it must be that preset's level, which defines it (e.g. ``"benchmark"``).
            Checked also without noise.
        presets: preset name -> sigma_u; default: the name ``noise=True`` selects.
        model: the factory's name, for error messages.
    """
    if isinstance(noise, str):
        if noise not in presets:
            raise ValueError(f"noise must be True, False or a noise preset of {model} "
                             f"({', '.join(repr(p) for p in presets)}); got {noise!r}")
        preset = noise
    elif flag(noise, "noise"):
        preset = default
    else:
        preset = None
    if sigma_u is None:
        return (None, None) if preset is None else (preset, presets[preset])
    sigma_u = non_negative(sigma_u, "sigma_u")
    if preset is None:
        return None, None
    if isinstance(noise, str):
        if sigma_u != presets[preset]:
            raise ValueError(f"sigma_u must be None with noise={preset!r}, whose level is fixed "
                             f"(sigma_u = {presets[preset]:g}); got sigma_u={sigma_u!r}")
        return preset, sigma_u
    return (preset if sigma_u == presets[preset] else "custom"), sigma_u
