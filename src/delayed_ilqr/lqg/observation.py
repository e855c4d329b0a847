"""The linear delayed observation model of the sensorimotor loop, in deviations:

    dy_k = H_k dx_{k-l_s} + G_k v_k,    v_k ~ N(0, I_q),    k = l_s..K-1

``dy_k`` is available when du_k is computed (the information for du_k is dy_{l_s..k}, the commands
already sent, and dx_0 = 0 exactly; states before time 0 equal x0, so their deviations are 0). No
measurement arrives at k < l_s: rows k < l_s of H and G are never used. Row k belongs to the step at
which the measurement *arrives*; linearising y_k = h(x_{k-l_s}) + G v_k around a nominal gives
H_k = dh/dx at x_bar_{k-l_s}.

A sensor sampled every m steps (``period`` m) samples the states x_j with j % m == 0, so its
measurement arrives at the steps k >= l_s with (k - l_s) % m == 0; at the other steps its rows are
absent (``present``). Several sensors with one delay are one ``DelayedObservation`` whose rows
carry their own periods; sensors with different delays are fused by ``lqg.fusion``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import _precision, _validate

__all__ = ["DelayedObservation"]


class DelayedObservation:
    """The delayed, noisy sensors dy_k = H_k dx_{k-l_s} + G_k v_k (k >= l_s).

    Args:
        H: [K, m, n] output matrix of the measurement that arrives at step k (of the state l_s steps
            earlier).
        G: [K, m, q] sensory noise columns; G_k G_k' must be positive definite at every k >= l_s
            (every measurement is noisy, so the innovation covariance is invertible).
        delay_steps: l_s >= 0, the sensory delay in steps.
        period: m >= 1, the steps between two samples (default 1: every step), or one period per
            row (a tuple of m ints: several sensors with one delay, stacked).

    Instances are JAX pytrees whose static fields are ``delay_steps`` and ``period`` (a tuple, one
    per row).
    """

    def __init__(self, H, G, delay_steps, period=1):
        _precision.require_x64("lqg.DelayedObservation")
        self.delay_steps = _validate.delay_steps(delay_steps, "observation delay_steps")
        H = _validate.array(H, "H", (None, None, None))
        K, m = H.shape[0], H.shape[1]
        self.period = row_periods(period, m, "observation period")
        G = _validate.array(G, "G", (K, m, None))
        if not isinstance(G, jax.core.Tracer) and K > self.delay_steps:
            used = np.einsum("kmq,kpq->kmp", G, G)[self.delay_steps:]
            _validate.symmetric_psd(used, "G G' (rows k >= delay_steps)", definite=True)
        self.H, self.G = jnp.asarray(H), jnp.asarray(G)

    @property
    def horizon(self) -> int:
        return self.H.shape[0]

    @property
    def n_outputs(self) -> int:
        """m, the size of one measurement."""
        return self.H.shape[1]

    @property
    def present(self) -> jax.Array:
        """[K, m] bool: row r of the measurement that arrives at k exists (k >= l_s and
        (k - l_s) % period_r == 0)."""
        return sampled_rows(self.horizon, self.delay_steps, self.period)

    @property
    def measurement_cov(self) -> jax.Array:
        """[K, m, m] G_k G_k', the covariance of the sensory noise."""
        return self.G @ jnp.swapaxes(self.G, 1, 2)

    def __repr__(self) -> str:
        return (f"DelayedObservation(K={self.horizon}, m={self.n_outputs}, q={self.G.shape[2]}, "
                f"delay_steps={self.delay_steps}, period={self.period})")


def row_periods(period, m: int, name: str) -> tuple:
    """``period`` (a positive int, or one per row) as a tuple of m positive ints."""
    periods = (period,) * m if np.ndim(period) == 0 else tuple(period)
    if len(periods) != m:
        raise ValueError(f"{name} must be one positive integer or one per row ({m}); got {period!r}")
    return tuple(_validate.positive_int(p, name) for p in periods)


def sampled_rows(K: int, delay_steps: int, period: tuple) -> jax.Array:
    """[K, m] bool: row r arrives at step k when k >= l_s and (k - l_s) % period_r == 0."""
    k = np.arange(K)[:, None] - delay_steps
    return jnp.asarray((k >= 0) & (k % np.asarray(period)[None, :] == 0))


def _flatten(obs: DelayedObservation):
    return (obs.H, obs.G), (obs.delay_steps, obs.period)


def _unflatten(aux, arrays):
    new = object.__new__(DelayedObservation)
    new.delay_steps, new.period = aux
    new.H, new.G = arrays
    return new


jax.tree_util.register_pytree_node(DelayedObservation, _flatten, _unflatten)
