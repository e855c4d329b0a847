"""Eq. (3)-(4): the LQG approximation of a :class:`~delayed_ilqr.Problem` around a nominal trajectory.

Jacobians come from JAX autodiff (reverse mode for f, forward mode for F), vectorised over time with ``vmap``::

    A = I + dt f_x,  B0 = dt f_u,  B1 = dt f_ud,  c = sqrt(dt) F,  C0 = sqrt(dt) F_u,  C1 = sqrt(dt) F_ud

(the printed dt in front of the C terms is erratum E7). As in the paper, F is linearised in the
commands only; its dependence on x is evaluated on the nominal (erratum N14). The cost of eq. (2)
is expanded to second order in the factor-2 convention of eq. (4): d = dt l_x / 2, D = dt l_xx / 2,
e = dt l_u / 2, E = dt l_uu / 2, N = dt l_ux / 2 for the running cost l, and the final cost alike.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from ._scan import packed_scan
from .lqg import DelayedLQG
from .problem import Problem

__all__ = ["delayed_commands", "rollout", "trajectory_cost", "path_cost", "linearize"]


def delayed_commands(problem: Problem, us):
    """u_{k-l} for k = 0..K-1 (zeros before t = 0); [K, d]. For l = 0 this is ``us`` itself."""
    l = problem.delay_steps
    if l == 0:
        return us
    return jnp.concatenate([jnp.zeros((l,) + us.shape[1:], us.dtype), us])[: us.shape[0]]


def rollout(problem: Problem, us):
    """Noise-free Euler rollout of an open-loop command sequence: xs [K+1, n]."""
    uds = delayed_commands(problem, us)

    def step(x, u_pair):
        u, ud = u_pair
        x_new = x + problem.dt * problem.dynamics(x, u, ud)
        return x_new, x_new

    _, xs = packed_scan(step, problem.x0, (us, uds))
    return jnp.concatenate([problem.x0[None], xs])


def trajectory_cost(problem: Problem, xs, us):
    """Eq. (2) discretised: sum_k dt running(x_k, u_k) + final(x_K)."""
    return path_cost(problem, xs[0], xs[1:], us)


def path_cost(problem: Problem, x0, xs_next, us):
    """:func:`trajectory_cost` from x_0 [n] and x_1 .. x_K [K, n], the states a rollout writes
    (the line search's candidates share x_0 and never store it)."""
    running = problem.cost.running(x0, us[0]) + jnp.sum(jax.vmap(problem.cost.running)(xs_next[:-1], us[1:]))
    return problem.dt * running + problem.cost.final(xs_next[-1])


def noise_columns(problem: Problem, xs, us):
    """c_k = sqrt(dt) F(x_k, u_k, u_{k-l})' : [K, p, n] (zero-width without noise)."""
    if problem.noise is None:
        return jnp.zeros((us.shape[0], 0, problem.n_states), us.dtype)
    F = jax.vmap(problem.noise)(xs[:-1], us, delayed_commands(problem, us))
    return jnp.sqrt(problem.dt) * jnp.swapaxes(F, 1, 2)


def linearize(problem: Problem, xs, us) -> DelayedLQG:
    """The delayed LQG (3)-(4) around the nominal (xs [K+1, n], us [K, d])."""
    dt, nx, nd = problem.dt, problem.n_states, problem.n_controls
    K = us.shape[0]
    uds = delayed_commands(problem, us)
    # reverse mode: f has n outputs and n + 2 d inputs, so n vector-Jacobian products instead of
    # n + 2 d Jacobian-vector ones (the six-muscle arm: 10 against 22)
    fx, fu, fud = jax.vmap(jax.jacrev(problem.dynamics, argnums=(0, 1, 2)))(xs[:-1], us, uds)
    A = jnp.eye(nx) + dt * fx
    B0, B1 = dt * fu, dt * fud
    if problem.noise is None:
        c = jnp.zeros((K, 0, nx))
        C0 = C1 = jnp.zeros((K, 0, nx, nd))
    else:
        F = jax.vmap(problem.noise)(xs[:-1], us, uds)                        # [K, n, p]
        Fu, Fud = jax.vmap(jax.jacfwd(problem.noise, argnums=(1, 2)))(xs[:-1], us, uds)  # [K, n, p, d]
        root = jnp.sqrt(dt)
        c = root * jnp.swapaxes(F, 1, 2)
        C0, C1 = root * jnp.moveaxis(Fu, 2, 1), root * jnp.moveaxis(Fud, 2, 1)

    running = problem.cost.running
    lx, lu = jax.vmap(jax.grad(running, argnums=(0, 1)))(xs[:-1], us)
    (lxx, lxu), (lux, luu) = jax.vmap(jax.hessian(running, argnums=(0, 1)))(xs[:-1], us)
    final = problem.cost.final
    half = 0.5 * dt
    d_tilde = jnp.concatenate([dt * jax.vmap(running)(xs[:-1], us), final(xs[-1])[None]])
    d = jnp.concatenate([half * lx, 0.5 * jax.grad(final)(xs[-1])[None]])
    D = jnp.concatenate([half * lxx, 0.5 * jax.hessian(final)(xs[-1])[None]])
    return DelayedLQG.from_traced(
        A=A, B0=B0, B1=B1, c=c, C0=C0, C1=C1, d_tilde=d_tilde, d=d, D=D,
        e=half * lu, E=half * luu, N=half * lux, delay_steps=problem.delay_steps)
