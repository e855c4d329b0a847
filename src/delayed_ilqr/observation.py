"""Delayed, noisy sensors of a nonlinear [`Problem`][delayed_ilqr.Problem]:

    y_k = h(x_{k-l_s}) + G(x_{k-l_s}) v_k,    v_k ~ N(0, I_q),    k = l_s..K-1

``y_k`` is available when u_k is computed: the information for u_k is y_{l_s..k}, the commands
already sent, and x0 (known exactly; states before time 0 equal x0). A sensor with ``period`` m
samples the states x_j with j % m == 0 (x0 included), so its measurements arrive at the steps k >= l_s
with (k - l_s) % m == 0. Several sensors, each with its own delay and period, are a list of
``Observation`` (``sensor_list``). A disturbance that changes
x_{k+1} is first seen in y_{k+1+l_s}. [`delayed_ilqr.solve`][delayed_ilqr.solve] designs the delayed Kalman filter
of the linearisation around its nominal (`linearized_observation`, ``lqg.delayed_kalman``) and
[`delayed_ilqr.simulate`][delayed_ilqr.simulate] runs it on the nonlinear plant (``docs/derivation.md`` §14).
"""
from __future__ import annotations

from typing import Callable, Union

import jax
import jax.numpy as jnp
import numpy as np

from . import _precision, _validate
from .lqg.observation import _unflatten as _delayed_observation

__all__ = ["Observation", "linearized_observation"]


class Observation:
    """The sensors y_k = h(x_{k-l_s}) + G v_k of a [`Problem`][delayed_ilqr.Problem].

    Args:
        output: an [m, n] array H (y = H x) or a callable ``h(x) -> [m]`` written with
            ``jax.numpy`` (linearised by autodiff around the nominal).
        noise: an [m, q] array G (additive sensory noise, covariance G G' per sample; G G' must be
            positive definite: every measurement is noisy), or a callable ``G(x) -> [m, q]`` for
            state-dependent sensory noise (evaluated at the sensed state x_{k-l_s}; the filter
            uses it at the nominal).
        delay_steps: l_s >= 0, the sensory delay in steps (below the problem's horizon).
        period: m >= 1, the steps between two samples (default 1: a measurement every step); the
            samples are of the states x_j with j % m == 0, arriving l_s steps later.

    Callables are static data (part of the compilation key; a frozen dataclass or a module-level
    function shares compilations), arrays are data. The state size n is checked against the
    problem that receives the observation.
    """

    def __init__(self, output: Union[Callable, object], noise: Union[Callable, object], delay_steps=0, period=1):
        _precision.require_x64("Observation")
        self.delay_steps = _validate.delay_steps(delay_steps, "delay_steps")
        self.period = _validate.positive_int(period, "observation period")
        if callable(output):
            self.output_fn, self.H = output, None
        else:
            self.output_fn = None
            self.H = jnp.asarray(_validate.array(output, "output", (None, None)))
            if self.H.shape[0] < 1:
                raise ValueError(f"output must have at least one row (one sensor); got shape {self.H.shape}")
        if callable(noise):
            self.noise_fn, self.G = noise, None
        else:
            m = None if self.H is None else self.H.shape[0]
            G = _validate.array(noise, "noise", (m, None))
            if not isinstance(G, jax.core.Tracer):
                _validate.symmetric_psd(G @ G.T, "noise G G'", definite=True)
            self.noise_fn, self.G = None, jnp.asarray(G)

    # -- the sensors at one state ---------------------------------------------------------------
    def measure(self, x):
        """h(x) [m]."""
        return self.H @ x if self.output_fn is None else jnp.asarray(self.output_fn(x), x.dtype)

    def noise_matrix(self, x):
        """G(x) [m, q] (the constant G when additive)."""
        return self.G if self.noise_fn is None else jnp.asarray(self.noise_fn(x), x.dtype)

    def jacobian(self, x):
        """dh/dx [m, n] at x."""
        return self.H if self.output_fn is None else jax.jacfwd(self.measure)(x)

    @property
    def additive(self) -> bool:
        """Whether the sensory noise is additive (a constant G)."""
        return self.noise_fn is None

    def check(self, x0, horizon: int) -> None:
        """Raises ValueError, naming the argument, unless the observation fits a problem with
        state x0 [n] and ``horizon`` K (shapes, finite values, G(x0) G(x0)' positive definite,
        l_s < K). Callables are evaluated once at a concrete x0: h(x0) and G(x0) must be finite,
        and may not index past x (JAX clamps such an index in compiled code)."""
        nx = x0.shape[0]
        if self.delay_steps >= horizon:
            raise ValueError(f"observation delay_steps must be below the horizon: a measurement that arrives at "
                             f"k >= K reaches no command; got delay_steps={self.delay_steps}, horizon={horizon}")
        x = jax.ShapeDtypeStruct((nx,), jnp.float64)
        if self.output_fn is None:
            if self.H.shape[1] != nx:
                raise ValueError(f"observation output must have shape (m, {nx}) to match x0 of shape ({nx},); "
                                 f"got shape {self.H.shape}")
            m = self.H.shape[0]
        else:
            out = _eval_shape("observation output h(x)", self.output_fn, x)
            if len(out.shape) != 1 or out.shape[0] < 1:
                raise ValueError(f"observation output h(x) must return shape (m,) with m >= 1; got {out.shape}")
            m = out.shape[0]
        if self.noise_fn is None:
            if self.G.shape[0] != m:
                raise ValueError(f"observation noise must have shape ({m}, q), one row per output; got shape "
                                 f"{self.G.shape}")
        else:
            out = _eval_shape("observation noise G(x)", self.noise_fn, x)
            if len(out.shape) != 2 or out.shape[0] != m:
                raise ValueError(f"observation noise G(x) must return shape ({m}, q); got {out.shape}")
            if not isinstance(x0, jax.core.Tracer):
                G0 = _at_x0("observation noise G(x)", self.noise_matrix, x0)
                _validate.array(G0, "observation noise G(x0)", G0.shape)
                _validate.symmetric_psd(G0 @ G0.T, "observation noise G(x0) G(x0)'", definite=True)
        if self.output_fn is not None and not isinstance(x0, jax.core.Tracer):
            _validate.array(_at_x0("observation output h(x)", self.measure, x0), "observation output h(x0)", (m,))

    def __repr__(self):
        output = "H" if self.output_fn is None else repr(self.output_fn)
        noise = "G" if self.noise_fn is None else repr(self.noise_fn)
        return f"Observation(output={output}, noise={noise}, delay_steps={self.delay_steps}, period={self.period})"


def _eval_shape(what, fn, x):
    try:
        out = jax.eval_shape(fn, x)
    except Exception as exc:    # a user's function failing on shapes: say which and why
        raise ValueError(f"{what} failed on x of shape {x.shape}: {exc}") from exc
    if not hasattr(out, "shape") or not jnp.issubdtype(out.dtype, jnp.floating):
        raise ValueError(f"{what} must return a floating-point array; got {out!r}")
    return out


def _at_x0(what, fn, x0):
    """fn(x0) as a NumPy array, evaluated once with JAX's index checks: an index past the state,
    which JAX clamps (or fills with NaN) inside compiled code, is refused here by name."""
    from jax.experimental import checkify

    x0 = jnp.asarray(x0, jnp.float64)
    error, out = checkify.checkify(fn, errors=checkify.index_checks)(x0)
    message = error.get()
    if message is not None:
        raise ValueError(f"{what} indexes past its argument at x0 of shape {x0.shape}: "
                         f"{message.splitlines()[0].strip()}")
    return np.asarray(out)


def _flatten(obs: Observation):
    return (obs.H, obs.G), (obs.output_fn, obs.noise_fn, obs.delay_steps, obs.period)


def _unflatten(aux, data):
    new = object.__new__(Observation)
    new.output_fn, new.noise_fn, new.delay_steps, new.period = aux
    new.H, new.G = data
    return new


jax.tree_util.register_pytree_node(Observation, _flatten, _unflatten)


def sensed_states(xs, delay_steps: int):
    """x_{k-l_s} for k = 0..K-1 (x0 before time 0): [K, n] from the nominal xs [K+1, n]."""
    K = xs.shape[0] - 1
    ls = min(delay_steps, K)
    return jnp.concatenate([jnp.broadcast_to(xs[0], (ls,) + xs.shape[1:]), xs[:K - ls]])


def linearized_observation(observation: Observation, xs):
    """The linear delayed observation (14.1) around the nominal xs [K+1, n], and the nominal outputs.

    Row k belongs to the measurement that arrives at k, of x_{k-l_s}: H_k = dh/dx and G_k = G at
    x_bar_{k-l_s} (x0 for k < l_s, rows the filter never uses). Sensors with one delay stacked
    (``sensor_list.SensorList``) give one observation whose rows keep their periods.

    Returns:
        ([`DelayedObservation`][delayed_ilqr.lqg.DelayedObservation], y_nominal [K, m] = h(x_bar_{k-l_s})).
    """
    sensed = sensed_states(xs, observation.delay_steps)
    H = jax.vmap(observation.jacobian)(sensed)
    G = jax.vmap(observation.noise_matrix)(sensed)
    m = H.shape[1]
    period = observation.period if isinstance(observation.period, tuple) else (observation.period,) * m
    return (_delayed_observation((observation.delay_steps, period), (H, G)),
            jax.vmap(observation.measure)(sensed))
