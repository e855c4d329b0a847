"""Monte Carlo of the nonlinear stochastic plant (eq. 1) under a delayed feedback [`Policy`][delayed_ilqr.Policy].

Each trial integrates the SDE ``dx = f(x, u, ud) dt + F(x, u, ud) dw`` by Euler-Maruyama, with
``substeps`` sub-steps of length h = dt / substeps per control step (zero-order hold of u and ud):

    x <- x + h f(x, u_k, ud_k) + sqrt(h) F(x, u_k, ud_k) xi,      xi ~ N(0, I_p)

(a time-dependent problem's f and F see each sub-step's own time, k dt + j h)

The commands are computed online from the state and the commands actually sent (eq. 6 in absolute
terms, without the feedforward, see [`Policy`][delayed_ilqr.Policy]; the law is the solver's,
``lqg.law.delayed_law``):

    u_k  = clip(u_nominal_k + L_k (x_k - x_nominal_k) + sum_i M_k^i (u_{k+i-l_p} - u_nominal_{k+i-l_p}))
    ud_k = u_{k-l}                       (l = problem.delay_steps; u_k = u_nominal_k = 0 for k < 0)

(with ``problem.delay_jitter``, l = l_k is drawn at every step of every trial from its distribution,
docs/derivation.md §21, from ``jax.random.fold_in(trial_key, 2)``: the motor noise stays the
trial's)

where l_p = ``policy.delay_feedback.shape[1]`` is the delay the policy was designed for. It may
differ from the plant's l: a delay-ignorant policy (designed with l_p = 0) can be run on a delayed
plant, which is how the cost of ignoring the delay is measured.

Trials run in parallel (``jax.vmap`` over per-trial keys, ``lax.scan`` over time) in one compiled
function; the result depends only on ``seed`` (``jax.random.PRNGKey(seed)`` split into one key per
trial), so two calls with the same arguments give identical trajectories, and two policies run with
the same seed see the same noise samples (common random numbers: their cost difference has a much
smaller variance than either cost).
"""
from __future__ import annotations

import math
import os
from functools import partial
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from . import _precision, _validate
from .lqg.frame import current_taps, tap_channels
from .lqg.law import augmented_feedback, delayed_law
from .ilqg.linearize import trajectory_cost
from .lqg import Gains
from .fused_estimator import FusedEstimator
from .lqg.estimator import delayed_rows, estimator_predict, estimator_update
from .lqg.fusion import FusionGains, fusion_advance, fusion_init, fusion_rows, fusion_update
from .problem import Problem
from .sensor_list import SensorList
from .solution import Estimator, Policy
from .statistics import Summary, summarize

__all__ = ["simulate", "memory_estimate", "check_memory", "Runs"]


class Runs(NamedTuple):
    """Monte Carlo trials of the nonlinear plant under a policy.

    Attributes:
        x: [N, K+1, n] states (x[:, 0] = x0).
        u: [N, K, d] commands sent (the plant receives them ``problem.delay_steps`` steps later).
        cost: [N] eq. (2) of each trial, ``trajectory_cost(problem, x, u)``.
        x_hat: None with full-state feedback; with an [`Estimator`][delayed_ilqr.Estimator], [N, K, n]
            the estimates x_nominal_k + E[dx_k | I_k] the commands u_k were computed from.
    """

    x: jax.Array
    u: jax.Array
    cost: jax.Array
    x_hat: Optional[jax.Array] = None

    def summary(self) -> Summary:
        """Mean and median cost with 95 % intervals; mean and covariance of x_K (only non-finite
        costs count as diverged here; studies pass the plant's bound to
        [`summarize`][delayed_ilqr.statistics.summarize])."""
        return summarize(self.cost, self.x[:, -1])


def _plant_step(problem: Problem, x, u, ud, xi, t, substeps: int):
    """One step of the plant from x under the held commands (u, ud): ``substeps`` Euler-Maruyama
    sub-steps of h = dt / substeps with the noise samples xi [substeps, p], at the times
    t + j h (t: t_k, None for a problem without time)."""
    h = problem.dt / substeps
    root_h = math.sqrt(h)

    def substep(x, sub):
        xi_j, t_j = sub
        x_new = x + h * problem.dynamics_at(x, u, ud, t_j)
        if problem.noise is not None:
            x_new = x_new + root_h * problem.noise_at(x, u, ud, t_j) @ xi_j
        return x_new, None

    t_sub = None if t is None else t + h * jnp.arange(substeps, dtype=x.dtype)
    return jax.lax.scan(substep, x, (xi, t_sub))[0]


def _trial_step(problem: Problem, l_p: int, m: int, substeps: int):
    """The scan body of one trial: the state and the last m = max(l, l_p) sent commands and their
    nominals in time order, so that the policy's delay l_p need not be the plant's l. The law is
    the solver's (``lqg.law.delayed_law``) on z = [x - x_bar; u_{k-l_p} - u_bar_{k-l_p},
    ..., u_{k-1} - u_bar_{k-1}], with [L, M] in that order (``augmented_feedback``). Time order,
    not the solver's slot frame: under the vmap over trials it runs faster
    (docs/performance.md#simulate-pending-commands-in-time-order)."""
    l, framed, nd = problem.delay_steps, problem.delay_frame is not None, problem.n_controls

    def step(carry, data):
        x, sent, nominal = carry                 # sent[j] = u_{k-m+j}, nominal[j] = u_nominal_{k-m+j}
        # xi: [substeps, p]; t: t_k, None without time; lk: the step's jittered delay, None without
        # jitter; disturbance: [W_k] or []
        x_bar, u_bar, I, LM, xi, t, lk, *disturbance = data
        pending = (sent[m - l_p:] - nominal[m - l_p:]).reshape(-1)        # u_{k+i-l_p} - u_nominal, i < l_p
        du = delayed_law(I, LM, jnp.concatenate([x - x_bar, pending]))
        u = jnp.clip(u_bar + du, problem.u_min, problem.u_max)
        if lk is not None:      # a jittered delay, drawn for this step (derivation §21)
            ud = jnp.where(lk == 0, u, sent[jnp.clip(m - lk, 0, max(m - 1, 0))]) if m > 0 else u
        elif framed and m == 0:   # every delay 0
            ud = u
        elif framed:    # l is data (Problem.delay_frame <= m): a dynamic index, and u itself for l = 0
            acting = jnp.minimum(m - l, m - 1)
            # per-channel delays: channel j's command sent l_j steps ago; taps: channel i mod d's
            ud = jnp.where(l == 0, current_taps(u, l), sent[acting] if jnp.ndim(l) == 0
                           else sent[acting, tap_channels(jnp.shape(l)[0], nd)])
        else:
            ud = sent[m - l] if l > 0 else u

        x_new = _plant_step(problem, x, u, ud, xi, t, substeps)
        if disturbance:
            x_new = x_new + disturbance[0]
        if m > 0:
            sent = jnp.concatenate([sent[1:], u[None]])
            nominal = jnp.concatenate([nominal[1:], u_bar[None]])
        return (x_new, sent, nominal), (x_new, u)

    return step


@partial(jax.jit, static_argnames=("n_trials", "substeps"))
def _simulate(problem: Problem, policy: Policy, n_trials: int, substeps: int, key, disturbance=None) -> Runs:
    K, nd, p = problem.horizon, problem.n_controls, problem.n_noise
    l_p = policy.delay_feedback.shape[1]
    m = max(problem.frame_steps, l_p)
    step = _trial_step(problem, l_p, m, substeps)
    dtype = problem.x0.dtype
    # simulate runs the law without its feedforward (see Policy)
    gains = Gains(jnp.zeros_like(policy.feedforward), policy.state_feedback, policy.delay_feedback)

    def trial(trial_key):
        xi = jax.random.normal(trial_key, (K, substeps, p), dtype)
        init = (problem.x0, jnp.zeros((m, nd), dtype), jnp.zeros((m, nd), dtype))
        # a jittered delay is drawn per step from its own key: the motor noise is the fixed-delay run's
        delays = None if problem.delay_jitter is None else \
            problem.delay_jitter.sample(jax.random.fold_in(trial_key, 2), (K,))
        data = (policy.x_nominal[:-1], policy.u_nominal, gains.feedforward, augmented_feedback(gains), xi,
                problem.step_times(dtype), delays)
        if disturbance is not None:
            data = data + (disturbance,)
        _, (xs, us) = jax.lax.scan(step, init, data)
        xs = jnp.concatenate([problem.x0[None], xs])
        return xs, us, trajectory_cost(problem, xs, us)

    return Runs(*jax.vmap(trial)(jax.random.split(key, n_trials)))


def _observed_trial_step(problem: Problem, l_p: int, ls_e: int, buffer: int, substeps: int):
    """The scan body of one trial with delayed noisy sensors: the plant as in `_trial_step`,
    the measurement y_k = h(x_{k-l_s}) + G(x_{k-l_s}) v_k of the plant's sensors (l_s =
    ``problem.observation.delay_steps``; x0 before time 0), the policy's delayed filter on it
    (designed for l_s_e = ``ls_e`` and the motor delay l_p, ``lqg.estimator``) and the law on its
    estimate. ``buffer`` = max(l, l_s_e + l_p + 1) sent commands and their nominals are kept in time
    order: the plant reads u_{k-l}, the law u_{k-l_p}..u_{k-1}, the filter the deviations
    du_{k-l_s_e-l_p}..du_k."""
    l, obs = problem.delay_steps, problem.observation
    B, window = buffer, ls_e + l_p + 1

    def step(carry, data):
        past, sent, nominal, x_hat_prior, x_tilde = carry        # past[0] = x_{k-l_s}, past[-1] = x_k
        x_bar, u_bar, LM, xi, v, est, disturbance, t = data       # t: t_k, None without time
        A, B0, B1, Ad, B0d, B1d, H, y_bar, Kd, Kc = est
        x, sensed = past[-1], past[0]
        dy = obs.measure(sensed) + obs.noise_matrix(sensed) @ v - y_bar
        x_hat, x_del = estimator_update(x_hat_prior, x_tilde, dy, H, Kd, Kc)
        pending = (sent[B - l_p:] - nominal[B - l_p:]).reshape(-1)         # u_{k+i-l_p} - u_nominal, i < l_p
        u = jnp.clip(u_bar + delayed_law(jnp.zeros_like(u_bar), LM, jnp.concatenate([x_hat, pending])),
                     problem.u_min, problem.u_max)
        ud = sent[B - l] if l > 0 else u

        x_new = _plant_step(problem, x, u, ud, xi, t, substeps) + disturbance
        sent = jnp.concatenate([sent[1:], u[None]])
        nominal = jnp.concatenate([nominal[1:], u_bar[None]])
        # the filter moves with the commands actually sent (after clipping)
        prior = estimator_predict(x_hat, x_del, (sent - nominal)[B - window:], (A, B0, B1), (Ad, B0d, B1d), l_p, ls_e)
        past = jnp.concatenate([past[1:], x_new[None]])
        return (past, sent, nominal) + prior, (x_new, u, x_bar + x_hat)

    return step


@partial(jax.jit, static_argnames=("n_trials", "substeps"))
def _simulate_observed(problem: Problem, policy: Policy, n_trials: int, substeps: int, key, disturbance) -> Runs:
    K, nx, nd, p = problem.horizon, problem.n_states, problem.n_controls, problem.n_noise
    est = policy.estimator
    l_p, ls_e, ls = policy.delay_feedback.shape[1], est.sensory_delay, problem.observation.delay_steps
    B = max(problem.delay_steps, ls_e + l_p + 1)
    step = _observed_trial_step(problem, l_p, ls_e, B, substeps)
    dtype = problem.x0.dtype
    LM = augmented_feedback(Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback))
    B0, B1 = (est.B0 + est.B1, jnp.zeros_like(est.B1)) if l_p == 0 else (est.B0, est.B1)   # merged_if_undelayed
    delayed = tuple(delayed_rows(a, ls_e, fill) for a, fill in ((est.A, jnp.eye(nx)), (B0, 0.0), (B1, 0.0)))
    arrived = (jnp.arange(K) >= ls_e)[:, None, None]       # absent rows between samples have zero gains
    Kd, Kc = (jnp.where(arrived, g, 0.0) for g in (est.delayed_gain, est.current_gain))
    rows = (est.A, B0, B1) + delayed + (est.H, est.y_nominal, Kd, Kc)
    q = problem.observation.noise_matrix(problem.x0).shape[1]

    def trial(trial_key):
        xi = jax.random.normal(trial_key, (K, substeps, p), dtype)       # the motor noise of the full-state run
        v = jax.random.normal(jax.random.fold_in(trial_key, 1), (K, q), dtype)
        init = (jnp.broadcast_to(problem.x0, (ls + 1, nx)), jnp.zeros((B, nd), dtype), jnp.zeros((B, nd), dtype),
                jnp.zeros(nx, dtype), jnp.zeros(nx, dtype))
        data = (policy.x_nominal[:-1], policy.u_nominal, LM, xi, v, rows, disturbance, problem.step_times(dtype))
        _, (xs, us, x_hat) = jax.lax.scan(step, init, data)
        xs = jnp.concatenate([problem.x0[None], xs])
        return xs, us, trajectory_cost(problem, xs, us), x_hat

    return Runs(*jax.vmap(trial)(jax.random.split(key, n_trials)))


@partial(jax.jit, static_argnames=("n_trials", "substeps"))
def _simulate_fused(problem: Problem, policy: Policy, n_trials: int, substeps: int, key, disturbance) -> Runs:
    """The closed loop with sensors of different delays and the policy's fused filter
    (``FusedEstimator``, ``lqg.fusion``): sensor a reads the state l_a steps back with its own noise,
    the rows arriving at k update the filter's window, and the law acts on its estimate."""
    K, nx, nd, p = problem.horizon, problem.n_states, problem.n_controls, problem.n_noise
    est, sensors, l = policy.estimator, problem.observation, problem.delay_steps
    l_p, L, W = policy.delay_feedback.shape[1], sensors.delay_steps, est.window
    lags = np.asarray(est.lags)
    B = max(l, l_p, 1)
    dtype = problem.x0.dtype
    LM = augmented_feedback(Gains(policy.feedforward, policy.state_feedback, policy.delay_feedback))
    B0, B1 = (est.B0 + est.B1, jnp.zeros_like(est.B1)) if l_p == 0 else (est.B0, est.B1)   # merged_if_undelayed
    rows = fusion_rows(est.A, B0, B1, jnp.concatenate([jnp.zeros((W,) + est.H.shape[1:], dtype), est.H]),
                       FusionGains(est.base_gain, est.window_gain), W)
    q = sensors.noise_matrix(problem.x0).shape[1]

    def step(carry, data):
        past, sent, nominal, memory = carry                     # past[0] = x_{k-L}, past[-1] = x_k
        k, x_bar, u_bar, LMk, xi, v, y_bar, dist, t = data
        dy = sensors.measure_delayed(past, v) - y_bar
        x_hat, memory = fusion_update(memory, k, dy, rows, lags, W, l_p)
        pending = (sent[B - l_p:] - nominal[B - l_p:]).reshape(-1)
        u = jnp.clip(u_bar + delayed_law(jnp.zeros_like(u_bar), LMk, jnp.concatenate([x_hat, pending])),
                     problem.u_min, problem.u_max)
        ud = sent[B - l] if l > 0 else u
        x_new = _plant_step(problem, past[-1], u, ud, xi, t, substeps) + dist
        memory = fusion_advance(memory, u - u_bar)                 # the filter moves with the commands sent
        past = jnp.concatenate([past[1:], x_new[None]])
        sent = jnp.concatenate([sent[1:], u[None]])
        nominal = jnp.concatenate([nominal[1:], u_bar[None]])
        return (past, sent, nominal, memory), (x_new, u, x_bar + x_hat)

    def trial(trial_key):
        xi = jax.random.normal(trial_key, (K, substeps, p), dtype)
        v = jax.random.normal(jax.random.fold_in(trial_key, 1), (K, q), dtype)
        init = (jnp.broadcast_to(problem.x0, (L + 1, nx)), jnp.zeros((B, nd), dtype), jnp.zeros((B, nd), dtype),
                fusion_init(nx, est.n_outputs, nd, W, l_p, dtype))
        data = (jnp.arange(K), policy.x_nominal[:-1], policy.u_nominal, LM, xi, v, est.y_nominal, disturbance,
                problem.step_times(dtype))
        _, (xs, us, x_hat) = jax.lax.scan(step, init, data)
        xs = jnp.concatenate([problem.x0[None], xs])
        return xs, us, trajectory_cost(problem, xs, us), x_hat

    return Runs(*jax.vmap(trial)(jax.random.split(key, n_trials)))


def _check_fused_estimator(problem: Problem, est):
    """A FusedEstimator, checked against the problem's sensors of different delays."""
    sensors = problem.observation
    if not isinstance(est, FusedEstimator):
        raise ValueError("policy.estimator must be a delayed_ilqr.FusedEstimator for a problem whose sensors have "
                         "different delays (solve the problem with its observation); got "
                         f"{'None' if est is None else type(est).__name__}")
    if tuple(est.lags) != sensors.lags:
        raise ValueError(f"policy.estimator.lags must be the problem's sensor delays per row {sensors.lags}; got "
                         f"{tuple(est.lags)}")
    K, nx, nd, m = problem.horizon, problem.n_states, problem.n_controls, sum(sensors.sizes)
    W = min(sensors.delay_steps, K)
    shapes = dict(A=(K, nx, nx), B0=(K, nx, nd), B1=(K, nx, nd), H=(K, m, nx), y_nominal=(K, m),
                  base_gain=(K, nx, m), window_gain=(K, W, nx, m), error_covariance=(K + 1, nx, nx))
    checked = {name: jnp.asarray(_validate.array(getattr(est, name), f"policy.estimator.{name}", shape),
                                 jnp.float64) for name, shape in shapes.items()}
    return FusedEstimator(**checked, lags=est.lags)


def _check_estimator(problem: Problem, policy: Policy):
    """The policy's estimator, checked against the problem's sensors (None for full state)."""
    est, obs = policy.estimator, problem.observation
    if est is None and obs is None:
        return None
    if obs is None:
        raise ValueError("policy.estimator is set but the problem has no observation: a policy with a filter runs "
                         "on a problem with sensors (Problem(observation=...)); got observation=None")
    if isinstance(obs, SensorList) and not obs.equal_delays:
        return _check_fused_estimator(problem, est)
    if not isinstance(est, Estimator):
        raise ValueError("policy.estimator must be a delayed_ilqr.Estimator for a problem with an observation "
                         "(solve the problem with its observation); got "
                         f"{'None' if est is None else type(est).__name__}")
    K, nx, nd = problem.horizon, problem.n_states, problem.n_controls
    m = jax.eval_shape(obs.measure, jax.ShapeDtypeStruct((nx,), jnp.float64)).shape[0]
    shapes = dict(A=(K, nx, nx), B0=(K, nx, nd), B1=(K, nx, nd), H=(K, m, nx), y_nominal=(K, m),
                  delayed_gain=(K, nx, m), current_gain=(K, nx, m), error_covariance=(K + 1, nx, nx))
    checked = {name: jnp.asarray(_validate.array(getattr(est, name), f"policy.estimator.{name}", shape),
                                 jnp.float64) for name, shape in shapes.items()}
    ls_e = _validate.delay_steps(est.sensory_delay, "policy.estimator.sensory_delay")
    return Estimator(**checked, sensory_delay=ls_e)


def _check_policy(problem: Problem, policy) -> Policy:
    if not isinstance(policy, Policy):
        raise TypeError(f"policy must be a delayed_ilqr.Policy (e.g. solve(...).policy); got {type(policy).__name__}")
    K, nx, nd = problem.horizon, problem.n_states, problem.n_controls
    l_p = np.shape(policy.delay_feedback)[1] if np.ndim(policy.delay_feedback) == 4 else None
    checked = [
        _validate.array(policy.x_nominal, "policy.x_nominal", (K + 1, nx)),
        _validate.array(policy.u_nominal, "policy.u_nominal", (K, nd)),
        _validate.array(policy.feedforward, "policy.feedforward", (K, nd), finite=False),
        _validate.array(policy.state_feedback, "policy.state_feedback", (K, nd, nx)),
        _validate.array(policy.delay_feedback, "policy.delay_feedback", (K, l_p, nd, nd)),
    ]
    return Policy(*(jnp.asarray(a, jnp.float64) for a in checked), estimator=_check_estimator(problem, policy))


# The largest share of the memory left to the process that one Monte Carlo may plan to hold.
MEMORY_FRACTION = 0.5

# What simulate holds at its peak, per byte of the arrays it makes (trajectories, costs, estimates,
# noise samples): XLA keeps the scan's stacked outputs besides the returned ones and the noise as
# random bits besides the normal samples. The measured peak is 1.8 to 2.8 times the arrays' size
# (tests/test_simulate.py measures it, and XLA's plan, against this bound).
PEAK_FACTOR = 4


def memory_estimate(problem: Problem, n_trials: int, substeps: int = 1) -> int:
    """An upper bound of the bytes [`simulate`][delayed_ilqr.simulate.simulate] holds at its peak for ``n_trials`` trials:
    PEAK_FACTOR times the arrays it makes, in float64: states [N, K+1, n], commands [N, K, d],
    costs [N] and the noise samples [N, K, substeps, p]; with an observation also the estimates
    [N, K, n] and the sensory noise samples [N, K, q]."""
    K, nx, nd, p = problem.horizon, problem.n_states, problem.n_controls, problem.n_noise
    per_trial = (K + 1) * nx + K * nd + 1 + K * int(substeps) * p
    if problem.observation is not None:
        q = jax.eval_shape(problem.observation.noise_matrix, jax.ShapeDtypeStruct((nx,), jnp.float64)).shape[1]
        per_trial += K * (nx + q)
    return PEAK_FACTOR * 8 * int(n_trials) * per_trial


def _address_space_left():
    """The bytes of address space the process may still map under RLIMIT_AS (``ulimit -v``), or
    None without a limit (or where it cannot be read)."""
    try:
        import resource
        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/statm") as statm:         # the mapped size, in pages
            mapped = int(statm.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (ImportError, OSError, ValueError):
        return None
    return max(0, limit - mapped)


def _available_memory() -> tuple:
    """(bytes, what they are): the accelerator's memory, or on CPU the machine's physical memory
    or the address space left under ``ulimit -v``, whichever is smaller."""
    device = jax.devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), "of the accelerator"
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    left = _address_space_left()
    if left is not None and left < physical:
        return left, "of address space left to this process under its address-space limit (ulimit -v)"
    return physical, "of this machine"


def check_memory(problem: Problem, n_trials: int, substeps: int = 1, what: str = "n_trials", runs: int = 1) -> None:
    """Raises ValueError, with the figures, when ``runs`` Monte Carlos of ``n_trials`` trials each,
    held together, would need more than MEMORY_FRACTION of the memory of the machine (or of the
    accelerator, or of the address space left under ``ulimit -v``); ``what`` names the trial count
    in the message (e.g. "--trials")."""
    need, (have, where) = memory_estimate(problem, n_trials * runs, substeps), _available_memory()
    if need > MEMORY_FRACTION * have:
        per_trial = memory_estimate(problem, 1, substeps)
        per_run = " per run" if runs > 1 else ""
        fit = int(MEMORY_FRACTION * have // (per_trial * runs))
        advice = (f"run at most {fit} trials{per_run} per call (several calls with different seeds) and pool their "
                  "statistics" if fit >= 1 else
                  f"even one trial{per_run} would not fit: shorten the horizon, use fewer substeps"
                  f"{' or fewer runs' if runs > 1 else ''}, or use a machine with more memory")
        raise ValueError(f"{what}={n_trials} trials{f' in each of {runs} runs' if runs > 1 else ''} would hold about "
                         f"{need / 1e9:.3g} GB at their peak ({per_trial} bytes per trial), more than "
                         f"{MEMORY_FRACTION:g} of the {have / 1e9:.3g} GB {where}; {advice}")


def _ran_out_of_memory(exc: Exception) -> bool:
    """Whether XLA's error is a failed allocation (its messages, XLA's CPU and GPU clients)."""
    text = str(exc)
    return any(s in text for s in ("RESOURCE_EXHAUSTED", "Out of memory", "out of memory", "YNNPACK operation failed",
                                   "allocate"))


def simulate(problem: Problem, policy: Policy, n_trials: int, seed: int = 0, substeps: int = 1,
             disturbance=None) -> Runs:
    """Monte Carlo of ``problem``'s stochastic plant under the delayed feedback law of ``policy``.

    With delayed sensors (``problem.observation``) the policy's [`Estimator`][delayed_ilqr.Estimator]
    runs on the measurements y_k = h(x_{k-l_s}) + G(x_{k-l_s}) v_k of the nonlinear plant (x0 before
    time 0) and the law acts on its estimate x_nominal_k + x_hat_k instead of x_k; the sensory noise
    v is drawn from ``jax.random.fold_in(trial_key, 1)``, so the motor noise xi of a trial is that
    of the full-state run with the same seed.

    Args:
        problem: the plant (dynamics, noise, delay ``delay_steps`` = l, limits, cost). Without
            noise (``problem.noise`` None) every trial is the same deterministic closed loop.
        policy: the [`Policy`][delayed_ilqr.Policy] to run, e.g. ``solve(problem).policy``. Its
            arrays must match the problem's horizon K, states n and controls d; its delay l_p
            (``delay_feedback.shape[1]``) may differ from the plant's l.
        n_trials: N, the number of independent trials (positive int).
        seed: non-negative integer; the trials use ``jax.random.split(jax.random.PRNGKey(seed), N)``.
        substeps: Euler-Maruyama sub-steps per control step (positive int); 1 integrates at dt,
            exactly like `rollout` in the noise-free case.
        disturbance: optional [K, n] array W added to every trial's state update,
            x_{k+1} = ... + W_k, and unknown to the controller (a perturbation experiment: a force
            pulse is W_k = dt f_pulse on the velocity rows). With delayed sensors, the first
            command that can respond to W_k is u_{k+1+l_s}.

    Returns:
        [`Runs`][delayed_ilqr.Runs] with x [N, K+1, n], u [N, K, d], cost [N] (and x_hat [N, K, n] with an
        estimator); ``runs.summary()`` gives the mean
        cost, its standard error and 95 % confidence interval, the median, and the final-state
        statistics. A trial whose closed loop blows up has a non-finite cost (counted in
        ``summary().n_diverged``); nothing is raised.

    Raises:
        TypeError, ValueError: naming the argument, for a wrong problem or policy type, a policy
            whose shapes do not match the problem (or a filter without sensors, sensors without a
            filter), a non-positive ``n_trials`` / ``substeps``, a seed that is not a
            non-negative integer, or a disturbance that is not a finite [K, n] array;
            ValueError when the trials would not fit in memory ([`check_memory`][delayed_ilqr.simulate.check_memory], before
            anything is computed); MemoryError when an allocation fails all the same.
    """
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be a delayed_ilqr.Problem; got {type(problem).__name__}")
    _precision.require_x64("simulate")
    n_trials = _validate.positive_int(n_trials, "n_trials")
    substeps = _validate.positive_int(substeps, "substeps")
    if substeps > 1 and problem.is_fractional:
        raise ValueError("substeps must be 1 for a problem whose delay is not a whole number of steps: its step is "
                         "the zero-order-hold integral over the whole step (docs/derivation.md §20), which "
                         f"sub-steps would split; got substeps={substeps}")
    seed = _validate.seed(seed)
    policy = _check_policy(problem, policy)
    if disturbance is not None:
        disturbance = jnp.asarray(_validate.array(disturbance, "disturbance", (problem.horizon, problem.n_states)))
    check_memory(problem, n_trials, substeps)
    key = jax.random.PRNGKey(seed)
    if policy.estimator is not None and disturbance is None:
        # with sensors, one compilation serves the runs with and without a disturbance
        disturbance = jnp.zeros((problem.horizon, problem.n_states))
    run = _simulate if policy.estimator is None else (
        _simulate_fused if isinstance(policy.estimator, FusedEstimator) else _simulate_observed)
    try:
        # waited for here, so that a failed allocation is reported by this call, not by a later read
        return jax.block_until_ready(run(problem, policy, n_trials, substeps, key, disturbance))
    except jax.errors.JaxRuntimeError as exc:
        if not _ran_out_of_memory(exc):
            raise
        per_trial = memory_estimate(problem, 1, substeps)
        raise MemoryError(f"simulate ran out of memory with n_trials={n_trials} (up to {per_trial} bytes per "
                          f"trial): run fewer trials per call (several calls with different seeds) and pool "
                          f"their statistics. XLA: {str(exc).splitlines()[0]}") from None
