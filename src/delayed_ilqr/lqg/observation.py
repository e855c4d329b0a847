"""The linear delayed observation model of the sensorimotor loop, in deviations:

    dy_k = H_k dx_{k-l_s} + G_k v_k,    v_k ~ N(0, I_q),    k = l_s..K-1

``dy_k`` is available when du_k is computed (the information for du_k is dy_{l_s..k}, the commands
already sent, and dx_0 = 0 exactly; states before time 0 equal x0, so their deviations are 0). No
measurement arrives at k < l_s: rows k < l_s of H and G are never used. Row k belongs to the step at
which the measurement *arrives*; linearising y_k = h(x_{k-l_s}) + G v_k around a nominal gives
H_k = dh/dx at x_bar_{k-l_s}.
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

    Instances are JAX pytrees whose only static field is ``delay_steps``.
    """

    def __init__(self, H, G, delay_steps):
        _precision.require_x64("lqg.DelayedObservation")
        self.delay_steps = _validate.delay_steps(delay_steps, "observation delay_steps")
        H = _validate.array(H, "H", (None, None, None))
        K, m = H.shape[0], H.shape[1]
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
    def measurement_cov(self) -> jax.Array:
        """[K, m, m] G_k G_k', the covariance of the sensory noise."""
        return self.G @ jnp.swapaxes(self.G, 1, 2)

    def __repr__(self) -> str:
        return (f"DelayedObservation(K={self.horizon}, m={self.n_outputs}, q={self.G.shape[2]}, "
                f"delay_steps={self.delay_steps})")


def _flatten(obs: DelayedObservation):
    return (obs.H, obs.G), obs.delay_steps


def _unflatten(delay_steps, arrays):
    new = object.__new__(DelayedObservation)
    new.delay_steps = delay_steps
    new.H, new.G = arrays
    return new


jax.tree_util.register_pytree_node(DelayedObservation, _flatten, _unflatten)
