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


#: added to each piece's width under the square root: far below round-off of any width that is not
#: zero, and what gives a zero width a finite slope (safe_sqrt)
_TINY_WIDTH = 1e-30


def safe_sqrt(w):
    """sqrt(w + 1e-30) for widths w >= 0: sqrt(w) to round-off, with a derivative that is right
    for the covariance at w = 0 too.

    A piece's noise enters the step as the column sqrt(w) F, and the solve through products of
    columns, w F F'. At w = 0 (a whole step, or equal fractions) d(w F F')/dw = F F', but the
    column's own slope is infinite; with the offset it is 1 / (2 sqrt(1e-30)), and the product
    rule gives 2 sqrt(1e-30) / (2 sqrt(1e-30)) F F' = F F' again. (A slope of 0 there left the
    new piece's noise out of the derivative.) A sample of the column, sqrt(w) F xi, has no finite
    derivative at w = 0, with or without the offset."""
    return jnp.sqrt(w + _TINY_WIDTH)


def diffusion(fn, x, u, ud2, phi, *t):
    """[sqrt(w_0) F(x, u, ud^(0)), ..., sqrt(w_d) F(x, u, ud^(d))]: [n, (d + 1) p]."""
    widths, ranks = pieces(phi)
    return jnp.concatenate([safe_sqrt(widths[i]) * fn(x, u, _held(ud2, ranks, i), *t)
                            for i in range(phi.shape[0] + 1)], axis=1)
