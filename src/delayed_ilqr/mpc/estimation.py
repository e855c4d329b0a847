"""The receding-horizon controller's delayed filter: what it knows of the state when its sensors
are delayed and noisy (a [`Problem`][delayed_ilqr.Problem] with an ``observation``).

The measurement of tick k is y_k = h(x_{k-l_s}) + G(x_{k-l_s}) v_k (``delayed_ilqr.observation``).
As in the library's delayed Kalman filter (``lqg.estimator``, ``docs/derivation.md`` §14) the
filter runs in delayed time j = k - l_s and is carried to the present with the commands already
sent; here in its extended (nonlinear) form, linearised at every tick about its own estimate:

    update   S = H P H' + R,  Kd = P H' S^-1,  x_del = x_tilde + Kd (y_k - h(x_tilde))     E[x_j | I_k]
             P_post = (I - Kd H) P (I - Kd H)' + Kd R Kd'                                (Joseph form)
    present  x_hat_k = the model from x_del over steps j..k-1 under the commands that act then
    predict  x_tilde' = x_del + dt f(x_del, c_j, c_{j-l_c}, t_j),  P' = A P_post A' + Q_j

with H = dh/dx and R = G G' at x_tilde, A = I + dt df/dx at x_del, c the commands the controller
computed (c_{j-l_c} is the one acting at j), and Q_j the process covariance: ``process_cov`` when
given, else dt F F' of the model's noise at x_del (zero for a model without noise: the filter then
trusts its model and ignores the sensors once the initial uncertainty is gone). Before time 0 the
state is x0 and does not move (no prediction, no process noise), as in the problem. For a linear
model the present estimate is x_hat_k = Phi_k x_del + (the commands' effect), the linear filter's
E[x_k | I_k].
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["FilterState", "filter_init", "filter_update", "present_estimate", "filter_predict"]


class FilterState(NamedTuple):
    """The delayed filter's state between ticks.

    Attributes:
        x_prior: [n] x_tilde, the estimate of x_{k-l_s} before y_k.
        cov: [n, n] its covariance P.
        earlier: [l_s, d] the commands computed before those in flight, c_{k-l_s-l_c}..c_{k-l_c-1}
            (what acts between the sensed state and the present).
    """

    x_prior: jax.Array
    cov: jax.Array
    earlier: jax.Array


def _sym(M):
    return 0.5 * (M + M.T)


def filter_init(x0, initial_cov, sensory_delay: int, n_controls: int) -> FilterState:
    """The filter before the first tick: x0 [n] with covariance ``initial_cov`` [n, n], no commands."""
    return FilterState(x0, initial_cov, jnp.zeros((sensory_delay, n_controls), x0.dtype))


def filter_update(problem, fstate: FilterState, y, gate=None, gate_cov=None):
    """The measurement update with y_k [m]: (x_del [n], P_post [n, n]) (module docstring).

    With an innovation ``gate`` (a number) and ``gate_cov`` [n, n]: when the innovation's
    normalised square e' S^-1 e (e = y_k - h(x_tilde); chi-square with m degrees of freedom while
    the model holds) exceeds ``gate``, the filter concludes that something it did not model moved
    the state (a push, a kick) and adds ``gate_cov`` to its prior covariance before the update,
    so that it believes the sensors at once instead of explaining them away as noise."""
    obs, x_tilde, P = problem.observation, fstate.x_prior, fstate.cov
    H = obs.jacobian(x_tilde)
    G = obs.noise_matrix(x_tilde)
    innovation = y - obs.measure(x_tilde)
    if gate is not None:
        S = _sym(H @ P @ H.T + G @ G.T)
        surprise = innovation @ jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(S, lower=True), innovation)
        P = jnp.where(surprise > gate, P + gate_cov, P)
    S = _sym(H @ P @ H.T + G @ G.T)
    gain = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(S, lower=True), H @ P).T     # P H' S^-1
    J = jnp.eye(P.shape[0], dtype=P.dtype) - gain @ H
    x_del = x_tilde + gain @ innovation
    return x_del, _sym(J @ P @ J.T + gain @ G @ G.T @ gain.T)


def _model_step(problem, x, u, ud, j):
    """x_{j+1} from x_j under the model (x itself for j < 0: nothing moves before time 0)."""
    t = problem.dt * jnp.maximum(j, 0).astype(x.dtype)
    return jnp.where(j >= 0, x + problem.dt * problem.dynamics_at(x, u, ud, t), x)


def present_estimate(problem, x_del, commands, tick, controller_delay: int):
    """x_hat_k [n]: the model from x_del (the estimate of x_{k-l_s}) over the l_s steps to the
    present. ``commands``: [l_s + l_c, d] c_{k-l_s-l_c}..c_{k-1}; step s acts c_{k-l_s+s-l_c} =
    commands[s], with the command computed then, commands[s + l_c], as the model's own u."""
    ls = commands.shape[0] - controller_delay

    def one(x, s):
        return _model_step(problem, x, commands[s + controller_delay], commands[s], tick - ls + s), None

    return jax.lax.scan(one, x_del, jnp.arange(ls))[0] if ls else x_del


def filter_predict(problem, x_del, P_post, commands, tick, controller_delay: int, process_cov):
    """The time update to the prior of x_{k+1-l_s}. ``commands``: [l_s + l_c + 1, d]
    c_{k-l_s-l_c}..c_k (the command just computed last). Returns the next `FilterState`."""
    ls = commands.shape[0] - controller_delay - 1
    j = tick - ls
    u, ud = commands[controller_delay], commands[0]
    step = lambda x: _model_step(problem, x, u, ud, j)
    A = jax.jacfwd(step)(x_del)
    if process_cov is not None:
        Q = process_cov
    elif problem.noise is not None:
        F = problem.noise_at(x_del, u, ud, problem.dt * jnp.maximum(j, 0).astype(x_del.dtype))
        Q = problem.dt * F @ F.T
    else:
        Q = jnp.zeros_like(P_post)
    Q = jnp.where(j >= 0, Q, 0.0)
    return FilterState(step(x_del), _sym(A @ P_post @ A.T + Q), commands[1:ls + 1])
