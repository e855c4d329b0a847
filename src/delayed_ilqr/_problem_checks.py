"""The checks of a [`Problem`][delayed_ilqr.Problem]'s arguments, each against the others: the delay and
its frame against the horizon and the sensors, the jitter, the command limits and their number,
the metadata's labels, the sensors, and the callables on the problem's shapes. Each failure names
the argument, the rule and what was received; the single-argument rules are `_validate`'s and the
delay's normalisation is `_delays`'.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from . import _delays, _validate
from .delay_jitter import DelayJitter

if TYPE_CHECKING:
    from .problem import Problem

__all__ = ["delay_below_horizon", "checked_frame", "checked_jitter", "check_labels", "resolve_n_controls",
           "checked_limits", "checked_sensors", "check_callables"]


def delay_below_horizon(delay_steps, horizon: int, n_controls: int):
    """A valid (l, phi) for a horizon K: a whole number of steps below K and phi None, or for a
    fractional delay its taps [l_j, l_j + 1] (l_j + 1 < K) and phi [d]."""
    split = _delays.fractional(delay_steps, n_controls)
    if split is not None:
        whole, phi = split
        if np.any(whole + 1 >= horizon):
            raise ValueError(f"delay_steps must be below the horizon less one step when it is not whole: the command "
                             f"acting over a step is u_(k-l) and u_(k-l-1), and both must act within the horizon; "
                             f"got delay_steps={np.asarray(delay_steps).tolist()!r}, horizon={horizon}")
        return _delays.taps_of(whole, n_controls), phi
    delay_steps = _delays.checked(delay_steps, n_controls)
    if _delays.is_per_channel(delay_steps):
        _delays.check_below_horizon(delay_steps, horizon)
    elif delay_steps >= horizon:
        raise ValueError(f"delay_steps must be below the horizon: a command sent at step k acts at k + l, so with "
                         f"l >= K no command ever acts; got delay_steps={delay_steps}, horizon={horizon}")
    return delay_steps, None


def checked_frame(delay_frame, delay_steps: int, observation, horizon: int, fractional: bool = False):
    """A valid delay_frame for delay l and horizon K (None, or l <= L < K), refused with sensors."""
    if fractional and observation is not None:
        raise ValueError("a delay_steps that is not a whole number of steps is not available with an observation "
                         "(delayed sensors): the delayed filter takes one whole input delay; got delay_steps="
                         f"{_delays.as_json(delay_steps)[:len(delay_steps) // 2]} plus a fraction")
    if _delays.is_per_channel(delay_steps) and observation is not None:
        raise ValueError("per-channel delay_steps are not available with an observation (delayed sensors): the "
                         f"delayed filter takes one input delay; got delay_steps={_delays.as_json(delay_steps)}")
    delay_frame = _delays.checked_frame(delay_frame, delay_steps)
    if delay_frame is not None and delay_frame >= horizon:
        raise ValueError(f"delay_frame must be below the horizon: it holds delays l < K, so a larger frame only "
                         f"costs memory and time; got delay_frame={delay_frame}, "
                         f"horizon={horizon}")
    if delay_frame is not None and observation is not None:
        raise ValueError("delay_frame is not available with an observation (delayed sensors): the output-feedback "
                         f"layer needs a static delay; got delay_frame={delay_frame} with an observation")
    return delay_frame


def checked_jitter(delay_jitter, delay_steps, problem: "Problem"):
    """A valid delay_jitter (None, or a DelayJitter whose longest delay is ``delay_steps``)."""
    if delay_jitter is None:
        return None
    if not isinstance(delay_jitter, DelayJitter):
        raise TypeError(f"delay_jitter must be None or a delayed_ilqr.DelayJitter; got {type(delay_jitter).__name__}")
    if _delays.is_per_channel(delay_steps) or delay_steps != delay_jitter.longest:
        raise ValueError("with delay_jitter, delay_steps must be the jitter's longest delay (the commands in flight "
                         f"the policy keeps); got delay_steps={problem._delay_repr()} with {delay_jitter!r}")
    for name, value in (("checked_sensors", problem.observation), ("delay_frame", problem.delay_frame)):
        if value is not None:
            raise ValueError(f"delay_jitter is not available with {name} (the jittered solver takes full-state "
                             f"feedback and a static delay); got {name}={value!r}")
    return delay_jitter


def check_labels(metadata, nx: int, nd: int) -> None:
    """The metadata's labels name every state and command (figures and tables read them)."""
    for field, size, symbol in (("state_labels", nx, "n"), ("control_labels", nd, "d")):
        labels = getattr(metadata, field, None)
        if labels is not None and len(labels) != size:
            raise ValueError(f"metadata.{field} must have one label per {'state' if symbol == 'n' else 'command'} "
                             f"({symbol} = {size}); got {len(labels)}: {labels!r}")


def resolve_n_controls(n_controls, nd_cost, u_min, u_max) -> int:
    candidates = {}
    if n_controls is not None:
        candidates["n_controls"] = _validate.positive_int(n_controls, "n_controls")
    if nd_cost is not None:
        candidates["cost.Q"] = nd_cost
    for name, lim in (("u_min", u_min), ("u_max", u_max)):
        if lim is not None and np.ndim(lim) == 1:
            candidates[name] = np.shape(lim)[0]
    if not candidates:
        raise ValueError("n_controls must be given when it cannot be read from cost.Q, u_min or u_max; got None")
    if len(set(candidates.values())) > 1:
        raise ValueError(f"the number of controls must agree across arguments; got {candidates}")
    return next(iter(candidates.values()))


def _limit(value, name, nd, default):
    """A limit as a [d] array: None, a scalar (every command) or shape (d,)."""
    if value is None:
        return np.full(nd, default)
    shape = (nd,) if np.ndim(value) else ()
    arr = _validate.array(value, name, shape, finite=False)
    if isinstance(arr, jax.core.Tracer):
        return jnp.broadcast_to(arr, (nd,))
    return np.broadcast_to(arr, (nd,)).copy()


def checked_limits(u_min, u_max, nd):
    """(u_min [d], u_max [d], has_limits). Concrete limits are checked here, in NumPy (under
    ``jit`` a ``jnp`` array made from them is a tracer already); traced ones (a ``vmap`` over
    limits) cannot be, and count as limits."""
    lo, hi = _limit(u_min, "u_min", nd, -np.inf), _limit(u_max, "u_max", nd, np.inf)
    if isinstance(lo, jax.core.Tracer) or isinstance(hi, jax.core.Tracer):
        return jnp.asarray(lo), jnp.asarray(hi), True
    for name, lim in (("u_min", lo), ("u_max", hi)):
        if np.any(np.isnan(lim)):
            raise ValueError(f"{name} must not contain NaN; got {lim}")
    if np.any(lo >= hi):
        raise ValueError(f"u_min must be below u_max in every component; got u_min={lo}, u_max={hi}")
    return jnp.asarray(lo), jnp.asarray(hi), bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))


def checked_sensors(observation, x0, horizon):
    """The problem's observation, checked against its state size and horizon (None: full state)."""
    if observation is None:
        return None
    from .sensor_list import checked_observation      # the sensors' module imports the LQG layer
    return checked_observation(observation, x0, horizon)


def check_callables(problem: "Problem") -> None:
    """The dynamics, the noise and the cost evaluate on the problem's shapes and return what they must
    (by ``jax.eval_shape``: nothing runs); a failure names the callable, the shapes and why."""
    nx, nd = problem.n_states, problem.n_controls
    x, u = jax.ShapeDtypeStruct((nx,), jnp.float64), jax.ShapeDtypeStruct((nd,), jnp.float64)
    t = jax.ShapeDtypeStruct((), jnp.float64)
    ts = ", t" if problem.time_dependent else ""
    at = " and t of shape ()" if problem.time_dependent else ""
    try:
        out = jax.eval_shape(problem.dynamics_at, x, u, u, t)
    except Exception as exc:  # a user's function failing on shapes: say which and why
        raise ValueError(f"dynamics(x, u, ud{ts}) failed on x of shape ({nx},) and u, ud of shape ({nd},)"
                         f"{at}: {exc}") from exc
    if getattr(out, "shape", None) != (nx,):
        raise ValueError(f"dynamics(x, u, ud{ts}) must return shape ({nx},); got {getattr(out, 'shape', type(out))}")
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise ValueError(f"dynamics(x, u, ud{ts}) must return floating-point values (autodiff needs them); "
                         f"got dtype {out.dtype}")
    if problem.noise is not None:
        try:
            out = jax.eval_shape(problem.noise_at, x, u, u, t)
        except Exception as exc:
            raise ValueError(f"noise(x, u, ud{ts}) failed on x of shape ({nx},) and u, ud of shape ({nd},)"
                             f"{at}: {exc}") from exc
        shape = getattr(out, "shape", None)
        if shape is None or len(shape) != 2 or shape[0] != nx:
            raise ValueError(f"noise(x, u, ud{ts}) must return shape ({nx}, p); got {shape}")
        if not jnp.issubdtype(out.dtype, jnp.floating):
            raise ValueError(f"noise(x, u, ud{ts}) must return floating-point values; got dtype {out.dtype}")
    ct = ", t" if getattr(problem.cost, "time_dependent", False) else ""
    for what, fn, args in ((f"cost.running(x, u{ct})", problem.cost.running, (x, u, t)),
                           (f"cost.final(x{ct})", problem.cost.final, (x, t))):
        try:
            out = jax.eval_shape(fn, *args)
        except Exception as exc:
            raise ValueError(f"{what} failed on x of shape ({nx},) and u of shape ({nd},): {exc}") from exc
        if getattr(out, "shape", None) != ():
            raise ValueError(f"{what} must return a scalar; got shape {getattr(out, 'shape', type(out))}")
