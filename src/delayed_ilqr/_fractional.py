"""A delay that is not a whole number of steps, tau_j = (l_j + phi_j) dt with 0 <= phi_j < 1, under
the zero-order hold (docs/derivation.md §20): one Euler step of the plant as the exact integral of
the held commands over the step, the state frozen at x_k.

Over step k channel j's acting command is u_{k-l_j-1, j} for t < phi_j dt and u_{k-l_j, j} after.
With the fractions sorted, s_0 = 0 <= s_1 <= ... <= s_d <= s_{d+1} = 1, the step is d + 1 pieces
of width w_i = s_{i+1} - s_i, on each of which every channel holds one command:

    dt f_bar = dt sum_i w_i f(x, u_k, ud^(i)),   ud^(i)_j = u_{k-l_j-1, j} if phi_j > s_i else u_{k-l_j, j}

and the Brownian increments of the pieces are independent, so the noise of the step is
sqrt(dt) [sqrt(w_0) F(x, u_k, ud^(0)), ..., sqrt(w_d) F(x, u_k, ud^(d))] xi with (d + 1) p
columns: its covariance dt sum_i w_i F_i F_i' is exact. The problem hands these to the solver as
two *taps* per channel, ud = [u_{k-l}, u_{k-l-1}] ([2 d]: tap l_j, then tap l_j + 1).
"""
from __future__ import annotations

import jax.numpy as jnp

__all__ = ["pieces", "drift", "diffusion", "safe_sqrt"]


def pieces(phi):
    """(widths [d+1], ranks [d]) of the step's pieces for fractions phi [d] (each in [0, 1)):
    piece i runs from the i-th smallest fraction (0 for i = 0) to the next (1 after the last), and
    ``ranks[j]`` is channel j's place in that order (ties kept in channel order)."""
    phi = jnp.asarray(phi)
    order = jnp.argsort(phi, stable=True)
    s = phi[order]
    starts = jnp.concatenate([jnp.zeros(1, phi.dtype), s])
    ends = jnp.concatenate([s, jnp.ones(1, phi.dtype)])
    return ends - starts, jnp.argsort(order)


def _held(ud2, ranks, i):
    """Every channel's command held on piece i: the older one (tap l_j + 1, ud2[d:]) on the pieces
    before its switch, ranks[j] >= i, the newer (tap l_j, ud2[:d]) after.

    The pattern comes from the ranks, not from comparing phi_j with the piece's start: a piece of
    zero width (phi_j = 0, a whole step, or two equal fractions) then holds the commands it would
    hold were it widened by moving the fraction that ends it, so the derivative of the widths
    (d w_i / d phi_j) meets the right commands. Compared by value, the channel switching at the end
    of a zero-width piece held its newer command there, and d f_bar / d phi_j came out as 0 at a
    whole step (and wrong at equal fractions) instead of f(older) - f(newer)."""
    d = ranks.shape[0]
    return jnp.where(ranks >= i, ud2[d:], ud2[:d])


def drift(fn, x, u, ud2, phi, *t):
    """sum_i w_i f(x, u, ud^(i)): the step's mean rate of change [n]."""
    widths, ranks = pieces(phi)
    return sum(widths[i] * fn(x, u, _held(ud2, ranks, i), *t) for i in range(phi.shape[0] + 1))


def safe_sqrt(w):
    """sqrt(w) for w >= 0 whose derivative at w = 0 is 0 rather than infinite: a piece of zero
    width (equal fractions, or phi = 0) has no noise, and its column stays out of the derivative."""
    positive = w > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, w, 1.0)), 0.0)


def diffusion(fn, x, u, ud2, phi, *t):
    """[sqrt(w_0) F(x, u, ud^(0)), ..., sqrt(w_d) F(x, u, ud^(d))]: [n, (d + 1) p]."""
    widths, ranks = pieces(phi)
    return jnp.concatenate([safe_sqrt(widths[i]) * fn(x, u, _held(ud2, ranks, i), *t)
                            for i in range(phi.shape[0] + 1)], axis=1)
