"""Eq. (3)-(4): the LQG approximation of a [`Problem`][delayed_ilqr.Problem] around a nominal trajectory.

One step's model comes from JAX autodiff (reverse mode for f, forward mode for F) at (x_k, u_k, u_{k-l}):

    A = I + dt f_x,  B0 = dt f_u,  B1 = dt f_ud,  c = sqrt(dt) F,  C0 = sqrt(dt) F_u,  C1 = sqrt(dt) F_ud

(the printed dt in front of the C terms is erratum E7). A time-dependent problem's callables see
the step's time t_k = k dt, the final cost t_K = K dt (``Problem.step_times``); a time-independent
one's rows carry no time (None), so its compiled loops are the same as without the feature. As in the paper, F is linearised in the
commands only; its dependence on x is evaluated on the nominal (erratum N14). The cost of eq. (2)
is expanded to second order in the factor-2 convention of eq. (4): d = dt l_x / 2, D = dt l_xx / 2,
e = dt l_u / 2, E = dt l_uu / 2, N = dt l_ux / 2 for the running cost l, and the final cost alike.

`linearize` stores the model of every step (``vmap``); `step_models` hands the solver's
structured pass the nominal instead, and the pass linearises each step as it reaches it.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from .._kernels.scan import packed_scan
from ..lqg.frame import acting_commands
from ..lqg.model import DelayedLQG, StepModels
from ..problem import Problem

__all__ = ["delayed_commands", "rollout", "trajectory_cost", "noise_columns", "step_models", "linearize"]


def delayed_commands(problem: Problem, us):
    """u_{k-l} for k = 0..K-1 (zeros before t = 0); [K, d]. For l = 0 this is ``us`` itself.
    With a frame (``Problem.delay_frame``) l is data: a dynamic slice instead of a static shift."""
    return acting_commands(us, problem.delay_steps, problem.delay_frame is not None)


def rollout(problem: Problem, us):
    """Noise-free Euler rollout of an open-loop command sequence: xs [K+1, n]."""
    uds = delayed_commands(problem, us)

    def step(x, row):
        u, ud, t = row
        x_new = x + problem.dt * problem.dynamics_at(x, u, ud, t)
        return x_new, x_new

    _, xs = packed_scan(step, problem.x0, (us, uds, problem.step_times(us.dtype)))
    return jnp.concatenate([problem.x0[None], xs])


def trajectory_cost(problem: Problem, xs, us):
    """Eq. (2) discretised: sum_k dt running(x_k, u_k) + final(x_K)."""
    running = jax.vmap(problem.cost.running)(xs[:-1], us, problem.step_times(us.dtype))
    return problem.dt * jnp.sum(running) + problem.cost.final(xs[-1], problem.final_time)


def noise_columns(problem: Problem, xs, us):
    """c_k = sqrt(dt) F(x_k, u_k, u_{k-l})' : [K, p, n] (zero-width without noise)."""
    if problem.noise is None:
        return jnp.zeros((us.shape[0], 0, problem.n_states), us.dtype)
    F = jax.vmap(problem.noise_at)(xs[:-1], us, delayed_commands(problem, us), problem.step_times(us.dtype))
    return jnp.sqrt(problem.dt) * jnp.swapaxes(F, 1, 2)


def _rows(problem: Problem, xs, us):
    """The rows (x_k, u_k, u_{k-l}, t_k) of `_step` (t_k None for a time-independent problem)."""
    return xs[:-1], us, delayed_commands(problem, us), problem.step_times(us.dtype)


def _step(problem: Problem, row):
    """Eq. (3)-(4) at one step k < K: (A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, N) from
    row = (x_k, u_k, u_{k-l}, t_k), shaped as one time step of [`DelayedLQG`][delayed_ilqr.lqg.DelayedLQG]."""
    x, u, ud, t = row
    dt, nx, nd = problem.dt, problem.n_states, problem.n_controls
    # reverse mode: f has n outputs and n + 2 d inputs, so n vector-Jacobian products instead of
    # n + 2 d Jacobian-vector ones (the six-muscle arm: 10 against 22)
    fx, fu, fud = jax.jacrev(partial(_at, problem.dynamics_at, t=t), argnums=(0, 1, 2))(x, u, ud)
    if problem.noise is None:
        c, C0 = jnp.zeros((0, nx), x.dtype), jnp.zeros((0, nx, nd), x.dtype)
        C1 = jnp.zeros((0, nx, ud.shape[0]), x.dtype)      # ud: [2 d] taps for a fractional delay
    else:
        root = jnp.sqrt(dt)
        Fu, Fud = jax.jacfwd(partial(_at, problem.noise_at, t=t), argnums=(1, 2))(x, u, ud)   # [n, p, d]
        c = root * problem.noise_at(x, u, ud, t).T
        C0, C1 = root * jnp.moveaxis(Fu, 1, 0), root * jnp.moveaxis(Fud, 1, 0)
    running = partial(problem.cost.running, t=t)
    lx, lu = jax.grad(running, argnums=(0, 1))(x, u)
    (lxx, lxu), (lux, luu) = jax.hessian(running, argnums=(0, 1))(x, u)
    half = 0.5 * dt
    return (jnp.eye(nx, dtype=x.dtype) + dt * fx, dt * fu, dt * fud, c, C0, C1, dt * running(x, u), half * lx,
            half * lxx, half * lu, half * luu, half * lux)


def _at(fn, x, u, ud, t):
    return fn(x, u, ud, t)


def _terminal(problem: Problem, x):
    """(d_tilde_K, d_K, D_K): the final cost expanded at x_K (at t_K = K dt)."""
    final = partial(problem.cost.final, t=problem.final_time)
    return final(x), 0.5 * jax.grad(final)(x), 0.5 * jax.hessian(final)(x)


def step_models(problem: Problem, xs, us) -> StepModels:
    """The delayed LQG (3)-(4) around the nominal (xs [K+1, n], us [K, d]), one step at a time:
    the structured pass linearises each step as it reaches it, and nothing stores the model."""
    return StepModels(partial(_step, problem), _rows(problem, xs, us),
                      _terminal(problem, xs[-1]), problem.delay_steps, problem.n_controls, problem.delay_frame)


def linearize(problem: Problem, xs, us) -> DelayedLQG:
    """The delayed LQG (3)-(4) around the nominal (xs [K+1, n], us [K, d]), stored: every step of
    `step_models` at once (``vmap``)."""
    A, B0, B1, c, C0, C1, d_tilde, d, D, e, E, N = jax.vmap(partial(_step, problem))(_rows(problem, xs, us))
    final = _terminal(problem, xs[-1])
    return DelayedLQG.from_traced(
        A=A, B0=B0, B1=B1, c=c, C0=C0, C1=C1, d_tilde=jnp.concatenate([d_tilde, final[0][None]]),
        d=jnp.concatenate([d, final[1][None]]), D=jnp.concatenate([D, final[2][None]]), e=e, E=E, N=N,
        delay_steps=problem.delay_steps, delay_frame=problem.delay_frame)
