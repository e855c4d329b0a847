"""The nonlinear delayed optimal control problem, eq. (1)-(2), discretised as in eq. (3).

    x_{k+1} = x_k + dt f(x_k, u_k, u_{k-l}) + sqrt(dt) F(x_k, u_k, u_{k-l}) xi_k,   u_k = 0 for k < 0
    J = sum_{k<K} dt * running(x_k, u_k) + final(x_K)

Time in the task (via-points, moving targets, force fields, timed perturbations): a problem built
with ``time_dependent=True`` calls its dynamics and noise with the step's time t_k = k dt (seconds)
as a last argument, f(x, u, ud, t); a ``GeneralCost(..., time_dependent=True)`` calls
running(x, u, params, t) with t_k and final(x, params, t) with t_K = K dt. The declaration is
explicit, not read from the signature: a signature cannot tell a time argument from an optional
parameter (``f(x, u, ud, gain=1.0)``), and ``functools.partial``, ``jax.jit``-wrapped functions
and callable objects hide it. Without it the callables are called exactly as before and the
compiled solver does not contain the time at all.

All callables are written with ``jax.numpy`` and see one time step (no batch axis). A
[`Problem`][delayed_ilqr.Problem] is a JAX pytree: its arrays (x0, the cost's arrays or parameters, the limits) are
data, its callables and sizes are static, so two problems that differ only in arrays share one
compiled solver, and ``jax.vmap`` over a batch of problems works.
"""
from __future__ import annotations

from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

from . import _delays, _fractional, _precision, _problem_checks, _problem_tree, _validate
from .costs import GeneralCost, QuadraticCost

__all__ = ["Problem", "QuadraticCost", "GeneralCost"]


class Problem:
    """A nonlinear, possibly stochastic, optimal control problem with input delay.

    Args:
        dynamics: ``f(x, u, ud) -> dx/dt`` [n]; ``ud`` is the command acting now, u_{k-l}; with
            per-channel delays, ``ud[j]`` = u_{k-l_j, j}, channel j's command sent l_j steps ago.
        x0: [n] initial state.
        dt: time step (s).
        horizon: K, the number of control steps (final time K dt).
        delay_steps: 0 <= l < K, the input delay in steps (tau = l dt). l >= K is refused: no
            command would act within the horizon (the LQG layer, ``lqg.DelayedLQG``, keeps
            accepting it as the reference case of its tests). A list [l_1, ..., l_d] gives one delay
            per command channel (0 <= l_j < K; docs/derivation.md §18, docs/guide/own_plant.md): they run
            in a frame of L = max_j l_j slots (``delay_frame``, which may be given larger), and the
            policy's ``delay_feedback`` spans u_{k-L}..u_{k-1}, channel j's entries older than l_j
            zero. Not with ``observation``. A delay that is not a whole number of steps, tau = (l + phi)
            dt (0 <= phi < 1; one value, or one per channel), has the zero-order-hold meaning: over
            a step the acting command switches from u_{k-l-1} to u_{k-l} at phi dt
            (docs/derivation.md §20). It runs as two taps per channel (l_j and l_j + 1, in a frame of
            at least max_j l_j + 1 slots), needs l_j + 1 < K, and is
            differentiable in phi. A floating-point array is taken this way even when whole.
        cost: a [`QuadraticCost`][delayed_ilqr.QuadraticCost] or [`GeneralCost`][delayed_ilqr.GeneralCost].
        noise: optional ``F(x, u, ud) -> [n, p]``, the continuous-time diffusion of eq. (1),
            dx = f dt + F dw: one step adds ``sqrt(dt) F xi``, xi ~ N(0, I_p), so its covariance is
            ``dt F F'``. A per-step relative noise sigma as in Todorov's discrete-time code
            (covariance ``dt^2 sigma^2 ...``) is ``F`` with sigma_u = sigma sqrt(dt):
            [`delayed_ilqr.models.per_step_noise_to_diffusion`][delayed_ilqr.models.per_step_noise_to_diffusion]. Entered unconverted, it is
            ``1 / sqrt(dt)`` times too large (10x at dt = 10 ms).
        u_min: optional [d] lower limits on the commands (a scalar for all; ``-inf`` for none).
        u_max: optional [d] upper limits on the commands (a scalar for all; ``inf`` for none).
        n_controls: d; needed only when it cannot be read from ``cost.Q`` or the limits.
        name: a label for reports.
        metadata: optional [`ModelMetadata`][delayed_ilqr.models.metadata.ModelMetadata] (labels, task space, warm
            start) that studies and figures read; static data, so it must be hashable.
        time_dependent: if True, ``dynamics`` and ``noise`` take the step's time as a last
            argument, ``f(x, u, ud, t)`` and ``F(x, u, ud, t)`` with t = k dt in seconds (within
            a step of [`simulate`][delayed_ilqr.simulate] with sub-steps, the sub-step's time): force
            fields, timed perturbations. A time-dependent cost is declared on the
            [`GeneralCost`][delayed_ilqr.GeneralCost]. Static: part of the compiled solver.
        observation: optional [`Observation`][delayed_ilqr.Observation], the delayed noisy sensors
            y_k = h(x_{k-l_s}) + G v_k. With it, [`solve`][delayed_ilqr.solve] adds the delayed
            Kalman filter to the policy and [`simulate`][delayed_ilqr.simulate] runs the controller on
            its estimate; without it (the default) the controller sees the state. A list of
            Observations is several sensors, each with its own delay and period, fused by one
            filter (``docs/guide/sensors.md``).
        delay_frame: optional L with l <= L < K: the delay becomes data, the pending commands are kept in a
            frame of L slots, and problems that differ only in ``delay_steps`` <= L share one
            compiled solver, under ``jax.vmap`` too (docs/derivation.md §17, docs/sweeps.md). A
            solve then costs what a solve at delay L costs; the policy's ``delay_feedback`` has L
            entries, of which those of the L - l commands that have acted are zero ([`solve`][delayed_ilqr.solve]
            trims them when l is known). Not with ``observation``.
        delay_jitter: optional [`DelayJitter`][delayed_ilqr.DelayJitter]: the delay jitters, the command
            acting at step k is u_{k-l_k} with l_k drawn independently at every step from its
            distribution (docs/derivation.md §21, docs/guide/own_plant.md); ``delay_steps`` is then
            its longest delay L, the number of commands in flight that the policy's
            ``delay_feedback`` spans (u_{k-L}..u_{k-1}). [`solve`][delayed_ilqr.solve] designs for the
            jitter and [`simulate`][delayed_ilqr.simulate] draws it. Its probabilities are data
            (problems whose jitters share a support share one compiled solver, under
            ``jax.vmap`` too). Not with ``observation``, ``delay_frame`` or per-channel delays.
    """

    def __init__(self, dynamics: Callable, x0, dt, horizon, delay_steps, cost, noise: Optional[Callable] = None,
                 u_min=None, u_max=None, n_controls: Optional[int] = None, name: str = "problem",
                 metadata=None, time_dependent: bool = False, observation=None, delay_frame=None,
                 delay_jitter=None):
        _precision.require_x64("Problem")
        if not isinstance(time_dependent, (bool, np.bool_)):
            raise TypeError(f"time_dependent must be True or False; got {time_dependent!r}")
        self.time_dependent = bool(time_dependent)
        t = ", t" if self.time_dependent else ""
        if not callable(dynamics):
            raise TypeError(f"dynamics must be callable as f(x, u, ud{t}); got {type(dynamics).__name__}")
        if noise is not None and not callable(noise):
            raise TypeError(f"noise must be None or callable as F(x, u, ud{t}); got {type(noise).__name__}")
        self.dynamics, self.noise, self.name = dynamics, noise, str(name)
        try:
            hash(metadata)
        except TypeError:
            raise TypeError("metadata must be None or a hashable ModelMetadata; "
                            f"got {type(metadata).__name__}") from None
        self.metadata = metadata
        self.dt = _validate.positive_float(dt, "dt")
        self.horizon = _validate.positive_int(horizon, "horizon")
        x0 = _validate.array(x0, "x0", (None,))
        nx = x0.shape[0]
        if isinstance(cost, QuadraticCost):
            P = _validate.array(cost.P, "cost.P", (None, None))
            if P.shape != (nx, nx):
                raise ValueError(f"cost.P must have shape ({nx}, {nx}) to match x0 of shape ({nx},); "
                                 f"got shape {P.shape}")
            P = _validate.symmetric_psd(P, "cost.P", definite=False)
            Q = _validate.array(cost.Q, "cost.Q", (None, None))
            nd_cost = Q.shape[0]
            Q = _validate.symmetric_psd(_validate.array(Q, "cost.Q", (nd_cost, nd_cost)), "cost.Q", definite=True)
            P_final = _validate.symmetric_psd(_validate.array(cost.P_final, "cost.P_final", (nx, nx)),
                                              "cost.P_final", definite=False)
            x_target = _validate.array(cost.x_target, "cost.x_target", (nx,))
            cost = QuadraticCost(*(jnp.asarray(a) for a in (P, Q, P_final, x_target)))
        elif isinstance(cost, GeneralCost):
            nd_cost = None
        else:
            raise TypeError(f"cost must be a QuadraticCost or a GeneralCost; got {type(cost).__name__}")
        nd = _problem_checks.resolve_n_controls(n_controls, nd_cost, u_min, u_max)
        self.n_controls = nd
        self.delay_fraction = None      # the callables are checked as the user wrote them
        delay_steps, delay_fraction = _problem_checks.delay_below_horizon(delay_steps, self.horizon, nd)
        self.x0, self.cost = jnp.asarray(x0), cost
        self.u_min, self.u_max, self._has_limits = _problem_checks.checked_limits(u_min, u_max, nd)
        _problem_checks.check_labels(metadata, self.n_states, nd)
        _problem_checks.check_callables(self)
        self.delay_steps, self.delay_fraction = delay_steps, delay_fraction
        self.observation = _problem_checks.checked_sensors(observation, self.x0, self.horizon)
        self.delay_frame = _problem_checks.checked_frame(delay_frame, self.delay_steps, self.observation,
                                                         self.horizon, delay_fraction is not None)
        self.delay_jitter = _problem_checks.checked_jitter(delay_jitter, self.delay_steps, self)

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def n_states(self) -> int:
        return self.x0.shape[0]

    @property
    def n_noise(self) -> int:
        """p, the number of noise columns (0 without noise)."""
        if self.noise is None:
            return 0
        return jax.eval_shape(self.noise_at, self.x0, jnp.zeros(self.n_controls), jnp.zeros(self.n_delayed),
                              0.0).shape[1]

    @property
    def n_delayed(self) -> int:
        """The width of ``ud`` the solver passes to `dynamics_at`: d, or 2 d taps for a fractional
        delay ([u_{k-l}, u_{k-l-1}], docs/derivation.md §20)."""
        return self.n_controls if self.delay_fraction is None else 2 * self.n_controls

    @property
    def is_fractional(self) -> bool:
        """Whether the delay runs as two taps per channel (a delay that is not whole steps)."""
        return self.delay_fraction is not None

    # -- time ----------------------------------------------------------------------------------
    @property
    def uses_time(self) -> bool:
        """Whether the dynamics, the noise or the cost depend on time (static)."""
        return self.time_dependent or bool(getattr(self.cost, "time_dependent", False))

    @property
    def final_time(self) -> float:
        """t_K = K dt (s), the time the final cost is evaluated at."""
        return self.horizon * self.dt

    def step_times(self, dtype=jnp.float64):
        """t_k = k dt for k = 0..K-1 ([K], seconds), or None when nothing depends on time, so
        that the loops of a time-independent problem carry no time at all."""
        if not self.uses_time:
            return None
        return self.dt * jnp.arange(self.horizon, dtype=dtype)

    def dynamics_at(self, x, u, ud, t):
        """f(x, u, ud), or f(x, u, ud, t) for a time-dependent problem (t: the time in s). With a
        fractional delay ``ud`` is the [2 d] taps [u_{k-l}, u_{k-l-1}] and this is the step's
        mean rate of change under the zero-order hold (`_fractional.drift`)."""
        t = (t,) if self.time_dependent else ()
        if self.delay_fraction is not None:
            return _fractional.drift(self.dynamics, x, u, ud, self.delay_fraction, *t)
        return self.dynamics(x, u, ud, *t)

    def noise_at(self, x, u, ud, t):
        """F(x, u, ud), or F(x, u, ud, t) for a time-dependent problem: [n, p]; with a fractional
        delay the step's (d + 1) p columns (`_fractional.diffusion`)."""
        t = (t,) if self.time_dependent else ()
        if self.delay_fraction is not None:
            return _fractional.diffusion(self.noise, x, u, ud, self.delay_fraction, *t)
        return self.noise(x, u, ud, *t)

    @property
    def has_limits(self) -> bool:
        """Whether any command limit is finite (static: fixed when the problem is built)."""
        return self._has_limits

    @property
    def delay(self) -> float:
        """tau = l dt in seconds ([d] per channel; (l_j + phi_j) dt for a fractional delay)."""
        return self.delay_in_steps * self.dt

    @property
    def delay_in_steps(self):
        """tau / dt: l, [l_j], or l_j + phi_j [d] for a fractional delay (whose ``delay_steps``
        holds its two taps [l_j, l_j + 1])."""
        if self.delay_fraction is None:
            return self.delay_steps
        return self.delay_steps[:self.n_controls] + self.delay_fraction

    @property
    def frame_steps(self) -> int:
        """The number of pending command slots (static): ``delay_frame``, or l without a frame."""
        return self.delay_steps if self.delay_frame is None else self.delay_frame

    def without_frame(self, where: str) -> "Problem":
        """The same problem with its delay static again (itself without a frame), for the parts of
        the library that need l as a number; ``where`` names the caller in the error raised when l
        is traced (a framed problem under jit or vmap)."""
        if self.delay_frame is None:
            return self
        if self.delay_fraction is not None:
            raise ValueError(f"{where} needs a whole number of steps as the input delay; got a fractional delay "
                             f"(delay_steps + fraction = {_delays.as_json(self.delay_steps)[:self.n_controls]} + "
                             f"{np.asarray(self.delay_fraction).tolist() if not isinstance(self.delay_fraction, jax.core.Tracer) else 'traced'})")
        if _delays.is_per_channel(self.delay_steps):
            raise ValueError(f"{where} needs one input delay for all command channels; got per-channel "
                             f"delay_steps={_delays.as_json(self.delay_steps)}")
        if isinstance(self.delay_steps, jax.core.Tracer):
            raise ValueError(f"{where} needs a static delay: it cannot take a problem with a delay_frame under jit "
                             "or vmap (its delay_steps is traced); call it outside, or on problems without a frame")
        return self._with_delay(self.delay_steps, None)

    def replace(self, **changes) -> "Problem":
        """A copy with some fields changed, validated again (e.g. ``delay_steps=0``, ``noise=None``,
        ``delay_frame=15``). Changing only the delay and the frame checks only them; in a frame the
        delay may then be traced (a fit's delay as data), and is not checked: a traced
        floating-point delay in steps is a fractional one (differentiable, docs/derivation.md §20)."""
        if changes and set(changes) <= {"delay_steps", "delay_frame"} and self.delay_jitter is None:
            return self._with_delay(changes.get("delay_steps", self.delay_steps),
                                    changes.get("delay_frame", self.delay_frame))
        fields = dict(dynamics=self.dynamics, x0=self.x0, dt=self.dt, horizon=self.horizon,
                      delay_steps=self.delay_in_steps, cost=self.cost, noise=self.noise, u_min=self.u_min,
                      u_max=self.u_max, n_controls=self.n_controls, name=self.name,
                      metadata=self.metadata, time_dependent=self.time_dependent, observation=self.observation,
                      delay_frame=self.delay_frame, delay_jitter=self.delay_jitter)
        fields.update(changes)
        x0 = changes.get("x0")
        if x0 is not None and "cost" not in changes and np.shape(x0) != (self.n_states,):
            raise ValueError(f"x0 must have shape ({self.n_states},), the problem's state size; got shape "
                             f"{np.shape(x0)}")
        return Problem(**fields)

    def _with_delay(self, delay_steps, delay_frame) -> "Problem":
        """[`replace`][delayed_ilqr.Problem.replace] of the delay and the frame alone: a copy, the callables not re-checked."""
        new = object.__new__(Problem)
        new.__dict__.update(self.__dict__)
        new.delay_fraction = None
        if delay_frame is not None and isinstance(delay_steps, jax.core.Tracer):
            # a traced delay is checked against the frame by the solver (Status.INVALID_TRACED_INPUT)
            new.delay_frame = _problem_checks.checked_frame(delay_frame, 0, new.observation, new.horizon)
            if jnp.issubdtype(delay_steps.dtype, jnp.floating):        # a fractional delay as data
                whole = jax.lax.stop_gradient(jnp.floor(delay_steps))
                new.delay_fraction = jnp.broadcast_to(delay_steps - whole, (new.n_controls,))
                new.delay_steps = _delays.taps_of(whole.astype(jnp.int32), new.n_controls)
            else:
                new.delay_steps = delay_steps
            return new
        if isinstance(delay_steps, (np.ndarray, jax.Array)) and delay_steps.ndim == 0 \
                and np.issubdtype(delay_steps.dtype, np.integer):
            delay_steps = int(delay_steps)      # a framed problem's leaf, outside jit
        new.delay_steps, new.delay_fraction = _problem_checks.delay_below_horizon(delay_steps, new.horizon,
                                                                                  new.n_controls)
        new.delay_frame = _problem_checks.checked_frame(delay_frame, new.delay_steps, new.observation, new.horizon,
                                                        new.delay_fraction is not None)
        return new

    def _delay_repr(self):
        if self.delay_fraction is None or isinstance(self.delay_fraction, jax.core.Tracer):
            return self.delay_steps
        return np.round(np.asarray(self.delay_in_steps, np.float64), 12).tolist()

    def __repr__(self):
        return (f"Problem({self.name!r}, n={self.n_states}, d={self.n_controls}, p={self.n_noise}, "
                f"K={self.horizon}, dt={self.dt}, delay_steps={self._delay_repr()}"
                + ("" if self.delay_frame is None else f", delay_frame={self.delay_frame}")
                + ("" if self.delay_jitter is None else f", delay_jitter={self.delay_jitter!r}") + ")")


def shared_delay_frame(problems) -> Optional[int]:
    """The frame that gives ``problems`` of different delays one compiled solver: their longest
    delay in steps (with per-channel delays, the longest channel's); None when they all have the
    same delay (a frame would only cost) or when one has delayed sensors (an ``observation``: its
    delays must be static, no frame is available)."""
    problems = list(problems)
    for p in problems:
        if p.is_fractional:
            raise ValueError("a study over delays takes a whole number of steps per problem (one, or one per "
                             f"channel); got delay_steps={p._delay_repr()} in {p!r}")
    delays = {delay_key(p.delay_steps) for p in problems}
    if len(delays) < 2 or any(p.observation is not None for p in problems):
        return None
    return max(_delays.longest(p.delay_steps) for p in problems)


def delay_key(delay_steps):
    """A problem's delay as a hashable value: the int l, or the tuple (l_1, ..., l_d) per channel."""
    value = _delays.as_json(delay_steps)
    return tuple(value) if isinstance(value, list) else value


_problem_tree.register(Problem)
